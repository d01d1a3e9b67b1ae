"""The routes campaign's scenes and scores: image-based routes laid on the true map, taught once and
repeated (forward, reverse, sun unchanged and moved, both matchers, orient off/on), then route-go over
the network; each repeat scored against the simulator's truth.

- scene: a 50 m world (7 % rock cover, three craters); a route of 20-50 m laid on the true map from a
  start within 8 m of the centre, cut into straight legs of at most 2.5 m that keep 0.45 m from every
  rock (lay_route, scene_routes), and a branch of 8-15 m from its end;
- per run (score_product): success (OK and within 0.5 m of the goal place), the final distance, the
  largest deviation from the taught true path, images grabbed, orient looks and refusals;
- the table (report) per matcher, sun, direction and orient.

Used by tests/bench/measure_routes.py, and by a campaign file through the hooks `runs` and
`campaign_report`. A routes run is not one fixed mission on one server: the repeats run on fresh
servers over the teaching server's data directory (the route database), each started at a pose drawn
near the taught TRUE path, so tests/bench/campaigns/routes.toml needs the campaign engine to hand one
run's data to the next, or a hook that plays a whole scene (see the issue 28 notes).
"""
from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from drivers.sim.config import WorldConfig
from drivers.sim.world import World
from toolbox.grid import GridSpec
from toolbox.planning import MapLayers, PlanningParams, cells_to_world, inflate_hazards, plan_path, segment_is_clear

SIZE_M = 50.0
LEG_M = 2.5
SUN = (135.0, 35.0)
MOVED_SUN = (175.0, 55.0)        # 40 degrees in azimuth, 20 degrees higher
START_OFFSET = (0.2, 5.0)        # metres, degrees off the route's first place
ARRIVED_M = 0.5

def lay_route(world: World, rng: np.random.Generator, start: tuple[float, float], lengths: tuple[float, float],
              heading: float | None = None) -> tuple[list[tuple[str, float]], float, float]:
    """Actions (kind, value: metres or degrees) of a route from `start` on the true map whose length
    lies within `lengths`, the starting heading in degrees (given, or along the first leg), and the
    route's length."""
    half = SIZE_M / 2 - 4.0
    spec = GridSpec.covering((-half, half), (-half, half), 0.05)
    hazard = world.obstacle_mask(0.10, 0.05, spec.x_range, spec.y_range)[:spec.rows, :spec.cols]
    layers = MapLayers(spec, np.zeros(spec.shape), hazard, np.zeros(spec.shape, bool))
    params = PlanningParams(weight=1.0, rover_radius_m=0.5, hazard_margin_m=0.0)
    # Legs as a person would teach them: chords of the shortest path, at most LEG_M long, that keep
    # 0.45 m from every rock (the body's half-diagonal is 0.37 m): no wheel climbs one.
    blocked = inflate_hazards(hazard, 0.05, 0.45).mask
    for _ in range(300):
        distance, bearing = rng.uniform(0.7 * lengths[0], lengths[1]), rng.uniform(-math.pi, math.pi)
        goal = (start[0] + distance * math.cos(bearing), start[1] + distance * math.sin(bearing))
        if max(abs(goal[0]), abs(goal[1])) > half - 1.0:
            continue
        plan = plan_path(layers, start, goal, params)
        if not plan.found or not lengths[0] <= plan.length_m <= lengths[1]:
            continue
        points = cells_to_world(spec, chords(plan.cells, blocked, LEG_M / 0.05))
        points[0] = start
        first = math.atan2(*(points[1] - points[0])[::-1])
        start_heading = first if heading is None else math.radians(heading)
        actions: list[tuple[str, float]] = []
        at = start_heading
        for p, q in zip(points[:-1], points[1:], strict=True):
            bearing_pq = math.atan2(q[1] - p[1], q[0] - p[0])
            turn = math.degrees((bearing_pq - at + math.pi) % (2 * math.pi) - math.pi)
            if abs(turn) > 3.0:
                actions.append(("turn", round(turn, 2)))
            at = bearing_pq
            actions.append(("forward", round(float(np.hypot(*(q - p))), 3)))
        length = sum(v for k, v in actions if k == "forward")
        if lengths[0] <= length <= lengths[1]:
            return actions, math.degrees(start_heading), length
    raise RuntimeError(f"no route of {lengths[0]:g}-{lengths[1]:g} m from {start}")


def scene_routes(seed: int) -> dict:
    """The scene's main route (20-50 m, from a random start near the centre) and a branch of 8-15 m
    taught from the main route's end, for route-connect and route-go."""
    world = World.build(WorldConfig(seed=seed, size_m=(SIZE_M, SIZE_M)))
    rng = np.random.default_rng([seed, 3])
    obstacles = world.obstacle_mask(0.10, 0.05, (-10.0, 10.0), (-10.0, 10.0))
    for _ in range(100):
        start = (float(rng.uniform(-8, 8)), float(rng.uniform(-8, 8)))
        row, col = int((start[1] + 10) / 0.05), int((start[0] + 10) / 0.05)
        if not obstacles[max(0, row - 12):row + 12, max(0, col - 12):col + 12].any():
            break
    actions, heading, length = lay_route(world, rng, start, (20.0, 50.0))
    return {"start": start, "heading": heading, "actions": actions, "length": length, "rng": rng, "world": world}


