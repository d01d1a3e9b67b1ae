"""Campaign: track3d-detect and track3d-start on seeded scenes with scripted walks, scored on the truth
with motmetrics (CLEAR MOT).

    pip install -e '.[bench]'        # motmetrics
    python tests/bench/track_campaign.py --sensor tof --seeds 20 [--first-seed 401] [--seconds 40]
        [--results tests/bench/results/track.jsonl] [--out /tmp/rvs-track]
    python tests/bench/track_campaign.py --report tests/bench/results/track.jsonl

Each finished scene is appended to --results at once (clients/run_log.py: seed, sensor, settings,
every score, seconds); a rerun with the same settings skips the scenes already there. --report prints
the summary per settings and sensor from the file alone.

Per scene (a 20 m seeded world, one real rvs-server at sim-speed 1: the tracker's rate is in
simulation time and its processing in wall time, so only 1 is honest about frame rate):
- a standing boulder of a person's height (1.6-2.0 m, 0.6-0.9 m across) 3-4.5 m out, and the walk
  passing behind it (0.5-1.5 m/s, 1.5-2.5 m beyond the boulder): the occlusion;
- the walk turns at its far end (a corner) and stands 0-3 s at each end before it turns back; one
  scene in three its far corner lies beyond the sensor's range (leaving the field of view and coming
  back); one more boulder of person height stands elsewhere as a distractor;
- `track3d-detect --pan -90:90` (again, up to three times, while it finds nobody: the walker may be
  out of range or hidden while the sweep passes), then `track3d-start` for `--seconds`, then `track3d-stop`; the
  product's track.csv holds, per frame, the estimate and the truth at the frame's own time (where
  the person was, and the share of its body axis the sensor saw past every rock).

Scoring, per frame: the person is ground truth where at least VISIBLE of it was in view and it was
within the tracker's range; frames where less but some of it was seen are left out (don't care,
as KITTI does with truncated objects); the hypothesis is the estimate of every frame in state
`tracking`, coasting included: a coasted estimate while the person is hidden or out of range is a
false positive unless it is still within MATCH_M of the person (KITTI's DontCare: a tracker is
neither rewarded nor punished for following what the truth does not count).
A hypothesis within MATCH_M of the truth matches. Reported: MOTA, MOTP, precision and recall (and
by true range band), identity switches, 3-D position RMSE of matched frames (within 8 m and all),
the share of visible time tracked, the time to match again after each occlusion, frames per second.
Prints one line per scene and the summary (--rescore scores the track.csv files of the runs in
--results again, while their work folders are still there).
"""
from __future__ import annotations

import argparse
import csv
import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from clients.run_log import RunLog, add_results_options, report, reported  # noqa: E402

import conftest  # noqa: E402
from conftest import ServerProcess, pairs, write_configs  # noqa: E402

VISIBLE = 0.5          # share of the body axis in view that makes the person ground truth
DONT_CARE = 0.05       # seen less than VISIBLE but more than this: the frame is left out
MATCH_M = 0.5          # a hypothesis this near the truth matches it
RANGE_M = 9.5          # tracking.toml max_range_m
DETECT_TRIES = 3       # searches before a scene counts as not found (the person may be out of range)
BANDS = ((0.0, 4.0), (4.0, 6.0), (6.0, 8.0), (8.0, 10.0))
RESULTS = Path(__file__).resolve().parent / "results" / "track.jsonl"
# The tracker's revision, part of the results' settings so a changed tracker is measured anew: the
# runs without a TRACKER coasted past the sensor's range; "lost-past-range" took the ground under a
# person from the ring round it alone (0.1-0.3 m high at 7-9 m); "feet-ground" from its feet;
# "whole-prior" seeds the person's height with the search's only where it is a whole person's;
# "stereo-noise" finds a stereo frame's ground from cell medians and stands points clear of its noise;
# "stereo-legs" judges stereo clusters by a legs-to-torso limit of its own (0.92-1.02); "reach" learns
# the height only from a search within 6 m and takes a person outside the gate within a walker's reach.
# "plane-ground": the emulated stereo pair renders the walker where it was at the trigger pulse in both
# cameras (before, the right camera saw it up to a few cm further on); the target's ground is a local
# plane over where it walked (not a running average); acquisition waits until the view holds the
# search's sighting (a boulder passed while the unit turned there took the track). "far-height": beyond
# 6 m too, a whole grown person's height stands in for the hidden-feet rule until one is seen near.
# "exposure-heading": a frame is placed with the PTU angles of its exposure (a stereo pair exposes at
# the start of its grab; the mean of the readings put a turning head 0.4-1 degree off); while the
# target walks, stereo takes its centre behind the face it sees from the walk's heading, not from the
# legs' width (which the matcher widens); the stereo covariance is sure across the line of sight and
# unsure along it, and a frame whose person reads taller or shorter than the target counts less.
# "height-gate": the gate is the sensor's own (a widened covariance let a wrong cluster in), a restart
# wants a person near the target's height, only a grown person's height is learnt (near too), and the
# stereo filter's white acceleration is 2.0 (its 5 Hz, range-noisy frames lagged a fast walker's turns).
# "ptu-speed": a frame exposed in a PTU hop takes the unit's set speed between the two readings.
# "upper-legs": while it follows a person, a cluster of the target's height whose legs alone fail is
# judged by the legs above the knees (a low rock at the walker's feet joined the cluster).
# "legs-floor": a stereo cluster's legs are measured from one noise deviation above where its points
# start to stand (the ground's noise tail beside the feet widened them at 7 m).
TRACKER = "legs-floor"


