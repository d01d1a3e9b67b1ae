"""The routes campaign's scenes and scores: image-based routes laid on the true map, taught once and
repeated (forward, reverse, sun unchanged and moved, both matchers, orient off/on), then route-go over
the network; each repeat scored against the simulator's truth.

- scene: a 50 m world (7 % rock cover, three craters); a route of 20-50 m laid on the true map from a
  start within 8 m of the centre, cut into straight legs of at most 2.5 m that keep 0.45 m from every
  rock (lay_route, scene_routes), and a branch of 8-15 m from its end;
- per run (score_product): success (OK and within 0.5 m of the goal place), the final distance, the
  largest deviation from the taught true path, images grabbed, orient looks and refusals;
- the table (report) per matcher, sun, direction and orient.

A routes run is not one fixed mission on one server: the repeats run on fresh servers over the
teaching server's data directory (the route database), each started at a pose drawn near the taught
TRUE path. scene() plays a whole scene so (teach, the repeats, the network);
tests/bench/measure_routes.py runs scenes in a process pool, and tests/bench/campaigns/routes.toml one
Dask run per scene through the hooks `runs`, `execute` and `campaign_report` below.
"""
from __future__ import annotations

import json
import math
import shutil
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from clients.campaign import override_config
from drivers.sim.config import WorldConfig
from drivers.sim.world import World
from toolbox.grid import GridSpec
from toolbox.planning import MapLayers, PlanningParams, cells_to_world, inflate_hazards, plan_path, segment_is_clear

REPO = Path(__file__).resolve().parents[2]
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


def _conftest():
    """tests/conftest.py (ServerProcess, pairs, SIM_SPEED), also in a Dask worker that loaded this file
    by its path, whose sys.path has no tests/."""
    tests = str(REPO / "tests")
    if tests not in sys.path:
        sys.path.insert(0, tests)
    import conftest
    return conftest


# -- a scene: taught once, repeated on fresh servers (measure_routes.py's runs) -----------------------------

WORLD = """seed = {seed}
size_m = [{size}, {size}]
rover_start = [{x:.4f}, {y:.4f}, {heading:.3f}]
[sun]
azimuth_deg = {azimuth}
elevation_deg = {elevation}
"""
# The teacher steers (as a person at the controls would): the route taught is the route laid, clear
# of rocks. Repeats drive with the simulated rover's drive error.
TEACHER = """[drive_error]
turn_scale = 0.0
turn_noise_deg = 0.0
distance_scale = 0.0
heading_drift_deg_per_m = 0.0
lateral_slip_per_m = 0.0
"""


def configs_for(root: Path, seed: int, pose: tuple[float, float, float], sun: tuple[float, float],
                teacher: bool = False, orient: bool = False) -> Path:
    configs = root / "configs"
    shutil.rmtree(configs, ignore_errors=True)
    shutil.copytree(REPO / "configs", configs)
    override_config(configs, "routes.toml", {"orient": orient})
    (configs / "world.toml").write_text(WORLD.format(seed=seed, size=SIZE_M, x=pose[0], y=pose[1], heading=pose[2],
                                                     azimuth=sun[0], elevation=sun[1]) + (TEACHER if teacher else ""))
    return configs


def teach(seed: int, out: Path) -> dict:
    """Teach the main route r and, from its end, the branch b, in one session of one server."""
    root = out / f"scene{seed}"
    shutil.rmtree(root, ignore_errors=True)
    laid = scene_routes(seed)
    start = (*laid["start"], laid["heading"])
    server = _conftest().ServerProcess(data_dir=root / "data",
                                       config_dir=configs_for(root, seed, start, SUN, teacher=True))
    server.start(timeout=300)
    taught = {}
    products = root / "data" / "products"
    try:
        with server.connect(timeout=600) as client:
            taught["r"] = record(client, seed, "r", laid["actions"], products)
            end = taught["r"]["taught"][-1]
            try:
                branch, _, _ = lay_route(laid["world"], laid["rng"], (end[0], end[1]), (8.0, 15.0),
                                         heading=math.degrees(end[2]))
                taught["b"] = record(client, seed, "b", branch, products)
            except RuntimeError as exc:   # the main route is still scored
                print(f"scene {seed}: no branch: {exc}", flush=True)
    finally:
        server.stop()
    return {"seed": seed, **taught["r"], "branch": taught.get("b")}


