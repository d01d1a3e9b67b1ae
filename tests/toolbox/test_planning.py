"""Tests of the path planner (rvs_server/toolbox/planning*.py): exactness of A* against a Dijkstra
reference, the metric, hazard inflation, unknown-cell policies, map fusion, straight segments,
the drivable prefix, and the reasons given when there is no path."""
from __future__ import annotations

import math
import tomllib

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from toolbox.grid import GridSpec
from toolbox.planning import (
    MapLayers,
    PlanningParams,
    apply_unknown_policy,
    astar,
    blank_map_spanning,
    cells_to_world,
    dijkstra_reference,
    distance_to_border,
    douglas_peucker,
    drivable_prefix,
    fuse_maps,
    inflate_hazards,
    keep_route,
    path_cost,
    path_length,
    plan_path,
    polyline_cost,
    proximity_cost,
    resample_onto,
    segment_cells,
    segment_is_clear,
    simplify_path,
    terrain_cost,
    world_to_cells,
)
from toolbox.planning.search import ASTAR_SLACK

from conftest import REPO

SQRT2 = math.sqrt(2.0)


def random_cost_grid(rng: np.random.Generator, rows: int, cols: int, obstacle_density: float,
                     cost_scale: float) -> np.ndarray:
    cost = rng.random((rows, cols)) * cost_scale
    cost[rng.random((rows, cols)) < obstacle_density] = np.inf
    return cost


def assert_valid_path(cells: np.ndarray, cost: np.ndarray, start, goal) -> None:
    assert tuple(cells[0]) == tuple(start) and tuple(cells[-1]) == tuple(goal)
    steps = np.abs(np.diff(cells, axis=0))
    assert (steps.max(axis=1) == 1).all(), "consecutive cells must be distinct 8-neighbours"
    assert np.isfinite(cost[cells[:, 0], cells[:, 1]]).all(), "the path enters a blocked cell"


# --- A*: exact, on one metric ---------------------------------------------------------------------

@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(rows=st.integers(1, 40), cols=st.integers(1, 40), seed=st.integers(0, 2**32 - 1),
       obstacle_density=st.sampled_from([0.0, 0.1, 0.3, 0.5]),
       cost_scale=st.sampled_from([0.0, 1.0, 5.0]),
       weight=st.one_of(st.just(0.0), st.just(1.0), st.floats(0.0, 1.0)),
       cell=st.sampled_from([0.05, 1.0, 0.3]),
       slack=st.sampled_from([0.0, ASTAR_SLACK, math.inf]),
       data=st.data())
def test_astar_cost_equals_dijkstra_reference(rows, cols, seed, obstacle_density, cost_scale, weight, cell,
                                              slack, data):
    rng = np.random.default_rng(seed)
    cost = random_cost_grid(rng, rows, cols, obstacle_density, cost_scale)
    start = (data.draw(st.integers(0, rows - 1)), data.draw(st.integers(0, cols - 1)))
    goal = (data.draw(st.integers(0, rows - 1)), data.draw(st.integers(0, cols - 1)))

    result = astar(cost, start, goal, weight, cell, slack=slack)
    reference = dijkstra_reference(cost, start, goal, weight, cell)

    if math.isinf(reference):
        assert not result.found and len(result.cells) == 0
        return
    assert result.cost == pytest.approx(reference, rel=0, abs=1e-9)
    assert_valid_path(result.cells, cost, start, goal)
    assert path_cost(result.cells, cost, weight, cell) == pytest.approx(result.cost, rel=0, abs=1e-12)


@pytest.mark.parametrize("weight", [0.0, 0.25, 1.0])
def test_astar_matches_reference_on_full_size_grids(weight):
    rng = np.random.default_rng(int(weight * 100))
    for _ in range(8):
        cost = random_cost_grid(rng, 40, 40, obstacle_density=0.2, cost_scale=2.0)
        start, goal = tuple(rng.integers(0, 40, 2)), tuple(rng.integers(0, 40, 2))
        cost[start] = cost[goal] = 0.5
        result = astar(cost, start, goal, weight, 0.1)
        reference = dijkstra_reference(cost, start, goal, weight, 0.1)
        assert result.cost == pytest.approx(reference, rel=0, abs=1e-9)


def test_straight_line_on_an_empty_grid():
    cost = np.zeros((11, 30))
    result = astar(cost, (5, 2), (5, 27), weight=0.5, cell=0.1)
    assert (result.cells[:, 0] == 5).all() and len(result.cells) == 26
    assert result.cost == pytest.approx(0.5 * 25 * 0.1, abs=1e-12)  # w per metre on zero-cost ground
    assert len(simplify_path(result.cells, np.isinf(cost), 0.5)) == 2


def test_diagonal_step_costs_sqrt2():
    cost = np.full((20, 20), 0.4)
    result = astar(cost, (0, 0), (12, 12), weight=0.3, cell=0.2)
    per_metre = 0.3 + 0.7 * 0.4
    assert len(result.cells) == 13 and (result.cells[:, 0] == result.cells[:, 1]).all()
    assert result.cost == pytest.approx(12 * SQRT2 * 0.2 * per_metre, abs=1e-12)
    assert path_cost(np.array([[0, 0], [1, 1]]), cost, 1.0, 1.0) == pytest.approx(SQRT2)
    assert path_cost(np.array([[0, 0], [0, 1]]), cost, 1.0, 1.0) == pytest.approx(1.0)


def test_edge_cost_is_the_mean_of_the_two_cells():
    cost = np.array([[0.0, 1.0]])
    assert path_cost(np.array([[0, 0], [0, 1]]), cost, weight=0.0, cell=2.0) == pytest.approx(1.0)


def test_weight_trades_distance_for_ground():
    cost = np.ones((21, 21))
    cost[:, 0] = cost[20, :] = 0.0  # a free road round two sides
    detour = astar(cost, (0, 0), (20, 20), weight=0.0)
    direct = astar(cost, (0, 0), (20, 20), weight=1.0)
    assert detour.cost == pytest.approx(0.0) and (detour.cells[:, 1] == 0).sum() > 10
    assert direct.cost == pytest.approx(20 * SQRT2) and len(direct.cells) == 21