def world_toml(seed: int) -> str:
    return f"seed = {seed}\nsize_m = [24.0, 24.0]\n[rocks]\ncover = 0.05\n[craters]\ncount = 1\n"


def polar(range_m: float, bearing_deg: float) -> tuple[float, float]:
    """World X,Y of a place at this range and bearing (positive right) from the rover at the origin."""
    b = math.radians(bearing_deg)
    return range_m * math.cos(b), -range_m * math.sin(b)


def scenario(seed: int) -> dict:
    """The scene's script: boulders and the walk, drawn from the seed."""
    rng = np.random.default_rng([seed, 24])
    occluder_range, occluder_bearing = rng.uniform(3.0, 4.5), rng.uniform(-25, 25)
    behind = rng.uniform(1.5, 2.5)
    walk_range = occluder_range + behind
    half = math.degrees(math.atan2(rng.uniform(1.8, 2.6), walk_range))
    side = rng.choice([-1, 1])
    start = polar(walk_range, occluder_bearing - side * half)
    to = polar(walk_range, occluder_bearing + side * half)
    leaves = seed % 3 == 0
    corner_range = rng.uniform(10.5, 11.0) if leaves else rng.uniform(walk_range - 1.5, min(8.5, walk_range + 2.0))
    then = polar(corner_range, occluder_bearing + side * (half + rng.uniform(10, 25)))
    distractor_bearing = occluder_bearing - side * rng.uniform(35, 60)
    return {
        "seed": seed, "leaves_view": leaves,
        "occluder": {"at": polar(occluder_range, occluder_bearing), "height": rng.uniform(1.6, 2.0),
                     "diameter": rng.uniform(0.6, 0.9), "seed": int(seed)},
        "distractor": {"at": polar(rng.uniform(3.5, 7.0), distractor_bearing), "height": rng.uniform(1.6, 2.0),
                       "diameter": rng.uniform(0.5, 0.9), "seed": int(seed) + 1},
        "walk": {"at": start, "to": to, "then": then, "speed": rng.uniform(0.5, 1.5), "pause": rng.uniform(0, 3)},
    }


def xy(point: tuple[float, float]) -> str:
    return f"{point[0]:.3f},{point[1]:.3f}"


