"""Hazard maps from a DEM: slope, step and roughness (the thesis' RSS maps, 3.1.6 and 5.3).

    step = step_height(heights, cell, ...)                       # height above the ground around
    step = agreed_step(step, cell, ...)                          # only where enough cells agree
    slope, roughness = plane_fit(ground, cell, plane_radius)    # regression plane per cell, steps left out
    code = hazard_code(heights, slope, step, roughness, config)  # thresholds -> uint8 codes

Windows are squares of (2k + 1) x (2k + 1) cells, k = round(radius / cell): "within `radius`" in
each axis. Every measure is NaN-aware: unknown cells take no part in any window, and a cell without
data has no measure (NaN). How they are computed, for speed (issue 26: within 10 times of five box
filters over the grid; tests/bench/bench_hazard.py): the plane fit from running window sums of its
moments (box filters in numpy below COMPILED_MIN_CELLS, one compiled pass above:
_hazard_kernel.py), the step as grey-level morphology (cv2.erode / cv2.dilate in float32 where
float32 holds the heights, as for every Dem, else an exact float64 doubling). Results are those of
the per-cell definitions within float rounding: tests/toolbox/test_toolbox_hazard.py holds them to
the implementation before issue 26 on random DEMs with holes and on a simulated one.

Hazard codes (uint8), one per cell:
    0     SAFE: every measure known and within its limit
    255   UNKNOWN: no height, or a measure unknown and none over its limit
    else  HAZARD (bit 0 set) with one bit per cause: 2 slope, 4 step, 8 roughness;
          e.g. 5 = hazard by step, 7 = by slope and step.
`is_hazard(code)` is (code & 1) on cells that are not 255. Unknown is never safe: the planner
decides what to do with it.

Default limits, for the test bed's rover (Pioneer 3-AT: about 0.55 x 0.50 m, wheels of 0.11 m
radius on a 0.40 m track, mast and PTU raising the centre of mass):
- step 0.10 m: a wheel climbs about its radius (0.11 m), so a 0.5 m rover's clearance for steps
  is about 0.1 m. Edge window radius 0.10 m (the wheel's reach, as ETH's 0.08 m first window),
  counted only where at least 5 cells exceed it (ETH's nCellCritical 5) so a lone noisy cell or a
  surviving flying pixel is no step. Ground plate 0.5 m half-size (1 m square, twice the rover's
  width): rocks up to 1 m across, the largest the simulator places, are flagged over their whole
  top, not only along their rims (on the simulated scene of tests/toolbox/test_toolbox_hazard.py this
  lifts the step recall of obstacle cells from 0.68 with a 0.25 m plate to 0.97), while on
  terrain that curves over metres the plate sits within a centimetre of the crest (it lowers a
  crest of curvature c by c r^2).
- slope 20 degrees over a 0.25 m radius: GESTALT (MER, thesis 2.1.2) fits its plane over a
  rover-sized patch, and a 0.5 m patch is this rover's size. The static sideways tip-over angle is
  atan(0.20 m half-track / 0.40 m centre of mass, assumed) = 27 degrees; 20 keeps a margin for loose
  ground and motion. (ETH's legged robots allow 35 degrees; a high-mast wheeled rover cannot.)
- roughness 0.04 m RMS about the same plane: four times the SR4000's range noise (about 1 cm at a
  few metres), so noise never trips it (thesis 5.3: thresholds tuned not to react to noise), yet a
  field of stones a little below the step limit, which the step filter lets through, is caught.
  (ETH: 0.02 m over 0.05 m, for a legged robot's foot.)
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

SAFE = 0
HAZARD = 1
SLOPE = 2
STEP = 4
ROUGHNESS = 8
UNKNOWN = 255

# A plane needs three cells; six leave three degrees of freedom for the roughness estimate.
MIN_FIT_CELLS = 6
# plane_fit runs the compiled kernel (toolbox/mapping/_hazard_kernel.py, numba) on grids of at least
# this many cells; smaller ones (a corridor, a test) stay in numpy and OpenCV and never load numba.
COMPILED_MIN_CELLS = 100_000


@dataclass(frozen=True)
class HazardConfig:
    slope_limit_deg: float = 20.0
    plane_radius: float = 0.25
    roughness_limit: float = 0.04
    step_limit: float = 0.10
    step_radius: float = 0.10
    ground_radius: float = 0.5
    step_min_cells: int = 5


@dataclass(frozen=True)
class HazardMaps:
    """The RSS maps (float32, NaN where unknown) and the hazard code map (uint8, see module doc)."""

    slope_deg: np.ndarray
    step: np.ndarray
    roughness: np.ndarray
    code: np.ndarray


def hazard_maps(heights: np.ndarray, cell: float, config: HazardConfig = HazardConfig()) -> HazardMaps:
    """Slope, step, roughness and hazard codes of a DEM (rows northwards, NaN: unknown)."""
    given = np.asarray(heights)
    heights = given.astype(np.float64)
    # A Dem's float32 heights need no check that float32 holds them (step_height's fast morphology).
    single = given if given.dtype == np.float32 else None
    step = step_height(heights, cell, config.step_radius, config.ground_radius, single=single)
    step = agreed_step(step, cell, config.step_radius, config.step_limit, config.step_min_cells)
    # Slope and roughness are the ground's: cells that are already a step hazard (rocks) take no
    # part in the plane fit. Otherwise every rock spreads a ring of false slope and roughness
    # hazards a plane window wide around itself, which the planner's clearance then grows again:
    # on 15-20 % rock cover that ring held half the mapped hazards and closed open passages.
    ground = np.where(_over(step, config.step_limit), np.nan, heights)
    slope, roughness = plane_fit(ground, cell, config.plane_radius)
    code = hazard_code(heights, slope, step, roughness, config)
    return HazardMaps(slope.astype(np.float32), step.astype(np.float32), roughness.astype(np.float32), code)


def _over(step: np.ndarray, limit: float) -> np.ndarray:
    """np.nan_to_num(step, nan=0.0) > limit, without the copy: NaN compares False."""
    over = step > limit
    return over | np.isnan(step) if limit < 0 else over


def is_hazard(code: np.ndarray) -> np.ndarray:
    code = np.asarray(code)
    return (code != UNKNOWN) & ((code & HAZARD) != 0)


def half_width(radius: float, cell: float) -> int:
    """Half the side, in cells, of the square window for `radius` (at least one cell)."""
    if not cell > 0 or not radius >= 0:
        raise ValueError(f"need cell > 0 and radius >= 0, got cell {cell!r}, radius {radius!r}")
    return max(1, int(round(radius / cell)))


# ---------------------------------------------------------------------------------- window sums
def window_sum(image: np.ndarray, k: int) -> np.ndarray:
    """Sum over the (2k + 1)^2 window around each cell, zeros beyond the grid (float64 in, float64 out).

    cv2.boxFilter's running sums: exact on integer-valued images (a mask and its coordinate moments
    stay far below 2^53), and on heights within a few ulps of the direct sum."""
    return cv2.boxFilter(image, cv2.CV_64F, (2 * k + 1, 2 * k + 1), normalize=False, borderType=cv2.BORDER_CONSTANT)


def running_extreme(image: np.ndarray, k: int, axis: int, minimum: bool) -> np.ndarray:
    """Minimum (or maximum) over the 2k + 1 cells around each cell along one axis, +inf (-inf) beyond
    the grid: cv2.erode / cv2.dilate of a (2k + 1) line with a constant border, to the bit, in float64.

    Van Herk-style doubling: the extreme over half-width s + d is the extreme of two half-width s
    windows d cells either side (d <= s), so half-width k takes about log2(k) + 2 np.minimum passes
    instead of 2k comparisons per cell (OpenCV has no SIMD morphology for float64)."""
    op = np.minimum if minimum else np.maximum
    pad = [(0, 0)] * image.ndim
    pad[axis] = (k, k)
    current = np.pad(image, pad, constant_values=np.inf if minimum else -np.inf)

    def cut(array: np.ndarray, start: int, stop: int) -> np.ndarray:
        index = [slice(None)] * array.ndim
        index[axis] = slice(start, array.shape[axis] + stop if stop <= 0 else stop)
        return array[tuple(index)]

    if k == 0:
        return image.copy()
    current = op(op(cut(current, 0, -2), cut(current, 1, -1)), cut(current, 2, 0))   # half-width 1
    half = 1
    while half < k:
        d = min(half, k - half)
        current = op(cut(current, 0, -2 * d), cut(current, 2 * d, 0))
        half += d
    return current


def box_extreme(image: np.ndarray, k: int, minimum: bool) -> np.ndarray:
    """Grey-level erosion (minimum) or dilation (maximum) with a flat (2k + 1)^2 square, constant border
    (+inf for the minimum, -inf for the maximum), float64 to the bit.

    Heights that float32 holds exactly (every Dem's: Dem.heights is float32) go through cv2.erode /
    cv2.dilate in float32, which has SIMD: a minimum or maximum only picks values, so the result is the
    same. Others take the float64 doubling of running_extreme."""
    image = np.asarray(image, dtype=np.float64)
    single = image.astype(np.float32)
    if np.count_nonzero(single != image) == np.count_nonzero(np.isnan(image)):
        kernel = cv2.getStructuringElement(cv2.MORPH_RECT, (2 * k + 1, 2 * k + 1))
        morph = cv2.erode if minimum else cv2.dilate
        return morph(single, kernel, borderType=cv2.BORDER_CONSTANT,
                     borderValue=np.inf if minimum else -np.inf).astype(np.float64)
    return running_extreme(running_extreme(image, k, 1, minimum), k, 0, minimum)


# ---------------------------------------------------------------------------------- plane fit
def plane_fit(heights: np.ndarray, cell: float, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """(slope in degrees, roughness in metres) of the regression plane z = a x + b y + c fitted to
    the known cells within `radius` of each cell (least squares in z, as the thesis' regression plane).

    Roughness is the RMS residual with three degrees of freedom removed (sqrt(SS / (n - 3))), so on a
    noisy plane it estimates the noise sigma. The normal equations are the window's centred second
    moments, which do not depend on where the coordinates start: each comes from box filters of the
    known mask times 1, x, y, x^2, y^2, xy and of the heights times 1, z, x, y (x, y in cells from the
    grid's middle), ten float64 box filters in all. The mask's moments are integers and come out exact;
    heights are taken relative to the map's median so no precision is lost to large map heights.
    NaN where the cell is unknown, fewer than MIN_FIT_CELLS cells are known, or they lie on a line."""
    z = np.asarray(heights, dtype=np.float64)
    known = np.isfinite(z)
    if not known.any():
        return np.full(z.shape, np.nan), np.full(z.shape, np.nan)
    k = half_width(radius, cell)
    centre = _centre(z, known)
    if z.size >= COMPILED_MIN_CELLS:
        from toolbox.mapping import _hazard_kernel
        slope, roughness = np.empty(z.shape), np.empty(z.shape)
        _hazard_kernel.plane_fit_cells(z, known, centre, k, MIN_FIT_CELLS, slope, roughness)
        np.divide(slope, cell, out=slope)                      # the kernel's gradient is per cell
        return np.degrees(np.arctan(slope, out=slope), out=slope), roughness
    slope, roughness = np.full(z.shape, np.nan), np.full(z.shape, np.nan)
    x = (np.arange(z.shape[1], dtype=np.float64) - z.shape[1] // 2)[None, :]
    y = (np.arange(z.shape[0], dtype=np.float64) - z.shape[0] // 2)[:, None]
    # Strips of rows, each with k rows of margin either side: the same window sums, but every
    # temporary stays in cache (the whole grid at once spent most of its time on memory).
    for top in range(0, z.shape[0], PLANE_STRIP_ROWS):
        bottom = min(top + PLANE_STRIP_ROWS, z.shape[0])
        low, high = max(0, top - k), min(z.shape[0], bottom + k)
        inner = slice(top - low, bottom - low)
        slope[top:bottom], roughness[top:bottom] = _plane_fit_rows(
            z[low:high], known[low:high], centre, x, y[low:high], k, cell, inner)
    return slope, roughness


# Rows per strip of plane_fit: 64 rows of a 1000-column grid keep the ~20 float64 temporaries in L2/L3.
PLANE_STRIP_ROWS = 64


def _plane_fit_rows(z: np.ndarray, known: np.ndarray, centre: float, x: np.ndarray, y: np.ndarray, k: int,
                    cell: float, inner: Any) -> Any:
    weight = known.astype(np.float64)
    zc = np.where(known, z - centre, 0.0)
    wx, wy = weight * x, weight * y
    n = window_sum(weight, k)[inner]
    sx, sy = window_sum(wx, k)[inner], window_sum(wy, k)[inner]
    sxx, syy, sxy = window_sum(wx * x, k)[inner], window_sum(wy * y, k)[inner], window_sum(wx * y, k)[inner]
    sz, szz = window_sum(zc, k)[inner], window_sum(zc * zc, k)[inner]
    sxz, syz = window_sum(zc * x, k)[inner], window_sum(zc * y, k)[inner]
    with np.errstate(divide="ignore", invalid="ignore"):
        # Centre the sums on the window's mean (eliminates the plane's offset c); cells as units of x, y.
        mx, my = sx / n, sy / n
        cxx, cyy, cxy = sxx - sx * mx, syy - sy * my, sxy - sx * my
        cxz, cyz, czz = sxz - mx * sz, syz - my * sz, szz - sz * sz / n
        det = cxx * cyy - cxy * cxy
        a = (cyy * cxz - cxy * cyz) / det          # metres per cell
        b = (cxx * cyz - cxy * cxz) / det
        residual = np.maximum(czz - a * cxz - b * cyz, 0.0)
        roughness = np.sqrt(residual / (n - 3))
        fit = known[inner] & (n >= MIN_FIT_CELLS - 0.5) & (det > 1e-12 * n * n)
        slope = np.degrees(np.arctan(np.hypot(a, b) / cell))
    return np.where(fit, slope, np.nan), np.where(fit, roughness, np.nan)


def _centre(z: np.ndarray, known: np.ndarray) -> float:
    """A height near the middle of the known ones (the median of at most ~100 000 of them): only for
    precision, any known height would do."""
    sample = z.ravel()[::max(1, z.size // 100_000)]
    sample = sample[np.isfinite(sample)]
    return float(np.median(sample if len(sample) else z[known]))


# ---------------------------------------------------------------------------------- step
def step_height(heights: np.ndarray, cell: float, edge_radius: float, ground_radius: float | None = None,
                single: np.ndarray | None = None) -> np.ndarray:
    """How far each cell stands above the ground around it (metres, >= 0; NaN where unknown).

    The larger of
    - its deviation from the local minimum within edge_radius (the thesis' step map, ETH's first
      window): steps up and down at edges, the drop into a hole included; and, if ground_radius,
    - its protrusion above the ground a flat plate of that half-size rests on from below
      (z - morphological opening): whole rocks up to the plate's size, not only their rims; zero on
      any plane however inclined and in any hollow, so slopes never read as steps. On a slope the
      plate under a rock rests on the ground's low side, so the rock reads a little taller than it
      is (by 0.03 m for a 0.4 m rock on 10 degrees): an error on the safe side.

    `single`: the same heights as float32, if the caller has them (hazard_maps with a Dem's)."""
    z = np.asarray(heights, dtype=np.float64)
    known = np.isfinite(z)
    if single is None:
        single = z.astype(np.float32)
        if np.count_nonzero(single != z) != np.count_nonzero(np.isnan(z)):   # float32 cannot hold them
            single = None
    if single is not None:
        # Every Dem's heights: the same minima and maxima in float32 (see box_extreme), one conversion.
        return _step_height_single(z, single, known, half_width(edge_radius, cell),
                                   half_width(ground_radius, cell) if ground_radius else 0)
    step = z - local_minimum(z, half_width(edge_radius, cell))
    if ground_radius:
        step = np.maximum(step, z - ground_surface(z, half_width(ground_radius, cell)))
    return np.where(known, step, np.nan)


def _step_height_single(z: np.ndarray, single: np.ndarray, known: np.ndarray, k_edge: int,
                        k_ground: int) -> np.ndarray:
    """step_height's local_minimum and ground_surface with cv2 in float32 (the values float32 holds)."""
    def square(k: int) -> np.ndarray:
        return cv2.getStructuringElement(cv2.MORPH_RECT, (2 * k + 1, 2 * k + 1))

    low = np.where(known, single, np.float32(np.inf))
    step = z - cv2.erode(low, square(k_edge), borderType=cv2.BORDER_CONSTANT, borderValue=np.inf)
    if k_ground:
        k = k_ground
        padded = cv2.copyMakeBorder(low, k, k, k, k, cv2.BORDER_CONSTANT, value=np.inf)
        eroded = cv2.erode(padded, square(k), borderType=cv2.BORDER_CONSTANT, borderValue=np.inf)
        np.putmask(eroded, eroded == np.inf, np.float32(-np.inf))
        opened = cv2.dilate(eroded, square(k), borderType=cv2.BORDER_CONSTANT, borderValue=-np.inf)
        step = np.maximum(step, z - opened[k:-k, k:-k])
    return np.where(known, step, np.nan)


def local_minimum(z: np.ndarray, k: int) -> np.ndarray:
    """Minimum of the known heights in the (2k + 1)^2 window (+inf where none)."""
    return box_extreme(np.where(np.isfinite(z), z, np.inf), k, minimum=True)


def ground_surface(z: np.ndarray, k: int) -> np.ndarray:
    """Morphological opening of the known heights with a flat (2k + 1)^2 plate: the highest a plate
    pushed up from below can reach at each cell without any known cell poking through it."""
    # Beyond the grid is unknown like any unseen cell: the plate may hang over it, resting on known
    # cells only (else a plane would read as a step along the grid's uphill edges).
    padded = np.pad(z, k, constant_values=np.nan)
    eroded = local_minimum(padded, k)
    eroded[np.isinf(eroded)] = -np.inf
    opened = box_extreme(eroded, k, minimum=False)
    return opened[k:-k, k:-k]


def agreed_step(step: np.ndarray, cell: float, radius: float, limit: float, min_cells: int) -> np.ndarray:
    """Step scaled by min(1, m / min_cells), m the number of cells within `radius` whose step is over
    `limit` (ETH's StepFilter rule, applied to the cell's own step): a step seen by too few cells,
    a noisy cell or a residual flying pixel, is shrunk below the limit unless it is enormous."""
    k = half_width(radius, cell)
    over = _over(step, limit).astype(np.float32)                        # counts: exact in float32
    agreeing = cv2.boxFilter(over, -1, (2 * k + 1, 2 * k + 1), normalize=False, borderType=cv2.BORDER_CONSTANT)
    # min(1, m / min_cells) for every possible count m, looked up: the same float64 values, fewer passes.
    scale = np.minimum(1.0, np.arange((2 * k + 1) ** 2 + 1) / min_cells)
    return step * scale[agreeing.astype(np.intp)]


# ---------------------------------------------------------------------------------- codes
def hazard_code(heights: np.ndarray, slope_deg: np.ndarray, step: np.ndarray, roughness: np.ndarray,
                config: HazardConfig) -> np.ndarray:
    """uint8 hazard codes from the three measures and their limits (see the module doc)."""
    # Each comparison's bool bytes shifted to its bit (NaN compares False, as no cause).
    causes = ((slope_deg > config.slope_limit_deg).view(np.uint8) << np.uint8(1)) \
        | ((step > config.step_limit).view(np.uint8) << np.uint8(2)) \
        | ((roughness > config.roughness_limit).view(np.uint8) << np.uint8(3))
    code = causes | (causes != 0).view(np.uint8)
    measured = np.isfinite(slope_deg) & np.isfinite(step) & np.isfinite(roughness)
    np.putmask(code, ~np.isfinite(heights) | ((causes == 0) & ~measured), UNKNOWN)
    return code
