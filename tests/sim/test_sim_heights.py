"""The world's heights kept sparse (drivers/sim/heights.py): every window equals the dense grid's to
the bit, with added obstacles too, and the dense grid is what a full assignment would have made."""
from __future__ import annotations

import numpy as np
import pytest

from drivers.sim.config import WorldConfig
from drivers.sim.heights import TopHeights
from drivers.sim.world import World


def test_windows_equal_the_dense_grid():
    rng = np.random.default_rng(4)
    ground = rng.normal(0, 0.1, (57, 83)).astype(np.float32)
    points = rng.integers(0, ground.size, 900)                  # repeats among them: the last wins
    tops = rng.uniform(0.1, 0.5, len(points)).astype(np.float32)
    dense = ground.copy()
    dense.ravel()[points] = tops
    heights = TopHeights.of(ground, points, tops)
    assert np.array_equal(heights.dense(), dense)
    assert heights.topped() == np.count_nonzero(dense > ground)
    for _ in range(200):
        r0, c0 = rng.integers(0, 57), rng.integers(0, 83)
        rows, cols = slice(r0, r0 + rng.integers(0, 20)), slice(c0, c0 + rng.integers(0, 30))
        assert np.array_equal(heights.window(rows, cols), dense[rows, cols]), (rows, cols)
    assert heights.window(slice(0, 57), slice(0, 83)).shape == (57, 83)
    with pytest.raises(ValueError, match="unit steps"):
        heights.window(slice(0, 10, 2), slice(0, 5))


def test_world_windows_with_an_added_rock_equal_the_dense_heights():
    world = World.build(WorldConfig(seed=9, size_m=(4.0, 4.0), cell_m=0.01))
    rock = world.add_rock(0.5, -0.4, height=0.25)
    dense = world.heights
    assert np.count_nonzero(dense != world._built.built_heights.dense()) > 100   # the rock is in it
    rows, cols = slice(100, 300), slice(150, 330)
    assert np.array_equal(world.heights_window(rows, cols), dense[rows, cols])
    assert np.array_equal(world.protrusion_window(rows, cols), (dense - world.ground)[rows, cols])
    world.remove_obstacle(rock)
    assert np.array_equal(world.heights_window(rows, cols), world._built.built_heights.dense()[rows, cols])