def test_astar_rejects_bad_input():
    with pytest.raises(ValueError, match="NaN"):
        astar(np.full((3, 3), np.nan), (0, 0), (2, 2), 0.5)
    with pytest.raises(ValueError, match="negative"):
        astar(-np.ones((3, 3)), (0, 0), (2, 2), 0.5)
    with pytest.raises(ValueError, match="weight"):
        astar(np.ones((3, 3)), (0, 0), (2, 2), 1.5)
    with pytest.raises(ValueError, match="outside"):
        astar(np.ones((3, 3)), (0, 0), (3, 2), 0.5)
    with pytest.raises(ValueError, match="8-connected"):
        path_cost(np.array([[0, 0], [0, 2]]), np.ones((3, 3)), 0.5, 1.0)


def test_free_ground_at_zero_weight_costs_nothing():
    result = astar(np.zeros((5, 9)), (0, 0), (4, 8), weight=0.0)
    assert result.found and result.cost == 0.0
    assert dijkstra_reference(np.zeros((5, 9)), (0, 0), (4, 8), 0.0) == 0.0


def test_astar_start_equals_goal_and_blocked_endpoints():
    cost = np.zeros((4, 4))
    cost[3, 3] = np.inf
    assert astar(cost, (1, 1), (1, 1), 0.5).cost == 0.0
    assert not astar(cost, (0, 0), (3, 3), 0.5).found


# --- costs -----------------------------------------------------------------------------------------

def test_terrain_cost_takes_the_worse_of_slope_and_roughness():
    slope = np.array([[0.0, 0.1, 0.4, np.nan]])
    roughness = np.array([[0.02, 0.0, 0.0, 0.0]])
    cost = terrain_cost(slope, 0.2, roughness, 0.04)
    assert cost[0, :3] == pytest.approx([0.5, 0.5, 1.0])  # over the limit clips to 1
    assert np.isnan(cost[0, 3])
    with pytest.raises(ValueError):
        terrain_cost(slope, 0.0)


def test_inflation_grows_hazards_by_the_clearance():
    hazard = np.zeros((21, 21), dtype=bool)
    hazard[10, 10] = True
    inflated = inflate_hazards(hazard, cell=0.1, clearance_m=0.25)
    rows, cols = np.nonzero(inflated.mask)
    assert ((rows - 10) ** 2 + (cols - 10) ** 2 <= 2.5 ** 2).all() and len(rows) == 21  # lattice disk r = 2.5
    assert inflated.distance_m[10, 13] == pytest.approx(0.3)
    assert inflated.distance_m[10, 10] == 0.0
    # An exact multiple of the cell size is inside despite 3 * 0.1 != 0.3 in floating point.
    assert inflate_hazards(hazard, 0.1, 0.3).mask[10, 13]
    assert not inflate_hazards(np.zeros((3, 3), bool), 0.1, 0.3).mask.any()


def test_proximity_cost_falls_off_beyond_the_clearance():
    distance = np.array([0.0, 0.4, 0.5, 0.6, 1.0])
    assert proximity_cost(distance, 0.4, 0.2) == pytest.approx([1.0, 1.0, 0.5, 0.0, 0.0])
    assert not proximity_cost(distance, 0.4, 0.0).any()


def test_proximity_cost_keeps_paths_off_hazards():
    spec = GridSpec(0.0, 0.0, 0.1, 30, 60)
    hazard = np.zeros(spec.shape, dtype=bool)
    hazard[:14, 30] = True  # a wall from the south edge, the path goes round its end
    layers = MapLayers(spec, np.zeros(spec.shape), hazard, np.zeros(spec.shape, bool))
    tight = plan_path(layers, (0.5, 0.5), (5.5, 0.5), PlanningParams(rover_radius_m=0.2, hazard_margin_m=0.0))
    wide = plan_path(layers, (0.5, 0.5), (5.5, 0.5),
                     PlanningParams(rover_radius_m=0.2, hazard_margin_m=0.0, proximity_falloff_m=0.5,
                                    proximity_cost=1.0))
    def closest_approach(result):
        return result.hazards.distance_m[result.cells[:, 0], result.cells[:, 1]].min()

    assert closest_approach(tight) < 0.25 < closest_approach(wide)
    assert wide.length_m > tight.length_m


def test_unknown_policies():
    cost = np.zeros((3, 3))
    unknown = np.zeros((3, 3), dtype=bool)
    unknown[1, 1] = True
    assert apply_unknown_policy(cost, unknown, "forbid")[1, 1] == np.inf
    assert apply_unknown_policy(cost, unknown, "allow")[1, 1] == 0.0
    assert apply_unknown_policy(cost, unknown, "penalize", 0.7)[1, 1] == 0.7
    with pytest.raises(ValueError, match="policy"):
        apply_unknown_policy(cost, unknown, "ignore")


def test_unknown_policies_in_planning():
    spec = GridSpec(0.0, 0.0, 1.0, 9, 20)
    cost = np.zeros(spec.shape)
    cost[:, 8:12] = np.nan  # an unseen band across the map but for a known gap in the north
    cost[8, 8:12] = 0.0
    layers = MapLayers.from_cost(spec, cost)
    start, goal = (2.5, 0.5), (17.5, 0.5)
    base = dict(weight=0.5, rover_radius_m=0.0, hazard_margin_m=0.0)
    allow = plan_path(layers, start, goal, PlanningParams(unknown_policy="allow", **base))
    forbid = plan_path(layers, start, goal, PlanningParams(unknown_policy="forbid", **base))
    penalize = plan_path(layers, start, goal,
                         PlanningParams(unknown_policy="penalize", unknown_cost=1.0, **base))
    assert allow.cost == pytest.approx(0.5 * 15) and (allow.cells[:, 0] == 0).all()  # straight through
    assert (forbid.cells[:, 0] == 8).any() and forbid.cost > allow.cost  # round by the known gap
    assert allow.cost < penalize.cost <= forbid.cost
    cost[8, 8:12] = np.nan
    closed = plan_path(MapLayers.from_cost(spec, cost), start, goal,
                       PlanningParams(unknown_policy="forbid", **base))
    assert closed.reason == "unreachable" and "unknown" in closed.message


