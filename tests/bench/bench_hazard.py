"""Benchmark: slope, step, roughness and hazard codes of a 1000 x 1000 DEM beside a per-cell reference.

The DEM: 2 cm cells (20 x 20 m) of rolling ground with rocks, 1 cm noise and 10 % unknown cells.
- ours: hazard.plane_fit, step_height + agreed_step, and hazard_maps (all three and the codes), with
  the default windows (plane 0.25 m: 25 x 25 cells; step 0.10 m; ground plate 0.5 m: 51 x 51);
- reference: the straightforward way, per cell with scipy.ndimage.generic_filter: a least-squares
  plane (numpy lstsq) over the same window for slope and roughness, and min / max / count windows
  for the step (ETH's loop structure), run on a 100 x 100 crop and scaled to the full grid.
Ours is checked against the reference on the crop before the times are printed.

    .venv/bin/python tests/bench/bench_hazard.py [--crop 100] [--repeats 3]
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from scipy import ndimage

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from toolbox.mapping import hazard as H  # noqa: E402

CELL = 0.02
SIZE = 1000
CONFIG = H.HazardConfig()


def test_dem(rng: np.random.Generator) -> np.ndarray:
    rows, cols = np.mgrid[0:SIZE, 0:SIZE] * CELL
    heights = 0.4 * np.sin(cols / 3.0) * np.cos(rows / 4.0) + 0.05 * cols
    for _ in range(400):                                   # rocks: half-ellipsoids up to 0.6 m across
        r0, c0 = rng.uniform(0, SIZE * CELL, 2)
        radius, height = rng.uniform(0.05, 0.3), rng.uniform(0.03, 0.3)
        inside = 1 - ((rows - r0) ** 2 + (cols - c0) ** 2) / radius ** 2
        heights += height * np.sqrt(np.clip(inside, 0, None))
    heights += rng.normal(0, 0.01, heights.shape)
    heights[rng.random(heights.shape) < 0.10] = np.nan
    return heights


def best_of(repeats: int, function, *args):
    times, result = [], None
    for _ in range(repeats):
        start = time.perf_counter()
        result = function(*args)
        times.append(time.perf_counter() - start)
    return min(times), result


# ---------------------------------------------------------------------------------- reference
def reference_plane_fit(heights: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    offsets = np.arange(-k, k + 1) * CELL
    dy, dx = np.meshgrid(offsets, offsets, indexing="ij")
    design_full = np.c_[dx.ravel(), dy.ravel(), np.ones(dx.size)]

    def fit(window: np.ndarray, out: str) -> float:
        known = np.isfinite(window)
        if known[len(window) // 2] == 0 or known.sum() < H.MIN_FIT_CELLS:
            return np.nan
        (a, b, _), residual, rank, _ = np.linalg.lstsq(design_full[known], window[known], rcond=None)
        if rank < 3:
            return np.nan
        if out == "slope":
            return float(np.degrees(np.arctan(np.hypot(a, b))))
        ss = float(residual[0]) if len(residual) else 0.0
        return float(np.sqrt(ss / (known.sum() - 3)))

    size = 2 * k + 1
    options = dict(size=size, mode="constant", cval=np.nan)
    slope = ndimage.generic_filter(heights, fit, extra_arguments=("slope",), **options)
    roughness = ndimage.generic_filter(heights, fit, extra_arguments=("roughness",), **options)
    return slope, roughness


def reference_step(heights: np.ndarray) -> np.ndarray:
    k_edge, k_plate = H.half_width(CONFIG.step_radius, CELL), H.half_width(CONFIG.ground_radius, CELL)
    options = dict(mode="constant", cval=np.nan)
    minimum = ndimage.generic_filter(heights, np.nanmin, size=2 * k_edge + 1, **options)
    padded = np.pad(heights, k_plate, constant_values=np.nan)
    eroded = ndimage.generic_filter(padded, lambda w: np.nanmin(w) if np.isfinite(w).any() else np.inf,
                                    size=2 * k_plate + 1, mode="constant", cval=np.nan)
    opened = ndimage.generic_filter(np.where(np.isfinite(eroded), eroded, -np.inf), np.max,
                                    size=2 * k_plate + 1, mode="constant", cval=-np.inf)
    opened = opened[k_plate:-k_plate, k_plate:-k_plate]
    step = np.maximum(heights - minimum, heights - opened)
    over = (np.nan_to_num(step) > CONFIG.step_limit).astype(float)
    agreeing = ndimage.generic_filter(over, np.sum, size=2 * k_edge + 1, mode="constant", cval=0.0)
    return step * np.minimum(1.0, agreeing / CONFIG.step_min_cells)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--crop", type=int, default=100)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    heights = test_dem(np.random.default_rng(0))
    k_plane = H.half_width(CONFIG.plane_radius, CELL)
    # The crop is cut with a margin so both see the same windows; only its middle is compared, and
    # the reference's time per cell of the whole crop is scaled to the full grid.
    margin = H.half_width(CONFIG.ground_radius, CELL) * 2
    crop = np.s_[400 - margin:400 + args.crop + margin, 400 - margin:400 + args.crop + margin]
    middle = np.s_[margin:-margin, margin:-margin]
    scale = SIZE * SIZE / heights[crop].size
    side = args.crop + 2 * margin
    print(f"{SIZE} x {SIZE} DEM, {CELL} m cells, {np.isnan(heights).mean():.0%} unknown; reference on a "
          f"{side} x {side} crop ({args.crop} x {args.crop} compared), scaled x{scale:.0f}")

    ref_plane_time, (ref_slope, ref_rough) = best_of(1, reference_plane_fit, heights[crop], k_plane)
    ref_step_time, ref_step = best_of(1, reference_step, heights[crop])
    plane_time, (slope, rough) = best_of(args.repeats, H.plane_fit, heights, CELL, CONFIG.plane_radius)

    def our_step(z):
        step = H.step_height(z, CELL, CONFIG.step_radius, CONFIG.ground_radius)
        return H.agreed_step(step, CELL, CONFIG.step_radius, CONFIG.step_limit, CONFIG.step_min_cells)

    step_time, step = best_of(args.repeats, our_step, heights)
    maps_time, maps = best_of(args.repeats, H.hazard_maps, heights, CELL)

    ours_crop = np.s_[crop[0].start + margin:crop[0].stop - margin, crop[1].start + margin:crop[1].stop - margin]
    assert np.allclose(slope[ours_crop], ref_slope[middle], atol=1e-6, equal_nan=True)
    assert np.allclose(rough[ours_crop], ref_rough[middle], atol=1e-7, equal_nan=True)
    assert np.allclose(step[ours_crop], ref_step[middle], atol=1e-9, equal_nan=True)

    ref_plane_full, ref_step_full = ref_plane_time * scale, ref_step_time * scale
    print(f"  slope + roughness  reference {ref_plane_full:8.1f} s (scaled)   ours {plane_time * 1000:7.1f} ms"
          f"   {ref_plane_full / plane_time:8.0f}x faster")
    print(f"  step               reference {ref_step_full:8.1f} s (scaled)   ours {step_time * 1000:7.1f} ms"
          f"   {ref_step_full / step_time:8.0f}x faster")
    total = ref_plane_full + ref_step_full
    print(f"  hazard_maps (all)  reference {total:8.1f} s (scaled)   ours {maps_time * 1000:7.1f} ms"
          f"   {total / maps_time:8.0f}x faster")
    codes, counts = np.unique(maps.code, return_counts=True)
    print("  codes: " + ", ".join(f"{c}: {n}" for c, n in zip(codes.tolist(), counts.tolist())))


if __name__ == "__main__":
    main()
