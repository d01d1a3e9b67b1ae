"""navigate on seeded rocky scenes, TOF and stereo, scored against the simulator's truth.

Each scene is a world of the given size whose rocks cover 15-20 % of the ground (cumulative
fractional area, drawn per scene; the rock cover of Jezero crater). The rover starts at the centre,
facing east; the goal is drawn 8-15 m away in a random direction, kept only if a path for the rover
exists on the TRUE map (rocks taller than the step limit and ground steeper than the slope limit,
grown by 0.4 m, at least navigate's own clearance) and the goal has room for the rover. For every scene and
sensor a real server runs `navigate --to X,Y --sensor S`, and the run is scored from its product:

- success: navigate answered OK and the rover truly stands within the tolerance (+0.1 m) of the goal;
- collisions: runs in which the rover's footprint covered a true obstacle at any sample of its path
  (every 5 cm), and the number of such samples;
- path length: the true driven length over the optimal (shortest) path on the true map;
- localisation error at the end: |estimated - true| position, beside dead reckoning alone.

    .venv/bin/python tests/bench/measure_navigation.py [--scenes 30] [--first-seed 101] [--jobs 2]
        [--sensors tof stereo] [--size 34] [--orient on|off] [--results tests/bench/results/navigation.jsonl]
        [--out /tmp/rvs-navigation]
    .venv/bin/python tests/bench/measure_navigation.py --report tests/bench/results/navigation.jsonl

Each finished run is appended to --results the moment it ends (clients/run_log.py: one JSON line
with its seed, sensor, settings (size, orient), every score and its seconds); a rerun with the same
settings skips the runs already there, so a campaign is continued chunk by chunk (--scenes 3, then
--scenes 6, ...). Which seeds have a goal is kept beside it (navigation-seeds.json) so a rerun does
not build every world again. --report prints the summary from the file alone, per settings.
"""
from __future__ import annotations

import argparse
import json
import math
import shutil
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "tests"))
sys.path.insert(0, str(REPO))
from clients.run_log import RunLog, report  # noqa: E402
from drivers.sim.config import WorldConfig  # noqa: E402
from drivers.sim.world import World  # noqa: E402
from toolbox.grid import GridSpec  # noqa: E402
from toolbox.planning import MapLayers, PlanningParams, plan_path  # noqa: E402

from conftest import ServerProcess, pairs  # noqa: E402

CLEARANCE_M = 0.4        # a way for the rover's radius 0.3 m plus 0.1 m: navigate plans with a 0.05 m margin,
                         # so a goal counts as reachable only with room to spare
STEP_M = 0.10
SLOPE_LIMIT_DEG = 20.0
CELL_M = 0.05
RESULTS = REPO / "tests" / "bench" / "results" / "navigation.jsonl"


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


class NoGoal(Exception):
    """The scene has no goal with a path for the rover; the campaign takes the next seed."""


def run(seed: int, sensor: str, size: float, out: Path, sim_speed: float, orient: bool = True) -> dict:
    config = scene_config(seed, size)
    world = World.build(WorldConfig(**config))
    cover = world.rock_cover()
    goal, optimal, clearance = pick_goal(world, seed, size)
    del world
    root = out / f"scene{seed}-{sensor}{'' if orient else '-no-orient'}"
    shutil.rmtree(root, ignore_errors=True)
    configs = root / "configs"
    shutil.copytree(REPO / "configs", configs)
    (configs / "world.toml").write_text(
        f"seed = {seed}\nsize_m = [{size}, {size}]\n[rocks]\ncover = {config['rocks']['cover']}\n")
    navigation = configs / "navigation.toml"
    navigation.write_text(navigation.read_text().replace("orient = false", f"orient = {str(orient).lower()}"))
    mapping = configs / "mapping.toml"
    mapping.write_text(mapping.read_text().replace('"../workflows"', json.dumps(str(REPO / "workflows"))))
    import conftest
    conftest.SIM_SPEED = sim_speed
    server = ServerProcess(data_dir=root / "data", config_dir=configs).start(timeout=180)
    started = time.perf_counter()
    try:
        with server.connect(timeout=3600) as client:
            reply = client.command(f"navigate --to {goal[0]},{goal[1]} --sensor {sensor} --max-steps 25",
                                   timeout=3600)
    finally:
        server.stop()
    seconds = time.perf_counter() - started
    fields = pairs(reply)
    if "product=" not in reply:
        raise RuntimeError(f"no product: {reply[:300]}")
    name = fields.get("product") or reply.split("product=")[-1].split()[0]
    product = root / "data" / "products" / name
    traverse = json.loads((product / "traverse.json").read_text())
    truth = json.loads((product / "truth" / "traverse.json").read_text())
    true_path = np.array(truth["path"])[:, :2]
    true_end = true_path[-1]
    driven = float(np.sum(np.linalg.norm(np.diff(true_path, axis=0), axis=1)))
    estimated = np.array(traverse["pose"][:2])
    odometry = np.array(traverse["odometry"][:2])
    ok = " OK " in f" {reply} "
    looks = traverse.get("orients", [])
    return {"seed": seed, "sensor": sensor, "cover": round(cover, 4), "goal": goal, "optimal_m": round(optimal, 3),
            "goal_clearance_m": round(clearance, 2), "ok": ok, "outcome": traverse["outcome"],
            "true_distance_to_goal": round(float(np.linalg.norm(true_end - goal)), 3),
            "success": bool(ok and np.linalg.norm(true_end - goal) <= 0.4),
            "contacts": int(truth["contacts"]), "driven_m": round(driven, 3),
            "length_ratio": round(driven / optimal, 3) if optimal > 0 else None,
            "localisation_error_m": round(float(np.linalg.norm(estimated - true_end)), 3),
            "odometry_error_m": round(float(np.linalg.norm(odometry - true_end)), 3),
            "cycles": traverse["cycle"], "looks": len(looks), "looks_failed": sum("failed" in look for look in looks),
            "seconds": round(seconds, 1), "product": str(product), "reply": reply[:300]}