# --- fusion ----------------------------------------------------------------------------------------

def test_fusion_of_a_coarse_global_map_with_a_fine_local_map():
    global_spec = GridSpec(0.0, 0.0, 0.5, 4, 4)
    global_cost = np.full(global_spec.shape, 0.2)
    global_cost[3, :] = np.nan  # the north row is unknown to the global map
    global_hazard = np.zeros(global_spec.shape, dtype=bool)
    global_hazard[0, 3] = True
    global_map = MapLayers.from_cost(global_spec, global_cost, global_hazard)

    local_spec = GridSpec(0.5, 0.5, 0.1, 10, 10)  # covers global cells rows 1-2, cols 1-2 exactly
    local_cost = np.full(local_spec.shape, 0.1)
    local_cost[0, 0] = 0.9       # one steep fine cell inside global cell (1, 1)
    local_cost[5:, 5:] = np.nan  # the local map has not seen global cell (2, 2)
    local_hazard = np.zeros(local_spec.shape, dtype=bool)
    local_hazard[3, 7] = True    # one small rock inside global cell (1, 2)
    local_map = MapLayers.from_cost(local_spec, local_cost, local_hazard)

    fused = fuse_maps(global_map, [local_map])
    assert fused.hazard[1, 2] and fused.hazard[0, 3] and fused.hazard.sum() == 2  # any hazard wins
    assert fused.cost[1, 1] == pytest.approx(0.9)  # the max over the covered area
    assert fused.cost[2, 1] == pytest.approx(0.2)  # max(global 0.2, local 0.1)
    assert fused.cost[2, 2] == pytest.approx(0.2)  # only the global map knows it
    assert fused.unknown[3, :].all() and fused.unknown.sum() == 4


def test_local_map_fills_unknown_global_cells_and_overhanging_parts_are_dropped():
    global_map = blank_map_spanning((0.0, 0.0), (2.0, 1.0), cell=0.5, margin_m=0.0)
    local_spec = GridSpec(1.5, 0.5, 0.25, 4, 4)  # hangs 0.5 m over the east edge
    local_map = MapLayers.from_cost(local_spec, np.full(local_spec.shape, 0.3))
    fused = fuse_maps(global_map, [local_map])
    assert fused.spec.shape == (2, 4)
    assert not fused.unknown[1, 3] and fused.cost[1, 3] == pytest.approx(0.3)
    assert fused.unknown.sum() == 7


def test_coarse_local_map_spreads_over_fine_cells():
    local_spec = GridSpec(0.0, 0.0, 1.0, 2, 2)
    local_hazard = np.array([[False, False], [False, True]])
    local_map = MapLayers.from_cost(local_spec, np.array([[0.1, 0.2], [0.3, np.nan]]), local_hazard)
    fine = resample_onto(local_map, GridSpec(0.0, 0.0, 0.25, 8, 8))
    assert fine.hazard[4:, 4:].all() and fine.hazard.sum() == 16
    assert fine.cost[:4, 4:] == pytest.approx(np.full((4, 4), 0.2))
    assert not fine.unknown.any()
    # A cell straddling two coarse cells takes the larger cost.
    shifted = resample_onto(local_map, GridSpec(0.5, 0.0, 1.0, 1, 1))
    assert shifted.cost[0, 0] == pytest.approx(0.2)


def test_blank_map_spans_start_goal_and_margin():
    blank = blank_map_spanning((1.0, 2.0), (-3.0, 5.5), cell=0.5, margin_m=1.0)
    assert blank.spec.x_range[0] <= -4.0 and blank.spec.x_range[1] >= 2.0
    assert blank.spec.y_range[0] <= 1.0 and blank.spec.y_range[1] >= 6.5
    assert blank.unknown.all() and not blank.hazard.any()


def test_map_layers_reject_mismatched_or_nan_known_layers():
    spec = GridSpec(0.0, 0.0, 1.0, 2, 2)
    with pytest.raises(ValueError, match="grid is"):
        MapLayers(spec, np.zeros((2, 3)), np.zeros((2, 2), bool), np.zeros((2, 2), bool))
    with pytest.raises(ValueError, match="NaN"):
        MapLayers(spec, np.full((2, 2), np.nan), np.zeros((2, 2), bool), np.zeros((2, 2), bool))


# --- straight segments -----------------------------------------------------------------------------

def test_segment_cells_match_dense_sampling_and_skip_corner_touches():
    rng = np.random.default_rng(7)
    for _ in range(100):
        a, b = rng.uniform(-3, 12, 2), rng.uniform(-3, 12, 2)
        cells, entry = segment_cells(a, b)
        t = np.linspace(0, 1, 5001)
        sampled = np.floor(a + 0.5 + t[:, None] * (b - a)).astype(int)
        assert {tuple(c) for c in sampled} <= {tuple(c) for c in cells}
        assert (np.diff(entry) > 0).all() and entry[0] == 0.0
    diagonal, _ = segment_cells(np.array([0.0, 0.0]), np.array([2.0, 2.0]))
    assert diagonal.tolist() == [[0, 0], [1, 1], [2, 2]]


def distance_to_polyline(points: np.ndarray, polyline: np.ndarray) -> np.ndarray:
    """Distance from each point to the nearest segment of the polyline, written out independently."""
    a, b = polyline[:-1][None, :, :], polyline[1:][None, :, :]
    p = points[:, None, :]
    t = np.clip(((p - a) * (b - a)).sum(-1) / ((b - a) ** 2).sum(-1), 0.0, 1.0)
    return np.linalg.norm(p - (a + t[..., None] * (b - a)), axis=-1).min(axis=1)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), tolerance=st.sampled_from([0.5, 1.0, 3.0]))
