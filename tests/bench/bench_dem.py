"""Benchmark: direct reconstruction (points to DEM) beside a straightforward reference, same run.

1 million points fall into a 1000 x 1000 grid (2 cm cells over 20 x 20 m). Timed:
- ours: dem.points_to_dem (the compiled two-pass kernel of toolbox/mapping/_dem_kernel.py: cell and
  float32 height per point, then highest and count per cell);
- reference (issue 26): a bare np.maximum.at of the heights on the flat cell index, the index
  computed beforehand and not timed; ours must be no slower (ratio <= 1);
- before: the numpy chain points_to_dem ran until issue 26 (cell index, np.maximum.at, bincount),
  which is still its path for small clouds (dem._points_to_dem_numpy);
- checks: a plain Python loop over the points (the obvious implementation), and the alternative
  measured and not taken, a stable argsort on the flat index + maximum.reduceat;
- the rest of the chain on the same grid: fill_small_holes, and isolated_blobs on an SR4000-sized frame.
Each result is checked against the Python loop before its time is printed. The machine is shared,
so ours, the reference and before are timed in interleaved rounds (each the best of --repeats) and
the ratios printed are the medians over --rounds.

    .venv/bin/python tests/bench/bench_dem.py [--points 1000000] [--repeats 5] [--rounds 7]
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from toolbox.grid import GridSpec  # noqa: E402
from toolbox.mapping import dem as D  # noqa: E402

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


def bare_maximum_at(flat: np.ndarray, z: np.ndarray, cells: int) -> np.ndarray:
    heights = np.full(cells, -np.inf)
    np.maximum.at(heights, flat, z)
    return heights


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--points", type=int, default=1_000_000)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--rounds", type=int, default=7)
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    points = terrain_points(args.points, rng)
    print(f"{args.points} points -> {SPEC.rows} x {SPEC.cols} grid ({SPEC.cell} m cells)")

    reference_time, reference = best_of(1, reference_loop, points, SPEC)
    D.points_to_dem(points[:D.COMPILED_MIN_POINTS], SPEC)          # numba: load and compile (or the cache)
    row, col, inside = SPEC.cell_of(points[:, 0], points[:, 1])
    flat, z = row[inside] * SPEC.cols + col[inside], points[inside, 2]
    ours, bare, before = [], [], []
    for _ in range(args.rounds):
        bare.append(best_of(args.repeats, bare_maximum_at, flat, z, SPEC.rows * SPEC.cols)[0])
        ours_time, dem = best_of(args.repeats, D.points_to_dem, points, SPEC)
        ours.append(ours_time)
        before_time, old = best_of(args.repeats, D._points_to_dem_numpy, points, SPEC)
        before.append(before_time)
    sort_time, sorted_heights = best_of(args.repeats, sort_reduceat, points, SPEC)
    assert np.array_equal(np.isnan(dem.heights), np.isnan(reference))
    assert np.array_equal(dem.heights, reference.astype(np.float32), equal_nan=True)
    assert np.array_equal(dem.counts, old.counts) and np.array_equal(dem.heights, old.heights, equal_nan=True)
    assert np.allclose(sorted_heights, reference, equal_nan=True)
    ratio = np.median(np.array(ours) / np.array(bare))
    before_ratio = np.median(np.array(before) / np.array(bare))
    print(f"  reference (Python loop)          {reference_time * 1000:9.1f} ms")
    print(f"  bare np.maximum.at (reference)   {np.median(bare) * 1000:9.1f} ms   (index precomputed; issue 26)")
    print(f"  points_to_dem (compiled)         {np.median(ours) * 1000:9.1f} ms   {ratio:7.2f}x the bare "
          f"np.maximum.at   {reference_time / np.median(ours):7.1f}x faster than the loop")
    print(f"  before (numpy: index, maximum.at, bincount) {np.median(before) * 1000:6.1f} ms   {before_ratio:7.2f}x "
          f"the bare np.maximum.at")
    print(f"    ratios per round, ours: {' '.join(f'{o / b:.2f}' for o, b in zip(ours, bare, strict=True))}; "
          f"before: {' '.join(f'{o / b:.2f}' for o, b in zip(before, bare, strict=True))}")
    print(f"  sort + reduceat (not taken)      {sort_time * 1000:9.1f} ms   {sort_time / np.median(ours):.1f}x ours")

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
