"""The navigation campaign: seeded rocky scenes, a goal with a true path, `navigate` scored on the truth.

Each scene is a world of `size` metres whose rocks cover 15-20 % of the ground (cumulative fractional
area, drawn per seed; the rock cover of Jezero crater). The rover starts at the centre, facing east;
the goal is drawn 8-15 m away in a random direction, kept only if a path for the rover exists on the
TRUE map (rocks taller than the step limit and ground steeper than the slope limit, grown by
CLEARANCE_M) and the goal has room for the rover. A run is scored from its navigate product:

- success: navigate arrived and the rover truly stands within 0.4 m of the goal;
- contacts: samples of the true path (every 5 cm) where the footprint covered a true obstacle;
- length_ratio: the true driven length over the optimal path on the true map;
- localisation_error_m: |estimated - true| position at the end, beside odometry_error_m (dead reckoning).

Used by tests/bench/campaigns/navigation.toml (`rvs campaign`, on Dask: its hooks name this file) and by
tests/bench/measure_navigation.py.
"""
from __future__ import annotations

import json
import math
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from clients.campaign import call_hook
from drivers.sim.config import WorldConfig
from drivers.sim.world import World
from toolbox.grid import GridSpec
from toolbox.planning import MapLayers, PlanningParams, plan_path

CLEARANCE_M = 0.4        # a way for the rover's radius 0.3 m plus 0.1 m: navigate plans with a 0.05 m margin,
                         # so a goal counts as reachable only with room to spare
STEP_M = 0.10
SLOPE_LIMIT_DEG = 20.0
CELL_M = 0.05
ARRIVED_M = 0.4          # the rover truly stands this close to the goal: a success
REPO = Path(__file__).resolve().parents[2]


class NoGoal(Exception):
    """The scene has no goal with a path for the rover; the campaign takes the next seed."""


def scene_config(seed: int, size: float) -> dict:
    cover = float(np.random.default_rng([seed, 5]).uniform(0.15, 0.20))
    return {"seed": seed, "size_m": [size, size], "rocks": {"cover": round(cover, 4)}}


def true_map(world: World, half: float) -> tuple[MapLayers, GridSpec]:
    """Hazards on the true world: rocks over the step limit, ground over the slope limit."""
    spec = GridSpec.covering((-half, half), (-half, half), CELL_M)
    obstacles = world.obstacle_mask(STEP_M, CELL_M, spec.x_range, spec.y_range)[:spec.rows, :spec.cols]
    xs, ys = spec.centres()
    ground = world.ground_height_at(*np.meshgrid(xs, ys))
    gy, gx = np.gradient(np.nan_to_num(ground, nan=0.0), CELL_M)
    steep = np.degrees(np.arctan(np.hypot(gx, gy))) > SLOPE_LIMIT_DEG
    hazard = obstacles | steep | ~np.isfinite(ground)
    return MapLayers(spec, np.zeros(spec.shape), hazard, np.zeros(spec.shape, bool)), spec


def pick_goal(world: World, seed: int, size: float) -> tuple[tuple[float, float], float, float]:
    """A goal 8-15 m from the start with a true path; (goal, optimal length, clearance at the goal)."""
    truth, spec = true_map(world, size / 2 - 0.5)
    params = PlanningParams(weight=1.0, rover_radius_m=CLEARANCE_M, hazard_margin_m=0.0)
    rng = np.random.default_rng([seed, 9])
    for _ in range(200):
        distance, angle = rng.uniform(8.0, 15.0), rng.uniform(-math.pi, math.pi)
        goal = (round(distance * math.cos(angle), 2), round(distance * math.sin(angle), 2))
        if max(abs(goal[0]), abs(goal[1])) > size / 2 - 2.0:
            continue
        plan = plan_path(truth, (0.0, 0.0), goal, params)
        if not plan.found:
            continue
        row, col = int((goal[1] - spec.origin_y) / CELL_M), int((goal[0] - spec.origin_x) / CELL_M)
        clearance = float(plan.hazards.distance_m[row, col])
        if clearance < CLEARANCE_M + 0.1:
            continue
        return goal, plan.length_m, clearance
    raise NoGoal(f"scene {seed}: the rover is boxed in: no goal 8-15 m away has a true path")


