"""Accuracy of the maps against the simulated world's truth, TOF, stereo and fused side by side.

For each seed, a real server on the default world (configs/world.toml with --world-seed) runs a full
dem-full-tof panorama and a dem-full panorama (and, with `--sensors ... fused`, a dem-full-fused one);
each product is scored from its own files only (the maps beside the truth/ grids, as anyone could
score it without our code):

- DEM height error over observed cells: RMSE, 95th percentile of |error|, mean (bias);
- share of the panorama's area observed: known cells within the sensor's reach of the rover;
- hazard recall: true obstacles (connected rocks protruding more than the step threshold) that
  were observed and have a hazard cell on them;
- false hazards: the share of truly safe observed cells (no obstacle within 0.1 m) marked hazardous.
Also prints dem-full-tof's time per step and the server's peak memory.

    .venv/bin/python tests/bench/measure_maps.py [--seeds 1 2 3 4 5] [--sim-speed 100]
        [--sensors tof stereo fused]
"""
from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "tests"))
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "tests" / "bench"))
from maps_scoring import mean_line, peak_rss_mib, score_product, seed_line, timing_line, timings  # noqa: E402

import conftest  # noqa: E402
from conftest import ServerProcess, pairs  # noqa: E402

COMMANDS = {"tof": "dem-full-tof", "stereo": "dem-full", "fused": "dem-full-fused"}


def run(client, line: str) -> dict[str, str]:
    reply = client.command(line, timeout=1800)
    if reply.split()[1] != "OK":
        raise RuntimeError(f"{line}: {reply}")
    return pairs(reply)


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3, 4, 5])
    parser.add_argument("--sim-speed", type=float, default=100.0)
    parser.add_argument("--sensors", nargs="+", choices=list(COMMANDS), default=["tof", "stereo"])
    args = parser.parse_args()
    conftest.SIM_SPEED = args.sim_speed
    rows: dict[str, list] = {sensor: [] for sensor in args.sensors}
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
                    replies = {sensor: run(c, f"{COMMANDS[sensor]} --output {sensor}") for sensor in args.sensors}
                peak = peak_rss_mib(server.proc.pid)
            finally:
                server.stop()
            for sensor, reply in replies.items():
                result = score_product(Path(reply["path"]), sensor)
                rows[sensor].append(result)
                print(seed_line(seed, sensor, result), flush=True)
            if "tof" in replies:
                print(timing_line(seed, timings(Path(replies["tof"]["path"])), peak), flush=True)
    for sensor, results in rows.items():
        print(mean_line(sensor, results))


if __name__ == "__main__":
    main()
