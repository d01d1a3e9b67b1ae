"""Benchmark: the planner's A* on a 1000 x 1000 cost grid beside pyastar2d and scikit-image's MCP_Geometric.

All three run in the same process on the same grid (random costs with obstacles, corner to corner),
so the ratios hold on a shared, noisy machine where absolute figures do not. Every path is scored on
our metric (planning_search): ours is exact, so its cost must be <= theirs. MCP_Geometric uses the
same metric and is exact too, so its cost should equal ours; pyastar2d charges a diagonal step like
a straight one and finds a path that is optimal for that metric only.

A second scenario (w = 1) shows the goal-limited A* stage at work; `--slack` sweeps that stage's width.
A compact pure-Python heapq A* (flat indices, precomputed neighbour offsets, early exit at the goal)
runs beside them: it is the design we did not take, kept here so the choice stays measured.

    pip install pyastar2d scikit-image    # bench-only, not runtime dependencies
    .venv/bin/python tests/bench/bench_astar.py [--size 1000] [--repeats 3] [--seed 0]
"""
from __future__ import annotations

import argparse
import heapq
import math
import sys
import time
from pathlib import Path

import numpy as np
from scipy.ndimage import binary_dilation

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))
from toolbox.planning import search as planning_search  # noqa: E402
from toolbox.planning.search import SQRT2, astar, cost_per_metre, path_cost  # noqa: E402


def cost_grid(size: int, seed: int) -> np.ndarray:
    """Uniform random terrain cost in [0, 1], ~10 % single-cell obstacles and some grown rocks."""
    rng = np.random.default_rng(seed)
    cost = rng.random((size, size))
    obstacles = rng.random((size, size)) < 0.08
    obstacles |= binary_dilation(rng.random((size, size)) < 0.0005, iterations=4)
    cost[obstacles] = np.inf
    cost[0, 0] = cost[-1, -1] = 0.0
    return cost


def best_time(run, repeats: int):
    best, result = np.inf, None
    for _ in range(repeats):
        started = time.perf_counter()
        result = run()
        best = min(best, time.perf_counter() - started)
    return best, result


def run_ours(cost, start, goal, weight, slack=planning_search.ASTAR_SLACK):
    return astar(cost, start, goal, weight, 1.0, slack=slack).cells


def run_heapq_astar(per_metre, start, goal):
    """A* in pure Python on the same metric and heuristic, over flat indices of a padded grid."""
    rows, cols = per_metre.shape
    width = cols + 2
    padded = np.full((rows + 2, width), np.inf)
    padded[1:-1, 1:-1] = per_metre
    cost = padded.ravel().tolist()
    least = float(per_metre[np.isfinite(per_metre)].min())
    steps = [(dr * width + dc, 0.5 * (SQRT2 if dr and dc else 1.0))
             for dr in (-1, 0, 1) for dc in (-1, 0, 1) if dr or dc]
    source, target = (start[0] + 1) * width + start[1] + 1, (goal[0] + 1) * width + goal[1] + 1
    goal_row, goal_col = divmod(target, width)

    def heuristic(node):
        d_row, d_col = abs(node // width - goal_row), abs(node % width - goal_col)
        return least * (max(d_row, d_col) + (SQRT2 - 1.0) * min(d_row, d_col))

    g = [math.inf] * len(cost)
    parent = [-1] * len(cost)
    closed = bytearray(len(cost))
    g[source] = 0.0
    frontier = [(heuristic(source), source)]
    while frontier:
        _, node = heapq.heappop(frontier)
        if closed[node]:
            continue
        if node == target:
            break
        closed[node] = 1
        g_node, cost_node = g[node], cost[node]
        for offset, half_length in steps:
            neighbour = node + offset
            if closed[neighbour] or cost[neighbour] == math.inf:
                continue
            g_new = g_node + half_length * (cost_node + cost[neighbour])
            if g_new < g[neighbour]:
                g[neighbour], parent[neighbour] = g_new, node
                heapq.heappush(frontier, (g_new + heuristic(neighbour), neighbour))
    path = [target]
    while path[-1] != source:
        path.append(parent[path[-1]])
    return np.array([divmod(node, width) for node in path[::-1]]) - 1


def run_pyastar2d(weights32, start, goal):
    import pyastar2d
    return pyastar2d.astar_path(weights32, start, goal, allow_diagonal=True)


def run_mcp(per_metre, start, goal):
    from skimage.graph import MCP_Geometric
    mcp = MCP_Geometric(per_metre, fully_connected=True)
    mcp.find_costs([start], [goal])
    return np.array(mcp.traceback(goal))


def bench_scenario(name: str, cost: np.ndarray, weight: float, repeats: int) -> None:
    start, goal = (0, 0), (cost.shape[0] - 1, cost.shape[1] - 1)
    per_metre = cost_per_metre(cost, weight)
    # pyastar2d needs float32 weights >= 1: the per-metre cost scaled so its cheapest cell costs 1.
    weights32 = (per_metre / per_metre[np.isfinite(per_metre)].min()).astype(np.float32)
    runs = {
        "ours (A* + Dijkstra, SciPy)": lambda: run_ours(cost, start, goal, weight),
        "pyastar2d (C++ A*)": lambda: run_pyastar2d(weights32, start, goal),
        "skimage MCP_Geometric": lambda: run_mcp(per_metre, start, goal),
        "pure-Python heapq A*": lambda: run_heapq_astar(per_metre, start, goal),
    }
    print(f"\n{name}: {cost.shape[0]} x {cost.shape[1]}, w = {weight}, "
          f"{np.isinf(cost).mean():.1%} blocked, corner to corner, best of {repeats}")
    header = ("planner", "time s", "ours/them", "path cost (our metric)", "cells")
    print("  {:30s} {:>8s} {:>10s} {:>24s} {:>6s}".format(*header))
    times, costs = {}, {}
    for label, run in runs.items():
        times[label], cells = best_time(run, repeats)
        costs[label] = path_cost(np.asarray(cells), cost, weight, 1.0)
        ours = next(iter(times))
        ratio = times[ours] / times[label]
        print(f"  {label:30s} {times[label]:8.3f} {ratio:10.2f} {costs[label]:24.9f} {len(cells):6d}")
    ours_cost = costs[next(iter(costs))]
    worst_gap = min(c - ours_cost for c in costs.values())
    print(f"  ours <= every other path cost: {worst_gap >= -1e-9} (smallest margin {worst_gap:+.3e})")


def sweep_slack(cost: np.ndarray, weight: float, repeats: int, slacks: list[float]) -> None:
    start, goal = (0, 0), (cost.shape[0] - 1, cost.shape[1] - 1)
    print(f"\n  A* stage width (slack) sweep, w = {weight}:", end="")
    for slack in slacks:
        elapsed, _ = best_time(lambda: run_ours(cost, start, goal, weight, slack), repeats)
        print(f"  {slack:g}: {elapsed:.3f} s", end="")
    print()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--size", type=int, default=1000)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--slack", type=float, nargs="*", default=[0.0, 0.02, 0.05, 0.1])
    args = parser.parse_args()
    cost = cost_grid(args.size, args.seed)
    for weight in (0.5, 1.0):
        bench_scenario("random costs with obstacles", cost, weight, args.repeats)
        if args.slack:
            sweep_slack(cost, weight, args.repeats, args.slack)


if __name__ == "__main__":
    main()
