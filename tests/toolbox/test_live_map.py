"""toolbox/mapping/live.py: frames inserted one at a time give the map and hazard maps of gridding
them all at once and computing the hazards over the whole grid."""
from __future__ import annotations

import numpy as np
import pytest

from toolbox.grid import GridSpec
from toolbox.mapping.dem import points_to_dem
from toolbox.mapping.hazard import HazardConfig, hazard_maps
from toolbox.mapping.live import LiveMap, hazard_reach


def terrain(rng, n: int) -> np.ndarray:
    """Points of a rolling slope with rocks (boxes up to 0.3 m) over 8 x 8 m."""
    xy = rng.uniform(-4.0, 4.0, (n, 2))
    z = 0.08 * xy[:, 0] + 0.1 * np.sin(xy[:, 1]) + rng.normal(0, 0.005, n)
    for cx, cy, r, h in rng.uniform([-4, -4, 0.1, 0.05], [4, 4, 0.3, 0.3], (25, 4)):
        z[np.hypot(xy[:, 0] - cx, xy[:, 1] - cy) < r] += h
    return np.column_stack([xy, z])


def frames(rng, points: np.ndarray, count: int) -> list[np.ndarray]:
    """Wedges seen from the middle, as a panning sensor's frames, in a shuffled order."""
    bearing = np.arctan2(points[:, 1], points[:, 0])
    edges = np.linspace(-np.pi, np.pi, count + 1)
    wedges = [points[(bearing >= a) & (bearing < b)] for a, b in zip(edges[:-1], edges[1:], strict=True)]
    return [wedges[i] for i in rng.permutation(count)]


@pytest.mark.parametrize("seed", [1, 2])
def test_frames_inserted_one_at_a_time_equal_the_whole_grid_recomputed(seed):
    rng = np.random.default_rng(seed)
    spec = GridSpec.covering((-4.5, 4.5), (-4.5, 4.5), 0.05)
    config = HazardConfig(step_min_cells=2)
    live = LiveMap.empty(spec, config)
    seen = []
    for frame in frames(rng, terrain(rng, 120_000), 12)[:6]:
        inserted = live.insert(frame)
        assert inserted is not None and inserted.points == len(frame) and inserted.outside == 0
        seen.append(frame)
        whole = points_to_dem(np.vstack(seen), spec)
        assert np.array_equal(live.heights, whole.heights, equal_nan=True)
        assert np.array_equal(live.counts, whole.counts)
        maps = hazard_maps(whole.heights, spec.cell, config)
        assert np.array_equal(live.step, maps.step, equal_nan=True)
        assert np.allclose(live.slope, maps.slope_deg, atol=1e-3, equal_nan=True)
        assert np.allclose(live.roughness, maps.roughness, atol=1e-5, equal_nan=True)
        differ = live.code != maps.code
        # Codes agree except where a float-rounded measure sits on its limit.
        assert differ.sum() <= 2, differ.sum()
    known = live.code != 255
    assert known.mean() > 0.3 and (live.code[known] & 1).mean() > 0.02    # half the ground seen, rocks on it


def test_a_frame_refreshes_only_its_window_and_points_outside_are_counted():
    rng = np.random.default_rng(3)
    spec = GridSpec.covering((-4.5, 4.5), (-4.5, 4.5), 0.05)
    live = LiveMap.empty(spec)
    patch = terrain(rng, 40_000)
    patch = patch[(np.abs(patch[:, 0] - 1.0) < 0.5) & (np.abs(patch[:, 1]) < 0.5)]
    beyond = np.array([[9.0, 0.0, 0.1], [0.0, -9.0, 0.2]])
    inserted = live.insert(np.vstack([patch, beyond]))
    assert inserted.outside == 2 and inserted.points == len(patch)
    rows, cols = inserted.refreshed
    k = hazard_reach(spec.cell, live.config)
    assert rows.start == inserted.touched[0].start - k and cols.stop == inserted.touched[1].stop + k
    outside_window = np.ones(spec.shape, dtype=bool)
    outside_window[rows, cols] = False
    assert (live.code[outside_window] == 255).all()         # nothing known there, nothing recomputed
    assert live.insert(beyond) is None
    twin = live.copy()                                       # independent: a frame into it leaves the map
    twin.insert(patch + [0.0, 0.0, 0.5])
    assert not np.array_equal(twin.heights, live.heights, equal_nan=True) and twin.counts.sum() == 2 * live.counts.sum()
