"""The compiled A* (toolbox/planning/_astar_kernel.py) against the search it replaced.

`scipy_astar` below is search.astar as it was before the numba kernel (commit 9fbef23): A* run as
SciPy's Dijkstra on heuristic-reduced costs over a padded CSR grid graph, first limited to an ellipse
round the goal, then in full. It shares nothing with the kernel but the metric, so the two agree on
every path cost (the paths themselves may differ where several are equally cheap). The Dijkstra
reference of search.py is too slow for the larger grids here; test_planning.py holds A* to it.
"""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra

from toolbox.planning import _astar_kernel
from toolbox.planning.search import (
    NEIGHBOUR_STEPS,
    NO_PATH,
    SQRT2,
    SearchResult,
    _cell_tuple,
    astar,
    check_search_inputs,
    cost_per_metre,
    dijkstra_reference,
    path_cost,
)

# --- the previous implementation, verbatim but for names --------------------------------------------

ASTAR_SLACK = 0.02
NO_LIMIT = float(np.finfo(np.float64).max)


def octile_heuristic(shape: tuple[int, int], goal: tuple[int, int], cell: float,
                     min_cost_per_metre: float) -> np.ndarray:
    """Lower bound of the cost from every cell to the goal: octile distance times the least cost per metre."""
    d_row = np.abs(np.arange(shape[0]) - goal[0])[:, None]
    d_col = np.abs(np.arange(shape[1]) - goal[1])[None, :]
    octile = np.maximum(d_row, d_col) + (SQRT2 - 1.0) * np.minimum(d_row, d_col)
    return min_cost_per_metre * cell * octile


class GridGraph:
    """The grid as a SciPy CSR graph: 8 edge slots per cell, +inf where a step is impossible.

    The grid is padded with one ring of impassable cells so every cell has 8 in-range neighbours and
    the graph needs neither bounds tests nor compaction: an edge of weight +inf is never relaxed.
    """

    def __init__(self, per_metre: np.ndarray, cell: float):
        self.shape = per_metre.shape
        self.cell = cell
        self.width = per_metre.shape[1] + 2
        self.per_metre = self._padded(per_metre, fill=np.inf)
        self.nodes = self.per_metre.size
        if 8 * self.nodes >= 2**31:  # SciPy's CSR graphs index edges with int32
            raise ValueError(f"a grid of {per_metre.shape[0]} x {per_metre.shape[1]} cells is too large")
        self.offsets = np.array([dr * self.width + dc for dr, dc in NEIGHBOUR_STEPS], dtype=np.int32)
        neighbours = np.arange(self.nodes, dtype=np.int32)[:, None] + self.offsets[None, :]
        self.indices = np.clip(neighbours, 0, self.nodes - 1, out=neighbours).ravel()
        self.indptr = np.arange(0, 8 * self.nodes + 1, 8, dtype=np.int32)

    def _padded(self, grid: np.ndarray, fill: float) -> np.ndarray:
        padded = np.full((self.shape[0] + 2, self.width), fill)
        padded[1:-1, 1:-1] = grid
        return padded.ravel()

    def csr(self, potential: np.ndarray | None = None) -> csr_matrix:
        """The graph, with edge costs reduced by a potential (the A* heuristic) when one is given."""
        weights = self._edge_weights(potential)
        return csr_matrix((weights.ravel(), self.indices, self.indptr), shape=(self.nodes, self.nodes))

    def _edge_weights(self, potential: np.ndarray | None) -> np.ndarray:
        """(nodes, 8) step costs, node-major as CSR rows want them, each reduced by h(v) - h(u)."""
        # Built slot by slot in contiguous rows, then transposed once: faster than strided columns.
        weights = np.empty((8, self.nodes))
        # Nodes of the first and last padded rows have neighbours outside the array: no edges.
        inner = slice(self.width + 1, self.nodes - self.width - 1)
        weights[:, :inner.start] = np.inf
        weights[:, inner.stop:] = np.inf
        per_metre = self.per_metre
        heights = None if potential is None else self._padded(potential, fill=0.0)
        for slot, ((d_row, d_col), offset) in enumerate(zip(NEIGHBOUR_STEPS, self.offsets, strict=True)):
            neighbour = slice(inner.start + offset, inner.stop + offset)
            edge = weights[slot, inner]
            np.add(per_metre[inner], per_metre[neighbour], out=edge)
            edge *= 0.5 * self.cell * (SQRT2 if d_row and d_col else 1.0)
            if heights is not None:
                edge += heights[neighbour]
                edge -= heights[inner]
        # A consistent heuristic makes reduced costs >= 0; clip the rounding (~1e-16) below zero.
        np.maximum(weights, 0.0, out=weights)
        return np.ascontiguousarray(weights.T)

    def node(self, cell: tuple[int, int]) -> int:
        return (cell[0] + 1) * self.width + cell[1] + 1

    def cell_of_node(self, nodes: np.ndarray) -> np.ndarray:
        rows, cols = np.divmod(np.asarray(nodes, dtype=np.int64), self.width)
        return np.stack([rows - 1, cols - 1], axis=1)

    def shortest_path(self, graph: csr_matrix, start: tuple[int, int], goal: tuple[int, int],
                      limit: float) -> np.ndarray | None:
        """Cells of a shortest path, or None if the goal lies beyond `limit` (or is unreachable)."""
        source, target = self.node(start), self.node(goal)
        distance, predecessor = dijkstra(graph, directed=True, indices=source,
                                         return_predecessors=True, limit=limit)
        if not np.isfinite(distance[target]):
            return None
        nodes = [target]
        while nodes[-1] != source:
            nodes.append(int(predecessor[nodes[-1]]))
        return self.cell_of_node(np.array(nodes[::-1]))


