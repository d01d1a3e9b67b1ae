"""The bounded-error terrain mesh (RTIN): crack-free, within tolerance, and tiles agree."""
from __future__ import annotations

import numpy as np
import pytest

from drivers.sim.grid import GridSpec
from drivers.sim.mesh import TriangleSurface, grid_surface_parts
from drivers.sim.noise import fractal_noise
from drivers.sim.rtin import extract_triangles, vertex_errors

BLOCK = 32


@pytest.fixture(scope="module")
def heights() -> np.ndarray:
    """Rough ground with a sharp step, on 3 x 2 blocks."""
    rng = np.random.default_rng(5)
    field = 0.02 * fractal_noise(rng, (2 * BLOCK + 1, 3 * BLOCK + 1), 2.0, 16.0)
    field[20:40, 30:45] += 0.05
    return field


def edge_counts(triangles: np.ndarray) -> dict[tuple[int, int], int]:
    edges = np.sort(np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]]), axis=1)
    keys, counts = np.unique(edges, axis=0, return_counts=True)
    return {tuple(k): c for k, c in zip(keys.tolist(), counts.tolist(), strict=True)}


@pytest.mark.parametrize("tolerance", [0.0005, 0.003, 0.02])
def test_mesh_is_within_tolerance_of_every_grid_point(heights, tolerance):
    grid = GridSpec(0.0, 0.0, 0.01, heights.shape[0] - 1, heights.shape[1] - 1)
    triangles = extract_triangles(vertex_errors(heights, BLOCK), tolerance, BLOCK)
    surface = TriangleSurface(*grid_surface_parts(grid, heights, triangles))
    rows, cols = np.mgrid[0:grid.rows + 1, 0:grid.cols + 1]
    # Stay a hair inside the outer edge, where a vertical ray could slip past the last triangle.
    x = np.clip(grid.x_of(cols.ravel()), 1e-6, grid.x_max - 1e-6)
    y = np.clip(grid.y_of(rows.ravel()), 1e-6, grid.y_max - 1e-6)
    z, _ = surface.top_height(x, y)
    assert not np.isnan(z).any()
    assert np.max(np.abs(z - heights.ravel())) <= tolerance + 1e-6


def test_mesh_has_no_cracks_and_covers_the_grid(heights):
    triangles = extract_triangles(vertex_errors(heights, BLOCK), 0.003, BLOCK)
    width = heights.shape[1]
    rows, cols = np.divmod(triangles, width)
    # Counter-clockwise from above, and the areas add up to the whole grid.
    doubled_area = ((cols[:, 1] - cols[:, 0]) * (rows[:, 2] - rows[:, 0])
                    - (rows[:, 1] - rows[:, 0]) * (cols[:, 2] - cols[:, 0]))
    assert np.all(doubled_area > 0)
    assert doubled_area.sum() == 2 * (heights.shape[0] - 1) * (heights.shape[1] - 1)
    # Conforming: every edge inside the grid is shared by exactly two triangles (no T-junctions).
    for (p, q), count in edge_counts(triangles).items():
        (r1, c1), (r2, c2) = divmod(p, width), divmod(q, width)
        on_border = (r1 == r2 and r1 in (0, heights.shape[0] - 1)) or (c1 == c2 and c1 in (0, width - 1))
        assert count == (1 if on_border else 2)


def test_blocks_meshed_alone_match_the_whole_mesh(heights):
    errors = vertex_errors(heights, BLOCK)
    whole = extract_triangles(errors, 0.003, BLOCK)
    tiles = [extract_triangles(errors, 0.003, BLOCK, np.array([r]), np.array([c]))
             for r in range(2) for c in range(3)]
    as_set = lambda t: {tuple(sorted(row)) for row in t.tolist()}  # noqa: E731
    assert as_set(np.concatenate(tiles)) == as_set(whole)


def test_flat_ground_needs_two_triangles_per_block():
    flat = np.zeros((BLOCK + 1, 2 * BLOCK + 1), dtype=np.float32)
    assert len(extract_triangles(vertex_errors(flat, BLOCK), 0.001, BLOCK)) == 4
