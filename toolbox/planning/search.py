"""Exact shortest paths on a cost grid: the planner's A*, its Dijkstra reference, and the path metric.

The metric. Each cell holds a cost c >= 0 (0 = flat, easy ground; 1 = as steep or rough as the rover
may go; more where penalties are added; +inf = impassable). With the weight w in [0, 1], a metre of
travel through a cell costs `w + (1 - w) * c`. The graph is 8-connected; a step between neighbours
u and v has length d = cell (straight) or sqrt(2) * cell (diagonal) and costs

    d * (w + (1 - w) * (c_u + c_v) / 2)  =  w * d + (1 - w) * terrain * d,   terrain = (c_u + c_v) / 2

i.e. an edge cost: half the step over each cell (the trapezoid rule along the step). It is symmetric,
so a path costs the same both ways, and it is the metric of scikit-image's `MCP_Geometric`, which
lets the benchmark compare costs exactly. w = 1 plans the shortest path, w = 0 the cheapest ground.
A diagonal step between two blocked cells is allowed: hazards are grown by the rover's radius and
a margin before the search, so the rover's body stays clear where its centre passes a corner.

The search. A* with the octile distance times the least cost per metre on the grid,
m = w + (1 - w) * min(c), as heuristic: every step costs at least m times its length and the octile
distance is the exact length of the shortest 8-connected path on an empty grid, so the heuristic is
admissible and consistent for every w, and it is 0 (plain Dijkstra, still exact) when m = 0.
It runs compiled (numba, _astar_kernel.py): a closed set and an indexed heap over flat indices of
the grid, stopping when the goal leaves the heap. On a 1000 x 1000
grid with random costs it is about 5 times faster than the SciPy Dijkstra on heuristic-reduced costs
it replaced, and no slower than pyastar2d; tests/bench/bench_astar.py measures both in one run.
The path's cost is then recomputed by `path_cost`, so it is the metric's definition to the last bit.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra

SQRT2 = float(np.sqrt(2.0))
# The 8 neighbour steps (d_row, d_col), in the order of _astar_kernel's STEP_ROWS and STEP_COLS.
NEIGHBOUR_STEPS = ((-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1))
# The default of astar's `slack`, which no longer does anything (it was the width of a goal-limited stage).
ASTAR_SLACK = 0.02


@dataclass(frozen=True)
class SearchResult:
    cells: np.ndarray  # (K, 2) int (row, col) from start to goal; (0, 2) when there is no path
    cost: float        # path cost on the metric above; inf when there is no path

    @property
    def found(self) -> bool:
        return bool(np.isfinite(self.cost))


NO_PATH = SearchResult(np.zeros((0, 2), dtype=np.int64), float("inf"))


def cost_per_metre(cost: np.ndarray, weight: float) -> np.ndarray:
    """`w + (1 - w) * c` per cell, +inf where the cell is impassable (even for w = 1)."""
    cost = np.asarray(cost, dtype=np.float64)
    impassable = np.isinf(cost)
    return np.where(impassable, np.inf, weight + (1.0 - weight) * np.where(impassable, 0.0, cost))


def step_cost(cost: np.ndarray, u: tuple[int, int], v: tuple[int, int], weight: float, cell: float) -> float:
    """Cost of one step between 8-neighbours u and v: the metric's definition, one edge at a time."""
    diagonal = u[0] != v[0] and u[1] != v[1]
    length = cell * (SQRT2 if diagonal else 1.0)
    per_metre = [math.inf if math.isinf(c) else weight + (1.0 - weight) * c for c in (cost[u], cost[v])]
    return length * (per_metre[0] + per_metre[1]) / 2.0


def path_cost(cells: np.ndarray, cost: np.ndarray, weight: float, cell: float) -> float:
    """Cost of an 8-connected cell path on the metric; inf if it enters an impassable cell."""
    cells = np.asarray(cells, dtype=np.int64).reshape(-1, 2)
    steps = np.abs(np.diff(cells, axis=0))
    if steps.size and (steps.max() > 1 or (steps.sum(axis=1) == 0).any()):
        raise ValueError("path_cost needs a path of distinct, 8-connected cells")
    per_metre = cost_per_metre(np.asarray(cost)[cells[:, 0], cells[:, 1]], weight)  # the path's cells only
    lengths = cell * np.where(steps.sum(axis=1) == 2, SQRT2, 1.0)
    return float(np.sum(lengths * (per_metre[:-1] + per_metre[1:]) / 2.0))