def scene(seed: int, size: float) -> dict[str, Any] | None:
    """The scene of a seed: its goal, optimal path length, clearance and rock cover; None: boxed in."""
    world = World.build(WorldConfig(**scene_config(seed, size)))
    try:
        goal, optimal, clearance = pick_goal(world, seed, size)
    except NoGoal:
        return None
    return {"goal": list(goal), "optimal_m": round(optimal, 3), "goal_clearance_m": round(clearance, 2),
            "cover": round(world.rock_cover(), 4)}


def usable_scenes(first: int, count: int, size: float, jobs: int = 2,
                  known: Path | None = None) -> tuple[dict[int, dict[str, Any]], list[int]]:
    """The first `count` seeds from `first` whose scene has a goal with a true path, with their scenes;
    and the seeds skipped. Each world is built in a process of its own (one process building 31 worlds
    grew to 7 GB). `known` (JSON: size -> seed -> scene or false) keeps the answers, so a rerun builds
    no world twice."""
    cache = json.loads(known.read_text()) if known is not None and known.exists() else {}
    answers = {int(k): v for k, v in cache.get(f"{size:g}", {}).items()}
    answers = {k: v for k, v in answers.items() if v is False or isinstance(v, dict)}   # old caches: bools
    scenes: dict[int, dict[str, Any]] = {}
    boxed_in, seed = [], first
    with ProcessPoolExecutor(max_workers=jobs, max_tasks_per_child=1) as pool:
        while len(scenes) < count:
            batch = list(range(seed, seed + count - len(scenes)))
            unknown = [s for s in batch if s not in answers]
            # By the hook's spec: loaded as a campaign's FILE.py hook, this module is not importable by name.
            found = pool.map(call_hook, [f"{Path(__file__).resolve()}:scene"] * len(unknown), unknown,
                             [size] * len(unknown))
            answers.update({s: (f if f is not None else False) for s, f in zip(unknown, found, strict=True)})
            for candidate in batch:
                if answers[candidate]:
                    scenes[candidate] = answers[candidate]
                else:
                    boxed_in.append(candidate)
            seed = batch[-1] + 1
    if known is not None:
        cache[f"{size:g}"] = {str(k): v for k, v in sorted(answers.items())}
        known.parent.mkdir(parents=True, exist_ok=True)
        known.write_text(json.dumps(cache, indent=1) + "\n")
    return scenes, boxed_in


def score_product(product: Path, goal: tuple[float, float], optimal_m: float) -> dict[str, Any]:
    """Every score of one navigate product against its truth (truth/traverse.json)."""
    traverse = json.loads((product / "traverse.json").read_text())
    truth = json.loads((product / "truth" / "traverse.json").read_text())
    true_path = np.array(truth["path"])[:, :2]
    true_end = true_path[-1]
    driven = float(np.sum(np.linalg.norm(np.diff(true_path, axis=0), axis=1)))
    estimated = np.array(traverse["pose"][:2])
    odometry = np.array(traverse["odometry"][:2])
    arrived = traverse["outcome"] == "arrived"
    looks = traverse.get("orients", [])
    miss = float(np.linalg.norm(true_end - np.asarray(goal)))
    return {"ok": arrived, "outcome": traverse["outcome"], "true_distance_to_goal": round(miss, 3),
            "success": bool(arrived and miss <= ARRIVED_M), "contacts": int(truth["contacts"]),
            "driven_m": round(driven, 3), "length_ratio": round(driven / optimal_m, 3) if optimal_m > 0 else None,
            "localisation_error_m": round(float(np.linalg.norm(estimated - true_end)), 3),
            "odometry_error_m": round(float(np.linalg.norm(odometry - true_end)), 3),
            "cycles": traverse["cycle"], "looks": len(looks), "looks_failed": sum("failed" in look for look in looks),
            "product": str(product)}