def test_simplification_keeps_the_deviation_bound_and_clears_hazards(seed, tolerance):
    rng = np.random.default_rng(seed)
    cost = random_cost_grid(rng, 40, 40, 0.25, 1.0)
    cost[0, 0] = cost[39, 39] = 0.0
    result = astar(cost, (0, 0), (39, 39), weight=0.8)
    if not result.found:
        return
    blocked = np.isinf(cost)
    keep = simplify_path(result.cells, blocked, tolerance)
    kept = result.cells[keep]
    assert keep[0] == 0 and keep[-1] == len(result.cells) - 1 and (np.diff(keep) > 0).all()
    assert distance_to_polyline(result.cells.astype(float), kept.astype(float)).max() <= tolerance + 1e-9
    assert all(segment_is_clear(blocked, a, b) for a, b in zip(kept[:-1], kept[1:], strict=True))


def test_a_segment_crossing_a_hazard_is_split():
    cells = np.array([[0, 0], [1, 1], [2, 2], [2, 3], [2, 4], [1, 5], [0, 6]])
    blocked = np.zeros((3, 7), dtype=bool)
    blocked[0, 3] = True  # Douglas-Peucker with a 3-cell tolerance would draw (0,0)-(0,6) through it
    assert douglas_peucker(cells, 3.0).tolist() == [0, 6]
    keep = simplify_path(cells, blocked, 3.0)
    assert keep.tolist() == [0, 2, 6]  # split at the first of the farthest points
    assert all(segment_is_clear(blocked, cells[a], cells[b]) for a, b in zip(keep[:-1], keep[1:], strict=True))


# --- world coordinates, lengths, the drivable prefix -----------------------------------------------

def test_world_cell_round_trip_and_length():
    spec = GridSpec(-2.0, 1.0, 0.25, 10, 12)
    cells = np.array([[0, 0], [3, 4], [9, 11]])
    xy = cells_to_world(spec, cells)
    assert xy[0] == pytest.approx([-1.875, 1.125])
    back, inside = world_to_cells(spec, xy)
    assert (back == cells).all() and inside.all()
    assert not world_to_cells(spec, np.array([[-2.1, 1.5]]))[1][0]
    assert path_length(np.array([[0, 0], [3, 4], [3, 5]])) == pytest.approx(6.0)


def test_drivable_prefix_cuts_at_the_margin_from_the_known_border():
    spec = GridSpec(0.0, 0.0, 0.1, 40, 40)
    known = np.zeros(spec.shape, dtype=bool)
    known[:, :30] = True  # known up to x = 3.0 m
    border = distance_to_border(known, spec.cell)
    assert border[20, 29] == pytest.approx(0.1) and border[20, 30] == 0.0
    assert border[0, 10] == pytest.approx(0.1)  # the map's own edge is a border too
    waypoints = np.array([[0.55, 2.05], [1.55, 2.05], [3.85, 2.05]])
    prefix = drivable_prefix(waypoints, spec, border, margin_m=0.5)
    assert not prefix.complete and len(prefix.waypoints) == 3
    # Cell centre x = 2.55 is 0.5 m from the first unknown centre (3.05); the next cell is too close.
    assert prefix.waypoints[-1] == pytest.approx([2.6, 2.05])
    inside = drivable_prefix(waypoints[:2], spec, border, margin_m=0.5)
    assert inside.complete and len(inside.waypoints) == 2
    stuck = drivable_prefix(np.array([[2.85, 2.05], [1.0, 2.05]]), spec, border, margin_m=0.5)
    assert not stuck.complete and len(stuck.waypoints) == 1


def test_drivable_prefix_keeps_the_margin_all_along():
    spec = GridSpec(0.0, 0.0, 0.1, 60, 60)
    yy, xx = np.mgrid[0:60, 0:60]
    known = (yy - 30) ** 2 + (xx - 30) ** 2 < 25 ** 2  # a round local map
    border = distance_to_border(known, spec.cell)
    waypoints = cells_to_world(spec, np.array([[30, 30], [35, 40], [50, 45], [59, 10]]))
    prefix = drivable_prefix(waypoints, spec, border, margin_m=0.4)
    assert not prefix.complete
    legs = zip(prefix.waypoints[:-1], prefix.waypoints[1:], strict=True)
    along = np.concatenate([np.linspace(a, b, 200) for a, b in legs])
    cells, _ = world_to_cells(spec, along[:-1])  # the cut point itself is on the edge of the first bad cell
    assert (border[cells[:, 0], cells[:, 1]] >= 0.4).all()


# --- the whole pipeline and its reasons ------------------------------------------------------------

def test_plan_path_round_a_rock():
    spec = GridSpec(0.0, 0.0, 0.1, 50, 50)
    hazard = np.zeros(spec.shape, dtype=bool)
    hazard[20:30, 20:30] = True
    layers = MapLayers(spec, np.zeros(spec.shape), hazard, np.zeros(spec.shape, bool))
    params = PlanningParams(weight=0.7, rover_radius_m=0.2, hazard_margin_m=0.1, max_deviation_m=0.15)
    result = plan_path(layers, (0.55, 0.55), (4.55, 4.55), params)
    assert result.found and result.reason == ""
    assert not result.hazards.mask[result.cells[:, 0], result.cells[:, 1]].any()
    assert result.waypoints[0] == pytest.approx([0.55, 0.55])
    assert result.waypoints[-1] == pytest.approx([4.55, 4.55])
    blocked = np.isinf(result.cost_grid)
    legs = zip(result.waypoint_cells[:-1], result.waypoint_cells[1:], strict=True)
    assert all(segment_is_clear(blocked, a, b) for a, b in legs)
    assert result.length_m >= path_length(result.waypoints) - 1e-9
    reference = dijkstra_reference(result.cost_grid, result.cells[0], result.cells[-1], 0.7, 0.1)
    assert result.cost == pytest.approx(reference, abs=1e-9)


