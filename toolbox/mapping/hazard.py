"""Hazard maps from a DEM: slope, step and roughness (the thesis' RSS maps, 3.1.6 and 5.3).

    step = step_height(heights, cell, ...)                       # height above the ground around
    step = agreed_step(step, cell, ...)                          # only where enough cells agree
    slope, roughness = plane_fit(ground, cell, plane_radius)    # regression plane per cell, steps left out
    code = hazard_code(heights, slope, step, roughness, config)  # thresholds -> uint8 codes

Windows are squares of (2k + 1) x (2k + 1) cells, k = round(radius / cell): "within `radius`" in
each axis. Every measure is computed with box filters or separable correlations over the whole grid
(no per-cell loop), NaN-aware: unknown cells take no part in any window, and a cell without data
has no measure (NaN).

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
    heights = np.asarray(heights, dtype=np.float64)
    step = step_height(heights, cell, config.step_radius, config.ground_radius)
    step = agreed_step(step, cell, config.step_radius, config.step_limit, config.step_min_cells)
    # Slope and roughness are the ground's: cells that are already a step hazard (rocks) take no
    # part in the plane fit. Otherwise every rock spreads a ring of false slope and roughness
    # hazards a plane window wide around itself, which the planner's clearance then grows again:
    # on 15-20 % rock cover that ring held half the mapped hazards and closed open passages.
    ground = np.where(np.nan_to_num(step, nan=0.0) > config.step_limit, np.nan, heights)
    slope, roughness = plane_fit(ground, cell, config.plane_radius)
    code = hazard_code(heights, slope, step, roughness, config)
    return HazardMaps(slope.astype(np.float32), step.astype(np.float32), roughness.astype(np.float32), code)


def is_hazard(code: np.ndarray) -> np.ndarray:
    code = np.asarray(code)
    return (code != UNKNOWN) & ((code & HAZARD) != 0)


def half_width(radius: float, cell: float) -> int:
    """Half the side, in cells, of the square window for `radius` (at least one cell)."""
    if not cell > 0 or not radius >= 0:
        raise ValueError(f"need cell > 0 and radius >= 0, got cell {cell!r}, radius {radius!r}")
    return max(1, int(round(radius / cell)))


# ---------------------------------------------------------------------------------- plane fit
def plane_fit(heights: np.ndarray, cell: float, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """(slope in degrees, roughness in metres) of the regression plane z = a x + b y + c fitted to
    the known cells within `radius` of each cell (least squares in z, as the thesis' regression plane).

    Roughness is the RMS residual with three degrees of freedom removed (sqrt(SS / (n - 3))), so on a
    noisy plane it estimates the noise sigma. The ten sums of the normal equations come from
    separable correlations with the window's own offsets (1, dx, dy, dx^2, dy^2, dx dy), so the
    coordinates are local and no precision is lost to large map coordinates; heights are taken
    relative to the map's median for the same reason. NaN where the cell is unknown, fewer than
    MIN_FIT_CELLS cells are known, or they lie on a line."""
    z = np.asarray(heights, dtype=np.float64)
    known = np.isfinite(z)
    if not known.any():
        nan = np.full(z.shape, np.nan)
        return nan, nan.copy()
    k = half_width(radius, cell)
    ones = np.ones(2 * k + 1)
    offsets = np.arange(-k, k + 1) * cell
    weight = known.astype(np.float64)
    zc = np.where(known, z - np.median(z[known]), 0.0)

    def window_sum(image, along_x, along_y):
        # kernelX runs along columns (x, east), kernelY along rows (y, north); correlation, zeros outside.
        return cv2.sepFilter2D(image, cv2.CV_64F, along_x, along_y, borderType=cv2.BORDER_CONSTANT)

    n = window_sum(weight, ones, ones)
    sx, sy = window_sum(weight, offsets, ones), window_sum(weight, ones, offsets)
    sxx, syy = window_sum(weight, offsets ** 2, ones), window_sum(weight, ones, offsets ** 2)
    sxy = window_sum(weight, offsets, offsets)
    sz, szz = window_sum(zc, ones, ones), window_sum(zc * zc, ones, ones)
    sxz, syz = window_sum(zc, offsets, ones), window_sum(zc, ones, offsets)
    with np.errstate(divide="ignore", invalid="ignore"):
        # Centre the sums on the window's mean (eliminates the plane's offset c).
        cxx, cyy, cxy = sxx - sx * sx / n, syy - sy * sy / n, sxy - sx * sy / n
        cxz, cyz, czz = sxz - sx * sz / n, syz - sy * sz / n, szz - sz * sz / n
        det = cxx * cyy - cxy * cxy
        a = (cyy * cxz - cxy * cyz) / det
        b = (cxx * cyz - cxy * cxz) / det
        residual = np.maximum(czz - a * cxz - b * cyz, 0.0)
        roughness = np.sqrt(residual / (n - 3))
    fit = known & (n >= MIN_FIT_CELLS - 0.5) & (det > 1e-12 * (cell ** 4) * n * n)
    slope = np.where(fit, np.degrees(np.arctan(np.hypot(a, b))), np.nan)
    return slope, np.where(fit, roughness, np.nan)


# ---------------------------------------------------------------------------------- step
def step_height(heights: np.ndarray, cell: float, edge_radius: float, ground_radius: float | None = None) -> np.ndarray:
    """How far each cell stands above the ground around it (metres, >= 0; NaN where unknown).

    The larger of
    - its deviation from the local minimum within edge_radius (the thesis' step map, ETH's first
      window): steps up and down at edges, the drop into a hole included; and, if ground_radius,
    - its protrusion above the ground a flat plate of that half-size rests on from below
      (z - morphological opening): whole rocks up to the plate's size, not only their rims; zero on
      any plane however inclined and in any hollow, so slopes never read as steps. On a slope the
      plate under a rock rests on the ground's low side, so the rock reads a little taller than it
      is (by 0.03 m for a 0.4 m rock on 10 degrees): an error on the safe side."""
    z = np.asarray(heights, dtype=np.float64)
    known = np.isfinite(z)
    step = z - local_minimum(z, half_width(edge_radius, cell))
    if ground_radius:
        step = np.maximum(step, z - ground_surface(z, half_width(ground_radius, cell)))
    return np.where(known, step, np.nan)


def local_minimum(z: np.ndarray, k: int) -> np.ndarray:
    """Minimum of the known heights in the (2k + 1)^2 window (+inf where none)."""
    kernel = np.ones((2 * k + 1, 2 * k + 1), np.uint8)
    return cv2.erode(np.where(np.isfinite(z), z, np.inf), kernel, borderType=cv2.BORDER_CONSTANT,
                     borderValue=np.inf)


def ground_surface(z: np.ndarray, k: int) -> np.ndarray:
    """Morphological opening of the known heights with a flat (2k + 1)^2 plate: the highest a plate
    pushed up from below can reach at each cell without any known cell poking through it."""
    kernel = np.ones((2 * k + 1, 2 * k + 1), np.uint8)
    # Beyond the grid is unknown like any unseen cell: the plate may hang over it, resting on known
    # cells only (else a plane would read as a step along the grid's uphill edges).
    padded = np.pad(z, k, constant_values=np.nan)
    eroded = local_minimum(padded, k)
    eroded = np.where(np.isfinite(eroded), eroded, -np.inf)
    opened = cv2.dilate(eroded, kernel, borderType=cv2.BORDER_CONSTANT, borderValue=-np.inf)
    return opened[k:-k, k:-k]


def agreed_step(step: np.ndarray, cell: float, radius: float, limit: float, min_cells: int) -> np.ndarray:
    """Step scaled by min(1, m / min_cells), m the number of cells within `radius` whose step is over
    `limit` (ETH's StepFilter rule, applied to the cell's own step): a step seen by too few cells,
    a noisy cell or a residual flying pixel, is shrunk below the limit unless it is enormous."""
    k = half_width(radius, cell)
    over = (np.nan_to_num(step, nan=0.0) > limit).astype(np.float64)
    agreeing = cv2.boxFilter(over, -1, (2 * k + 1, 2 * k + 1), normalize=False, borderType=cv2.BORDER_CONSTANT)
    return step * np.minimum(1.0, agreeing / min_cells)


# ---------------------------------------------------------------------------------- codes
def hazard_code(heights: np.ndarray, slope_deg: np.ndarray, step: np.ndarray, roughness: np.ndarray,
                config: HazardConfig) -> np.ndarray:
    """uint8 hazard codes from the three measures and their limits (see the module doc)."""
    causes = ((slope_deg > config.slope_limit_deg) * SLOPE | (step > config.step_limit) * STEP
              | (roughness > config.roughness_limit) * ROUGHNESS).astype(np.uint8)
    code = np.where(causes > 0, causes | HAZARD, SAFE).astype(np.uint8)
    measured = np.isfinite(slope_deg) & np.isfinite(step) & np.isfinite(roughness)
    code[(code == SAFE) & ~measured] = UNKNOWN
    code[~np.isfinite(heights)] = UNKNOWN
    return code