def scipy_astar(cost: np.ndarray, start: tuple[int, int], goal: tuple[int, int], weight: float,
          cell: float = 1.0, slack: float = ASTAR_SLACK) -> SearchResult:
    """Exact least-cost 8-connected path from `start` to `goal` (row, col) on the metric above."""
    cost = check_search_inputs(cost, weight, cell)
    start, goal = _cell_tuple(start, cost.shape), _cell_tuple(goal, cost.shape)
    per_metre = cost_per_metre(cost, weight)
    if np.isinf(per_metre[start]) or np.isinf(per_metre[goal]):
        return NO_PATH
    if start == goal:
        return SearchResult(np.array([start], dtype=np.int64), 0.0)
    grid = GridGraph(per_metre, cell)
    # A*: Dijkstra on heuristic-reduced costs, limited to the ellipse f <= (1 + slack) * h(start).
    heuristic = octile_heuristic(cost.shape, goal, cell, _least_cost_per_metre(per_metre))
    limit = min(slack * heuristic[start], NO_LIMIT) if slack < np.inf else NO_LIMIT
    cells = grid.shortest_path(grid.csr(heuristic), start, goal, limit=limit)
    # Not inside the ellipse: the heuristic is loose here, and a full Dijkstra is the faster exact search.
    if cells is None:
        cells = grid.shortest_path(grid.csr(), start, goal, limit=NO_LIMIT)
    if cells is None:
        return NO_PATH
    return SearchResult(cells, path_cost(cells, cost, weight, cell))


def _least_cost_per_metre(per_metre: np.ndarray) -> float:
    finite = per_metre[np.isfinite(per_metre)]
    return float(finite.min()) if finite.size else 0.0


# --- the kernel against it ----------------------------------------------------------------------------

def random_cost_grid(rng: np.random.Generator, rows: int, cols: int, obstacle_density: float,
                     cost_scale: float) -> np.ndarray:
    cost = rng.random((rows, cols)) * cost_scale
    cost[rng.random((rows, cols)) < obstacle_density] = np.inf
    return cost