def test_polyline_cost_is_length_times_cost_per_metre_without_staircase():
    spec = GridSpec(0.0, 0.0, 0.1, 40, 40)
    cost = np.full(spec.shape, 0.4)
    line = np.array([[0.25, 0.25], [3.25, 3.25], [3.25, 0.35]])
    assert polyline_cost(line, cost, spec, 0.5) == pytest.approx(path_length(line) * (0.5 + 0.5 * 0.4))
    cost[20, :] = np.inf                                   # a wall across the second leg's way back
    assert polyline_cost(line, cost, spec, 0.5) == math.inf
    assert polyline_cost(np.array([[0.25, 0.25], [9.0, 0.25]]), cost, spec, 0.5) == math.inf   # off the grid


def two_ways_round_a_wall(dearer_side: str | None) -> tuple[MapLayers, PlanningParams]:
    """A wall across the middle with gaps at both ends; one side's ground a little dearer."""
    spec = GridSpec(0.0, 0.0, 0.1, 60, 60)
    hazard = np.zeros(spec.shape, dtype=bool)
    hazard[28:32, 8:52] = True
    cost = np.zeros(spec.shape)
    if dearer_side == "west":
        cost[:, :30] = 0.1
    elif dearer_side == "east":
        cost[:, 30:] = 0.1
    return MapLayers(spec, cost, hazard, np.zeros(spec.shape, bool)), PlanningParams(weight=0.5, rover_radius_m=0.2,
                                                                                     hazard_margin_m=0.1)


def test_keep_route_stays_on_a_near_equal_route_and_drops_a_blocked_or_clearly_worse_one():
    start, goal = (2.95, 0.55), (2.95, 5.45)
    layers, params = two_ways_round_a_wall("east")
    west = plan_path(layers, start, goal, params)
    assert west.found and west.waypoints[:, 0].min() < 1.0          # round the wall's west end
    # The next look makes the west a little dearer: the new plan goes east, the old route is kept.
    layers, params = two_ways_round_a_wall("west")
    east = plan_path(layers, start, goal, params)
    assert east.waypoints[:, 0].max() > 5.0
    kept = keep_route(east, west.waypoints, start, layers.spec, params, hysteresis=0.2)
    assert kept.kept and kept.waypoints[:, 0].min() < 1.0
    assert kept.waypoints[0] == pytest.approx(start) and kept.waypoints[-1] == pytest.approx(goal)
    assert kept.cost == pytest.approx(polyline_cost(kept.waypoints, east.cost_grid, layers.spec, 0.5))
    assert not keep_route(east, west.waypoints, start, layers.spec, params, hysteresis=0.0).kept
    assert not keep_route(east, west.waypoints, start, layers.spec, params, hysteresis=0.01).kept
    # A rock on the old route drops it whatever the hysteresis.
    hazard = layers.hazard.copy()
    hazard[28:32, 0:8] = True
    blocked = plan_path(MapLayers(layers.spec, layers.cost, hazard, layers.unknown), start, goal, params)
    assert not keep_route(blocked, west.waypoints, start, layers.spec, params, hysteresis=5.0).kept
    # A rover far off the old route (more than join_m) plans afresh.
    assert not keep_route(east, west.waypoints + [0.0, 2.0], start, layers.spec, params, hysteresis=5.0).kept


def test_no_path_reasons():
    hazard = np.zeros((50, 50), dtype=bool)
    hazard[10, 10] = True
    hazard[:, 40] = True  # a wall from south to north
    unknown = np.zeros((50, 50), dtype=bool)
    unknown[5, 30] = True
    layers = MapLayers(GridSpec(0.0, 0.0, 0.1, 50, 50), np.zeros((50, 50)), hazard, unknown)
    params = PlanningParams(rover_radius_m=0.2, hazard_margin_m=0.0, unknown_policy="forbid")

    def reason(start, goal):
        result = plan_path(layers, start, goal, params)
        assert not result.found and len(result.waypoints) == 0 and math.isinf(result.cost)
        return result.reason, result.message

    assert reason((1.05, 1.05), (2.0, 2.0)) == ("start_blocked", "start (1.05, 1.05) is on a hazard")
    code, message = reason((0.5, 0.5), (1.25, 1.05))
    assert code == "goal_blocked" and "0.20 m from a hazard" in message and "clearance" in message
    code, message = reason((3.05, 0.55), (0.5, 0.5))
    assert code == "start_blocked" and "unknown" in message
    assert reason((0.5, 0.5), (5.5, 0.5))[0] == "goal_outside_map"
    assert reason((-0.1, 0.5), (0.5, 0.5))[0] == "start_outside_map"
    code, message = reason((0.5, 0.5), (4.65, 2.0))
    assert code == "unreachable" and "no path from (0.5, 0.5) to (4.65, 2)" in message


def test_planning_params_are_checked():
    with pytest.raises(ValueError, match="weight"):
        PlanningParams(weight=-0.1)
    with pytest.raises(ValueError, match="unknown_policy"):
        PlanningParams(unknown_policy="maybe")
    with pytest.raises(ValueError, match="rover_radius_m"):
        PlanningParams(rover_radius_m=-1.0)


def test_two_local_maps_fuse_by_the_same_rule():
    global_map = blank_map_spanning((0.0, 0.0), (1.0, 1.0), cell=0.5, margin_m=0.0)
    first = MapLayers.from_cost(GridSpec(0.0, 0.0, 0.25, 4, 4), np.full((4, 4), 0.2))
    second = MapLayers.from_cost(GridSpec(0.5, 0.5, 0.1, 5, 5), np.full((5, 5), 0.6))
    fused = fuse_maps(global_map, [first, second])
    assert fused.cost == pytest.approx(np.array([[0.2, 0.2], [0.2, 0.6]]))
    assert not fused.unknown.any()


