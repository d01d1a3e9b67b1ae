"""Accuracy of the maps against the simulated world's truth, TOF and stereo side by side.

For each seed, a real server on the default world (configs/world.toml with --world-seed) runs a full
dem-full-tof panorama and a dem-full panorama; each product is scored from its own files only (the
maps beside the truth/ grids, as anyone could score it without our code):

- DEM height error over observed cells: RMSE, 95th percentile of |error|, mean (bias);
- share of the panorama's area observed: known cells within the sensor's reach of the rover;
- hazard recall: true obstacles (connected rocks protruding more than the step threshold) that
  were observed and have a hazard cell on them;
- false hazards: the share of truly safe observed cells (no obstacle within 0.1 m) marked hazardous.
Also prints dem-full-tof's time per step and the server's peak memory.

    .venv/bin/python tests/bench/measure_maps.py [--seeds 1 2 3 4 5] [--sim-speed 100]
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np
from scipy import ndimage

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "tests"))
sys.path.insert(0, str(REPO))
from rvs_server.products.rasters import read_geotiff  # noqa: E402

import conftest  # noqa: E402
from conftest import ServerProcess, pairs  # noqa: E402

REACH_M = {"tof": 4.5, "stereo": 4.5}  # the same disc for both, inside both sensors' range


def score(product: Path, sensor: str) -> dict[str, float]:
    dem, spec = read_geotiff(product / "dem.tif")
    truth, _ = read_geotiff(product / "truth" / "height.tif")
    code, _ = read_geotiff(product / "hazard.tif")
    obstacles = read_geotiff(product / "truth" / "obstacles.tif")[0] > 0.5
    state = json.loads((product / "truth" / "state.json").read_text())
    known = np.isfinite(dem)
    error = (dem - truth)[known]
    hazard = known & (code != 255) & (code.astype(np.int64) % 2 == 1)
    xs, ys = spec.centres()
    distance = np.hypot(xs[None, :] - state["rover"]["x"], ys[:, None] - state["rover"]["y"])
    reach = distance <= REACH_M[sensor]
    labels, count = ndimage.label(obstacles)
    seen = detected = 0
    near_hazard = ndimage.binary_dilation(hazard, iterations=1)
    for index in range(1, count + 1):
        rock = labels == index
        if (rock & known).any():
            seen += 1
            detected += bool((rock & near_hazard).any())
    safe = known & ~ndimage.binary_dilation(obstacles, iterations=max(1, int(round(0.1 / spec.cell))))
    return {"rmse": float(np.sqrt(np.mean(error ** 2))), "p95": float(np.percentile(np.abs(error), 95)),
            "bias": float(error.mean()), "observed": float(known[reach].mean()),
            "recall": detected / max(seen, 1), "rocks": seen,
            "false_hazard": float(hazard[safe].sum() / max(safe.sum(), 1))}


def run(client, line: str) -> dict[str, str]:
    reply = client.command(line, timeout=1800)
    if reply.split()[1] != "OK":
        raise RuntimeError(f"{line}: {reply}")
    return pairs(reply)


def peak_rss_mib(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3, 4, 5])
    parser.add_argument("--sim-speed", type=float, default=100.0)
    args = parser.parse_args()
    conftest.SIM_SPEED = args.sim_speed
    rows = {"tof": [], "stereo": []}
    with tempfile.TemporaryDirectory() as tmp:
        for seed in args.seeds:
            base = Path(tmp) / f"seed{seed}"
            config_dir = base / "configs"
            conftest.write_configs(config_dir)
            (config_dir / "world.toml").write_text((REPO / "configs" / "world.toml").read_text())
            server = ServerProcess(data_dir=base / "data", config_dir=config_dir,
                                   extra_args=["--world-seed", str(seed)]).start()
            try:
                with server.connect(timeout=900) as c:
                    tof, stereo = (run(c, line) for line in ("dem-full-tof --output tof", "dem-full --output stereo"))
                peak = peak_rss_mib(server.proc.pid)
            finally:
                server.stop()
            for sensor, reply in (("tof", tof), ("stereo", stereo)):
                result = score(Path(reply["path"]), sensor)
                rows[sensor].append(result)
                print(f"seed {seed} {sensor:6s} rmse {result['rmse'] * 100:5.2f} cm  "
                      f"p95 {result['p95'] * 100:5.2f} cm  "
                      f"bias {result['bias'] * 100:+5.2f} cm  observed {result['observed']:.2f}  "
                      f"recall {result['recall']:.2f} ({result['rocks']} rocks)  "
                      f"false hazard {result['false_hazard']:.3f}")
            timings = json.loads((Path(tof["path"]) / "product.json").read_text())["timings_s"]
            print(f"seed {seed} dem-full-tof seconds: " + ", ".join(f"{k} {v:.2f}" for k, v in timings.items())
                  + f"; server peak memory {peak:.0f} MiB (world included)")
    for sensor, results in rows.items():
        mean = {key: np.mean([r[key] for r in results]) for key in results[0]}
        print(f"mean {sensor:6s} rmse {mean['rmse'] * 100:5.2f} cm  p95 {mean['p95'] * 100:5.2f} cm  bias "
              f"{mean['bias'] * 100:+5.2f} cm  observed {mean['observed']:.2f}  recall {mean['recall']:.2f}  "
              f"false hazard {mean['false_hazard']:.3f}")


if __name__ == "__main__":
    main()
