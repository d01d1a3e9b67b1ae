"""Path planning for the rover (thesis 3.1.7, 3.3.1, 4.4): from a fused map to straight-line waypoints.

`plan_path` is the method, step by step: grow the hazards by the rover's size, cost the ground,
give unknown cells their policy's cost, search the exact least-cost path with A*, and cut it into
straight segments that keep clear of hazards. The steps live in small modules:

    costs            terrain cost, hazard inflation, soft cost near hazards, unknown-cell policy
    search           the path metric, A* and its Dijkstra reference
    fusion           planning maps and the fusion of a global map with local maps
    paths            world <-> cells, straight segments, the drivable part inside the local map
    drive_error      how far the rover may drive before its drive error could reach a hazard

Fusing the maps comes before `plan_path` and cutting the path at the local map's border after it;
the navigate loop calls them.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.ndimage import label

from toolbox.grid import GridSpec
from toolbox.planning.costs import (
    UNKNOWN_POLICIES,
    InflatedHazards,
    UnknownPolicy,
    apply_unknown_policy,
    inflate_hazards,
    proximity_cost,
    terrain_cost,
)
from toolbox.planning.fusion import (
    FusedLayers,
    MapLayers,
    blank_map,
    blank_map_spanning,
    enclosed_unknown,
    fuse_maps,
    fuse_nearest,
    hazards_onto,
    holes_on_path,
    inside_box,
    outside_box,
    resample_onto,
    with_hazards,
    with_unknown,
)
from toolbox.planning.paths import (
    DrivablePrefix,
    cells_to_world,
    distance_to_border,
    douglas_peucker,
    drivable_prefix,
    first_touch,
    path_length,
    segment_cells,
    segment_is_clear,
    short_of_first_touch,
    simplify_path,
    world_to_cells,
    world_to_grid,
)
from toolbox.planning.search import SearchResult, astar, cost_per_metre, dijkstra_reference, path_cost

__all__ = [
    "PlanningParams", "PlanResult", "plan_path", "planning_cost", "polyline_cost", "keep_route",
    "plan_through_unconfirmed",
    "terrain_cost", "inflate_hazards", "InflatedHazards", "proximity_cost", "apply_unknown_policy",
    "UnknownPolicy", "UNKNOWN_POLICIES",
    "astar", "dijkstra_reference", "path_cost", "SearchResult",
    "MapLayers", "blank_map", "blank_map_spanning", "resample_onto", "fuse_maps", "fuse_nearest", "hazards_onto",
    "enclosed_unknown", "holes_on_path", "inside_box", "outside_box", "with_hazards", "with_unknown", "FusedLayers",
    "cells_to_world", "world_to_cells", "path_length", "douglas_peucker", "segment_cells",
    "segment_is_clear", "simplify_path", "distance_to_border", "drivable_prefix", "DrivablePrefix",
    "first_touch", "short_of_first_touch",
]


@dataclass(frozen=True)
class PlanningParams:
    weight: float = 0.5                 # w: 1 = shortest path, 0 = cheapest ground (thesis used 0.4 and 0.7)
    rover_radius_m: float = 0.3         # hazards grow by radius + margin: the path is for the rover's centre
    hazard_margin_m: float = 0.1
    proximity_falloff_m: float = 0.0    # soft cost reaches 0 this far beyond the grown hazards; 0 = off
    proximity_cost: float = 0.5         # soft cost at the grown hazards' edge, added to the terrain cost
    unknown_policy: UnknownPolicy = "penalize"
    unknown_cost: float = 0.5           # cost of an unknown cell under "penalize"
    max_deviation_m: float = 0.1        # straight segments stay this close to the A* path

    def __post_init__(self) -> None:
        if not 0.0 <= self.weight <= 1.0:
            raise ValueError(f"weight must be in [0, 1], got {self.weight!r}")
        for name in ("rover_radius_m", "hazard_margin_m", "proximity_falloff_m", "proximity_cost",
                     "unknown_cost", "max_deviation_m"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)!r}")
        if self.unknown_policy not in UNKNOWN_POLICIES:
            raise ValueError(f"unknown_policy must be one of {', '.join(UNKNOWN_POLICIES)}, "
                             f"got {self.unknown_policy!r}")

    @property
    def clearance_m(self) -> float:
        return self.rover_radius_m + self.hazard_margin_m


@dataclass(frozen=True)
class PlanResult:
    found: bool
    reason: str                 # "" when found; else start_outside_map, goal_outside_map,
    message: str                # start_blocked, goal_blocked or unreachable, and a sentence saying why
    cells: np.ndarray           # (K, 2) A* cell path (row, col), start to goal
    waypoint_cells: np.ndarray  # (M, 2) the cells kept as waypoints
    waypoints: np.ndarray       # (M, 2) world (x, y) of the waypoints, at cell centres
    cost: float                 # A* path cost on the planning metric; inf without a path
    length_m: float             # A* path length; inf without a path
    cost_grid: np.ndarray = field(repr=False)  # what A* searched: +inf where blocked
    hazards: InflatedHazards = field(repr=False)
    kept: bool = False          # True: the previous route, kept over a new plan (keep_route)


def plan_path(planning_map: MapLayers, start_xy: tuple[float, float], goal_xy: tuple[float, float],
              params: PlanningParams = PlanningParams()) -> PlanResult:
    """The least-cost safe path from start to goal (world x, y) on a planning map, as waypoints."""
    spec = planning_map.spec
    # Grow the hazards by the rover's radius plus a margin.
    hazards = inflate_hazards(planning_map.hazard, spec.cell, params.clearance_m)
    # Cost the ground: terrain, unknown cells by policy, the soft cost near hazards; grown hazards block.
    cost = planning_cost(planning_map, hazards, params)
    # A rover already standing within the clearance of a hazard (drive error, a map that grew a
    # rock) may leave it, as long as no step takes it closer to the hazard than it stands now.
    cost = open_escape(cost, planning_map, hazards, params, start_xy)
    # Refuse, with the reason, a start or goal off the map or on a blocked cell.
    refusal = refuse_endpoints(planning_map, hazards, cost, start_xy, goal_xy, params)
    if refusal:
        return _no_path(*refusal, cost, hazards)
    # A*: the exact least-cost 8-connected path.
    start, goal = world_to_cells(spec, np.array([start_xy, goal_xy], dtype=np.float64))[0]
    search = astar(cost, tuple(start), tuple(goal), params.weight, spec.cell)
    if not search.found:
        blockers = "hazards or unknown cells" if params.unknown_policy == "forbid" else "hazards"
        return _no_path("unreachable", f"no path from ({start_xy[0]:g}, {start_xy[1]:g}) to "
                        f"({goal_xy[0]:g}, {goal_xy[1]:g}): {blockers} (grown by "
                        f"{params.clearance_m:.2f} m) close every way", cost, hazards)
    # Straight segments close to the path and clear of every blocked cell.
    keep = simplify_path(search.cells, np.isinf(cost), params.max_deviation_m / spec.cell)
    return PlanResult(found=True, reason="", message="", cells=search.cells,
                      waypoint_cells=search.cells[keep], waypoints=cells_to_world(spec, search.cells[keep]),
                      cost=search.cost, length_m=path_length(cells_to_world(spec, search.cells)),
                      cost_grid=cost, hazards=hazards)


def polyline_cost(points_xy: np.ndarray, cost_grid: np.ndarray, spec: GridSpec, weight: float) -> float:
    """Cost of driving straight segments on the planning metric: each segment's length times the
    cost per metre of the cells it crosses, weighted by the length inside each; inf if a segment
    crosses a blocked cell or leaves the grid. Comparing routes on their segments, not on A* cell
    chains, keeps an 8-connected staircase from looking longer than the line it stands for."""
    points = np.asarray(points_xy, dtype=np.float64).reshape(-1, 2)
    per_metre = cost_per_metre(cost_grid, weight)
    rc = world_to_grid(spec, points)
    total = 0.0
    for a, b, length in zip(rc[:-1], rc[1:], np.linalg.norm(np.diff(points, axis=0), axis=1), strict=True):
        cells, t = segment_cells(a, b)
        if not ((cells >= 0) & (cells < cost_grid.shape)).all():
            return float("inf")
        share = np.diff(np.append(t, 1.0))
        total += length * float(np.sum(share * per_metre[cells[:, 0], cells[:, 1]]))
    return total


def keep_route(plan: PlanResult, previous_xy: np.ndarray | None, start_xy: tuple[float, float], spec: GridSpec,
               params: PlanningParams, hysteresis: float, join_m: float = 1.0) -> PlanResult:
    """The previous route from where the rover stands instead of the new plan, while it is still
    clear and costs at most (1 + hysteresis) times the new plan (both as straight segments).

    Replanning from scratch after every look makes a rover swing between near-equal routes: each
    look at unknown ground makes the side just seen dearer than the side not yet seen, so it turns
    back and forth, driving far and arriving late or never. Commitment with a margin damps that;
    a route that a new look blocks, or that has become clearly worse, is still dropped at once."""
    if not plan.found or previous_xy is None or len(previous_xy) < 2 or hysteresis <= 0:
        return plan
    previous = np.asarray(previous_xy, dtype=np.float64).reshape(-1, 2)
    start = np.asarray(start_xy, dtype=np.float64)
    # Join at the point of the previous route nearest the rover.
    a, b = previous[:-1], previous[1:]
    d = b - a
    t = np.clip(np.einsum("ij,ij->i", start - a, d) / np.maximum(np.einsum("ij,ij->i", d, d), 1e-12), 0.0, 1.0)
    foot = a + t[:, None] * d
    k = int(np.argmin(np.linalg.norm(foot - start, axis=1)))
    if np.linalg.norm(foot[k] - start) > join_m:
        return plan
    route = np.vstack([start, foot[k], previous[k + 1:]])
    route = route[np.r_[True, np.linalg.norm(np.diff(route, axis=0), axis=1) > 1e-6]]
    if len(route) < 2:
        return plan
    old = polyline_cost(route, plan.cost_grid, spec, params.weight)
    new = polyline_cost(plan.waypoints, plan.cost_grid, spec, params.weight)
    if not np.isfinite(old) or old > (1.0 + hysteresis) * new:
        return plan
    rc = np.rint(world_to_grid(spec, route)).astype(np.int64)
    cells = np.vstack([segment_cells(p, q)[0] for p, q in zip(rc[:-1], rc[1:], strict=True)] + [rc[-1:]])
    cells = cells[np.r_[True, np.abs(np.diff(cells, axis=0)).sum(axis=1) > 0]]
    return PlanResult(found=True, reason="", message="", cells=cells, waypoint_cells=rc, waypoints=route,
                      cost=old, length_m=path_length(route), cost_grid=plan.cost_grid, hazards=plan.hazards,
                      kept=True)


def plan_through_unconfirmed(closed: PlanResult, open_map: MapLayers, start_xy: tuple[float, float],
                             goal_xy: tuple[float, float], params: PlanningParams, detour: float) -> PlanResult | None:
    """The plan on `open_map`, the map with its unconfirmed cells (guesses a closer look may clear:
    holes, hazards seen only from afar) as unknown ground, when they close every way (`closed`, planned
    with them as hazards, is unreachable) or the way round them is more than `detour` (a fraction)
    longer than the way through. Otherwise None: `closed` stands."""
    if not (closed.found or closed.reason == "unreachable"):
        return None
    through = plan_path(open_map, start_xy, goal_xy, params)
    if not through.found or (closed.found and closed.length_m <= (1.0 + detour) * through.length_m):
        return None
    return through


def nearest_open_cell(cost_grid: np.ndarray, spec: GridSpec, goal_xy: tuple[float, float],
                      radius_m: float, from_xy: tuple[float, float] | None = None) -> tuple[float, float] | None:
    """The centre of the open (finite-cost) cell nearest the goal within radius_m, or None: where to
    aim when the goal itself is too close to a hazard but arriving within a tolerance will do. With
    from_xy (on an open cell), only cells a path from there can reach: a pocket of open ground walled
    in by grown hazards is no place to aim for."""
    xs, ys = spec.centres()
    distance = np.hypot(xs[None, :] - goal_xy[0], ys[:, None] - goal_xy[1])
    candidates = np.isfinite(cost_grid) & (distance <= radius_m)
    if from_xy is not None:
        (start,), inside = world_to_cells(spec, np.array([from_xy], dtype=np.float64))
        if inside[0] and np.isfinite(cost_grid[start[0], start[1]]):
            labels, _ = label(np.isfinite(cost_grid), structure=np.ones((3, 3), bool))
            candidates &= labels == labels[start[0], start[1]]
    if not candidates.any():
        return None
    row, col = np.unravel_index(np.argmin(np.where(candidates, distance, np.inf)), distance.shape)
    return float(xs[col]), float(ys[row])


def open_escape(cost: np.ndarray, planning_map: MapLayers, hazards: InflatedHazards, params: PlanningParams,
                start_xy: tuple[float, float]) -> np.ndarray:
    """Unblock, within the clearance around a start that lies in the grown zone (not on a hazard),
    the grown cells no closer to a hazard than the start: the way out, never the way in."""
    spec = planning_map.spec
    (start,), inside = world_to_cells(spec, np.array([start_xy], dtype=np.float64))
    if not inside[0] or not hazards.mask[start[0], start[1]] or planning_map.hazard[start[0], start[1]]:
        return cost
    xs, ys = spec.centres()
    near = np.hypot(xs[None, :] - start_xy[0], ys[:, None] - start_xy[1]) <= params.clearance_m + spec.cell
    way_out = (near & hazards.mask & ~planning_map.hazard
               & (hazards.distance_m >= hazards.distance_m[start[0], start[1]]))
    if params.unknown_policy == "forbid":
        way_out &= ~planning_map.unknown
    opened = planning_cost(planning_map, hazards, params, masked=False)
    return np.where(way_out, opened, cost)


def planning_cost(planning_map: MapLayers, hazards: InflatedHazards, params: PlanningParams,
                  masked: bool = True) -> np.ndarray:
    """The grid A* searches: terrain cost, unknown cells' cost, soft cost near hazards; +inf where
    blocked (unless masked=False)."""
    ground = np.where(planning_map.hazard, 0.0, planning_map.cost)  # hazards are blocked below anyway
    cost = apply_unknown_policy(ground, planning_map.unknown, params.unknown_policy, params.unknown_cost)
    cost = cost + params.proximity_cost * proximity_cost(hazards.distance_m, hazards.clearance_m,
                                                         params.proximity_falloff_m)
    return np.where(hazards.mask, np.inf, cost) if masked else cost


def refuse_endpoints(planning_map: MapLayers, hazards: InflatedHazards, cost: np.ndarray,
                     start_xy: tuple[float, float], goal_xy: tuple[float, float],
                     params: PlanningParams) -> tuple[str, str] | None:
    """(reason, sentence) if the start or the goal is off the map or on a blocked cell, else None."""
    spec = planning_map.spec
    cells, inside = world_to_cells(spec, np.array([start_xy, goal_xy], dtype=np.float64))
    for name, point, cell, on_map in zip(("start", "goal"), (start_xy, goal_xy), cells, inside, strict=True):
        where = f"{name} ({point[0]:g}, {point[1]:g})"
        if not on_map:
            (x0, x1), (y0, y1) = spec.x_range, spec.y_range
            extent = f"x {x0:g}..{x1:g} m, y {y0:g}..{y1:g} m"
            return f"{name}_outside_map", f"{where} is outside the map ({extent})"
        if np.isinf(cost[cell[0], cell[1]]):
            why = _why_blocked(planning_map, hazards, (cell[0], cell[1]), params)
            return f"{name}_blocked", f"{where} {why}"
    return None


def _why_blocked(planning_map: MapLayers, hazards: InflatedHazards, cell: tuple[int, int],
                 params: PlanningParams) -> str:
    if planning_map.hazard[cell]:
        return "is on a hazard"
    if hazards.mask[cell]:
        return (f"is {hazards.distance_m[cell]:.2f} m from a hazard, within the rover's clearance of "
                f"{params.clearance_m:.2f} m (radius {params.rover_radius_m:g} m + margin "
                f"{params.hazard_margin_m:g} m)")
    return "is on an unknown cell and the unknown-cell policy is 'forbid'"


def _no_path(reason: str, message: str, cost: np.ndarray, hazards: InflatedHazards) -> PlanResult:
    empty_cells = np.zeros((0, 2), dtype=np.int64)
    return PlanResult(False, reason, message, empty_cells, empty_cells, np.zeros((0, 2)),
                      float("inf"), float("inf"), cost, hazards)
