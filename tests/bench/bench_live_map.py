"""Benchmark: one TOF frame into an existing map (its world points with the artifacts removed, as
dem.view_points makes them, then toolbox/mapping/live.py: its cells and the hazard maps of the window
it touched) beside the full update of the same views (every view's points made and gridded again and
the hazard maps of the whole grid: what dem-update-tof's dem.view_points, dem.grid and hazard.maps
do), in one run, on one core. Goal (issue 26): the frame under 100 ms.

The views are real: a dem-full-tof product's stored views (views/, made by a fresh server on the
default world unless --product names one), turned into world points as dem.view_points does.

    .venv/bin/python tests/bench/bench_live_map.py [--product DATA/products/NAME] [--repeats 20]
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("NUMBA_NUM_THREADS", "1")     # one core, as the goal says

import cv2  # noqa: E402
import numpy as np  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "tests"))
sys.path.insert(0, str(REPO))
from rvs_server.mapping.stored_views import load_views  # noqa: E402
from toolbox.mapping import dem as dem_tools  # noqa: E402
from toolbox.mapping.hazard import HazardConfig, hazard_maps  # noqa: E402
from toolbox.mapping.live import LiveMap  # noqa: E402

from conftest import ServerProcess, pairs, write_configs  # noqa: E402

MAX_RANGE_M = 4.8     # mapping.toml max_range_m
CELL = 0.05


def make_product() -> Path:
    root = Path(tempfile.mkdtemp(prefix="rvs-bench-live-"))
    server = ServerProcess(data_dir=root / "data", config_dir=write_configs(root / "configs")).start(timeout=300)
    try:
        with server.connect(timeout=600) as c:
            reply = c.command("dem-full-tof --output views", timeout=900)
    finally:
        server.stop()
    assert " OK " in reply, reply
    return Path(pairs(reply)["path"])


def world_points(view: dict) -> np.ndarray:
    points = view["points_camera"]
    valid = view["valid"] & (np.linalg.norm(np.nan_to_num(points, nan=np.inf), axis=-1) <= MAX_RANGE_M)
    return dem_tools.view_points(points, valid, view["camera_to_world"])


def timed(func, repeats: int) -> float:
    """Median wall milliseconds of `repeats` calls."""
    times = []
    for _ in range(repeats):
        started = time.perf_counter()
        func()
        times.append(time.perf_counter() - started)
    return 1000.0 * float(np.median(times))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--product", type=Path, default=None)
    parser.add_argument("--repeats", type=int, default=20)
    args = parser.parse_args()
    cv2.setNumThreads(1)
    views = [v for v in load_views(args.product or make_product()).results["acquire.tof"]["views"]
             if len(world_points(v))]
    frames = [world_points(v) for v in views]
    everything = np.vstack(frames)
    spec = dem_tools.grid_covering(everything, CELL, margin=CELL)
    config = HazardConfig(step_min_cells=2)
    before = dem_tools.points_to_dem(np.vstack(frames[:-1]), spec)
    last = frames[-1]
    base = LiveMap(before, config)

    def one_frame() -> None:
        live = base.copy()                    # the map as it stood before the frame, copied untimed
        started = time.perf_counter()
        live.insert(world_points(views[-1]))
        one_frame.times.append(time.perf_counter() - started)
    one_frame.times = []

    def full_update() -> None:
        dem = dem_tools.points_to_dem(np.vstack([world_points(v) for v in views]), spec)
        hazard_maps(dem.heights, spec.cell, config)

    full_update()                              # warm up (numba's compilation, caches)
    one_frame()
    one_frame.times.clear()
    for _ in range(args.repeats):
        one_frame()
    frame_ms = 1000.0 * float(np.median(one_frame.times))
    full_ms = timed(full_update, max(3, args.repeats // 4))
    print(f"{len(frames)} TOF views, {len(everything)} points, grid {spec.rows} x {spec.cols} at {CELL * 100:.0f} cm; "
          f"last frame {len(last)} points")
    print(f"one frame into the map (points, cells, hazards of its window): {frame_ms:8.1f} ms "
          f"(median of {args.repeats})")
    print(f"full update of the same views (points, grid, hazards):          {full_ms:8.1f} ms")
    print(f"ratio frame / full: {frame_ms / full_ms:.3f}; goal: frame under 100 ms on one core "
          f"({'met' if frame_ms < 100 else 'missed'})")


if __name__ == "__main__":
    main()
