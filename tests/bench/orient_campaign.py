"""Campaign: orient's visual odometry on seeded traverses, scored against the simulator's true pose.

    .venv/bin/python tests/bench/orient_campaign.py [--seeds 1..20] [--sensors stereo tof] [--jobs 2]
        [--length 30] [--max-turn 15] [--label NAME] [--results tests/bench/results/orient.jsonl]
        [--out /tmp/rvs-orient]
    .venv/bin/python tests/bench/orient_campaign.py --report tests/bench/results/orient.jsonl

Each finished run is appended to --results at once (clients/run_log.py: one JSON line with its seed,
sensor, settings, scores, looks and seconds); a rerun with the same settings skips the runs already
there, so a campaign the clock stops is continued by running it again. --report prints the summary
tables from the file alone, one per settings (length, max turn) and sensor.

Per scene and sensor: a real rvs-server on a 40 m seeded world (rock cover 7 %, three craters, the
world's drive error on: 2 % of distance, 2 % + 0.5 deg of a turn, 0.3 deg/m heading creep, 1 % slip)
drives a 30 m traverse from (-13, -13) toward the far corner in steps of 0.5-1.5 m, each after a
turn (steered to the corner, off course by N(0, 8 deg), round rocks taller than 8 cm and slopes over
15 deg, as navigate with its 9 cm step limit would; a turn over --max-turn deg is made in parts, a look
after each; 15 keeps consecutive views overlapping, 90 drives the turns a GNC would, unsplit, with a look
before the forward drive after a turn of more than --look-before-drive deg, 45, as orient's refusal
advises: runs recorded before that setting existed drove on without it); after every step
`orient --sensor S` looks and its answer becomes the pose estimate. Scored
against the true pose in each orient product's truth/ (KITTI's odometry metrics on the looks):

- relative error over 5 m and 10 m segments of true path: |translation error| / length (%) and
  |rotation error| / length (deg/m), from every look to the first look at least that far along;
- end-point error as a percent of the distance driven, and the heading error at the end;
- convergence: the share of orient calls answered OK; milliseconds per call (the job, wall clock;
  the server's own: the wall less the acquisition, which here is the PTU on the simulation clock and
  the emulator's rendering; and the odometry alone);
- beside dead reckoning of the same commanded steps (what the rover would believe without orient).
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "tests"))
sys.path.insert(0, str(REPO))

from clients.campaign import override_config  # noqa: E402
from clients.run_log import (  # noqa: E402
    RunLog,
    add_config_options,
    add_results_options,
    config_overrides,
    report,
    reported,
)
from drivers.sim.motion import dead_reckon  # noqa: E402

from conftest import ServerProcess, pairs, write_configs  # noqa: E402

START = (-13.0, -13.0, 45.0)
AIM = (13.0, 13.0)
LANE_HALF_WIDTH = 0.5
MAX_TURN_DEG = 15.0         # default --max-turn: a turn larger than this is made in parts, a look after each
LOOK_BEFORE_DRIVE_DEG = 45.0  # orient.toml reach_drive_turn_deg: a larger turn gets its look before driving on
RESULTS = REPO / "tests" / "bench" / "results" / "orient.jsonl"
TALL_ROCK_M = 0.08          # navigate's step limit is 9 cm: a traverse it would drive


def world_toml(seed: int) -> str:
    return (f"seed = {seed}\nsize_m = [40.0, 40.0]\nrover_start = [{START[0]}, {START[1]}, {START[2]}]\n"
            "[rocks]\ncover = 0.07\n[craters]\ncount = 3\n")


def wrap(angle: float) -> float:
    return math.atan2(math.sin(angle), math.cos(angle))


def lane_height(world, x: float, y: float, heading: float, length: float) -> float:
    """The tallest rock on the lane the footprint sweeps, with slopes over 15 degrees counted as
    1 m (a crater wall the rover should not climb)."""
    along = np.arange(0.0, length + 0.4, 0.05)
    across = np.arange(-LANE_HALF_WIDTH, LANE_HALF_WIDTH + 1e-9, 0.05)
    a, b = np.meshgrid(along, across)
    c, s = math.cos(heading), math.sin(heading)
    xs, ys = x + a * c - b * s, y + a * s + b * c
    steep = np.nanmax(world.slope_at(xs[::4, ::4], ys[::4, ::4], 0.25)) > 15.0
    return 1.0 if steep else float(np.nanmax(world.protrusion_at(xs, ys)))


def plan_step(world, rng, true_pose) -> tuple[float, float]:
    """(turn deg, forward m) of the next step: toward the aim, off course by chance, round rocks
    and steep ground (chosen on the truth: the campaign measures odometry, not hazard avoidance);
    the lowest lane when none is clear."""
    x, y, h = true_pose
    length = float(rng.uniform(0.5, 1.5))
    wanted = math.atan2(AIM[1] - y, AIM[0] - x) + math.radians(rng.normal(0.0, 8.0))
    # Nearest the aim, and not far from where it faces: a rover does not zigzag on open ground.
    options = sorted((wanted + math.radians(d) for d in range(-120, 121, 5)),
                     key=lambda a: abs(wrap(a - wanted)) + 0.5 * abs(wrap(a - h)))
    heights = [lane_height(world, x, y, a, length) for a in options]
    clear = [a for a, height in zip(options, heights, strict=True) if height < TALL_ROCK_M]
    target = clear[0] if clear else options[int(np.argmin(heights))]
    return math.degrees(wrap(target - h)), length


def run(seed: int, sensor: str, length: float, max_turn: float, look_before_drive: float, out: Path,
        verbose: bool = False, configs: dict[str, dict] | None = None) -> dict:
    import tomllib

    from drivers.sim.config import WorldConfig
    from drivers.sim.world import World
    started = time.perf_counter()
    text = world_toml(seed)
    world = World.build(WorldConfig(**tomllib.loads(text)))
    rng = np.random.default_rng([seed, 7])
    workdir = Path(tempfile.mkdtemp(prefix=f"orient-{sensor}-{seed}-", dir=out))
    config_dir = write_configs(workdir / "configs", {"world.toml": text})
    for name, over in (configs or {}).items():
        override_config(config_dir, name, over)
    server = ServerProcess(workdir / "data", config_dir).start(timeout=300)
    client = server.connect(timeout=900)
    looks, calls, failures = [], 0, []
    dr = (START[0], START[1], math.radians(START[2]))
    driven = 0.0
    try:
        def orient() -> None:
            nonlocal calls
            calls += 1
            started = time.perf_counter()
            reply = client.command(f"orient --sensor {sensor}", timeout=900)
            wall = time.perf_counter() - started
            fields = pairs(reply) if " OK " in reply else {}
            if "product=" not in reply:
                raise RuntimeError(f"orient answered no product: {reply}")
            folder = workdir / "data" / "products" / reply.rsplit("product=", 1)[1].split()[0]
            truth = json.loads((folder / "truth" / "state.json").read_text())["rover"]
            record = json.loads((folder / "orient.json").read_text())
            timings = json.loads((folder / "product.json").read_text()).get("timings_s", {})
            true = (truth["x"], truth["y"], truth["heading_rad"])
            if " OK " not in reply:
                failures.append(reply)
                if verbose:
                    print(f"  {sensor} {seed} look {calls}: {reply.strip()[:200]} true {true}", flush=True)
                return
            looks.append({"true": true, "estimate": (float(fields["x"]), float(fields["y"]),
                                                     math.radians(float(fields["heading"]))),
                          "dead_reckoning": dr, "driven": driven, "wall_ms": 1000 * wall,
                          "odometry_ms": record.get("odometry_ms", 0.0),
                          "acquisition_ms": 1000.0 * timings.get("acquisition", float("nan")),
                          "sigma_xy": float(fields["sigma_xy"]),
                          "sigma_heading": math.radians(float(fields["sigma_heading"])),
                          "rekeyed": record.get("rekeyed"), "sources": fields.get("sources", ""),
                          "inliers": int(fields.get("matches", 0)),
                          "method": (record.get("motion") or {}).get("method", "")})
            if verbose:
                lk = looks[-1]
                print(f"  {sensor} {seed} look {calls}: "
                      f"error {100 * math.dist(lk['true'][:2], lk['estimate'][:2]):.1f} cm "
                      f"{math.degrees(wrap(lk['estimate'][2] - lk['true'][2])):+.2f} deg, dead reckoning "
                      f"{100 * math.dist(lk['true'][:2], dr[:2]):.1f} cm, inliers {lk['inliers']}, "
                      f"rekeyed {lk['rekeyed']}", flush=True)

        orient()
        while driven < length:
            true = looks[-1]["true"] if looks else (START[0], START[1], math.radians(START[2]))
            turn, forward = plan_step(world, rng, true)
            # Turns in parts of at most max_turn, a look after each (15 deg: the views overlap).
            parts = math.ceil(abs(turn) / max_turn) if abs(turn) >= 0.5 else 0
            for _ in range(parts):
                reply = client.command(f"drive --turn {turn / parts:.2f}", timeout=300)
                if " OK " not in reply:
                    raise RuntimeError(reply)
                dr = dead_reckon(dr, math.radians(turn / parts), 0.0)
                if parts > 1:
                    orient()
            if parts == 1 and abs(turn) > look_before_drive:
                orient()      # as a refusal advises: past this turn the forward drive would lose the keyframe
            reply = client.command(f"drive --forward {forward:.3f}", timeout=300)
            if " OK " not in reply:
                raise RuntimeError(reply)
            dr = dead_reckon(dr, 0.0, forward)
            driven += forward
            orient()
    finally:
        client.close()
        server.stop()
    return {"seed": seed, "sensor": sensor, "calls": calls, "failures": failures, "looks": looks,
            "seconds": time.perf_counter() - started}


# ---------------------------------------------------------------------------------- scoring
def se2(pose) -> np.ndarray:
    x, y, h = pose
    return np.array([[math.cos(h), -math.sin(h), x], [math.sin(h), math.cos(h), y], [0, 0, 1]])


def segment_errors(looks: list[dict], key: str, length: float) -> list[tuple[float, float]]:
    """(translation % of length, rotation deg/m) from every look to the first one `length` further
    along the true path."""
    true = [np.array(lk["true"][:2]) for lk in looks]
    along = np.concatenate([[0.0], np.cumsum([np.linalg.norm(b - a)
                                              for a, b in zip(true[:-1], true[1:], strict=True)])])
    errors = []
    for i in range(len(looks)):
        j = int(np.searchsorted(along, along[i] + length))
        if j >= len(looks):
            break
        d = along[j] - along[i]
        dt = np.linalg.inv(se2(looks[i]["true"])) @ se2(looks[j]["true"])
        de = np.linalg.inv(se2(looks[i][key])) @ se2(looks[j][key])
        e = np.linalg.inv(dt) @ de
        errors.append((100 * math.hypot(e[0, 2], e[1, 2]) / d, abs(math.degrees(math.atan2(e[1, 0], e[0, 0]))) / d))
    return errors


def end_errors(result: dict, key: str) -> tuple[float, float]:
    last = result["looks"][-1]
    distance = sum(math.dist(a["true"][:2], b["true"][:2])
                   for a, b in zip(result["looks"][:-1], result["looks"][1:], strict=True))
    position = math.dist(last[key][:2], last["true"][:2])
    return 100 * position / max(distance, 1e-9), abs(math.degrees(wrap(last[key][2] - last["true"][2])))


def scores(result: dict) -> dict:
    """One run's own figures, written beside its looks (the summary pools the looks of all runs)."""
    out = {"calls": result["calls"], "failed": len(result["failures"]),
           "converged_pct": round(100 * (result["calls"] - len(result["failures"])) / max(result["calls"], 1), 2)}
    if not result["looks"]:
        return out
    for key, name in (("estimate", "orient"), ("dead_reckoning", "dead_reckoning")):
        for length in (5.0, 10.0):
            errors = np.array(segment_errors(result["looks"], key, length)).reshape(-1, 2)
            if len(errors):
                out[f"{name}_seg{length:g}m_pct"] = round(float(np.median(errors[:, 0])), 4)
                out[f"{name}_seg{length:g}m_deg_m"] = round(float(np.median(errors[:, 1])), 5)
        end, heading = end_errors(result, key)
        out[f"{name}_end_pct"], out[f"{name}_end_heading_deg"] = round(end, 4), round(heading, 4)
    wall = [lk["wall_ms"] for lk in result["looks"][1:]]
    if wall:
        out["wall_ms_median"] = round(float(np.median(wall)), 1)
    return out