def test_navigation_step_fuse_plan_and_cut():
    """One turn of the navigate loop: blank global map, local map round the rover, plan, cut at its border."""
    start, goal = (0.5, 0.5), (8.0, 6.0)
    local_spec = GridSpec(0.0, 0.0, 0.05, 60, 60)  # 3 m x 3 m around the start
    local_cost = np.full(local_spec.shape, 0.1)
    local_hazard = np.zeros(local_spec.shape, dtype=bool)
    local_hazard[20:30, 15:45] = True  # a rock between the rover and the goal
    local_map = MapLayers.from_cost(local_spec, local_cost, local_hazard)
    global_map = blank_map_spanning(start, goal, cell=0.1, margin_m=1.0, local_maps=[local_map])
    fused = fuse_maps(global_map, [local_map])

    result = plan_path(fused, start, goal, PlanningParams(rover_radius_m=0.2, unknown_policy="penalize"))
    assert result.found
    border = distance_to_border(~local_map.unknown, local_spec.cell)
    prefix = drivable_prefix(result.waypoints, local_spec, border, margin_m=0.3)
    assert not prefix.complete and 1 < len(prefix.waypoints) <= len(result.waypoints)
    end_cell, inside = world_to_cells(local_spec, prefix.waypoints[-1:] - 1e-9)
    assert inside.all() and border[end_cell[0, 0], end_cell[0, 1]] >= 0.25


def test_fuse_nearest_takes_the_closest_look_but_keeps_close_hazards():
    from toolbox.planning import fuse_nearest
    spec = GridSpec(0.0, 0.0, 0.1, 10, 40)              # 4 m east-west, 1 m north-south
    blank = MapLayers(spec, np.full(spec.shape, np.nan), np.zeros(spec.shape, bool), np.ones(spec.shape, bool))
    far_says_rock = np.zeros(spec.shape, bool)
    far_says_rock[:, 30] = True                          # x = 3.05: seen as a rock from x = 0 ...
    near_says_clear = np.zeros(spec.shape, bool)         # ... and as clear from x = 3.5
    maps = [MapLayers(spec, np.zeros(spec.shape), far_says_rock, np.zeros(spec.shape, bool)),
            MapLayers(spec, np.zeros(spec.shape), near_says_clear, np.zeros(spec.shape, bool))]
    fused = fuse_nearest(blank, maps, [(0.0, 0.5), (3.5, 0.5)])
    assert not fused.hazard.any() and not fused.unknown.any()
    xs, _ = spec.centres()
    assert np.allclose(fused.seen_from[5], np.minimum(np.hypot(xs, 0.05), np.hypot(xs - 3.5, 0.05)))
    # The conservative rule would keep the far, noisy reading.
    assert fuse_maps(blank, maps).hazard[:, 30].all()
    # A hazard seen from within the sticky range stays even when a nearer look misses it.
    close_rock = np.zeros(spec.shape, bool)
    close_rock[:, 20] = True                             # x = 2.05, seen from x = 1.0
    maps[0] = MapLayers(spec, np.zeros(spec.shape), close_rock, np.zeros(spec.shape, bool))
    fused = fuse_nearest(blank, maps, [(1.0, 0.5), (2.1, 0.5)], sticky_range_m=1.5)
    assert fused.hazard[:, 20].all()
    assert not fuse_nearest(blank, maps, [(1.0, 0.5), (2.1, 0.5)]).hazard.any()


def test_holes_walled_in_by_seen_ground_become_hazards_but_not_the_outside_the_specks_or_the_start():
    from toolbox.planning import enclosed_unknown, with_hazards
    spec = GridSpec(0.0, 0.0, 0.1, 30, 30)
    unknown = np.zeros(spec.shape, bool)
    unknown[:, 25:] = True                               # the unexplored outside, open to the border
    unknown[10:14, 10:14] = True                         # a 0.4 m hole: a rock the sensor got nothing from
    unknown[20, 5] = True                                # a dropped pixel
    unknown[3:6, 3:6] = True                             # the blind ring round the start ...
    unknown[4, 4] = False                                # ... round the rover's known footprint
    unknown[5:7, 6] = True                               # a rock's hole reaching into that ring
    start = np.zeros(spec.shape, bool)
    start[3:6, 3:6] = True                               # the sensor's blind disc round the start
    layers = MapLayers(spec, np.where(unknown, np.nan, 0.0), np.zeros(spec.shape, bool), unknown)
    holes = enclosed_unknown(layers, min_cells=2, exempt=start)
    expected = np.zeros(spec.shape, bool)
    expected[10:14, 10:14] = True
    expected[5:7, 6] = True                              # the part of the rock's hole outside the disc
    assert (holes == expected).all()
    assert enclosed_unknown(layers, min_cells=2)[3:6, 3:6].sum() == 8   # not exempt: the ring is a hole too
    assert enclosed_unknown(layers, min_cells=1, exempt=start)[20, 5]
    # Planned through, the hole was the short way; made a hazard, the path goes round it.
    params = PlanningParams(rover_radius_m=0.1, hazard_margin_m=0.0, unknown_policy="penalize", unknown_cost=0.05)
    through = plan_path(layers, (0.55, 1.25), (2.05, 1.25), params)
    assert through.found and np.any(holes[through.cells[:, 0], through.cells[:, 1]])
    around = plan_path(with_hazards(layers, holes), (0.55, 1.25), (2.05, 1.25), params)
    assert around.found and not np.any(holes[around.cells[:, 0], around.cells[:, 1]])
    assert around.length_m > through.length_m


def test_holes_are_hazards_for_stereo_and_stay_unknown_for_tof_by_default():
    """navigation.toml holes: stereo's holes are often rocks it could not match, TOF's occlusion shadows."""
    from rvs_server.navigation.commands import NavigationSettings, holes_as_hazards
    from toolbox.geometry import RoverPose
    spec = GridSpec(0.0, 0.0, 0.1, 30, 30)
    unknown = np.zeros(spec.shape, bool)
    unknown[20:24, 20:24] = True                         # 2.5 m from the start: outside either blind ring
    layers = MapLayers(spec, np.where(unknown, np.nan, 0.0), np.zeros(spec.shape, bool), unknown)
    settings = NavigationSettings()
    start = RoverPose(0.5, 0.5)
    assert holes_as_hazards(layers, start, "stereo", settings).hazard[20:24, 20:24].all()
    assert holes_as_hazards(layers, start, "tof", settings) is layers
    both = NavigationSettings(holes={"tof": "hazard", "stereo": "hazard"})
    assert holes_as_hazards(layers, start, "tof", both).hazard[20:24, 20:24].all()