def run_scene(seed: int, sensor: str, seconds: float, out: Path, tracking: dict[str, str] | None = None) -> dict:
    script = scenario(seed)
    workdir = out / f"{sensor}-{seed}"
    files = {"world.toml": world_toml(seed)}
    if tracking:   # the repository's tracking.toml with the overridden keys' lines replaced
        own = (conftest.REPO / "configs" / "tracking.toml").read_text().splitlines()
        kept = [line for line in own if line.split("=", 1)[0].strip() not in tracking]
        files["tracking.toml"] = "\n".join(kept + [f"{key} = {value}" for key, value in tracking.items()]) + "\n"
    config = write_configs(workdir / "configs", files)
    conftest.SIM_SPEED = 1.0
    server = ServerProcess(workdir / "data", config).start(timeout=300)
    try:
        with server.connect(timeout=900) as c:
            for rock in ("occluder", "distractor"):
                r = script[rock]
                reply = c.command(f"sim-rock --at {xy(r['at'])} --height {r['height']:.2f} "
                                  f"--diameter {r['diameter']:.2f} --seed {r['seed']}", timeout=300)
                if " OK " not in reply:
                    raise RuntimeError(f"sim-rock: {reply}")
            w = script["walk"]
            reply = c.command(f"astronaut --at {xy(w['at'])} --to {xy(w['to'])} --then {xy(w['then'])} "
                              f"--speed {w['speed']:.2f} --pause {w['pause']:.1f}", timeout=300)
            if " OK " not in reply:
                raise RuntimeError(f"astronaut: {reply}")
            for tries in range(1, DETECT_TRIES + 1):  # noqa: B007  reported below; search again as an operator would
                detect = pairs(c.command(f"track3d-detect --sensor {sensor} --pan -90:90", timeout=900))
                if detect.get("found", "0") != "0":
                    break
            detect["tries"] = tries
            if detect.get("found", "0") == "0":
                return {"seed": seed, "sensor": sensor, "script": script, "detect": detect, "not_found": True}
            started = pairs(c.command(f"track3d-start --sensor {sensor}", timeout=60))
            time.sleep(seconds)
            stopped = pairs(c.command("track3d-stop", timeout=120))
        rows = list(csv.DictReader(open(Path(stopped["path"]) / "track.csv")))
        scores = score_scene(rows)
        return {"seed": seed, "sensor": sensor, "script": script, "detect": detect, "start": started,
                "stop": stopped, **scores}
    finally:
        server.stop()


def rescored(result: dict) -> dict:
    if "stop" not in result:
        return result
    rows = list(csv.DictReader(open(Path(result["stop"]["path"]) / "track.csv")))
    return {**result, **score_scene(rows)}


def _f(value: str) -> float:
    return float(value) if value not in ("", None) else math.nan


def score_scene(rows: list[dict]) -> dict:
    """The frames of one run as motmetrics events plus the figures motmetrics does not give."""
    import motmetrics as mm
    acc = mm.MOTAccumulator(auto_id=True)
    frames = []
    for r in rows:
        if r["state"] == "unknown":
            continue
        visible, true_range = _f(r["true_visible"]), math.nan
        truth = np.array([_f(r["true_x"]), _f(r["true_y"]), _f(r["true_z"])])
        estimate = np.array([_f(r["x"]), _f(r["y"]), _f(r["z"])])
        true_range = float(np.hypot(*truth[:2])) if np.isfinite(truth).all() else math.nan
        is_gt = np.isfinite(visible) and visible >= VISIBLE and true_range <= RANGE_M
        is_hyp = r["state"] == "tracking"
        if not is_gt and np.isfinite(visible) and visible > DONT_CARE:
            continue                                      # partly seen: don't care
        if not is_gt and is_hyp and np.linalg.norm(estimate[:2] - truth[:2]) <= MATCH_M:
            continue                                      # hidden or out of range, and still followed: don't care
        gt, hyp = ([1] if is_gt else []), ([1] if is_hyp else [])
        distance = mm.distances.norm2squared_matrix(truth[None, :2], estimate[None, :2], max_d2=MATCH_M ** 2) \
            if gt and hyp else np.empty((len(gt), len(hyp)))
        acc.update(gt, hyp, np.sqrt(distance) if distance.size else distance)
        error = estimate - truth
        matched = bool(gt and hyp and np.linalg.norm(error[:2]) <= MATCH_M)
        frames.append({"t": _f(r["sim_s"]), "gt": is_gt, "hyp": is_hyp, "matched": matched,
                       "range": true_range if is_gt else _f(r["range_m"]), "error": error,
                       "seen": r["seen"] == "1", "visible": visible})
    mh = mm.metrics.create()
    summary = mh.compute(acc, metrics=["mota", "motp", "precision", "recall", "num_switches", "num_false_positives",
                                       "num_misses", "num_matches", "num_objects"], name="scene")
    s = summary.iloc[0]
    # Every frame the tracker made counts for its rate, the ones left out of the scoring too.
    times = [_f(r["sim_s"]) for r in rows if r["state"] != "unknown"]
    return {"frames": len(frames), "mota": float(s["mota"]), "motp_m": float(s["motp"]),
            "precision": float(s["precision"]), "recall": float(s["recall"]), "id_switches": int(s["num_switches"]),
            "fp": int(s["num_false_positives"]), "misses": int(s["num_misses"]), "matches": int(s["num_matches"]),
            "objects": int(s["num_objects"]),
            "fps": (len(times) - 1) / (times[-1] - times[0]) if len(times) > 1 else 0.0,
            "errors": [[float(v) for v in f["error"]] + [f["range"]] for f in frames if f["matched"]],
            "bands": band_counts(frames), "reacquire_s": reacquisitions(frames),
            "coasted_fp": sum(f["hyp"] and not f["gt"] and not f["seen"] for f in frames)}


