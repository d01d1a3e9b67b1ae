"""The compiled gridding kernel of dem.points_to_dem (numba), imported only when a cloud is large.

Importing numba costs about 110 MB and its first compilation about a second (cached on disk after),
so dem.py loads this module only for clouds where it pays (a full panorama, not one TOF frame).
Two passes, each a plain loop: the first computes every point's cell (vectorised by LLVM; the same
division and truncation as GridSpec.cell_of, so the same cell to the bit) and its height in float32;
the second keeps the highest and counts, one read-modify-write per point. Fusing them into one loop
measured two to three times slower (the scatter stops the first loop's vectorisation).
Taking the maximum in float32 is exact: rounding to float32 is monotonic, so the float32 of the
highest point is the highest of the float32 points, which is what Dem.heights stores anyway.
"""
from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, nogil=True, boundscheck=False)
def cells_and_heights(points: np.ndarray, origin_x: float, origin_y: float, cell: float, rows: int, cols: int,
                      flat: np.ndarray, heights32: np.ndarray) -> None:
    """flat[i]: the flat cell index of point i (-1 outside the grid or z not finite); heights32[i]: its z."""
    for i in range(points.shape[0]):
        col = (points[i, 0] - origin_x) / cell
        row = (points[i, 1] - origin_y) / cell
        z = points[i, 2]
        inside = col >= 0 and col < cols and row >= 0 and row < rows and np.isfinite(z)
        flat[i] = np.int64(row) * cols + np.int64(col) if inside else -1
        heights32[i] = np.float32(z)


@numba.njit(cache=True, nogil=True, boundscheck=False)
def highest_and_count(flat: np.ndarray, heights32: np.ndarray, heights: np.ndarray, counts: np.ndarray) -> None:
    """heights (-inf on entry) takes each cell's highest point, NaN where none; counts (0 on entry) its points."""
    for i in range(flat.shape[0]):
        f = flat[i]
        if f >= 0:
            heights[f] = max(heights[f], heights32[i])
            counts[f] += 1
    for f in range(heights.shape[0]):
        if counts[f] == 0:
            heights[f] = np.nan


@numba.njit(cache=True, nogil=True, boundscheck=False)
def top_band_means(flat: np.ndarray, heights32: np.ndarray, top_band: float, heights: np.ndarray) -> None:
    """heights (each cell's highest on entry) takes the mean of the cell's points within top_band of it
    (float64 sums, as dem._top_band_means)."""
    sums = np.zeros(heights.shape[0])
    members = np.zeros(heights.shape[0], np.int64)
    band = np.float32(top_band)
    for i in range(flat.shape[0]):
        f = flat[i]
        if f >= 0 and heights32[i] >= heights[f] - band:
            sums[f] += heights32[i]
            members[f] += 1
    for f in range(heights.shape[0]):
        if members[f] > 0:
            heights[f] = np.float32(sums[f] / members[f])


def points_to_dem_arrays(points: np.ndarray, origin_x: float, origin_y: float, cell: float, rows: int,
                         cols: int, top_band: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """(heights float32 with NaN, counts int32), both flat (rows * cols), of float64 points (N, 3);
    top_band > 0: the mean of each cell's points within top_band of its highest (dem.points_to_dem)."""
    cells = rows * cols
    flat = np.empty(len(points), np.int32 if cells < 2 ** 31 else np.int64)
    heights32 = np.empty(len(points), np.float32)
    cells_and_heights(points, float(origin_x), float(origin_y), float(cell), int(rows), int(cols), flat, heights32)
    heights = np.full(cells, -np.inf, np.float32)
    counts = np.zeros(cells, np.int32)
    highest_and_count(flat, heights32, heights, counts)
    if top_band > 0:
        top_band_means(flat, heights32, top_band, heights)
    return heights, counts