def assert_same_search(cost: np.ndarray, start, goal, weight: float, cell: float) -> SearchResult:
    """astar and scipy_astar agree: both find a path or neither, and on its cost to rounding."""
    result = astar(cost, start, goal, weight, cell)
    before = scipy_astar(cost, start, goal, weight, cell)
    assert result.found == before.found
    if not before.found:
        assert result.cells.shape == (0, 2) and result.cost == np.inf
        return result
    assert result.cost == pytest.approx(before.cost, rel=1e-12, abs=1e-9)
    cells = result.cells
    assert tuple(cells[0]) == tuple(start) and tuple(cells[-1]) == tuple(goal)
    assert (np.abs(np.diff(cells, axis=0)).max(axis=1) == 1).all(), "steps must be distinct 8-neighbours"
    assert np.isfinite(cost[cells[:, 0], cells[:, 1]]).all(), "the path enters a blocked cell"
    assert result.cost == path_cost(cells, cost, weight, cell)
    return result


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(rows=st.integers(1, 60), cols=st.integers(1, 60), seed=st.integers(0, 2**32 - 1),
       obstacle_density=st.sampled_from([0.0, 0.1, 0.3, 0.45, 0.6]),
       cost_scale=st.sampled_from([0.0, 1.0, 5.0, 1e3]),
       weight=st.one_of(st.just(0.0), st.just(1.0), st.floats(0.0, 1.0)),
       cell=st.sampled_from([0.05, 1.0, 0.3]),
       data=st.data())
def test_kernel_agrees_with_the_scipy_search_on_random_grids(rows, cols, seed, obstacle_density, cost_scale,
                                                             weight, cell, data):
    rng = np.random.default_rng(seed)
    cost = random_cost_grid(rng, rows, cols, obstacle_density, cost_scale)
    start = (data.draw(st.integers(0, rows - 1)), data.draw(st.integers(0, cols - 1)))
    goal = (data.draw(st.integers(0, rows - 1)), data.draw(st.integers(0, cols - 1)))
    assert_same_search(cost, start, goal, weight, cell)


@pytest.mark.parametrize("weight", [0.0, 0.3, 0.5, 1.0])
@pytest.mark.parametrize("seed", range(3))
def test_kernel_agrees_with_the_scipy_search_on_large_grids(weight, seed):
    rng = np.random.default_rng(seed)
    cost = random_cost_grid(rng, 240, 310, obstacle_density=0.1, cost_scale=1.0)
    for _ in range(4):
        start, goal = tuple(rng.integers(0, 240, 2)), (int(rng.integers(0, 240)), int(rng.integers(0, 310)))
        cost[start] = cost[goal] = 0.5
        assert_same_search(cost, start, goal, weight, 0.1)


@pytest.mark.parametrize("weight", [0.0, 0.6, 1.0])
def test_unreachable_goals(weight):
    rng = np.random.default_rng(7)
    cost = random_cost_grid(rng, 50, 70, obstacle_density=0.1, cost_scale=1.0)
    cost[20:31, 40] = cost[20:31, 50] = cost[20, 40:51] = cost[30, 40:51] = np.inf  # a closed box
    cost[25, 45] = cost[2, 3] = 0.2
    inside = assert_same_search(cost, (2, 3), (25, 45), weight, 0.1)
    outside = assert_same_search(cost, (25, 45), (2, 3), weight, 0.1)
    assert not inside.found and not outside.found
    assert_same_search(cost, (25, 45), (28, 48), weight, 0.1)  # within the box: found
    wall = np.zeros((30, 30))
    wall[:, 15] = np.inf
    assert_same_search(wall, (0, 0), (29, 29), weight, 1.0)
    # A diagonal step between two blocked cells is allowed (hazards are grown before the search).
    corner = np.zeros((2, 2))
    corner[0, 1] = corner[1, 0] = np.inf
    result = assert_same_search(corner, (0, 0), (1, 1), weight, 1.0)
    assert result.found and len(result.cells) == 2


