"""Benchmark: slope, step, roughness and hazard codes of a 1000 x 1000 DEM beside its references.

The DEM: 2 cm cells (20 x 20 m) of rolling ground with rocks, 1 cm noise and 10 % unknown cells, in
float32 as a Dem holds its heights. Timed, with the default windows (plane 0.25 m: 25 x 25 cells;
step 0.10 m; ground plate 0.5 m: 51 x 51):
- ours: hazard_maps (all three and the codes), and its parts plane_fit and step_height + agreed_step;
- reference (issue 26): five cv2.boxFilter passes (25 x 25) over the same grid; ours must stay
  within 10 times. Printed against the float32 grid (the DEM's own, the harder reference) and the
  same grid in float64;
- before: hazard_maps as it was before issue 26, kept as reference_hazard_maps in
  tests/toolbox/test_toolbox_hazard.py (the tests hold ours to it);
- ours on float64 heights float32 cannot hold (the step's exact float64 morphology, slower);
- the straightforward way, per cell with scipy.ndimage.generic_filter: a least-squares plane (numpy
  lstsq) over the same window for slope and roughness, and min / max / count windows for the step
  (ETH's loop structure), run on a 100 x 100 crop and scaled to the full grid.
Ours is checked against the per-cell way on the crop and against before on the whole grid. The
machine is shared, so ours, the references and before are timed in interleaved rounds (each the
best of --repeats) and the ratios printed are medians over --rounds.

    .venv/bin/python tests/bench/bench_hazard.py [--crop 100] [--repeats 3] [--rounds 5]
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import cv2
import numpy as np
from scipy import ndimage

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "toolbox"))
from test_toolbox_hazard import reference_hazard_maps  # noqa: E402

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
    parser.add_argument("--rounds", type=int, default=5)
    args = parser.parse_args()
    heights = test_dem(np.random.default_rng(0)).astype(np.float32)
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

    ref_plane_time, (ref_slope, ref_rough) = best_of(1, reference_plane_fit, heights[crop].astype(np.float64), k_plane)
    ref_step_time, ref_step = best_of(1, reference_step, heights[crop].astype(np.float64))

    def our_step(z):
        step = H.step_height(z, CELL, CONFIG.step_radius, CONFIG.ground_radius)
        return H.agreed_step(step, CELL, CONFIG.step_radius, CONFIG.step_limit, CONFIG.step_min_cells)

    def five_box_filters(grid):
        return [cv2.boxFilter(grid, -1, (2 * k_plane + 1, 2 * k_plane + 1), normalize=False,
                              borderType=cv2.BORDER_CONSTANT) for _ in range(5)]

    wide = test_dem(np.random.default_rng(0))                 # float64 values float32 cannot hold
    grid64 = heights.astype(np.float64)
    H.hazard_maps(heights[:400, :400], CELL)                   # numba: load and compile (or the cache)
    times = {name: [] for name in ("box32", "box64", "maps", "plane", "step", "maps64", "before")}
    for round_ in range(args.rounds):
        times["box32"].append(best_of(args.repeats, five_box_filters, heights)[0])
        times["box64"].append(best_of(args.repeats, five_box_filters, grid64)[0])
        maps_time, maps = best_of(args.repeats, H.hazard_maps, heights, CELL)
        times["maps"].append(maps_time)
        plane_time, (slope, rough) = best_of(args.repeats, H.plane_fit, heights, CELL, CONFIG.plane_radius)
        times["plane"].append(plane_time)
        step_time, step = best_of(args.repeats, our_step, heights)
        times["step"].append(step_time)
        times["maps64"].append(best_of(1, H.hazard_maps, wide, CELL)[0])
        if round_ < 3:                                        # 0.7 s each: three rounds are enough
            before_time, before = best_of(1, reference_hazard_maps, heights, CELL)
            times["before"].append(before_time)

    ours_crop = np.s_[crop[0].start + margin:crop[0].stop - margin, crop[1].start + margin:crop[1].stop - margin]
    assert np.allclose(slope[ours_crop], ref_slope[middle], atol=1e-6, equal_nan=True)
    assert np.allclose(rough[ours_crop], ref_rough[middle], atol=1e-7, equal_nan=True)
    assert np.allclose(step[ours_crop], ref_step[middle], atol=1e-9, equal_nan=True)
    assert np.array_equal(maps.code, before.code)
    for name in ("slope_deg", "step", "roughness"):
        assert np.allclose(getattr(maps, name), getattr(before, name), rtol=1e-6, atol=1e-6, equal_nan=True)

    def median(name):
        return float(np.median(times[name]))

    def ratio(name, reference):
        rounds = min(len(times[name]), len(times[reference]))
        return float(np.median(np.array(times[name][:rounds]) / np.array(times[reference][:rounds])))

    ref_plane_full, ref_step_full = ref_plane_time * scale, ref_step_time * scale
    print(f"  five cv2.boxFilter 25 x 25 (reference)   float32 grid {median('box32') * 1000:7.1f} ms"
          f"   float64 grid {median('box64') * 1000:7.1f} ms")
    print(f"  hazard_maps (all)     ours {median('maps') * 1000:7.1f} ms   {ratio('maps', 'box32'):5.1f}x the "
          f"reference on float32 ({ratio('maps', 'box64'):4.1f}x on float64; issue 26: within 10x)")
    ratios = ' '.join(f'{m / b:.1f}' for m, b in zip(times['maps'], times['box32'], strict=True))
    print(f"    ratios per round: {ratios}")
    print(f"  before (until issue 26) {median('before') * 1000:7.1f} ms   {ratio('before', 'box32'):5.1f}x the "
          f"reference on float32 ({ratio('before', 'box64'):4.1f}x on float64); "
          f"ours {median('before') / median('maps'):.1f}x faster")
    print(f"  float64 heights     ours {median('maps64') * 1000:7.1f} ms   {ratio('maps64', 'box32'):5.1f}x "
          f"(heights float32 cannot hold: exact float64 morphology)")
    print(f"  slope + roughness  per-cell {ref_plane_full:8.1f} s (scaled)   ours {median('plane') * 1000:7.1f} ms"
          f"   {ref_plane_full / median('plane'):8.0f}x faster")
    print(f"  step               per-cell {ref_step_full:8.1f} s (scaled)   ours {median('step') * 1000:7.1f} ms"
          f"   {ref_step_full / median('step'):8.0f}x faster")
    codes, counts = np.unique(maps.code, return_counts=True)
    print("  codes: " + ", ".join(f"{c}: {n}" for c, n in zip(codes.tolist(), counts.tolist(), strict=True)))


if __name__ == "__main__":
    main()