def band_counts(frames: list[dict]) -> dict:
    bands = {}
    for low, high in BANDS:
        def inside(f: dict, low: float = low, high: float = high) -> bool:
            return low <= f["range"] < high
        bands[f"{low:g}-{high:g}"] = {
            "gt": sum(f["gt"] and inside(f) for f in frames),
            "gt_matched": sum(f["gt"] and f["matched"] and inside(f) for f in frames),
            "hyp": sum(f["hyp"] and inside(f) for f in frames),
            "hyp_matched": sum(f["hyp"] and f["matched"] and inside(f) for f in frames)}
    return bands


def reacquisitions(frames: list[dict]) -> list[list[float]]:
    """Per occlusion (the person unseen, then in view again): [how long it was hidden, seconds until
    the track matched it again (inf: never in this run)]."""
    found = []
    hidden_since = None
    for i, f in enumerate(frames):
        if not f["gt"] and f["visible"] <= DONT_CARE and hidden_since is None and i > 0 and frames[i - 1]["gt"]:
            hidden_since = f["t"]
        elif f["gt"] and hidden_since is not None:
            back = f["t"]
            again = next((g["t"] for g in frames[i:] if g["matched"]), math.inf)
            found.append([back - hidden_since, again - back])
            hidden_since = None
    return found


def summarise(results: list[dict], sensor: str) -> dict:
    import motmetrics  # noqa: F401  (the same library scored every scene)
    ok = [r for r in results if not r.get("not_found")]
    total = {k: sum(r[k] for r in ok) for k in ("fp", "misses", "matches", "objects", "id_switches")}
    errors = np.array([e for r in ok for e in r["errors"]]) if ok else np.zeros((0, 4))
    near = errors[errors[:, 3] <= 8.0] if len(errors) else errors
    bands = {}
    for band in (f"{lo:g}-{hi:g}" for lo, hi in BANDS):
        c = {k: sum(r["bands"][band][k] for r in ok) for k in ("gt", "gt_matched", "hyp", "hyp_matched")}
        bands[band] = {"recall": c["gt_matched"] / c["gt"] if c["gt"] else None,
                       "precision": c["hyp_matched"] / c["hyp"] if c["hyp"] else None, **c}
    occlusions = [o for r in ok for o in r["reacquire_s"]]
    short = [o[1] for o in occlusions if o[0] <= 3.0]
    return {
        "sensor": sensor, "scenes": len(results), "scored": len(ok), "not_found": [r["seed"] for r in results
                                                                                   if r.get("not_found")],
        "mota": 1 - (total["fp"] + total["misses"] + total["id_switches"]) / max(1, total["objects"]),
        "precision": total["matches"] / max(1, total["matches"] + total["fp"]),
        "recall": total["matches"] / max(1, total["objects"]), **total,
        "visible_time_tracked": total["matches"] / max(1, total["objects"]),
        "rmse_3d_m_within_8m": float(np.sqrt(np.mean(np.sum(near[:, :3] ** 2, axis=1)))) if len(near) else None,
        "rmse_3d_m_all": float(np.sqrt(np.mean(np.sum(errors[:, :3] ** 2, axis=1)))) if len(errors) else None,
        "rmse_xy_m_within_8m": float(np.sqrt(np.mean(np.sum(near[:, :2] ** 2, axis=1)))) if len(near) else None,
        "bands": bands, "occlusions": len(occlusions), "occlusions_up_to_3s": len(short),
        "reacquire_s_median": float(np.median(short)) if short else None,
        "reacquire_s_max": float(np.max(short)) if short else None,
        "reacquired_within_1s": sum(t <= 1.0 for t in short),
        "fps_median": float(np.median([r["fps"] for r in ok])) if ok else None,
        "fps_min": float(np.min([r["fps"] for r in ok])) if ok else None,
        "coasted_fp": sum(r["coasted_fp"] for r in ok),
    }


def sensor_table(runs: list[dict], sensor: str) -> str:
    """One sensor's summary table (run_log.report's per-sensor part)."""
    return f"{sensor}:\n" + format_summary(summarise([r for r in runs if r["sensor"] == sensor], sensor))


