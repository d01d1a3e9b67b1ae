"""Which height per cell: the highest point, or the mean of the points within a band of it (issue 27 item 3).

    .venv/bin/python tests/bench/measure_dem_estimator.py [--seeds 1 2 3 4 5] [--bands 0 0.02 0.03 0.04 0.06]
        [--sensors stereo tof] [--work /tmp/rvs-dem-estimator]

Per seed and sensor, one full panorama on the default world (a real server: dem-full or dem-full-tof,
views kept in the product), then `rvs remap` of those stored views with the same workflow but the
grid step's `top_band_m` set to each band (no device, the very same points), each product scored on
its truth/ grids as tests/bench/maps_scoring.py scores the maps campaign: DEM RMSE, bias and p95 of
|error| over observed cells, rock recall and the share of truly safe cells marked hazardous. Band 0
is the highest point (today's DEM). The work folder is kept: a rerun reuses panoramas already made.
"""
from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
sys.path.insert(0, str(HERE))
from maps_scoring import score_product  # noqa: E402

from conftest import REPO, ServerProcess  # noqa: E402

WORKFLOW = {"stereo": "dem-full", "tof": "dem-full-tof"}


def panorama(work: Path, seed: int, sensor: str) -> Path:
    """The product folder of one full panorama of this seed and sensor, made once."""
    base = work / f"{sensor}-{seed}"
    done = base / "product.txt"
    if done.exists():
        return Path(done.read_text().strip())
    configs = base / "configs"
    base.mkdir(parents=True, exist_ok=True)
    subprocess.run(["cp", "-r", str(REPO / "configs"), str(configs)], check=True)
    subprocess.run(["cp", "-r", str(REPO / "workflows"), str(base / "workflows")], check=True)
    world = (configs / "world.toml").read_text()
    (configs / "world.toml").write_text(re.sub(r"(?m)^seed = \d+", f"seed = {seed}", world))
    server = ServerProcess(data_dir=base / "data", config_dir=configs, extra_args=["--sim-speed", "100"])
    server.start(timeout=300)
    try:
        with server.connect(timeout=600) as client:
            reply = client.command(f"{WORKFLOW[sensor]} --output {sensor}", timeout=1800)
    finally:
        server.stop()
    if " OK " not in reply:
        raise RuntimeError(f"{sensor} seed {seed}: {reply}")
    path = next((base / "data" / "products").glob(f"{sensor}*"))
    done.write_text(str(path))
    return path


def remapped(product: Path, sensor: str, band: float, work: Path) -> Path:
    """The product re-made from its stored views with the grid's top band set to `band`."""
    out = work / f"{product.parent.parent.parent.name}-band{band:g}"
    existing = sorted((out / "products").glob("*")) if (out / "products").exists() else []
    if existing:
        return existing[-1]
    text = (REPO / "workflows" / f"{WORKFLOW[sensor]}.yaml").read_text()
    text, count = re.subn(r"top_band_m: \$config\.\w+", f"top_band_m: {band}", text, count=1)
    if count != 1:
        raise RuntimeError(f"no dem.grid params in {WORKFLOW[sensor]}.yaml to set the band in")
    flow = work / f"{WORKFLOW[sensor]}-band{band:g}.yaml"
    flow.write_text(text)
    result = subprocess.run([sys.executable, "-m", "rvs_server.mapping.remap_batch", str(product), "--workflow",
                             str(flow), "--workers", "1", "--out", str(out)], cwd=REPO, capture_output=True,
                            text=True)
    if result.returncode != 0:
        raise RuntimeError(f"remap {product.name} band {band}: {result.stdout[-800:]} {result.stderr[-800:]}")
    return sorted((out / "products").glob("*"))[-1]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3, 4, 5])
    parser.add_argument("--bands", type=float, nargs="+", default=[0.0, 0.02, 0.03, 0.04, 0.06])
    parser.add_argument("--sensors", nargs="+", choices=("stereo", "tof"), default=["stereo", "tof"])
    parser.add_argument("--work", type=Path, default=Path("/tmp/rvs-dem-estimator"))
    args = parser.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    table: dict[tuple[str, float], list[dict[str, float]]] = {}
    for sensor in args.sensors:
        for seed in args.seeds:
            product = panorama(args.work, seed, sensor)
            for band in args.bands:
                scores = score_product(remapped(product, sensor, band, args.work), sensor)
                table.setdefault((sensor, band), []).append(scores)
                print(f"{sensor} seed {seed} band {band * 100:g} cm: " + " ".join(
                    f"{k} {v:.4f}" for k, v in scores.items()), flush=True)
    print("\nper sensor and band, over seeds " + " ".join(map(str, args.seeds)) +
          " (RMSE, p95, bias in cm over observed cells; recall of rocks over the step limit;"
          " safe cells called hazardous)")
    for (sensor, band), rows in table.items():
        mean = {k: float(np.mean([r[k] for r in rows])) for k in rows[0]}
        worst = min(r["recall"] for r in rows)
        print(f"{sensor:6s} band {band * 100:4g} cm: RMSE {100 * mean['rmse']:.2f}  p95 {100 * mean['p95']:.2f}  "
              f"bias {100 * mean['bias']:+.2f}  recall {mean['recall']:.3f} (worst seed {worst:.3f}, "
              f"{sum(r['rocks'] for r in rows)} rocks)  false hazard {100 * mean['false_hazard']:.2f} %")
    (args.work / "table.json").write_text(json.dumps({f"{s} {b}": rows for (s, b), rows in table.items()}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
