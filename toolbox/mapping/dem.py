"""Digital elevation models by direct reconstruction (thesis 3.3.3, 5.2.2) and their clean-up.

A DEM is a height per GridSpec cell (world frame, z up, metres; float32, NaN where nothing was seen)
with the number of points that fell into each cell. The chain for one view, in order:

    points = view_points(points_camera, valid, camera_to_world)   # drop TOF artifacts, to world
    points = remove_rover_body(points, footprint)                  # the rover sees itself
    dem = points_to_dem(points, spec)                              # the highest point wins per cell
    dem = fill_small_holes(dem, max_reach_cells)                   # small gaps only; unseen stays NaN

and `mosaic` merges the DEMs of several views onto one grid. Interpolated cells keep count 0, so a
later step can always tell measured from filled.

Why the highest point wins: within one view several points fall into one cell where the surface is
steep (a rock's face) or where a near surface overhangs a far one (thesis figs. 43-44); the top is
what a wheel meets, so taking it keeps obstacles at their full height.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from scipy import ndimage

from toolbox.geometry import apply
from toolbox.grid import GridSpec

# A cell boundary within this fraction of a cell counts as exact when DEMs are aligned for a mosaic.
ALIGNMENT_TOLERANCE = 1e-6
EIGHT_NEIGHBOURS = np.ones((3, 3), dtype=bool)
# points_to_dem grids clouds of at least this many points with the compiled kernel: a TOF frame
# (176 x 144 = 25 344 pixels) stays in numpy, where it takes about a millisecond.
COMPILED_MIN_POINTS = 100_000


@dataclass(frozen=True)
class Dem:
    """Heights (float32, NaN: unknown) and points per cell (int32; 0 where filled or unknown) on a grid."""

    spec: GridSpec
    heights: np.ndarray
    counts: np.ndarray

    def __post_init__(self) -> None:
        for name in ("heights", "counts"):
            if getattr(self, name).shape != self.spec.shape:
                raise ValueError(f"{name} is {getattr(self, name).shape}, the grid is {self.spec.shape}")


@dataclass(frozen=True)
class DemConfig:
    """The clean-up parameters of the DEM chain, with the reasons for their defaults.

    max_reach_cells: a hole is filled only if every cell of it lies within this many cells of a
        measured one (so holes up to about twice as wide); 3 cells bridge the gaps a TOF camera's
        pixel footprint leaves between its points at a few metres, not the shadow behind a rock.
    max_blob_pixels: connected groups of at most this many pixels that the range image separates
        from everything around them are artifacts (thesis 5.2.3): 1 % of the SR4000's 176 x 144, a
        blob about 20 cm across at 3 m. On simulated rocky and cratered panoramas the filter takes 0.03 % of
        the real pixels (small patches seen past a crest), the same from 64 to 1024 pixels.
    max_relative_jump: neighbouring pixels belong to one surface while their ranges differ by less
        than this fraction: 5 % keeps ground seen at grazing angles down to about 5 degrees together
        (SR4000, 0.25 degree pixels) and cuts a blob hanging 10 cm above the ground 2 m away loose.
    body_margin: metres added around the rover footprint before removing points in it (cables,
        wheels, calibration error).
    """

    max_reach_cells: float = 3.0
    max_blob_pixels: int = 256
    max_relative_jump: float = 0.05
    body_margin: float = 0.05


# ---------------------------------------------------------------------------------- the chain
def view_points(points_camera: np.ndarray, valid: np.ndarray | None, camera_to_world: np.ndarray,
                config: DemConfig = DemConfig()) -> np.ndarray:
    """World points (N, 3) of one organized view (H, W, 3 in the camera frame), artifacts removed.

    `valid` marks the pixels the sensor trusts (confidence, saturation); None: every finite point."""
    points_camera = np.asarray(points_camera, dtype=np.float64)
    keep = np.isfinite(points_camera).all(axis=-1)
    if valid is not None:
        keep &= valid
    # Artifacts: small groups cut off from their surroundings by range jumps (thesis 5.2.3).
    keep &= ~isolated_blobs(np.where(keep[..., None], points_camera, np.nan), config.max_blob_pixels,
                            config.max_relative_jump)
    # Into the world frame.
    return apply(camera_to_world, points_camera[keep])


def dem_from_points(points: np.ndarray, spec: GridSpec, footprint: np.ndarray | None = None,
                    config: DemConfig = DemConfig()) -> Dem:
    """A DEM from world points: the rover body removed, direct reconstruction, small holes filled."""
    if footprint is not None:
        points = remove_rover_body(points, footprint, config.body_margin)
    dem = points_to_dem(points, spec)
    return fill_small_holes(dem, config.max_reach_cells)


# ---------------------------------------------------------------------------------- direct reconstruction
def grid_covering(points: np.ndarray, cell: float, margin: float = 0.0) -> GridSpec:
    """The smallest grid aligned to multiples of `cell` holding every finite point, plus `margin` metres."""
    points = np.asarray(points, dtype=np.float64)
    finite = points[np.isfinite(points).all(axis=1)]
    if len(finite) == 0:
        raise ValueError("no finite points to cover")
    low = finite[:, :2].min(axis=0) - margin
    # A point exactly on the far boundary belongs to the next cell: nudge so that cell is included.
    high = finite[:, :2].max(axis=0) + margin + cell * 1e-6
    return GridSpec.covering((low[0], high[0]), (low[1], high[1]), cell)


def points_to_dem(points: np.ndarray, spec: GridSpec, top_band: float = 0.0) -> Dem:
    """Direct reconstruction: each point falls into its cell; the highest point of a cell is its height.

    `top_band` > 0 (metres): a cell's height is instead the mean of its points within `top_band` of
    its highest. The highest of n noisy points on flat ground reads high by about the noise times
    the expected maximum of n normal samples (+1.9 sigma for 20 points: stereo's bias); the mean of
    the top band is nearly unbiased there, while on a rock's edge, where a cell holds the rock's top
    and the ground below it, the band holds only the top, so obstacles keep their height.

    Large clouds go through a compiled two-pass kernel (toolbox/mapping/_dem_kernel.py, numba): on
    1 M points into 1000 x 1000 cells it runs in about the time of a bare np.maximum.at on the
    precomputed cell index alone (tests/bench/bench_dem.py measures both in one run); the numpy
    chain below (cell index, np.maximum.at, bincount) took about six times that. Small clouds (a TOF
    frame) stay in numpy, so a server that never grids a panorama never loads numba. Both give the
    same heights and counts to the bit (tests/toolbox/test_toolbox_dem.py)."""
    if not top_band >= 0:
        raise ValueError(f"top_band {top_band!r}: a height band in metres, 0 or more")
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(points) >= COMPILED_MIN_POINTS:
        from toolbox.mapping import _dem_kernel
        heights, counts = _dem_kernel.points_to_dem_arrays(np.ascontiguousarray(points), spec.origin_x,
                                                           spec.origin_y, spec.cell, spec.rows, spec.cols,
                                                           float(top_band))
        return Dem(spec, heights.reshape(spec.shape), counts.reshape(spec.shape))
    return _points_to_dem_numpy(points, spec, top_band)


def _points_to_dem_numpy(points: np.ndarray, spec: GridSpec, top_band: float = 0.0) -> Dem:
    # GridSpec.cell_of's arithmetic, without its floor: inside the grid truncation is the floor, and
    # NaN coordinates fail the comparisons (filtering non-finite rows first would double the time).
    col = (points[:, 0] - spec.origin_x) / spec.cell
    row = (points[:, 1] - spec.origin_y) / spec.cell
    inside = (col >= 0) & (col < spec.cols) & (row >= 0) & (row < spec.rows) & np.isfinite(points[:, 2])
    flat = row[inside].astype(np.int64) * spec.cols + col[inside].astype(np.int64)
    heights = np.full(spec.rows * spec.cols, -np.inf)
    np.maximum.at(heights, flat, points[inside, 2])
    counts = np.bincount(flat, minlength=spec.rows * spec.cols).astype(np.int32)
    heights[counts == 0] = np.nan
    if top_band > 0:
        heights = _top_band_means(flat, points[inside, 2].astype(np.float32), heights.astype(np.float32), top_band)
    return Dem(spec, heights.astype(np.float32).reshape(spec.shape), counts.reshape(spec.shape))


def _top_band_means(flat: np.ndarray, z32: np.ndarray, highest: np.ndarray, top_band: float) -> np.ndarray:
    """Per cell, the mean (float64 sums) of its float32 heights within `top_band` of its highest."""
    band = z32 >= highest[flat] - np.float32(top_band)
    sums = np.bincount(flat[band], weights=z32[band], minlength=len(highest))
    members = np.bincount(flat[band], minlength=len(highest))
    means = np.full(len(highest), np.nan)
    np.divide(sums, members, out=means, where=members > 0)
    return means


# ---------------------------------------------------------------------------------- hole filling
def fillable_holes(heights: np.ndarray, max_reach_cells: float) -> np.ndarray:
    """Unknown cells that belong to small holes: connected unknown areas not touching the grid's edge
    (data all round: interpolation, not extrapolation) whose every cell lies within max_reach_cells
    of a known cell (the inscribed radius bounds the gap, whatever the hole's length)."""
    unknown = np.isnan(heights)
    labels, count = ndimage.label(unknown, structure=EIGHT_NEIGHBOURS)
    if count == 0:
        return np.zeros_like(unknown)
    distance = cv2.distanceTransform(unknown.astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    reach = np.zeros(count + 1)
    np.maximum.at(reach, labels[unknown], distance[unknown])
    small = reach <= max_reach_cells
    edge = np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]])
    small[edge] = False
    small[0] = False
    return small[labels]