def _own_time(looks: list[dict]) -> str:
    """The call's wall less its acquisition (the PTU's travel on the simulation clock and the
    emulator rendering the frames: a real camera delivers a frame in tens of milliseconds): what
    the server itself spends per call. Runs recorded before acquisition_ms was kept have none."""
    own = np.array([lk["wall_ms"] - lk["acquisition_ms"] for lk in looks if "acquisition_ms" in lk])
    own = own[np.isfinite(own)]
    if not len(own):
        return ""
    return (f"the server's own (wall less acquisition) {np.median(own):.0f} ms median "
            f"(p95 {np.percentile(own, 95):.0f}); ")


def summarise(results: list[dict], sensor: str) -> str:
    runs = [r for r in results if r["sensor"] == sensor and r["looks"]]
    if not runs:
        return f"{sensor}: no runs"
    lines = [f"{sensor}: {len(runs)} traverses, {sum(len(r['looks']) for r in runs)} looks"]
    for key, label in (("estimate", "orient"), ("dead_reckoning", "dead reckoning")):
        parts = []
        for length in (5.0, 10.0):
            errors = np.array([e for r in runs for e in segment_errors(r["looks"], key, length)]).reshape(-1, 2)
            if not len(errors):
                continue
            parts.append(f"{length:g} m: median {np.median(errors[:, 0]):.2f} % {np.median(errors[:, 1]):.4f} deg/m "
                         f"(mean {errors[:, 0].mean():.2f} % {errors[:, 1].mean():.4f} deg/m, n={len(errors)})")
        ends = np.array([end_errors(r, key) for r in runs])
        lines.append(f"  {label:15s} segments {'; '.join(parts)}")
        lines.append(f"  {label:15s} end point median {np.median(ends[:, 0]):.2f} % of distance "
                     f"(max {ends[:, 0].max():.2f} %), "
                     f"end heading error median {np.median(ends[:, 1]):.3f} deg, max {ends[:, 1].max():.3f} deg")
    calls = sum(r["calls"] for r in runs)
    failed = sum(len(r["failures"]) for r in runs)
    looks = [lk for r in runs for lk in r["looks"][1:]]
    wall = np.array([lk["wall_ms"] for lk in looks])
    odo = np.array([lk["odometry_ms"] for lk in looks])
    end_sigma = np.array([math.dist(r["looks"][-1]["estimate"][:2], r["looks"][-1]["true"][:2])
                          / max(r["looks"][-1]["sigma_xy"], 1e-9) for r in runs])
    lines.append(f"  converged {calls - failed}/{calls} = {100 * (calls - failed) / max(calls, 1):.2f} %; "
                 f"per call {np.median(wall):.0f} ms median wall (p95 {np.percentile(wall, 95):.0f}), odometry "
                 f"{np.median(odo):.0f} ms median (p95 {np.percentile(odo, 95):.0f}); "
                 f"{_own_time(looks)}keyframes {sum(bool(lk['rekeyed']) for lk in looks)}"
                 f"/{len(looks)} looks; end error / believed sigma median {np.median(end_sigma):.2f}")
    turns = sum(lk.get("method") == "icp-rotation" for lk in looks)
    if turns:
        lines.append(f"  {turns} looks after a turn on the spot measured by the rotation alone (free ICP refused)")
    for r in runs:
        for f in r["failures"][:2]:
            lines.append(f"  seed {r['seed']} failed: {f.strip()[:160]}")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--seeds", type=int, nargs="+", default=list(range(1, 21)))
    parser.add_argument("--sensors", nargs="+", default=["stereo", "tof"])
    parser.add_argument("--length", type=float, default=30.0)
    parser.add_argument("--max-turn", type=float, default=MAX_TURN_DEG,
                        help="a turn larger than this (deg) is made in parts, a look after each")
    parser.add_argument("--look-before-drive", type=float, default=LOOK_BEFORE_DRIVE_DEG,
                        help="an unsplit turn larger than this (deg) gets a look before the forward drive")
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--label", help="names the code's revision in the runs' settings (a table of its own)")
    add_results_options(parser, RESULTS)
    add_config_options(parser)
    parser.add_argument("--out", type=Path, default=Path("/tmp/rvs-orient"), help="the servers' work folders")
    parser.add_argument("--verbose", action="store_true", help="a line per look")
    args = parser.parse_args()
    if reported(args, summarise):
        return
    try:
        configs = config_overrides(args.config_set)
    except ValueError as exc:
        parser.error(str(exc))
    args.out.mkdir(parents=True, exist_ok=True)
    log = RunLog(args.results, {"length_m": args.length, "max_turn_deg": args.max_turn,
                                "look_before_drive_deg": args.look_before_drive,
                                **({"label": args.label} if args.label else {}),
                                **({"configs": configs} if configs else {})})
    started = time.perf_counter()
    planned = [{"seed": seed, "sensor": sensor} for sensor in args.sensors for seed in args.seeds]
    tasks = log.todo(planned)
    print(f"{len(planned) - len(tasks)} of {len(planned)} runs already in {args.results}; {len(tasks)} to go",
          flush=True)
    with ProcessPoolExecutor(args.jobs, max_tasks_per_child=1) as pool:
        futures = {pool.submit(run, task["seed"], task["sensor"], args.length, args.max_turn,
                               args.look_before_drive, args.out, args.verbose, configs):
                   task for task in tasks}
        for future in as_completed(futures):
            task = futures[future]
            try:
                result = future.result()
            except Exception as exc:   # a run that broke is written and reported; the campaign goes on
                log.append(task, 0.0, error=repr(exc)[:500])
                print(f"{task['sensor']} seed {task['seed']}: broke: {exc}", flush=True)
                continue
            seconds = result["seconds"]
            record = log.append(task, seconds, **scores(result), failures=result["failures"], looks=result["looks"])
            print(f"{task['sensor']} seed {task['seed']}: {len(result['looks'])} looks, {record['failed']} failed, "
                  f"end {record.get('orient_end_pct', float('nan')):.2f} % (dead reckoning "
                  f"{record.get('dead_reckoning_end_pct', float('nan')):.2f} %), {seconds:.0f} s", flush=True)
    print(report(args.results, summarise))
    print(f"campaign took {time.perf_counter() - started:.0f} s")


if __name__ == "__main__":
    main()