def check_search_inputs(cost: np.ndarray, weight: float, cell: float) -> np.ndarray:
    cost = np.asarray(cost, dtype=np.float64)
    if cost.ndim != 2 or cost.size == 0:
        raise ValueError(f"cost grid must be a non-empty 2-D array, got shape {cost.shape}")
    lowest = cost.min()  # one pass for both tests: the minimum is NaN if any cell is, else the least cost
    if np.isnan(lowest):
        raise ValueError("cost grid holds NaN: resolve unknown cells first (apply_unknown_policy)")
    if lowest < 0:
        raise ValueError("cost grid holds negative costs; costs must be >= 0 (+inf = impassable)")
    if not 0.0 <= weight <= 1.0:
        raise ValueError(f"weight must be in [0, 1], got {weight!r}")
    if not cell > 0:
        raise ValueError(f"cell size must be > 0, got {cell!r}")
    return cost


def astar(cost: np.ndarray, start: tuple[int, int], goal: tuple[int, int], weight: float,
          cell: float = 1.0, slack: float = ASTAR_SLACK) -> SearchResult:
    """Exact least-cost 8-connected path from `start` to `goal` (row, col) on the metric above.

    `slack` is no longer used (the compiled A* stops at the goal and needs no search limit); it stays
    so that callers which pass it keep working."""
    cost = check_search_inputs(cost, weight, cell)
    start, goal = _cell_tuple(start, cost.shape), _cell_tuple(goal, cost.shape)
    if cost.size >= 2**31:  # the kernel's heap holds int32 indices
        raise ValueError(f"a grid of {cost.shape[0]} x {cost.shape[1]} cells is too large")
    if np.isinf(cost[start]) or np.isinf(cost[goal]):
        return NO_PATH
    if start == goal:
        return SearchResult(np.array([start], dtype=np.int64), 0.0)
    # numba is imported with the kernel, on the first search rather than with the planner.
    from toolbox.planning import _astar_kernel
    cells = _astar_kernel.astar_cells(cost, start, goal, weight, cell)
    if cells is None:
        return NO_PATH
    return SearchResult(cells, path_cost(cells, cost, weight, cell))


def dijkstra_reference(cost: np.ndarray, start: tuple[int, int], goal: tuple[int, int], weight: float,
                       cell: float = 1.0) -> float:
    """Least path cost by a plain Dijkstra over a graph built edge by edge from `step_cost`.

    Slow and obvious on purpose: it shares nothing with `astar` but the metric's definition, so the
    tests and the benchmark can hold `astar` to it."""
    cost = check_search_inputs(cost, weight, cell)
    start, goal = _cell_tuple(start, cost.shape), _cell_tuple(goal, cost.shape)
    rows, cols = cost.shape
    sources, targets, weights = [], [], []
    for r in range(rows):
        for c in range(cols):
            for d_row, d_col in NEIGHBOUR_STEPS:
                r2, c2 = r + d_row, c + d_col
                if 0 <= r2 < rows and 0 <= c2 < cols:
                    edge = step_cost(cost, (r, c), (r2, c2), weight, cell)
                    if np.isfinite(edge):
                        sources.append(r * cols + c)
                        targets.append(r2 * cols + c2)
                        weights.append(edge)
    if np.isinf(cost[start]) or np.isinf(cost[goal]):
        return float("inf")
    graph = csr_matrix((weights, (sources, targets)), shape=(rows * cols, rows * cols))
    distance = dijkstra(graph, directed=True, indices=start[0] * cols + start[1])
    return float(distance[goal[0] * cols + goal[1]])


def _cell_tuple(cell: tuple[int, int], shape: tuple[int, int]) -> tuple[int, int]:
    row, col = int(cell[0]), int(cell[1])
    if not (0 <= row < shape[0] and 0 <= col < shape[1]):
        raise ValueError(f"cell {(row, col)} is outside the {shape[0]} x {shape[1]} grid")
    return row, col