def fill_small_holes(dem: Dem, max_reach_cells: float) -> Dem:
    """Fill the fillable holes from their rim inwards, each ring by the mean of its known neighbours.

    Ring by ring rather than one global interpolation: cost is a few 3x3 box filters per ring, and
    nothing beyond the holes is touched. Filled cells keep count 0."""
    holes = fillable_holes(dem.heights, max_reach_cells)
    if not holes.any():
        return dem
    heights = dem.heights.astype(np.float64)
    known = np.isfinite(heights)
    for _ in range(int(np.ceil(max_reach_cells)) + 1):
        if not (holes & ~known).any():
            break
        values = np.where(known, heights, 0.0)
        weight = known.astype(np.float64)
        total = cv2.boxFilter(values, -1, (3, 3), normalize=False, borderType=cv2.BORDER_CONSTANT)
        neighbours = cv2.boxFilter(weight, -1, (3, 3), normalize=False, borderType=cv2.BORDER_CONSTANT)
        ring = holes & ~known & (neighbours > 0)
        heights[ring] = total[ring] / neighbours[ring]
        known |= ring
    return Dem(dem.spec, heights.astype(np.float32), dem.counts)


# ---------------------------------------------------------------------------------- rover body
def inside_polygon(xy: np.ndarray, polygon: np.ndarray) -> np.ndarray:
    """True for points (N, 2) inside a simple polygon (M, 2) (even-odd rule, any orientation)."""
    xy = np.asarray(xy, dtype=np.float64)
    polygon = np.asarray(polygon, dtype=np.float64)
    x, y = xy[:, 0], xy[:, 1]
    inside = np.zeros(len(xy), dtype=bool)
    for (x0, y0), (x1, y1) in zip(polygon, np.roll(polygon, -1, axis=0), strict=True):
        crosses = (y0 > y) != (y1 > y)
        with np.errstate(divide="ignore", invalid="ignore"):
            x_cross = x0 + (y - y0) * (x1 - x0) / (y1 - y0)
        inside ^= crosses & (x < x_cross)
    return inside


