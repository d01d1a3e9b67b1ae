"""The compiled A* of search.astar (numba), imported on the first search.

Importing numba costs about 110 MB and its first compilation about two seconds (cached on disk after),
so search.py loads this module when a search runs, not when the planner is imported.
The search is A* with a closed set over flat indices of the cost grid itself, its open set an indexed
4-ary min-heap (a node is in it at most once, its key lowered in place when a shorter way is found),
so every array is allocated once at the grid's size and nothing grows during the search. Only nodes
on the grid's border test their neighbours' bounds. The search is bound by memory (its arrays are far
larger than the caches), so it keeps them few and small: no per-metre copy of the grid (a padded one,
which spares the bounds tests, measured as fast on random ground and 1.5 ms slower per 1000 x 1000
grid where the search is short), int32 heap slots, int8 parent steps.
The metric, the step cost and the heuristic are search.py's, operation for operation:
`w + (1 - w) * c` per metre (a +inf cell is never entered), a step
`0.5 * length * (per_metre_u + per_metre_v)`, and h = least per-metre cost * cell * octile distance
to the goal. h is consistent, so a node's g is final when it leaves the heap, the goal's included:
the search stops there, exact.
Equal keys leave the heap in no set order; breaking ties on g (deeper first) measured slower on
random ground and gained little on open ground, and the exact cost does not depend on it.
"""
from __future__ import annotations

import numba
import numpy as np

SQRT2 = np.sqrt(2.0)
# The 8 neighbour steps (d_row, d_col) in search.NEIGHBOUR_STEPS' order.
STEP_ROWS = np.array([-1, -1, -1, 0, 0, 1, 1, 1], dtype=np.int64)
STEP_COLS = np.array([-1, 0, 1, -1, 1, -1, 0, 1], dtype=np.int64)
UNSEEN, CLOSED = 0, -1  # where[node]: these, or 1 + the node's heap slot while it is open
HEAP_ARITY = 4  # children per heap node: half the levels of a binary heap, measured 10 % faster here
# The search's array indices are cast to unsigned: numba then drops its negative-index wraparound (a
# shift, an and and an add per access), measured 15-20 % of the search's time. They are all >= 0.
u = numba.uint64


