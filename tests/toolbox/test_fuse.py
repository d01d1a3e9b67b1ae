"""toolbox.mapping.fuse: the TOF and stereo DEMs of the same views as one."""
from __future__ import annotations

import numpy as np
import pytest

from toolbox.grid import GridSpec
from toolbox.mapping.dem import Dem
from toolbox.mapping.fuse import FusionNoise, fuse_dems

NOISE = FusionNoise()


def flat_pair(seed: int, bias: float = 0.02, tof_reach_m: float = 4.5, bias_per_m: float = 0.0):
    """DEMs of flat ground at z = 0 round a rover at (0, 0): TOF to tof_reach_m, stereo to 7 m,
    each with its own noise at each cell's range and the stereo `bias` (+ bias_per_m x range) high."""
    rng = np.random.default_rng(seed)
    spec = GridSpec.covering((-7.0, 7.0), (-7.0, 7.0), 0.05)
    xs, ys = spec.centres()
    r = np.hypot(xs[None, :], ys[:, None])
    tof = np.where((r > 1.0) & (r <= tof_reach_m), rng.normal(0, NOISE.tof_sigma(r)), np.nan)
    stereo = np.where((r > 1.0) & (r <= 7.0), bias + bias_per_m * r + rng.normal(0, NOISE.stereo_sigma(r)), np.nan)
    as_dem = lambda h: Dem(spec, h.astype(np.float32), np.where(np.isfinite(h), 4, 0).astype(np.int32))  # noqa: E731
    return as_dem(tof), as_dem(stereo), r


def test_the_stereo_bias_is_measured_and_removed_and_both_together_beat_either():
    tof, stereo, r = flat_pair(1)
    fused = fuse_dems(tof, stereo, (0.0, 0.0))
    assert fused.bias_measured and abs(fused.stereo_bias_m - 0.02) < 0.001
    shared = np.isfinite(tof.heights) & np.isfinite(stereo.heights)
    rmse = lambda h: float(np.sqrt(np.mean(np.square(h[shared]))))  # noqa: E731
    assert rmse(fused.dem.heights) < rmse(tof.heights) and rmse(fused.dem.heights) < rmse(stereo.heights - 0.02)
    far = np.isfinite(stereo.heights) & ~np.isfinite(tof.heights)
    assert abs(float(np.mean(fused.dem.heights[far]))) < 0.003           # the bias is gone beyond the TOF too
    assert fused.stereo_only == int(far.sum()) and fused.dem.counts[shared].min() == 8
    assert fused.tof_kept < 0.01 * shared.sum()                          # noise alone rarely disagrees


def test_a_stereo_bias_growing_with_range_is_taken_off_as_a_line_held_level_past_the_tof():
    """The stereo reads -0.6 cm at 1-2 m and +1.6 cm at 4-5 m on a simulated panorama: one median
    left the cells past the TOF's reach 1-2 cm high."""
    tof, stereo, r = flat_pair(5, bias=-0.012, bias_per_m=0.006)
    fused = fuse_dems(tof, stereo, (0.0, 0.0))
    assert abs(fused.bias.per_m - 0.006) < 0.001 and 2.5 < fused.bias.at_m < 3.5
    assert abs(fused.stereo_bias_m - (-0.012 + 0.006 * fused.bias.at_m)) < 0.001
    for near, far in [(1.0, 2.0), (3.0, 4.0), (4.5, 6.0)]:     # the last beyond the TOF: the line carried on
        band = (r > near) & (r <= far) & np.isfinite(fused.dem.heights)
        assert abs(float(np.median(fused.dem.heights[band]))) < 0.003, (near, far)
    held = fused.bias(np.array([6.9]))[0]                       # level from 1.5 m past the last band
    assert abs(held - fused.bias(np.array([fused.bias.far_m]))[0]) < 1e-12 and fused.bias.far_m < 6.9
    assert fused.summary()["stereo_bias_per_m"] == round(fused.bias.per_m, 5)


def test_a_stereo_mismatch_where_the_tof_measured_is_not_believed_a_rock_only_the_stereo_saw_is():
    tof, stereo, r = flat_pair(2)
    rows, cols = np.nonzero((r > 2.0) & (r < 2.1))   # 3 sigma together here: 7 cm
    spike = (rows[:3], cols[:3])
    stereo.heights[spike] = 0.02 + 0.12        # a mismatched patch 12 cm up where the TOF read the ground
    rows, cols = np.nonzero((r > 5.5) & (r < 5.6))
    rock = (rows[:3], cols[:3])                # beyond the TOF's reach
    stereo.heights[rock] = 0.02 + 0.15
    fused = fuse_dems(tof, stereo, (0.0, 0.0))
    np.testing.assert_array_equal(fused.dem.heights[spike], tof.heights[spike])
    np.testing.assert_allclose(fused.dem.heights[rock], 0.15, atol=0.002)
    assert fused.tof_kept >= 3


def test_too_few_shared_cells_leave_the_stereo_heights_as_they_are():
    tof, stereo, _ = flat_pair(3, tof_reach_m=1.2)
    fused = fuse_dems(tof, stereo, (0.0, 0.0), FusionNoise(min_shared_cells=5000))
    assert not fused.bias_measured and fused.stereo_bias_m == 0.0
    only = np.isfinite(stereo.heights) & ~np.isfinite(tof.heights)
    np.testing.assert_array_equal(fused.dem.heights[only], stereo.heights[only])


def test_grids_of_another_cell_size_are_refused():
    tof, _, _ = flat_pair(4)
    spec = GridSpec.covering((-1.0, 1.0), (-1.0, 1.0), 0.1)
    other = Dem(spec, np.zeros(spec.shape, np.float32), np.ones(spec.shape, np.int32))
    with pytest.raises(ValueError, match="cannot fuse a 0.05 m TOF grid with a 0.1 m stereo grid"):
        fuse_dems(tof, other, (0.0, 0.0))
