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
import shutil
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "tests"))
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "tests" / "bench"))
from navigation_scoring import scene_config, score_product, summarise, usable_scenes  # noqa: E402

from clients.campaign import override_config  # noqa: E402
from clients.run_log import RunLog, add_results_options, report, reported  # noqa: E402

from conftest import ServerProcess, pairs  # noqa: E402

RESULTS = REPO / "tests" / "bench" / "results" / "navigation.jsonl"


def run(seed: int, scene: dict, sensor: str, size: float, out: Path, sim_speed: float, orient: bool = True) -> dict:
    """One navigate on the scene of `seed` (navigation_scoring.py: its goal and world), scored."""
    goal = tuple(scene["goal"])
    root = out / f"scene{seed}-{sensor}{'' if orient else '-no-orient'}"
    shutil.rmtree(root, ignore_errors=True)
    configs = root / "configs"
    shutil.copytree(REPO / "configs", configs)
    cover = scene_config(seed, size)["rocks"]["cover"]
    (configs / "world.toml").write_text(f"seed = {seed}\nsize_m = [{size}, {size}]\n[rocks]\ncover = {cover}\n")
    override_config(configs, "navigation.toml", {"orient": orient})   # for both sensors, whatever the default
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
    if "product=" not in reply:
        raise RuntimeError(f"no product: {reply[:300]}")
    name = pairs(reply).get("product") or reply.split("product=")[-1].split()[0]
    scores = score_product(root / "data" / "products" / name, goal, scene["optimal_m"])
    return {"seed": seed, "sensor": sensor, "cover": scene["cover"], "goal": list(goal),
            "optimal_m": scene["optimal_m"], "goal_clearance_m": scene["goal_clearance_m"], **scores,
            "seconds": round(seconds, 1), "reply": reply[:300]}


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
    add_results_options(parser, RESULTS)
    parser.add_argument("--orient", choices=["on", "off"], default="off", help="navigation.toml orient: an orient "
                        "look between the moves")
    args = parser.parse_args()
    if reported(args, summarise):
        return
    args.out.mkdir(parents=True, exist_ok=True)
    log = RunLog(args.results, {"size_m": args.size, "orient": args.orient})
    known = args.results.with_name(args.results.stem + "-seeds.json")
    if args.only:  # checked one by one: building all the campaign's worlds first takes minutes
        scenes, boxed_in = {}, []
        for seed in args.only:
            found, skipped = usable_scenes(seed, 1, args.size, known=known)
            scenes.update({s: f for s, f in found.items() if s == seed})
            boxed_in += skipped
    else:
        scenes, boxed_in = usable_scenes(args.first_seed, args.scenes, args.size, args.jobs, known=known)
    seeds = list(scenes)
    print(f"{len(seeds)} scenes: seeds {seeds[0]}-{seeds[-1]}; {len(boxed_in)} seeds skipped because the rover is "
          f"boxed in at the start on the true map: {boxed_in}", flush=True)
    planned = [{"seed": seed, "sensor": sensor} for seed in seeds for sensor in args.sensors]
    tasks = log.todo(planned)
    print(f"{len(planned) - len(tasks)} of {len(planned)} runs already in {args.results}; {len(tasks)} to go",
          flush=True)
    with ProcessPoolExecutor(max_workers=args.jobs, max_tasks_per_child=1) as pool:   # a fresh process per scene
        futures = {pool.submit(run, task["seed"], scenes[task["seed"]], task["sensor"], args.size, args.out,
                               args.sim_speed, args.orient == "on"): task for task in tasks}
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
