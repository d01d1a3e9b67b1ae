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
A* with a consistent heuristic h is Dijkstra on the reduced costs c(u, v) - h(u) + h(v) >= 0, and
that is how we run it: in SciPy's compiled Dijkstra, about 5 times faster on a 1000 x 1000 grid
than a compact Python heapq A* where the heuristic is loose, and faster still where it is tight.
SciPy cannot stop at the goal, so the heuristic pays only through its `limit`:
we first search the ellipse f = g + h <= (1 + slack) * h(start), which holds the goal whenever the
heuristic is tight (short paths on open ground, w near 1), and fall back to a full Dijkstra
otherwise. Both stages are exact; tests/bench/bench_astar.py measures what the first one buys.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra

SQRT2 = float(np.sqrt(2.0))
# The 8 neighbour steps (d_row, d_col); their order fixes the edge layout of the graph.
NEIGHBOUR_STEPS = ((-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1))
# Width of the first, goal-limited A* stage, as a fraction of h(start); measured in bench_astar.py.
ASTAR_SLACK = 0.02
# A finite "no limit": SciPy's Dijkstra pushes nodes reached at cost +inf when its limit is +inf.
NO_LIMIT = float(np.finfo(np.float64).max)


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
    per_metre = cost_per_metre(cost, weight)[cells[:, 0], cells[:, 1]]
    lengths = cell * np.where(steps.sum(axis=1) == 2, SQRT2, 1.0)
    return float(np.sum(lengths * (per_metre[:-1] + per_metre[1:]) / 2.0))


def check_search_inputs(cost: np.ndarray, weight: float, cell: float) -> np.ndarray:
    cost = np.asarray(cost, dtype=np.float64)
    if cost.ndim != 2 or cost.size == 0:
        raise ValueError(f"cost grid must be a non-empty 2-D array, got shape {cost.shape}")
    if np.isnan(cost).any():
        raise ValueError("cost grid holds NaN: resolve unknown cells first (apply_unknown_policy)")
    if (cost < 0).any():
        raise ValueError("cost grid holds negative costs; costs must be >= 0 (+inf = impassable)")
    if not 0.0 <= weight <= 1.0:
        raise ValueError(f"weight must be in [0, 1], got {weight!r}")
    if not cell > 0:
        raise ValueError(f"cell size must be > 0, got {cell!r}")
    return cost


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
        for slot, ((d_row, d_col), offset) in enumerate(zip(NEIGHBOUR_STEPS, self.offsets)):
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


def astar(cost: np.ndarray, start: tuple[int, int], goal: tuple[int, int], weight: float,
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


def _least_cost_per_metre(per_metre: np.ndarray) -> float:
    finite = per_metre[np.isfinite(per_metre)]
    return float(finite.min()) if finite.size else 0.0


def _cell_tuple(cell: tuple[int, int], shape: tuple[int, int]) -> tuple[int, int]:
    row, col = int(cell[0]), int(cell[1])
    if not (0 <= row < shape[0] and 0 <= col < shape[1]):
        raise ValueError(f"cell {(row, col)} is outside the {shape[0]} x {shape[1]} grid")
    return row, col