def record(client, seed: int, name: str, actions: list[tuple[str, float]], products: Path) -> dict:
    assert " OK " in f" {client.command(f'route-record start --name {name}', timeout=300)} "
    for kind, value in actions:
        reply = client.command(f"drive --{kind} {value}", timeout=300)
        if " OK " not in f" {reply} ":
            raise RuntimeError(f"scene {seed}: drive --{kind} {value}: {reply}")
    stop = _conftest().pairs(client.command("route-record stop", timeout=300))
    taught = json.loads((products / stop["product"] / "truth" / "path.json").read_text())["path"]
    return {"actions": actions, "legs": int(stop["triplets"]), "length_m": float(stop["length"]),
            "bytes": int(stop["bytes"]), "bytes_per_m": float(stop["bytes_per_m"]), "taught": taught}


def repeat(seed: int, out: Path, route: dict, matcher: str, sun_moved: bool, reverse: bool,
           orient: bool = False) -> dict:
    taught = np.array(route["taught"])
    place = taught[-1] if reverse else taught[0]
    goal = taught[0] if reverse else taught[-1]
    rng = np.random.default_rng([seed, int(reverse), int(sun_moved), len(matcher)])
    name = (f"{matcher}-{'moved' if sun_moved else 'same'}-{'reverse' if reverse else 'forward'}"
            f"{'-orient' if orient else ''}")
    command = f"route-follow --name r {'--reverse ' if reverse else ''}--matcher {matcher} --output {name}"
    result = run_from(seed, out, name, near(place, rng), MOVED_SUN if sun_moved else SUN, [], command, goal, taught,
                      orient)
    return {"seed": seed, "matcher": matcher, "sun": "moved" if sun_moved else "same",
            "direction": "reverse" if reverse else "forward", "orient": orient, **result,
            "length_m": route["length_m"], "legs": route["legs"]}


def network(seed: int, out: Path, route: dict) -> dict:
    """route-connect, then route-go from near the main route's start to the branch's end."""
    branch = route["branch"]
    taught = np.vstack([route["taught"], branch["taught"]])
    rng = np.random.default_rng([seed, 7])
    command = f"route-go --to b:{branch['legs']} --output network"
    result = run_from(seed, out, "network", near(route["taught"][0], rng), SUN, ["route-connect"], command,
                      np.array(branch["taught"][-1]), taught)
    return {"seed": seed, "matcher": "features", "sun": "same", "direction": "network", "orient": False, **result,
            "length_m": route["length_m"] + branch["length_m"], "legs": route["legs"] + branch["legs"]}


def near(place, rng: np.random.Generator) -> tuple[float, float, float]:
    """A start START_OFFSET off a place: metres in a random direction, degrees either way."""
    angle = rng.uniform(-math.pi, math.pi)
    return (place[0] + START_OFFSET[0] * math.cos(angle), place[1] + START_OFFSET[0] * math.sin(angle),
            math.degrees(place[2]) + rng.choice([-1, 1]) * START_OFFSET[1])