def test_weight_outside_zero_one_is_refused_as_before():
    for weight in (-0.1, 1.5):
        for search in (astar, scipy_astar):
            with pytest.raises(ValueError, match="weight"):
                search(np.ones((4, 4)), (0, 0), (3, 3), weight)


def test_kernel_and_reference_costs_on_a_small_grid():
    """The kernel, the SciPy search and the edge-by-edge Dijkstra: one cost on a grid with obstacles."""
    rng = np.random.default_rng(3)
    cost = random_cost_grid(rng, 25, 25, obstacle_density=0.25, cost_scale=2.0)
    cost[0, 0] = cost[24, 24] = 0.0
    for weight in (0.0, 0.5, 1.0):
        result = astar(cost, (0, 0), (24, 24), weight, 0.2)
        assert result.cost == pytest.approx(dijkstra_reference(cost, (0, 0), (24, 24), weight, 0.2), abs=1e-9)
        assert result.cost == pytest.approx(scipy_astar(cost, (0, 0), (24, 24), weight, 0.2).cost, abs=1e-9)


def test_kernel_returns_no_nodes_when_the_goal_is_walled_off():
    cost = np.zeros((5, 5))
    cost[:, 2] = np.inf
    nodes = _astar_kernel.astar_nodes(cost.ravel(), 5, 5, 0.5, 0, 24, 1.0, 0.5)
    assert nodes.shape == (0,)
    assert _astar_kernel.astar_cells(cost, (0, 0), (4, 4), 0.5, 1.0) is None
    cells = _astar_kernel.astar_cells(cost, (0, 0), (4, 1), 0.5, 1.0)
    assert tuple(cells[0]) == (0, 0) and tuple(cells[-1]) == (4, 1) and len(cells) == 5
    assert path_cost(cells, cost, 0.5, 1.0) == pytest.approx(0.5 * (3 + SQRT2), abs=1e-12)


@pytest.mark.parametrize("shape", [(1, 1), (1, 9), (9, 1), (2, 2), (3, 7)])
def test_paths_along_the_grid_border(shape):
    """No padding ring: nodes on the border must neither step off the grid nor wrap to the other side."""
    rows, cols = shape
    cost = np.linspace(0.0, 1.0, rows * cols).reshape(shape)[:, ::-1].copy()
    for start in [(0, 0), (rows - 1, cols - 1), (0, cols - 1), (rows - 1, 0)]:
        for goal in [(0, 0), (rows - 1, cols - 1), (0, cols - 1), (rows - 1, 0)]:
            for weight in (0.0, 0.5, 1.0):
                result = assert_same_search(cost, start, goal, weight, 1.0)
                assert result.cost == pytest.approx(dijkstra_reference(cost, start, goal, weight, 1.0), abs=1e-12)
    # Flat index (0, 11) + 1 is (1, 0): a wrapped step would make this path one cell long.
    result = astar(np.zeros((4, 12)), (0, 11), (1, 0), 1.0)
    assert result.cost == pytest.approx(10 + SQRT2) and len(result.cells) == 12


def test_kernel_steps_are_the_neighbour_steps():
    assert list(zip(_astar_kernel.STEP_ROWS, _astar_kernel.STEP_COLS, strict=True)) == list(NEIGHBOUR_STEPS)


def test_slack_no_longer_changes_the_result():
    rng = np.random.default_rng(5)
    cost = random_cost_grid(rng, 80, 80, obstacle_density=0.1, cost_scale=1.0)
    cost[0, 0] = cost[79, 79] = 0.0
    results = [astar(cost, (0, 0), (79, 79), 0.7, 0.1, slack=slack) for slack in (0.0, ASTAR_SLACK, np.inf)]
    assert all(np.array_equal(r.cells, results[0].cells) and r.cost == results[0].cost for r in results)