def summarise(results: list[dict], sensor: str) -> str:
    """The table of one sensor's runs (clients/run_log.report gives each settings' runs)."""
    rows = [r for r in results if r["sensor"] == sensor]
    if not rows:
        return ""
    ok = [r for r in rows if r["success"]]
    ratio = [r["length_ratio"] for r in ok]
    loc = [r["localisation_error_m"] for r in rows]
    odo = [r["odometry_error_m"] for r in rows]
    collided = [r for r in rows if r["contacts"] > 0]
    lines = [f"{sensor}: {len(rows)} scenes (rock cover {min(r['cover'] for r in rows):.3f}-"
             f"{max(r['cover'] for r in rows):.3f}, goals {min(r['optimal_m'] for r in rows):.1f}-"
             f"{max(r['optimal_m'] for r in rows):.1f} m of optimal path)",
             f"  success {len(ok)}/{len(rows)} ({100 * len(ok) / len(rows):.0f} %)",
             f"  collisions: {len(collided)} runs touched a true obstacle ({sum(r['contacts'] for r in rows)} path "
             f"samples of 5 cm in all)"]
    if ratio:
        lines.append(f"  driven / optimal path length (successes): median {np.median(ratio):.3f}, "
                     f"mean {np.mean(ratio):.3f}, max {np.max(ratio):.3f}")
    lines.append(f"  localisation error at the end: median {100 * np.median(loc):.1f} cm, p90 "
                 f"{100 * np.percentile(loc, 90):.1f} cm, max {100 * np.max(loc):.1f} cm; dead reckoning alone: "
                 f"median {100 * np.median(odo):.1f} cm, max {100 * np.max(odo):.1f} cm")
    lines.append(f"  cycles median {np.median([r['cycles'] for r in rows]):.0f}; wall time per run median "
                 f"{np.median([r['seconds'] for r in rows]):.0f} s")
    looks = [r.get("looks", 0) for r in rows]
    if any(looks):
        lines.append(f"  orient looks per run median {np.median(looks):.0f}; {sum(r['looks_failed'] for r in rows)} of "
                     f"{sum(looks)} refused (the estimate stayed dead reckoning's)")
    for r in rows:
        if not r["success"]:
            lines.append(f"  failed: scene {r['seed']} goal {r['goal']}: {r['outcome']} (true distance to goal "
                         f"{r['true_distance_to_goal']} m) {r['product']}")
    return "\n".join(lines)


# -- the campaign file's hooks (tests/bench/campaigns/navigation.toml) -------------------------------------


def runs(scenes: int = 10, first_seed: int = 101, sensors: list[str] | None = None, orient: list[bool] | None = None,
         size: float = 34.0, jobs: int = 2, known: str = "") -> list[dict[str, Any]]:
    """One run per usable scene, sensor and orient setting; the goal and the scene's world go with it.
    `known`: the scenes' cache (JSON; relative to the repository), so the worlds are built once."""
    cache = (REPO / known if not Path(known).is_absolute() else Path(known)) if known else None
    found, _ = usable_scenes(first_seed, scenes, size, jobs, cache)
    made = []
    for seed, found_scene in found.items():
        config = scene_config(seed, size)
        for sensor in sensors or ["tof", "stereo"]:
            for on in orient if orient is not None else [False]:
                goal = found_scene["goal"]
                made.append({"seed": seed, "world": {"size_m": config["size_m"], "rocks": config["rocks"]},
                             "configs": {"navigation.toml": {"orient": bool(on)}},
                             "SENSOR": sensor, "GOAL": f"{goal[0]},{goal[1]}", "ORIENT": "on" if on else "off",
                             "OPTIMAL_M": found_scene["optimal_m"], "COVER": found_scene["cover"]})
    return made


def score(run: dict[str, Any], data_dir: Path) -> dict[str, Any]:
    """The run's scores from its navigate product (the newest, there is one per run)."""
    products = sorted(Path(data_dir, "products").glob("navigate-*/traverse.json"), key=lambda p: p.stat().st_mtime)
    if not products:
        raise FileNotFoundError(f"no navigate product in {data_dir}/products")
    goal = tuple(float(v) for v in str(run["GOAL"]).split(","))
    return {"sensor": run["SENSOR"], "cover": run["COVER"], "goal": list(goal), "optimal_m": run["OPTIMAL_M"],
            **score_product(products[-1].parent, goal, float(run["OPTIMAL_M"]))}


def report(records: list[dict[str, Any]]) -> str:
    """The summary per orient setting and sensor of a campaign's finished runs."""
    rows = [{**record.get("values", {}), "seed": record["run"].get("seed"), "seconds": record.get("seconds", 0.0),
             "orient": record["run"].get("ORIENT")} for record in records]
    parts = []
    for orient in sorted({r["orient"] for r in rows}):
        chosen = [r for r in rows if r["orient"] == orient]
        tables = [summarise(chosen, sensor) for sensor in sorted({r["sensor"] for r in chosen})]
        parts.append(f"== orient={orient}: {len(chosen)} runs\n" + "\n".join(t for t in tables if t))
    return "\n\n".join(parts)
