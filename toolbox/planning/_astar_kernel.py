"""The compiled A* of search.astar (numba), imported on the first search.

Importing numba costs about 110 MB and its first compilation about two seconds (cached on disk after),
so search.py loads this module when a search runs, not when the planner is imported.
One pass builds the padded per-metre grid (a ring of impassable cells, so no step needs a bounds
test), the second is the search: A* with a closed set over flat indices of that padded grid, its open
set an indexed 4-ary min-heap (a node is in it at most once, its key lowered in place when a shorter
way is found), so every array is allocated once at the grid's size and nothing grows during the search.
The metric, the step cost and the heuristic are search.py's, operation for operation:
`w + (1 - w) * c` per metre (+inf where c is), a step `0.5 * length * (per_metre_u + per_metre_v)`,
and h = least per-metre cost * cell * octile distance to the goal. h is consistent, so a node's g is
final when it leaves the heap, the goal's included: the search stops there, exact.
Equal keys leave the heap in no set order; breaking ties on g (deeper first) measured slower on
random ground and gained little on open ground, and the exact cost does not depend on it.
On tests/bench/bench_astar.py's 1000 x 1000 grid (random costs, w = 0.5) it took 69 ms beside 74 ms
for pyastar2d (C++, a weaker metric) and 341 ms for the SciPy search it replaced; a binary heap ~77 ms.
"""
from __future__ import annotations

import numba
import numpy as np

SQRT2 = np.sqrt(2.0)
# The 8 neighbour steps (d_row, d_col) in search.NEIGHBOUR_STEPS' order.
STEP_ROWS = np.array([-1, -1, -1, 0, 0, 1, 1, 1], dtype=np.int64)
STEP_COLS = np.array([-1, 0, 1, -1, 1, -1, 0, 1], dtype=np.int64)
UNSEEN, CLOSED = 0, -1  # where[node]: these, or 1 + the node's heap slot while it is open


@numba.njit(cache=True, nogil=True, boundscheck=False)
def padded_cost_per_metre(cost, weight):
    """(rows + 2) * (cols + 2) flat `w + (1 - w) * c` (+inf where c is, and on the ring), and its least finite value."""
    rows, cols = cost.shape
    width = cols + 2
    per_metre = np.empty((rows + 2) * width)
    per_metre[:width] = np.inf
    per_metre[(rows + 1) * width:] = np.inf
    least = np.inf
    for r in range(rows):
        base = (r + 1) * width
        per_metre[base] = np.inf
        per_metre[base + width - 1] = np.inf
        for c in range(cols):
            value = cost[r, c]
            if value == np.inf:
                per_metre[base + 1 + c] = np.inf
            else:
                value = weight + (1.0 - weight) * value
                per_metre[base + 1 + c] = value
                least = min(least, value)
    return per_metre, (least if least < np.inf else 0.0)


HEAP_ARITY = 4  # children per heap node: half the levels of a binary heap, measured 10 % faster here