def has_goal(seed: int, size: float) -> bool:
    try:
        pick_goal(World.build(WorldConfig(**scene_config(seed, size))), seed, size)
        return True
    except NoGoal:
        return False


def usable_seeds(first: int, count: int, size: float, jobs: int = 2,
                 known: Path | None = None) -> tuple[list[int], list[int]]:
    """The first `count` seeds from `first` whose scene has a goal with a true path. Each world is
    built in a process of its own: one process building 31 worlds grew to 7 GB and was killed.
    `known` (JSON: size -> seed -> usable) keeps the answers, so a rerun builds no world twice."""
    cache = json.loads(known.read_text()) if known is not None and known.exists() else {}
    answers = {int(k): v for k, v in cache.get(f"{size:g}", {}).items()}
    seeds, boxed_in, seed = [], [], first
    with ProcessPoolExecutor(max_workers=jobs, max_tasks_per_child=1) as pool:
        while len(seeds) < count:
            batch = list(range(seed, seed + count - len(seeds)))
            unknown = [s for s in batch if s not in answers]
            answers.update(zip(unknown, pool.map(has_goal, unknown, [size] * len(unknown)), strict=True))
            for candidate in batch:
                (seeds if answers[candidate] else boxed_in).append(candidate)
            seed = batch[-1] + 1
    if known is not None:
        cache[f"{size:g}"] = {str(k): v for k, v in sorted(answers.items())}
        known.parent.mkdir(parents=True, exist_ok=True)
        known.write_text(json.dumps(cache, indent=1) + "\n")
    return seeds, boxed_in


def summarise(results: list[dict], sensor: str) -> str:
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
    failures = [r for r in rows if not r["success"]]
    for r in failures:
        lines.append(f"  failed: scene {r['seed']} goal {r['goal']}: {r['outcome']} (true distance to goal "
                     f"{r['true_distance_to_goal']} m) {r['product']}")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scenes", type=int, default=30)
    parser.add_argument("--first-seed", type=int, default=101)
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--sensors", nargs="+", default=["tof", "stereo"])
    parser.add_argument("--size", type=float, default=34.0)
    parser.add_argument("--sim-speed", type=float, default=100.0)
    parser.add_argument("--only", type=int, nargs="+", help="run only these seeds of the campaign (a quick check)")
    parser.add_argument("--out", type=Path, default=Path("/tmp/rvs-navigation"), help="the servers' work folders")
    parser.add_argument("--results", type=Path, default=RESULTS, help="the JSON-lines file runs are kept in")
    parser.add_argument("--report", type=Path, help="print the summary of this results file and exit")
    parser.add_argument("--orient", choices=["on", "off"], default="off", help="navigation.toml orient: an orient "
                        "look between the moves")
    args = parser.parse_args()
    if args.report:
        print(report(args.report, summarise))
        return
    args.out.mkdir(parents=True, exist_ok=True)
    log = RunLog(args.results, {"size_m": args.size, "orient": args.orient})
    known = args.results.with_name(args.results.stem + "-seeds.json")
    if args.only:  # checked one by one: building all the campaign's worlds first takes minutes
        seeds, boxed_in = [], []
        for seed in args.only:
            found, skipped = usable_seeds(seed, 1, args.size, known=known)
            seeds += [s for s in found if s == seed]
            boxed_in += skipped
    else:
        seeds, boxed_in = usable_seeds(args.first_seed, args.scenes, args.size, args.jobs, known=known)
    print(f"{len(seeds)} scenes: seeds {seeds[0]}-{seeds[-1]}; {len(boxed_in)} seeds skipped because the rover is "
          f"boxed in at the start on the true map: {boxed_in}", flush=True)
    planned = [{"seed": seed, "sensor": sensor} for seed in seeds for sensor in args.sensors]
    tasks = log.todo(planned)
    print(f"{len(planned) - len(tasks)} of {len(planned)} runs already in {args.results}; {len(tasks)} to go",
          flush=True)
    with ProcessPoolExecutor(max_workers=args.jobs, max_tasks_per_child=1) as pool:   # a fresh process per scene
        futures = {pool.submit(run, task["seed"], task["sensor"], args.size, args.out, args.sim_speed,
                               args.orient == "on"): task for task in tasks}
        for future in as_completed(futures):
            task = futures[future]
            try:
                result = future.result()
            except Exception as exc:  # a scene that cannot run is written and reported, not hidden
                log.append(task, 0.0, error=repr(exc)[:500])
                print(f"scene {task['seed']} {task['sensor']}: ERROR {exc!r}"[:400], flush=True)
                continue
            scores = {k: v for k, v in result.items() if k not in ("seed", "sensor", "seconds")}
            log.append(task, result["seconds"], **scores)
            print(f"scene {task['seed']} {task['sensor']}: "
                  f"{'success' if result['success'] else 'FAILED ' + result['outcome']}, "
                  f"{result['driven_m']:.1f} m driven for {result['optimal_m']:.1f} m optimal, contacts "
                  f"{result['contacts']}, localisation {100 * result['localisation_error_m']:.1f} cm "
                  f"(odometry {100 * result['odometry_error_m']:.1f} cm), {result['seconds']:.0f} s", flush=True)
    print(report(args.results, summarise))


if __name__ == "__main__":
    main()
