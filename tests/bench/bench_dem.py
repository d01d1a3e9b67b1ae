"""Benchmark: direct reconstruction (points to DEM) beside a straightforward reference, same run.

1 million points fall into a 1000 x 1000 grid (2 cm cells over 20 x 20 m). Timed:
- ours: dem.points_to_dem (cell index, np.maximum.at on the flat index, bincount for counts);
- reference: a plain Python loop over the points (the obvious implementation);
- the alternative we measured and did not take: a stable argsort on the flat index + maximum.reduceat;
- the rest of the chain on the same grid: fill_small_holes, and isolated_blobs on an SR4000-sized frame.
Each result is checked against the reference before its time is printed.

    .venv/bin/python tests/bench/bench_dem.py [--points 1000000] [--repeats 5]
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from toolbox.mapping import dem as D  # noqa: E402
from toolbox.grid import GridSpec  # noqa: E402

SPEC = GridSpec(-10.0, -10.0, 0.02, 1000, 1000)


def best_of(repeats: int, function, *args):
    times, result = [], None
    for _ in range(repeats):
        start = time.perf_counter()
        result = function(*args)
        times.append(time.perf_counter() - start)
    return min(times), result


def terrain_points(count: int, rng: np.random.Generator) -> np.ndarray:
    x = rng.uniform(-10.2, 10.2, count)       # a few points fall outside the grid
    y = rng.uniform(-10.2, 10.2, count)
    z = 0.3 * np.sin(x / 3) * np.cos(y / 4) + rng.normal(0, 0.01, count)
    return np.c_[x, y, z]


def reference_loop(points: np.ndarray, spec: GridSpec) -> np.ndarray:
    heights = np.full(spec.shape, np.nan)
    for x, y, z in points.tolist():
        col = math.floor((x - spec.origin_x) / spec.cell)
        row = math.floor((y - spec.origin_y) / spec.cell)
        if 0 <= row < spec.rows and 0 <= col < spec.cols:
            current = heights[row, col]
            if not current >= z:          # NaN (empty) or lower
                heights[row, col] = z
    return heights


def sort_reduceat(points: np.ndarray, spec: GridSpec) -> np.ndarray:
    row, col, inside = spec.cell_of(points[:, 0], points[:, 1])
    flat = row[inside] * spec.cols + col[inside]
    order = np.argsort(flat, kind="stable")
    flat, z = flat[order], points[inside, 2][order]
    starts = np.flatnonzero(np.r_[True, flat[1:] != flat[:-1]])
    heights = np.full(spec.rows * spec.cols, np.nan)
    heights[flat[starts]] = np.maximum.reduceat(z, starts)
    return heights.reshape(spec.shape)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--points", type=int, default=1_000_000)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    points = terrain_points(args.points, rng)
    print(f"{args.points} points -> {SPEC.rows} x {SPEC.cols} grid ({SPEC.cell} m cells)")

    reference_time, reference = best_of(1, reference_loop, points, SPEC)
    ours_time, dem = best_of(args.repeats, D.points_to_dem, points, SPEC)
    sort_time, sorted_heights = best_of(args.repeats, sort_reduceat, points, SPEC)
    assert np.array_equal(np.isnan(dem.heights), np.isnan(reference))
    assert np.allclose(dem.heights, reference.astype(np.float32), equal_nan=True)
    assert np.allclose(sorted_heights, reference, equal_nan=True)
    print(f"  reference (Python loop)          {reference_time * 1000:9.1f} ms")
    print(f"  points_to_dem (np.maximum.at)    {ours_time * 1000:9.1f} ms   {reference_time / ours_time:7.1f}x faster")
    print(f"  sort + reduceat (not taken)      {sort_time * 1000:9.1f} ms   {reference_time / sort_time:7.1f}x faster"
          f"   ({sort_time / ours_time:.1f}x slower than ours)")

    # The rest of the chain on this grid: holes of every size.
    holes = dem.heights.copy()
    holes[rng.random(SPEC.shape) < 0.05] = np.nan
    holes[400:600, 400:600] = np.nan
    fill_time, filled = best_of(args.repeats, D.fill_small_holes, D.Dem(SPEC, holes, dem.counts), 3.0)
    print(f"  fill_small_holes (1000 x 1000)   {fill_time * 1000:9.1f} ms   "
          f"({np.isnan(holes).sum() - np.isnan(filled.heights).sum()} cells filled, big hole left)")

    # Artifact filter on an organized SR4000 frame (176 x 144).
    v, u = np.mgrid[0:144, 0:176]
    frame = np.stack([(u - 88) / 200, (v - 72) / 200, np.ones(u.shape)], axis=-1) * 3.0
    blob_time, _ = best_of(args.repeats * 20, D.isolated_blobs, frame, 256, 0.05)
    print(f"  isolated_blobs (176 x 144)       {blob_time * 1000:9.2f} ms")


if __name__ == "__main__":
    main()