def remove_rover_body(points: np.ndarray, footprint: np.ndarray, margin: float = 0.0) -> np.ndarray:
    """Points whose (x, y) lie outside the rover's footprint polygon (world frame), grown by margin.

    Everything above the footprint is rover (body, mast, wheels) or ground it hides, so no height
    cut is needed."""
    polygon = grow_polygon(np.asarray(footprint, dtype=np.float64), margin)
    return points[~inside_polygon(points[:, :2], polygon)]


def grow_polygon(polygon: np.ndarray, margin: float) -> np.ndarray:
    """A convex polygon grown outwards by `margin`: each vertex moves along the sum of its two edges'
    outward normals, as far as makes both edges move out by exactly `margin`."""
    if margin == 0:
        return polygon
    sign = 1.0 if _signed_area(polygon) > 0 else -1.0
    grown = np.empty_like(polygon)
    for i, vertex in enumerate(polygon):
        before, after = polygon[i - 1], polygon[(i + 1) % len(polygon)]
        normal_in = _outward_normal(before, vertex, sign)
        normal_out = _outward_normal(vertex, after, sign)
        bisector = normal_in + normal_out
        grown[i] = vertex + bisector * margin / (1 + normal_in @ normal_out)
    return grown


def _signed_area(polygon: np.ndarray) -> float:
    x, y = polygon[:, 0], polygon[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def _outward_normal(a: np.ndarray, b: np.ndarray, sign: float) -> np.ndarray:
    edge = (b - a) / np.linalg.norm(b - a)
    return sign * np.array([edge[1], -edge[0]])


# ---------------------------------------------------------------------------------- artifacts
def isolated_blobs(points_camera: np.ndarray, max_blob_pixels: int, max_relative_jump: float) -> np.ndarray:
    """True for the pixels of small groups that range jumps cut off from everything around them.

    Works on the organized cloud (H, W, 3, camera frame, NaN: no point), where such groups are easy
    to see: neighbouring pixels on one surface have ranges within max_relative_jump of each other,
    whatever the range; flying pixels, multipath patches and other TOF artifacts hang in front of or
    behind their surroundings, a jump away on every side. A real rock is joined to the ground along
    its base (the range runs on continuously from ground to rock face), so it is kept at any size.
    This is cv2.filterSpeckles on the log of the range: there a fixed difference is a relative jump.
    It is not a flying-pixel filter: a trail of mixed pixels along a depth edge runs on from the
    foreground to the background and stays; the sensor's confidence, low on mixed pixels, is the
    filter for those (the `valid` mask of view_points)."""
    ranges = np.linalg.norm(np.asarray(points_camera, dtype=np.float64), axis=-1)
    valid = np.isfinite(ranges) & (ranges > 0)
    scale = 1000.0   # log-range units per 1: 0.1 % range resolution, well inside int16
    invalid = np.iinfo(np.int16).min
    log_range = np.full(ranges.shape, invalid, dtype=np.int16)
    log_range[valid] = np.clip(np.round(np.log(ranges[valid]) * scale), invalid + 1, np.iinfo(np.int16).max)
    filtered, _ = cv2.filterSpeckles(log_range.copy(), invalid, int(max_blob_pixels),
                                     int(round(np.log1p(max_relative_jump) * scale)))
    return valid & (filtered == invalid)


# ---------------------------------------------------------------------------------- mosaic
def mosaic(dems: Sequence[Dem], spec: GridSpec | None = None) -> Dem:
    """Several DEMs merged cell for cell onto one grid (default: the grid covering them all).

    Where more than one DEM has a cell, the one with the most points in that cell wins (ties: the
    higher). The point count is how closely and squarely the cell was seen (density falls with
    range squared and with grazing incidence), and TOF and stereo errors grow the same way, so the
    densest view is the most accurate; a plain max would let any view's noise or mixed pixels win
    everywhere and bias the ground upwards. Measured cells (count > 0) always beat filled ones.
    The grids must share the cell size and be aligned to it (GridSpec.covering does that)."""
    if not dems:
        raise ValueError("no DEMs to merge")
    spec = spec or union_spec([dem.spec for dem in dems])
    heights = np.full(spec.shape, np.nan, dtype=np.float32)
    counts = np.zeros(spec.shape, dtype=np.int32)
    for dem in dems:
        target, source = _overlap_slices(dem.spec, spec)
        if target is None:
            continue
        new_h, new_c = dem.heights[source], dem.counts[source]
        old_h, old_c = heights[target], counts[target]
        wins = np.isfinite(new_h) & ((new_c > old_c) | ((new_c == old_c) & ~(new_h <= old_h)))
        old_h[wins], old_c[wins] = new_h[wins], new_c[wins]
    return Dem(spec, heights, counts)


def union_spec(specs: Sequence[GridSpec]) -> GridSpec:
    """The grid covering several grids of one cell size (aligned to it, as GridSpec.covering makes them)."""
    cell = specs[0].cell
    x_low = min(s.x_range[0] for s in specs)
    y_low = min(s.y_range[0] for s in specs)
    x_high = max(s.x_range[1] for s in specs)
    y_high = max(s.y_range[1] for s in specs)
    return GridSpec.covering((x_low, x_high), (y_low, y_high), cell)


def _overlap_slices(source: GridSpec, target: GridSpec) -> tuple[Any, Any]:
    """Slices (target, source) of the cells two aligned grids share; (None, None) if none."""
    if abs(source.cell - target.cell) > ALIGNMENT_TOLERANCE * target.cell:
        raise ValueError(f"cannot merge a {source.cell} m grid onto a {target.cell} m grid")
    col_offset = (source.origin_x - target.origin_x) / target.cell
    row_offset = (source.origin_y - target.origin_y) / target.cell
    if max(abs(col_offset - round(col_offset)), abs(row_offset - round(row_offset))) > ALIGNMENT_TOLERANCE:
        raise ValueError("grids are not aligned to the cell size; build them with GridSpec.covering")
    col_offset, row_offset = int(round(col_offset)), int(round(row_offset))
    rows = _shared_range(row_offset, source.rows, target.rows)
    cols = _shared_range(col_offset, source.cols, target.cols)
    if rows is None or cols is None:
        return None, None
    (t_r0, t_r1), (t_c0, t_c1) = rows, cols
    target_slices = (slice(t_r0, t_r1), slice(t_c0, t_c1))
    source_slices = (slice(t_r0 - row_offset, t_r1 - row_offset), slice(t_c0 - col_offset, t_c1 - col_offset))
    return target_slices, source_slices


def _shared_range(offset: int, source_count: int, target_count: int) -> tuple[int, int] | None:
    start, stop = max(0, offset), min(target_count, offset + source_count)
    return (start, stop) if stop > start else None