def test_navigation_toml_says_per_sensor_whether_navigate_orients():
    """navigation.toml orient: per sensor, as the navigation campaigns decided it; one value serves both."""
    from rvs_server.config import load_model
    from rvs_server.navigation.commands import NavigationSettings
    shipped = tomllib.loads((REPO / "configs" / "navigation.toml").read_text())["orient"]
    settings = load_model(REPO / "configs" / "navigation.toml", NavigationSettings)
    assert settings.orient.of("tof") is shipped["tof"] and settings.orient.of("stereo") is shipped["stereo"]
    assert settings.orient.of("fused") is shipped["tof"]           # fused orients with the SR4000
    both = NavigationSettings(orient=True)
    assert both.orient.of("tof") and both.orient.of("stereo")


def test_unknown_ground_is_to_look_at_until_a_look_from_close_by_has_seen_into_it():
    """look_first: unknown ground is to look at until a look from within close_look_m (beyond the
    blind ring) has seen into it; what is left then is a shadow. Nor is ground beside the rover, in
    its blind ring: no look from there can see it, and stopping for it would stall the rover."""
    from rvs_server.navigation.commands import NavigationSettings, unlooked_ground
    from toolbox.geometry import RoverPose
    spec = GridSpec(0.0, 0.0, 0.05, 120, 120)             # 6 x 6 m
    unknown = np.zeros(spec.shape, bool)
    unknown[60:64, 60:64] = True                          # a 20 cm shadow round (3.1, 3.1)
    unknown[:, 115:] = True                               # and unexplored ground from x = 5.75 m
    layers = MapLayers(spec, np.where(unknown, np.nan, 0.0), np.zeros(spec.shape, bool), unknown)
    settings = NavigationSettings()                       # TOF: blind ring 0.9 m, close look 2 m

    def unlooked(looks, here):
        return unlooked_ground(layers, looks, RoverPose(*here), "tof", settings)

    far = unlooked([(0.5, 0.5)], (0.5, 0.5))               # looked at from 3.7 m only
    assert far[60:64, 60:64].all() and far[:, 115:].all() and far.sum() == unknown.sum()
    close = unlooked([(0.5, 0.5), (1.8, 3.1)], (1.8, 3.1))  # then from 1.3 m
    assert not close[60:64, 60:64].any() and close[:, 115:].all()
    beside = unlooked([(0.5, 0.5), (3.1, 2.6)], (3.1, 2.6))  # in the rover's blind ring
    assert not beside[60:64, 60:64].any()
    left = unlooked([(0.5, 0.5), (3.1, 2.6)], (0.5, 0.5))   # a look from beside it saw nothing of it
    assert left[60:64, 60:64].all()
    assert not unlooked_ground(layers, [(0.5, 0.5)], RoverPose(0.5, 0.5), "stereo", settings).any()
    with pytest.raises(ValueError, match="close_look_m = 1.2 must exceed the 1.4 m"):
        NavigationSettings(close_look_m=1.2)


def test_the_drive_stops_short_of_the_first_unknown_ground_its_path_crosses():
    from toolbox.planning import short_of_first_touch
    spec = GridSpec(0.0, 0.0, 0.05, 40, 160)             # 8 x 2 m
    unknown = np.zeros(spec.shape, bool)
    unknown[18:22, 100:104] = True                        # a shadow on the line y = 1 at x = 5.0-5.2
    unknown[18:22, 130:134] = True                        # and another at x = 6.5-6.7
    layers = MapLayers(spec, np.where(unknown, np.nan, 0.0), np.zeros(spec.shape, bool), unknown)
    plan = plan_path(layers, (0.5, 1.0), (7.5, 1.0), PlanningParams(weight=1.0))
    assert plan.found
    whole = drivable_prefix(plan.waypoints, spec, np.full(spec.shape, 10.0), 0.5)
    short, cut = short_of_first_touch(whole, plan.cells, unknown, spec, 0.4, 1.4)
    assert cut and not short.complete
    # The path comes within 0.4 m of the first shadow's west edge (x = 5.0) first: it stops 1.4 m short of it.
    assert short.waypoints[-1][0] == pytest.approx(5.0 - 1.4, abs=0.06)
    beside = np.zeros(spec.shape, bool)
    beside[0:3, 60:140] = True                            # 0.85 m off the line: more than the clearance
    assert short_of_first_touch(whole, plan.cells, beside, spec, 0.4, 1.4) == (whole, False)


def test_ground_outside_the_operating_area_is_a_hazard_the_rover_keeps_clear_of():
    from toolbox.planning import outside_box, with_hazards
    spec = GridSpec(0.0, 0.0, 0.1, 40, 60)               # 6 x 4 m
    box = (0.0, 6.0, 0.0, 3.0)                           # the northern metre is off limits
    outside = outside_box(spec, box)
    xs, ys = spec.centres()
    assert (outside == (ys > 3.0)[:, None].repeat(spec.cols, axis=1)).all()
    hazard = np.zeros(spec.shape, bool)
    hazard[:34, 30] = True                               # a wall with its only gap in the off-limits strip
    layers = MapLayers(spec, np.zeros(spec.shape), hazard, np.zeros(spec.shape, bool))
    params = PlanningParams(rover_radius_m=0.2, hazard_margin_m=0.0)
    through_the_gap = plan_path(layers, (1.0, 1.0), (5.0, 1.0), params)
    assert through_the_gap.found and through_the_gap.waypoints[:, 1].max() > 3.0
    kept_in = plan_path(with_hazards(layers, outside), (1.0, 1.0), (5.0, 1.0), params)
    assert not kept_in.found and kept_in.reason == "unreachable"
    # Grown like a rock: a path along the edge keeps the rover's radius inside.
    along = plan_path(with_hazards(layers, outside), (1.0, 2.5), (2.5, 2.75), params)
    assert along.found and along.waypoints[:, 1].max() <= 3.0 - 0.2 + 1e-9