@numba.njit(cache=True, nogil=True, boundscheck=False)
def astar_nodes(cost: np.ndarray, rows: int, width: int, weight: float, source: int, target: int, cell: float,
                least: float) -> np.ndarray:
    """Flat indices of a least-cost path from source to target; empty when the target is unreachable.

    cost: the cost grid, flat (rows x width, C order, float64 >= 0, +inf blocked); weight, cell: as in
    search.astar; least: the least per-metre cost of a finite cell (the heuristic's slope; 0: Dijkstra)."""
    nodes = cost.shape[0]
    offsets = STEP_ROWS * width + STEP_COLS
    half_lengths = np.empty(8)
    for k in range(8):
        half_lengths[k] = 0.5 * cell * (SQRT2 if STEP_ROWS[k] != 0 and STEP_COLS[k] != 0 else 1.0)
    scale = least * cell
    # row = (node + 0.5) / width truncated, by a multiplication: exact while nodes < 2**31 (the
    # product's error, nodes / width * 2**-52, stays far below the 0.5 / width to the next integer),
    # and it saves an integer division per expanded node.
    inv_width = 1.0 / width
    goal_row, goal_col = target // width, target % width

    # UNSEEN (0), CLOSED or 1 + the node's heap slot while it is open.
    where = np.zeros(nodes, np.int32)
    g = np.empty(nodes)                # cost from the source, valid once seen
    parent = np.empty(nodes, np.int8)  # the step (0..7) that reached the node
    # The open set: a HEAP_ARITY-ary min-heap of f = g + h, keys and nodes in parallel arrays; the slots
    # past its end hold +inf so the pop compares whole families of children without bounds tests.
    heap_f = np.empty(nodes + HEAP_ARITY)
    heap_node = np.empty(nodes + HEAP_ARITY, np.int32)

    g[u(source)] = 0.0
    heap_f[u(0)], heap_node[u(0)] = 0.0, source
    where[u(source)] = 1
    size = 1
    found = False
    while size > 0:
        node = np.int64(heap_node[u(0)])
        size -= 1
        if size > 0:
            # Pop (Floyd's way): walk the root's hole down along the least children to a leaf, one
            # comparison per child and no test against the moved entry, then sift the last entry up
            # from there; it belongs near the bottom, so that walk is short.
            f, last = heap_f[u(size)], heap_node[u(size)]
            for j in range(HEAP_ARITY):
                heap_f[u(size + j)] = np.inf
            hole = 0
            while True:
                child = HEAP_ARITY * hole + 1
                if child >= size:
                    break
                # The least of the four children, branch-free (HEAP_ARITY = 4 written out).
                a = child + (heap_f[u(child + 1)] < heap_f[u(child)])
                b = child + 2 + (heap_f[u(child + 3)] < heap_f[u(child + 2)])
                child = b if heap_f[u(b)] < heap_f[u(a)] else a
                heap_f[u(hole)], heap_node[u(hole)] = heap_f[u(child)], heap_node[u(child)]
                where[u(heap_node[u(hole)])] = hole + 1
                hole = child
            while hole > 0:
                up = (hole - 1) // HEAP_ARITY
                if not f < heap_f[u(up)]:
                    break
                heap_f[u(hole)], heap_node[u(hole)] = heap_f[u(up)], heap_node[u(up)]
                where[u(heap_node[u(hole)])] = hole + 1
                hole = up
            heap_f[u(hole)], heap_node[u(hole)] = f, last
            where[u(last)] = hole + 1
        where[u(node)] = CLOSED
        if node == target:
            found = True
            break
        g_node = g[u(node)]
        per_metre = weight + (1.0 - weight) * cost[u(node)]
        row = np.int64((node + 0.5) * inv_width)
        col = node - row * width
        border = row == 0 or row == rows - 1 or col == 0 or col == width - 1
        for k in range(8):
            if border:
                next_row, next_col = row + STEP_ROWS[k], col + STEP_COLS[k]
                if next_row < 0 or next_row >= rows or next_col < 0 or next_col >= width:
                    continue
            neighbour = node + offsets[k]
            slot = where[u(neighbour)]
            if slot == CLOSED:
                continue
            cost_next = cost[u(neighbour)]
            if cost_next == np.inf:  # blocked (and 0 * inf would be NaN for w = 1)
                continue
            g_new = g_node + half_lengths[k] * (per_metre + (weight + (1.0 - weight) * cost_next))
            if slot > 0:       # open: lower its key if this way is shorter
                if not g_new < g[u(neighbour)]:
                    continue
                hole = slot - 1
            else:              # unseen: a new leaf (unless the sum overflowed to +inf)
                if not g_new < np.inf:
                    continue
                hole = size
                size += 1
            d_row = abs(row + STEP_ROWS[k] - goal_row)
            d_col = abs(col + STEP_COLS[k] - goal_col)
            f = g_new + scale * (max(d_row, d_col) + (SQRT2 - 1.0) * min(d_row, d_col))
            g[u(neighbour)] = g_new
            parent[u(neighbour)] = k
            # Sift up (written out twice: as an inlined numba function it measured 15 % slower).
            while hole > 0:
                up = (hole - 1) // HEAP_ARITY
                if not f < heap_f[u(up)]:
                    break
                heap_f[u(hole)], heap_node[u(hole)] = heap_f[u(up)], heap_node[u(up)]
                where[u(heap_node[u(hole)])] = hole + 1
                hole = up
            heap_f[u(hole)], heap_node[u(hole)] = f, neighbour
            where[u(neighbour)] = hole + 1

    if not found:
        return np.empty(0, np.int64)
    steps = 1
    node = np.int64(target)
    while node != source:
        node -= offsets[parent[node]]
        steps += 1
    path = np.empty(steps, np.int64)
    node = np.int64(target)
    for i in range(steps - 1, -1, -1):
        path[i] = node
        if i:
            node -= offsets[parent[node]]
    return path


def astar_cells(cost: np.ndarray, start: tuple[int, int], goal: tuple[int, int], weight: float,
                cell: float) -> np.ndarray | None:
    """(K, 2) int64 (row, col) of a least-cost path from start to goal on a checked float64 grid, or None."""
    rows, cols = cost.shape
    weight = float(weight)
    flat = np.ascontiguousarray(cost).ravel()
    # The least per-metre cost is that of the least cost (w + (1 - w) * c rises with c, rounding too);
    # +inf, the maximum, is the minimum only when every cell is blocked.
    lowest = float(flat.min())
    least = weight + (1.0 - weight) * lowest if lowest < np.inf else 0.0
    nodes = astar_nodes(flat, rows, cols, weight, start[0] * cols + start[1], goal[0] * cols + goal[1],
                        float(cell), least)
    if nodes.size == 0:
        return None
    cells = np.empty((nodes.size, 2), np.int64)
    np.divmod(nodes, cols, out=(cells[:, 0], cells[:, 1]))
    return cells