def format_summary(s: dict) -> str:
    def f(value, digits=3):
        return "-" if value is None else f"{value:.{digits}f}"
    lines = [f"  {s['scored']} of {s['scenes']} scenes scored (not found: {s['not_found'] or 'none'})",
             f"  MOTA {f(s['mota'])}  precision {f(s['precision'])}  recall {f(s['recall'])}  identity switches "
             f"{s['id_switches']}  (matches {s['matches']}, misses {s['misses']}, false positives {s['fp']}, "
             f"of which coasting {s['coasted_fp']})",
             f"  3-D RMSE within 8 m {f(s['rmse_3d_m_within_8m'])} m, all {f(s['rmse_3d_m_all'])} m; ground plane "
             f"within 8 m {f(s['rmse_xy_m_within_8m'])} m",
             f"  visible time tracked {f(s['visible_time_tracked'])}; "
             f"frames per second median {f(s['fps_median'], 1)}, "
             f"min {f(s['fps_min'], 1)}",
             f"  occlusions {s['occlusions']} ({s['occlusions_up_to_3s']} of at most 3 s): found again median "
             f"{f(s['reacquire_s_median'], 2)} s, max {f(s['reacquire_s_max'], 2)} s, within 1 s: "
             f"{s['reacquired_within_1s']}",
             "  range band   recall  precision  (truth frames, hypotheses)"]
    for band, b in s["bands"].items():
        lines.append(f"  {band:>8s} m   {f(b['recall'])}   {f(b['precision'])}     ({b['gt']}, {b['hyp']})")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sensor", choices=("tof", "stereo"), default="tof")
    parser.add_argument("--seeds", type=int, default=20)
    parser.add_argument("--first-seed", type=int, default=401)
    parser.add_argument("--seconds", type=float, default=40.0, help="wall (= simulated) seconds of tracking")
    add_results_options(parser, RESULTS)
    parser.add_argument("--out", type=Path, default=Path("/tmp/rvs-track"), help="the servers' work folders")
    parser.add_argument("--tracking", action="append", default=[], metavar="KEY=VALUE",
                        help="a tracking.toml setting for every scene (TOML value: stereo_resolution='medium'); "
                        "part of the results' settings")
    parser.add_argument("--rescore", action="store_true", help="score the runs in --results again from their "
                        "track.csv files (their work folders must still be there)")
    args = parser.parse_args()
    if reported(args, sensor_table):
        return
    args.out.mkdir(parents=True, exist_ok=True)
    tracking = dict(item.split("=", 1) for item in args.tracking)
    settings = {"seconds": args.seconds, "tracker": TRACKER, **({"tracking": tracking} if tracking else {})}
    log = RunLog(args.results, settings)
    if args.rescore:
        results = [rescored({**r, **r["run"]}) for r in log.runs()
                   if r["run"]["sensor"] == args.sensor and "error" not in r]
        print(format_summary(summarise(results, args.sensor)))
        return
    planned = [{"seed": seed, "sensor": args.sensor} for seed in range(args.first_seed, args.first_seed + args.seeds)]
    tasks = log.todo(planned)
    print(f"{len(planned) - len(tasks)} of {len(planned)} scenes already in {args.results}; {len(tasks)} to go",
          flush=True)
    for task in tasks:     # one at a time: the tracker's frame rate is part of what is measured
        started = time.monotonic()
        try:
            result = run_scene(task["seed"], task["sensor"], args.seconds, args.out, tracking)
        except Exception as exc:   # one broken scene is written and reported, not the campaign's end
            log.append(task, time.monotonic() - started, error=f"{type(exc).__name__}: {exc}")
            print(f"{task['sensor']} seed {task['seed']}: broke: {exc}", flush=True)
            continue
        seconds = time.monotonic() - started
        log.append(task, seconds, **{k: v for k, v in result.items() if k not in ("seed", "sensor")})
        if result.get("not_found"):
            print(f"{args.sensor} seed {task['seed']}: not found in {DETECT_TRIES} searches", flush=True)
        else:
            rmse = np.sqrt(np.mean(np.sum(np.array(result["errors"])[:, :3] ** 2, axis=1))) \
                if result["errors"] else math.nan
            print(f"{args.sensor} seed {task['seed']}: MOTA {result['mota']:.3f} recall {result['recall']:.3f} "
                  f"precision {result['precision']:.3f} idsw {result['id_switches']} rmse {rmse:.3f} m "
                  f"fps {result['fps']:.1f} occlusions {result['reacquire_s']} ({seconds:.0f} s)", flush=True)
    print(report(args.results, sensor_table))


if __name__ == "__main__":
    main()
