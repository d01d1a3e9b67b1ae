"""Height-map matching (toolbox/height_match.py): the horizontal shift between two clouds of one ground,
and whether the ground shows it."""
from __future__ import annotations

import numpy as np
import pytest

from toolbox.grid import GridSpec
from toolbox.mapping.height_match import height_grid, match_height_maps


def terrain(rng: np.random.Generator, rocks: int, extent: float = 3.0):
    """A height function: `rocks` Gaussian bumps of 3-12 cm on a plane tilted 3 degrees."""
    centres = rng.uniform(-extent, extent, (rocks, 2))
    heights, widths = rng.uniform(0.03, 0.12, rocks), rng.uniform(0.06, 0.2, rocks)

    def height(xy: np.ndarray) -> np.ndarray:
        d2 = ((xy[:, None, :] - centres[None]) ** 2).sum(axis=2)
        return 0.05 * xy[:, 0] + (heights * np.exp(-d2 / (2 * widths ** 2))).sum(axis=1)
    return height


def cloud(rng, height, low, high, count=40_000, noise=0.005) -> np.ndarray:
    xy = rng.uniform(low, high, (count, 2))
    return np.column_stack([xy, height(xy) + rng.normal(0, noise, count)])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_known_shift_between_partly_overlapping_clouds_is_found_to_a_fraction_of_a_cell(seed):
    rng = np.random.default_rng(seed)
    height = terrain(rng, rocks=60)
    truth = np.array([rng.uniform(-0.45, 0.45), rng.uniform(-0.45, 0.45), rng.uniform(-0.1, 0.1)])
    target = cloud(rng, height, [-1.6, -1.6], [1.6, 1.0])          # the previous hop saw the south
    seen = cloud(rng, height, [-1.6, -0.6], [1.6, 1.6])            # this hop the north: 50 % shared
    source = seen - truth                                          # where this hop's estimate put it
    match = match_height_maps(source, target, np.zeros(2), radius=1.5, search=0.6, cell=0.05, distinct=0.15)
    assert np.hypot(*(match.shift - truth[:2])) < 0.02             # a cell is 5 cm
    assert match.vertical == pytest.approx(truth[2], abs=0.01)
    assert match.contrast > 1.5 and match.misfit < 0.015


def test_flat_ground_is_reported_as_not_showing_the_shift():
    rng = np.random.default_rng(3)
    height = terrain(rng, rocks=0)                                 # the tilted plane alone
    target = cloud(rng, height, [-1.6, -1.6], [1.6, 1.6])
    source = cloud(rng, height, [-1.6, -1.6], [1.6, 1.6]) - [0.3, 0.1, 0.0]
    match = match_height_maps(source, target, np.zeros(2), radius=1.5, search=0.6, cell=0.05, distinct=0.15)
    assert match.contrast < 1.1                                    # hopping.toml icp_min_contrast


def test_the_cost_surface_has_its_minimum_at_the_shift_and_rises_around_it():
    rng = np.random.default_rng(4)
    height = terrain(rng, rocks=60)
    target = cloud(rng, height, [-1.6, -1.6], [1.6, 1.6])
    source = cloud(rng, height, [-1.6, -1.6], [1.6, 1.6]) - [0.2, -0.1, 0.0]
    match = match_height_maps(source, target, np.zeros(2), radius=1.5, search=0.4, cell=0.05, distinct=0.15)
    row, col = np.unravel_index(np.nanargmin(match.costs), match.costs.shape)
    assert (match.offsets[col], match.offsets[row]) == pytest.approx((0.2, -0.1), abs=1e-9)
    assert match.costs[row, 0] > 2 * match.misfit and match.costs[0, col] > 2 * match.misfit


def test_height_grid_known_answer():
    points = np.array([[0.01, 0.01, 1.0], [0.02, 0.03, 3.0], [0.11, 0.01, 5.0], [0.5, 0.5, 9.0]])
    grid = height_grid(points, GridSpec(origin_x=0.0, origin_y=0.0, cell=0.1, rows=3, cols=3))
    assert grid[0, 0] == 2.0 and grid[0, 1] == 5.0                 # [row = y, col = x]; mean per cell
    assert np.isnan(grid).sum() == 7                               # the far point is outside


def test_bad_parameters_and_disjoint_clouds_are_refused():
    rng = np.random.default_rng(5)
    flat = cloud(rng, terrain(rng, rocks=0), [-1, -1], [1, 1], count=2000)
    with pytest.raises(ValueError, match="cell=0"):
        match_height_maps(flat, flat, np.zeros(2), radius=1.0, search=0.3, cell=0.0, distinct=0.1)
    with pytest.raises(ValueError, match="too few to match"):
        match_height_maps(flat, flat, np.array([10.0, 0.0]), radius=1.0, search=0.3, cell=0.05, distinct=0.1)
    with pytest.raises(ValueError, match="share fewer than 10 cells"):
        match_height_maps(flat + [5, 0, 0], flat, np.zeros(2), radius=1.0, search=0.3, cell=0.05, distinct=0.1)