@numba.njit(cache=True, nogil=True, boundscheck=False)
def astar_nodes(per_metre, width, source, target, cell, least):
    """Flat padded indices of a least-cost path from source to target; empty when the target is unreachable.

    per_metre: the flat padded grid of padded_cost_per_metre, `width` its row length; cell: the cell size;
    least: the least finite per-metre cost (the heuristic's slope, 0 for plain Dijkstra)."""
    nodes = per_metre.shape[0]
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

    # UNSEEN, CLOSED or 1 + heap slot; zeros, so pages of the grid the search never reaches stay unmapped.
    where = np.zeros(nodes, np.int32)
    g = np.empty(nodes)                # cost from the source, valid once seen
    parent = np.empty(nodes, np.int8)  # the step (0..7) that reached the node
    # The open set: a HEAP_ARITY-ary min-heap of f = g + h, keys and nodes in parallel arrays; the slots
    # past its end hold +inf so the pop compares whole families of children without bounds tests.
    heap_f = np.empty(nodes + HEAP_ARITY)
    heap_node = np.empty(nodes + HEAP_ARITY, np.int32)

    g[source] = 0.0
    heap_f[0], heap_node[0] = 0.0, source
    where[source] = 1
    size = 1
    found = False
    while size > 0:
        node = np.int64(heap_node[0])
        size -= 1
        if size > 0:
            # Pop (Floyd's way): walk the root's hole down along the least children to a leaf, one
            # comparison per child and no test against the moved entry, then sift the last entry up
            # from there; it belongs near the bottom, so that walk is short.
            f, last = heap_f[size], heap_node[size]
            for j in range(HEAP_ARITY):
                heap_f[size + j] = np.inf
            hole = 0
            while True:
                child = HEAP_ARITY * hole + 1
                if child >= size:
                    break
                # The least of the four children, branch-free (HEAP_ARITY = 4 written out).
                a = child + (heap_f[child + 1] < heap_f[child])
                b = child + 2 + (heap_f[child + 3] < heap_f[child + 2])
                child = b if heap_f[b] < heap_f[a] else a
                heap_f[hole], heap_node[hole] = heap_f[child], heap_node[child]
                where[heap_node[hole]] = hole + 1
                hole = child
            while hole > 0:
                up = (hole - 1) // HEAP_ARITY
                if not f < heap_f[up]:
                    break
                heap_f[hole], heap_node[hole] = heap_f[up], heap_node[up]
                where[heap_node[hole]] = hole + 1
                hole = up
            heap_f[hole], heap_node[hole] = f, last
            where[last] = hole + 1
        where[node] = CLOSED
        if node == target:
            found = True
            break
        g_node, cost_node = g[node], per_metre[node]
        row = np.int64((node + 0.5) * inv_width)
        col = node - row * width
        for k in range(8):
            neighbour = node + offsets[k]
            slot = where[neighbour]
            if slot == CLOSED:
                continue
            # A +inf per-metre cost (blocked, or the padding ring) gives g_new = +inf: never taken.
            g_new = g_node + half_lengths[k] * (cost_node + per_metre[neighbour])
            if slot > 0:       # open: lower its key if this way is shorter
                if not g_new < g[neighbour]:
                    continue
                hole = slot - 1
            else:              # unseen: a new leaf
                if not g_new < np.inf:
                    continue
                hole = size
                size += 1
            d_row = abs(row + STEP_ROWS[k] - goal_row)
            d_col = abs(col + STEP_COLS[k] - goal_col)
            f = g_new + scale * (max(d_row, d_col) + (SQRT2 - 1.0) * min(d_row, d_col))
            g[neighbour] = g_new
            parent[neighbour] = k
            # Sift up (written out twice: as an inlined numba function it measured 15 % slower).
            while hole > 0:
                up = (hole - 1) // HEAP_ARITY
                if not f < heap_f[up]:
                    break
                heap_f[hole], heap_node[hole] = heap_f[up], heap_node[up]
                where[heap_node[hole]] = hole + 1
                hole = up
            heap_f[hole], heap_node[hole] = f, neighbour
            where[neighbour] = hole + 1

    if not found:
        return np.empty(0, np.int64)
    steps = 1
    node = target
    while node != source:
        node -= offsets[parent[node]]
        steps += 1
    path = np.empty(steps, np.int64)
    node = target
    for i in range(steps - 1, -1, -1):
        path[i] = node
        if i:
            node -= offsets[parent[node]]
    return path


def astar_cells(cost: np.ndarray, start: tuple[int, int], goal: tuple[int, int], weight: float,
                cell: float) -> np.ndarray | None:
    """(K, 2) int64 (row, col) of a least-cost path from start to goal on a checked float64 grid, or None."""
    width = cost.shape[1] + 2
    per_metre, least = padded_cost_per_metre(np.ascontiguousarray(cost), float(weight))
    source = (start[0] + 1) * width + start[1] + 1
    target = (goal[0] + 1) * width + goal[1] + 1
    nodes = astar_nodes(per_metre, width, source, target, float(cell), least)
    if nodes.size == 0:
        return None
    cells = np.empty((nodes.size, 2), np.int64)
    np.divmod(nodes, width, out=(cells[:, 0], cells[:, 1]))
    return cells - 1