def test_holes_on_path_are_the_holes_a_path_passes_within_the_clearance_of():
    from toolbox.planning import holes_on_path
    holes = np.zeros((40, 40), bool)
    holes[10:13, 18:21] = True                           # beside the path: 0.2 m from its cells
    holes[30:33, 5:8] = True                             # far from it
    holes[13, 21] = True                                 # touching the first one diagonally: the same hole
    path = np.column_stack([np.full(40, 15), np.arange(40)])   # row 15, west to east
    crossed = holes_on_path(path, holes, cell=0.1, clearance_m=0.3)
    expected = np.zeros_like(holes)
    expected[10:13, 18:21] = True
    expected[13, 21] = True
    assert (crossed == expected).all()
    assert not holes_on_path(path, holes, cell=0.1, clearance_m=0.1).any()
    assert not holes_on_path(path, np.zeros_like(holes), cell=0.1, clearance_m=0.3).any()


def test_unconfirmed_ground_is_planned_through_when_it_closes_the_way_or_makes_a_long_detour():
    from toolbox.planning import plan_through_unconfirmed, with_unknown
    spec = GridSpec(0.0, 0.0, 0.1, 60, 100)             # 10 m east-west, 6 m north-south
    params = PlanningParams(rover_radius_m=0.2, hazard_margin_m=0.0, proximity_cost=0.0)
    wall = np.zeros(spec.shape, bool)
    wall[:50, 50] = True                                 # x = 5.05, from the south edge to y = 5 m
    seen = MapLayers(spec, np.zeros(spec.shape), wall, np.zeros(spec.shape, bool))
    start, goal = (1.0, 1.0), (9.0, 1.0)
    closed = plan_path(seen, start, goal, params)
    assert closed.found and closed.length_m > 11.5       # round the wall's north end
    # The wall seen only from afar: the way through (8 m) saves a long detour.
    through = plan_through_unconfirmed(closed, with_unknown(seen, wall), start, goal, params, detour=0.25)
    assert through is not None and through.length_m == pytest.approx(8.0, abs=0.05)
    # A detour within the allowance stands; so does a plan when nothing is unconfirmed.
    assert plan_through_unconfirmed(closed, with_unknown(seen, wall), start, goal, params, detour=1.0) is None
    assert plan_through_unconfirmed(closed, seen, start, goal, params, 0.25) is None
    # Walled in on every side, the unconfirmed part is the only way.
    wall[:, 50] = True
    boxed = MapLayers(spec, np.zeros(spec.shape), wall, np.zeros(spec.shape, bool))
    closed = plan_path(boxed, start, goal, params)
    assert closed.reason == "unreachable"
    part = np.zeros(spec.shape, bool)
    part[20:30, 50] = True                               # only one stretch of the wall is a far guess
    through = plan_through_unconfirmed(closed, with_unknown(boxed, part), start, goal, params, detour=0.25)
    assert through is not None
    assert np.isin(through.cells[:, 0][through.cells[:, 1] == 50], np.arange(20, 30)).all()
    # Other refusals (a goal on a hazard) are not for looking again.
    on_rock = plan_path(boxed, start, (5.05, 1.0), params)
    assert on_rock.reason == "goal_blocked"
    assert plan_through_unconfirmed(on_rock, with_unknown(boxed, part), start, (5.05, 1.0), params, 0.25) is None


def test_a_blocked_goal_is_approached_at_the_nearest_open_cell_a_path_can_reach():
    from toolbox.planning import nearest_open_cell
    spec = GridSpec(0.0, 0.0, 0.1, 20, 20)               # 2 x 2 m
    cost = np.zeros(spec.shape)
    cost[8:13, 8:13] = np.inf                            # a blocked square round the goal (1.05, 1.05) ...
    cost[10, 10] = 0.0                                   # ... with one open cell in it, walled in
    goal, start = (1.05, 1.05), (0.15, 0.15)
    assert nearest_open_cell(cost, spec, goal, 0.35) == pytest.approx((1.05, 1.05))
    outside = nearest_open_cell(cost, spec, goal, 0.35, start)     # just outside the square, 0.3 m away
    assert math.dist(outside, goal) == pytest.approx(0.3)
    assert max(abs(outside[0] - 1.05), abs(outside[1] - 1.05)) > 0.25
    assert nearest_open_cell(cost, spec, goal, 0.25, start) is None


def test_the_hazard_margin_is_per_sensor_and_one_value_serves_both():
    """The margin covers a map's error at a rock's edge, which is the sensor's: each may have its own."""
    from rvs_server.navigation.commands import NavigationSettings, planning_params
    settings = NavigationSettings(hazard_margin_m={"tof": 0.05, "stereo": 0.1})
    assert planning_params(settings, None, "tof").clearance_m == pytest.approx(0.35)
    assert planning_params(settings, None, "stereo").clearance_m == pytest.approx(0.40)
    both = NavigationSettings(hazard_margin_m=0.2)
    assert both.hazard_margin_m.of("tof") == both.hazard_margin_m.of("stereo") == 0.2
    with pytest.raises(ValueError, match="hazard_margin_m.stereo"):
        NavigationSettings(hazard_margin_m={"tof": 0.1, "stereo": -0.1})


def test_hazards_of_a_fine_grid_onto_a_coarse_one_keep_every_rock():
    from toolbox.planning import hazards_onto
    fine = GridSpec(0.0, 0.0, 0.05, 40, 40)              # 2 x 2 m at 5 cm
    hazard = np.zeros(fine.shape, dtype=bool)
    hazard[10, 10] = True                                # one 5 cm cell: its centre (0.525, 0.525)
    hazard[39, 0] = True                                 # the corner: centre (0.025, 1.975)
    coarse = GridSpec(-1.0, -1.0, 0.2, 15, 15)           # -1..2 m at 20 cm
    onto = hazards_onto(coarse, fine, hazard)
    assert onto.sum() == 2 and onto[7, 7] and onto[14, 5]
    assert not hazards_onto(GridSpec(10.0, 10.0, 0.2, 5, 5), fine, hazard).any()   # beyond: nothing