def chords(cells: np.ndarray, blocked: np.ndarray, longest: float) -> np.ndarray:
    """Cells of the path kept so that each chord between them is at most `longest` cells long and
    crosses no blocked cell."""
    kept = [0]
    while kept[-1] < len(cells) - 1:
        first = kept[-1]
        best = first + 1
        for j in range(first + 2, len(cells)):
            if np.hypot(*(cells[j] - cells[first])) > longest:
                break
            if segment_is_clear(blocked, cells[first], cells[j]):
                best = j
        kept.append(best)
    return cells[kept]


def score_product(product: Path, goal: np.ndarray, taught: np.ndarray, ok: bool) -> dict[str, Any]:
    """A route-follow or route-go product against the goal place and the taught true path."""
    path = np.array(json.loads((product / "truth" / "path.json").read_text())["path"])
    follow = json.loads((product / "follow.json").read_text())
    final = float(np.linalg.norm(path[-1, :2] - np.asarray(goal)[:2]))
    taught = np.asarray(taught)
    gaps = np.min(np.linalg.norm(path[:, None, :2] - taught[None, :, :2], axis=2), axis=1)
    return {"ok": ok, "success": bool(ok and final <= ARRIVED_M), "final_m": round(final, 3),
            "max_deviation_m": round(float(gaps.max()), 3), "images": follow["images"],
            "orient_looks": follow.get("orient_looks", 0), "orient_refused": len(follow.get("orient_refused", [])),
            "last_matched": follow["segments"][-1]["last_matched"]}


def report(results: list[dict]) -> str:
    if not results:
        return "no results"
    lines = []
    scenes = sorted({r["seed"] for r in results})
    lengths = {r["seed"]: r["length_m"] for r in results}
    lines.append(f"{len(scenes)} scenes, routes {min(lengths.values()):.1f}-{max(lengths.values()):.1f} m, "
                 f"{np.mean([r['bytes_per_m'] for r in results]) / 1024:.1f} KiB stored per metre (mean)")
    lines.append("matcher   sun    direction orient success   final m (median, max)   deviation m (median, max)"
                 "   images/m   looks (refused)")
    for matcher in ("features", "contour"):
        for sun in ("same", "moved"):
            for direction in ("forward", "reverse", "network"):
                for orient in (False, True):
                    rows = [r for r in results if (r["matcher"], r["sun"], r["direction"], r.get("orient", False))
                            == (matcher, sun, direction, orient)]
                    if not rows:
                        continue
                    final = [r["final_m"] for r in rows]
                    deviation = [r["max_deviation_m"] for r in rows]
                    per_m = sum(r["images"] for r in rows) / sum(r["length_m"] for r in rows)
                    looks = (f"{sum(r.get('orient_looks', 0) for r in rows)} "
                             f"({sum(r.get('orient_refused', 0) for r in rows)})")
                    lines.append(f"{matcher:9s} {sun:6s} {direction:9s} {'on ' if orient else 'off'}    "
                                 f"{sum(r['success'] for r in rows):2d}/{len(rows):<2d}"
                                 f"     {np.median(final):6.2f} {np.max(final):6.2f}          "
                                 f"{np.median(deviation):6.2f} {np.max(deviation):6.2f}"
                                 f"          {per_m:5.2f}      {looks if orient else '-'}")
    return "\n".join(lines)




# -- campaign hooks ----------------------------------------------------------------------------------------

ORIENTS = {"off": (False,), "on": (True,), "both": (False, True)}


def runs(scenes: int = 10, first_seed: int = 501, matchers: list[str] | None = None, suns: list[str] | None = None,
         orient: str = "off", network: bool = True) -> list[dict[str, Any]]:
    """measure_routes.py's runs per scene, in its order: every matcher, sun, direction and orient setting,
    then the network (route-connect, route-go) when the scene has a branch."""
    made = []
    for seed in range(first_seed, first_seed + scenes):
        made += [{"seed": seed, "MATCHER": matcher, "SUN": sun, "DIRECTION": direction, "ORIENT": "on" if on else "off"}
                 for matcher in matchers or ["features", "contour"] for sun in suns or ["same", "moved"]
                 for direction in ("forward", "reverse") for on in ORIENTS[orient]]
        if network:
            made.append({"seed": seed, "MATCHER": "features", "SUN": "same", "DIRECTION": "network", "ORIENT": "off"})
    return made


def campaign_report(records: list[dict[str, Any]]) -> str:
    """The table of a campaign's runs whose values are measure_routes.py's result of a run."""
    return report([record["values"] for record in records if "final_m" in record.get("values", {})])