def run_from(seed: int, out: Path, name: str, pose, sun, before: list[str], command: str, goal: np.ndarray,
             taught: np.ndarray, orient: bool = False) -> dict:
    """A fresh server on the scene's data directory with the rover at pose: the commands `before`,
    then `command`, scored against the goal and the taught path."""
    root = out / f"scene{seed}"
    run = root / name
    shutil.rmtree(run, ignore_errors=True)
    server = _conftest().ServerProcess(data_dir=root / "data",
                                       config_dir=configs_for(run, seed, pose, sun, orient=orient))
    started = time.perf_counter()
    server.start(timeout=300)
    try:
        with server.connect(timeout=1800) as client:
            for line in before:
                reply = client.command(line, timeout=1800)
                if " OK " not in f" {reply} ":
                    raise RuntimeError(f"scene {seed}: {line}: {reply}")
            reply = client.command(command, timeout=1800)
    finally:
        server.stop()
    seconds = time.perf_counter() - started
    return {**score_product(root / "data" / "products" / name, goal, taught, " OK " in f" {reply} "),
            "seconds": round(seconds, 1), "reply": reply[:200]}


def scene(seed: int, out: Path, matchers: tuple[str, ...] = ("features", "contour"),
          suns: tuple[str, ...] = ("same", "moved"), orients: tuple[bool, ...] = (False,),
          with_network: bool = True) -> list[dict]:
    route = teach(seed, out)
    (out / f"scene{seed}" / "route.json").write_text(json.dumps(route))
    print(f"scene {seed}: taught {route['length_m']:.1f} m in {route['legs']} legs, "
          f"{route['bytes_per_m']:.0f} bytes/m", flush=True)
    results = []
    runs = [(repeat, (seed, out, route, matcher, sun == "moved", reverse, orient))
            for matcher in matchers for sun in suns for reverse in (False, True) for orient in orients]
    if route["branch"] and with_network:
        runs.append((network, (seed, out, route)))
    for function, arguments in runs:
        result = function(*arguments)
        results.append({**result, "bytes_per_m": route["bytes_per_m"]})
        print(f"scene {seed} {result['matcher']} sun {result['sun']} {result['direction']}"
              f"{' orient' if result.get('orient') else ''}: "
              f"{'success' if result['success'] else 'FAILED'}, final {result['final_m']:.2f} m, "
              f"deviation {result['max_deviation_m']:.2f} m, {result['seconds']:.0f} s", flush=True)
    return results


# -- campaign hooks ----------------------------------------------------------------------------------------

ORIENTS = {"off": (False,), "on": (True,), "both": (False, True)}


def runs(scenes: int = 10, first_seed: int = 501, matchers: list[str] | None = None, suns: list[str] | None = None,
         orient: str = "off", network: bool = True) -> list[dict[str, Any]]:
    """measure_routes.py's runs: one per scene (its route taught once, then every matcher, sun, direction
    and orient setting repeated on fresh servers over the taught data, then the network), with scene()'s
    arguments as its command line gives them."""
    if orient not in ORIENTS:
        raise ValueError(f"orient {orient!r}: expected one of {', '.join(ORIENTS)}")
    return [{"seed": seed, "matchers": list(matchers or ["features", "contour"]),
             "suns": list(suns or ["same", "moved"]), "orient": orient, "network": network}
            for seed in range(first_seed, first_seed + scenes)]


def execute(run: dict[str, Any], run_dir: Path, sim_speed: float) -> dict[str, Any]:
    """One scene of the campaign, as measure_routes.py plays it: scene() with the run's arguments, its
    servers (teacher, then one per repeat) under run_dir at sim_speed (the script's is conftest's 50).
    The values: the scene's rows (the script's results.jsonl lines) and their count of successes."""
    _conftest().SIM_SPEED = sim_speed
    rows = scene(run["seed"], Path(run_dir), tuple(run["matchers"]), tuple(run["suns"]), ORIENTS[run["orient"]],
                 bool(run["network"]))
    return {"length_m": rows[0]["length_m"] if rows else None, "repeats": len(rows),
            "successes": sum(bool(row["success"]) for row in rows), "results": rows}


def campaign_report(records: list[dict[str, Any]]) -> str:
    """measure_routes.py's table of the scenes' rows (execute's `results`)."""
    return report([row for record in records for row in record.get("values", {}).get("results", [])])
