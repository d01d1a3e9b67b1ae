"""One DEM from the SR4000's and the stereo pair's DEMs of the same views.

Each sensor is weak where the other is strong: the SR4000 is precise (1-1.5 cm) but short (5 m) and
narrow; the stereo pair reaches farther and wider but is biased (its cells read 1-2 cm high) and its
height noise grows with the square of the range. So:

1. The stereo bias is measured where both sensors saw the same cells near the rover (stereo minus
   TOF, within `bias_range_m`) and taken off every stereo cell. It grows with range (on a simulated
   full panorama, stereo against the truth by band: -0.6 cm at 1-2 m, +0.7 at 3-4 m, +1.6 cm at
   4-5 m), so it is a line in range: fitted to the medians of bias_band_m bands, each weighted by
   how well its median is known, and held level from bias_hold_m past the last band (beyond the
   TOF's reach nothing measures it). One band, too narrow a span or a slope within slope_sigmas
   of its standard error: one median. Too few shared cells: no correction, and the result says so.
2. A cell both saw is the mean of the two weighted by the inverse of each sensor's height variance
   at that cell's range; a cell one saw is that one's, so the stereo pair adds what the TOF did not
   reach (the fringe of its 5 m, the gaps between its views).
3. Where the two disagree by more than `disagree_sigmas` times their combined spread, the TOF's
   height stands. The stereo's errors are heavy-tailed (a mismatched patch reads 5-10 cm off) and
   the TOF's are not: on a simulated panorama (4 m round the rover, 5515 cells both saw) taking the
   higher of two that disagree gave 1.88 cm RMSE against the truth, the TOF's 1.16 cm, and the
   TOF's height there 1.17 cm. Where only the stereo saw a rock, its top is the map's.

    fused = fuse_dems(tof_dem, stereo_dem, rover_xy, FusionNoise())
    fused.dem, fused.stereo_bias_m, fused.summary()

Heights in metres, world frame (z up); the DEMs must share the cell size and its alignment
(GridSpec.covering makes them so).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from toolbox.mapping.dem import Dem, mosaic, union_spec


@dataclass(frozen=True)
class FusionNoise:
    """Each sensor's height noise per cell by range, and the fusion's rules.

    tof_sigma_m at tof_reference_m, growing in proportion to range (the SR4000's returned light
    falls with range, its phase noise grows with it); stereo: stereo_sigma_per_m2 times range
    squared (a disparity error of a fixed fraction of a pixel), at least stereo_sigma_min_m. The
    stereo's 0.005 is its cells' spread against the truth on the simulated panoramas (1.8-2 cm at
    2-3 m); the spread of stereo minus TOF is far smaller (the two share the cell's own relief),
    so it cannot stand in for it."""

    tof_sigma_m: float = 0.012
    tof_reference_m: float = 3.0
    stereo_sigma_per_m2: float = 0.005
    stereo_sigma_min_m: float = 0.005
    bias_range_m: float = 5.0
    bias_band_m: float = 0.5
    min_band_cells: int = 50
    bias_hold_m: float = 1.5
    slope_sigmas: float = 3.0
    min_shared_cells: int = 200
    disagree_sigmas: float = 3.0

    def tof_sigma(self, range_m: np.ndarray) -> np.ndarray:
        return self.tof_sigma_m * np.maximum(range_m, 0.5) / self.tof_reference_m

    def stereo_sigma(self, range_m: np.ndarray) -> np.ndarray:
        return np.maximum(self.stereo_sigma_per_m2 * np.square(range_m), self.stereo_sigma_min_m)


@dataclass(frozen=True)
class StereoBias:
    """The stereo's height bias against the TOF as a line in range, level outside [near_m, far_m]."""

    at_m: float                   # the reference range: the shared cells' median range
    bias_m: float                 # the bias there
    per_m: float                  # its growth per metre of range (0: one median)
    near_m: float
    far_m: float

    def __call__(self, range_m: np.ndarray) -> np.ndarray:
        return self.bias_m + self.per_m * (np.clip(range_m, self.near_m, self.far_m) - self.at_m)


NO_BIAS = StereoBias(0.0, 0.0, 0.0, 0.0, 0.0)


def measure_bias(difference: np.ndarray, range_m: np.ndarray, noise: FusionNoise) -> StereoBias:
    """The bias line through the band medians of stereo minus TOF (`difference`) at `range_m`, each
    band weighted by the inverse of its median's variance (pi/2 sigma^2 / n, sigma from its MAD); one
    median without two bands at least a band apart, or where the slope is within slope_sigmas of its
    standard error (a slope fitted to noise would tilt the far stereo cells for nothing)."""
    at = float(np.median(range_m))
    whole = StereoBias(at, float(np.median(difference)), 0.0, at, at)
    bands = np.floor(range_m / noise.bias_band_m).astype(np.int64)
    centres, medians, weights = [], [], []
    for band in np.unique(bands):
        inside = bands == band
        if np.count_nonzero(inside) < noise.min_band_cells:
            continue
        values = difference[inside]
        median = float(np.median(values))
        spread = max(1.4826 * float(np.median(np.abs(values - median))), 1e-4)
        centres.append(float(np.median(range_m[inside])))
        medians.append(median)
        weights.append(values.size / (np.pi / 2 * spread**2))    # 1 / a median's variance
    if len(centres) < 2 or max(centres) - min(centres) < 2 * noise.bias_band_m:
        return whole
    x, y, w = np.array(centres), np.array(medians), np.array(weights)
    mean_x = float(np.average(x, weights=w))
    leverage = float(np.sum(w * np.square(x - mean_x)))
    slope = float(np.sum(w * (x - mean_x) * (y - np.average(y, weights=w))) / leverage)
    if abs(slope) < noise.slope_sigmas / np.sqrt(leverage):    # no growth the medians can tell from noise
        return whole
    level = float(np.average(y, weights=w)) + slope * (at - mean_x)
    return StereoBias(at, level, slope, float(x.min()), float(x.max()) + noise.bias_hold_m)


@dataclass(frozen=True)
class Fused:
    dem: Dem
    stereo_bias_m: float          # taken off the stereo cells at the shared cells' median range (0: too few)
    bias: StereoBias              # ... and by range
    shared_cells: int             # cells both sensors measured within bias_range_m
    bias_measured: bool
    tof_only: int                 # cells by where their height came from
    stereo_only: int
    weighted: int
    tof_kept: int                 # shared cells where the two disagreed and the TOF's height stands

    def summary(self) -> dict[str, Any]:
        return {"stereo_bias_m": round(self.stereo_bias_m, 4), "stereo_bias_per_m": round(self.bias.per_m, 5),
                "stereo_bias_at_m": round(self.bias.at_m, 3), "bias_measured": self.bias_measured,
                "shared_cells": self.shared_cells, "tof_only": self.tof_only, "stereo_only": self.stereo_only,
                "weighted": self.weighted, "tof_kept": self.tof_kept}


def fuse_dems(tof: Dem, stereo: Dem, rover_xy: tuple[float, float], noise: FusionNoise = FusionNoise()) -> Fused:
    """The two DEMs (gridded, not yet filled: a measured cell has count > 0) as one, on the grid
    covering both; `rover_xy` is where the views were taken from (the ranges the noise grows with)."""
    if abs(tof.spec.cell - stereo.spec.cell) > 1e-9 * tof.spec.cell:
        raise ValueError(f"cannot fuse a {tof.spec.cell} m TOF grid with a {stereo.spec.cell} m stereo grid")
    spec = union_spec([tof.spec, stereo.spec])
    t, s = mosaic([tof], spec), mosaic([stereo], spec)
    xs, ys = spec.centres()
    range_m = np.hypot(xs[None, :] - rover_xy[0], ys[:, None] - rover_xy[1])
    seen_t = (t.counts > 0) & np.isfinite(t.heights)
    seen_s = (s.counts > 0) & np.isfinite(s.heights)
    both = seen_t & seen_s

    near = both & (range_m <= noise.bias_range_m)
    shared = int(np.count_nonzero(near))
    measured = shared >= noise.min_shared_cells
    bias = measure_bias((s.heights[near] - t.heights[near]).astype(np.float64), range_m[near], noise) \
        if measured else NO_BIAS
    s_heights = s.heights.astype(np.float64) - bias(range_m)

    var_t, var_s = np.square(noise.tof_sigma(range_m)), np.square(noise.stereo_sigma(range_m))
    heights = np.full(spec.shape, np.nan)
    heights[seen_t] = t.heights[seen_t]
    only_s = seen_s & ~seen_t
    heights[only_s] = s_heights[only_s]
    weighted = (t.heights * var_s + s_heights * var_t) / (var_t + var_s)
    apart = np.abs(t.heights - s_heights) > noise.disagree_sigmas * np.sqrt(var_t + var_s)
    mean = both & ~apart          # the rest of the shared cells keep the TOF's height, set above
    heights[mean] = weighted[mean]
    counts = t.counts + s.counts
    return Fused(Dem(spec, heights.astype(np.float32), counts.astype(np.int32)), bias.bias_m, bias, shared, measured,
                 tof_only=int(np.count_nonzero(seen_t & ~seen_s)), stereo_only=int(np.count_nonzero(only_s)),
                 weighted=int(np.count_nonzero(mean)), tof_kept=int(np.count_nonzero(both & apart)))

