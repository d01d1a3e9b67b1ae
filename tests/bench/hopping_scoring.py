"""The hopping campaign's scenes and scores: the hopping paper's chains (Table 1) and single hops, scored
against the simulator's truth from what hop and hop-plan wrote (measure_hopping.py's records of a run).

chains   per hop: the estimated touchdown's error with and without ICP as a percentage of the true
         touchdown's distance from the start, the launch corrections' errors, each chosen target
         against the true obstacles and how far the next hop truly touched down from it;
singles  the hop's reconstructed displacement against the true one, as a percentage of its length;
timing   hop-plan's steps for hops of 40-60 frames and the servers' peak memory.

A hopping run is not a fixed mission: each chain hop is launched as the previous hop-plan chose, and
each single hop heads from where the last one came to rest. chain() and singles() play one run on a
server of its own; tests/bench/measure_hopping.py runs them in a process pool (then `summary`), and
tests/bench/campaigns/hopping.toml on Dask through the hooks `runs`, `execute` and `report` below.
"""
from __future__ import annotations

import json
import math
import re
import shutil
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[2]
MOON_G = 1.62
PAPER_TABLE_1 = "paper Table 1 (simulated, 5-hop chains): with ICP 1.0-1.9 %, without 12.9-34.7 %"


def speed_for(distance: float, elevation_deg: float) -> float:
    """Launch speed of a hop of `distance` on flat ground at the elevation."""
    return math.sqrt(distance * MOON_G / math.sin(2 * math.radians(elevation_deg)))



def chain_errors(run: dict) -> list[dict]:
    """Per hop: touchdown error with and without ICP as a percentage of the true distance from the start."""
    hops = run["hops"]
    if not hops:                 # stopped at its first hop
        return []
    start = np.array(hops[0]["truth"]["launch"]["centre_m"][:2])
    without = start.copy()
    rows = []
    for k, hop in enumerate(hops):
        true = np.array(hop["truth"]["landing"]["centre_m"][:2])
        with_icp = np.array(hop["touchdown_m"][:2])
        without = without + with_icp - np.array(hop["launch_corrected_m"][:2])   # the hop's own displacement
        distance = float(np.linalg.norm(true - start))
        row = {"hop": k + 1, "distance_m": distance,
               "with_icp_pct": 100 * float(np.linalg.norm(with_icp - true)) / distance,
               "without_icp_pct": 100 * float(np.linalg.norm(without - true)) / distance,
               "bounce_m": hop["comparison"]["next_launch"]["bounce_horizontal_m"],
               "icp_used": bool(hop["icp"].get("used", False)) if hop["icp"] else None,
               **correction_errors(hop)}
        target = hop["comparison"].get("target")
        if target is not None:
            row["target_clear"] = target["footprint_clear"]
            row["target_nearest_obstacle_m"] = target["nearest_true_obstacle_m"]
        if k + 1 < len(hops) and hop["target_m"] is not None:
            landed = np.array(hops[k + 1]["truth"]["landing"]["centre_m"][:2])
            row["next_touchdown_from_target_m"] = float(np.linalg.norm(landed - np.array(hop["target_m"][:2])))
        rows.append(row)
    return rows


def correction_errors(hop: dict) -> dict:
    """How far each position correction's horizontal shift fell from the one the truth needed (m): the
    height match's, ICP's from it, and the one applied (none: the launch error itself)."""
    before = hop["comparison"]["launch_before_icp"]
    needed = np.array(before["true_m"][:2]) - np.array(before["estimated_m"][:2])
    icp = hop.get("icp") or {}
    shifts = {"match": icp.get("match", {}).get("shift_m"), "icp": icp.get("icp", {}).get("shift_m"),
              "applied": icp.get("shift_m") if icp.get("used") else [0.0, 0.0]}
    return {f"{name}_error_m": float(np.linalg.norm(np.array(shift[:2]) - needed))
            for name, shift in shifts.items() if shift is not None} | {"needed_m": float(np.linalg.norm(needed))}


def single_errors(run: dict) -> list[dict]:
    rows = []
    for record in run["hops"]:
        if "plan_error" in record:
            rows.append({"error": record["plan_error"], "commanded_m": record["commanded_m"]})
            continue
        truth = record["truth"]
        true = np.array(truth["landing"]["centre_m"][:2]) - np.array(truth["launch"]["centre_m"][:2])
        estimated = np.array(record["touchdown_m"][:2]) - np.array(record["launch_corrected_m"][:2])
        length = float(np.linalg.norm(true))
        rows.append({"commanded_m": record["commanded_m"], "true_m": length, "frames": record["frames"],
                     "registered": record["registered"],
                     "displacement_error_pct": 100 * float(np.linalg.norm(estimated - true)) / length,
                     "length_error_pct": 100 * (float(np.linalg.norm(estimated)) - length) / length,
                     "spin_deg_s": truth["launch"].get("spin_deg_s")})
    return rows


# ------------------------------------------------------------------------------------ report
def summary(runs: list[dict]) -> str:
    """The tables of chains, singles and timing from the runs' records (measure_hopping.py's results.jsonl
    lines: chain() and singles() give them)."""
    lines = []
    chains = [r for r in runs if r["kind"] == "chain"]
    if chains:
        lines.append(f"chains: {len(chains)} scenes, {sum(len(r['hops']) for r in chains)} hops; {PAPER_TABLE_1}")
        lines.extend(f"  chain {r['seed']} stopped: {r['stopped']}" for r in chains if r.get("stopped"))
        table = [chain_errors(r) for r in chains]
        lines.append("  hop  distance  with ICP %  (per scene)                    without ICP %  (per scene)")
        for k in range(max(len(t) for t in table)):
            rows = [t[k] for t in table if len(t) > k]
            each = {key: " ".join(f"{r[key]:.1f}" for r in rows) for key in ("with_icp_pct", "without_icp_pct")}
            lines.append(f"  {k + 1:3d}  {np.mean([r['distance_m'] for r in rows]):6.2f} m  "
                         f"{np.mean([r['with_icp_pct'] for r in rows]):5.2f}  ({each['with_icp_pct']})  "
                         f"{np.mean([r['without_icp_pct'] for r in rows]):6.2f}  ({each['without_icp_pct']})")
        every = [r for t in table for r in t]
        lines.append(f"  all hops: with ICP mean {np.mean([r['with_icp_pct'] for r in every]):.2f} %, max "
                     f"{np.max([r['with_icp_pct'] for r in every]):.2f} %; without mean "
                     f"{np.mean([r['without_icp_pct'] for r in every]):.2f} %, max "
                     f"{np.max([r['without_icp_pct'] for r in every]):.2f} %; bounces "
                     f"{np.mean([r['bounce_m'] for r in every]):.2f} m mean")
        corrected = [r for r in every if "needed_m" in r and r["hop"] > 1]
        columns = {"none": "needed_m", "height match": "match_error_m", "ICP from it": "icp_error_m",
                   "applied": "applied_error_m"}
        columns = {name: [r[key] for r in corrected if key in r] for name, key in columns.items()}
        if corrected:
            lines.append(f"  launch after the correction, horizontal error (median, max cm, hops), used on "
                         f"{sum(bool(r['icp_used']) for r in corrected)}/{len(corrected)}: " + "; ".join(
                             f"{name} {100 * np.median(v):.1f}, {100 * np.max(v):.1f}, {len(v)}"
                             for name, v in columns.items() if v))
        targets = [r for r in every if "target_clear" in r]
        missed = [r["next_touchdown_from_target_m"] for r in every if "next_touchdown_from_target_m" in r]
        lines.append(f"  targets: {sum(r['target_clear'] for r in targets)}/{len(targets)} clear of every true "
                     f"obstacle (nearest {min(r['target_nearest_obstacle_m'] or 9e9 for r in targets):.2f} m); the "
                     f"next first touchdown from the target: median {np.median(missed):.3f} m, max "
                     f"{np.max(missed):.3f} m")
    single = [r for r in runs if r["kind"] == "singles"]
    if single:
        rows = [row for r in single for row in single_errors(r)]
        good = [r for r in rows if "error" not in r]
        errors = np.array([r["displacement_error_pct"] for r in good])
        lines.append(f"singles: {len(rows)} hops of {min(r['commanded_m'] for r in rows):.1f}-"
                     f"{max(r['commanded_m'] for r in rows):.1f} m commanded, {len(good)} reconstructed "
                     f"(frames {min(r['frames'] for r in good)}-{max(r['frames'] for r in good)})")
        lines.append(f"  hop displacement error: mean {errors.mean():.2f} %, median {np.median(errors):.2f} %, "
                     f"max {errors.max():.2f} %; over 4 %: {(errors > 4).sum()}, over 10 %: {(errors > 10).sum()} "
                     f"(paper: under 4 % on average, never over 10 %)")
        lines.append(f"  length error: mean {np.mean([r['length_error_pct'] for r in good]):+.2f} %, mean |.| "
                     f"{np.mean([abs(r['length_error_pct']) for r in good]):.2f} %")
        for r in rows:
            if "error" in r:
                lines.append(f"  failed: {r['commanded_m']:.1f} m: {r['error']}")
    records = [h for r in runs for h in r["hops"] if "timings_s" in h]
    if records:
        steps = sorted({s for h in records for s in h["timings_s"]}, key=list(records[0]["timings_s"]).index)
        fifty = [h for h in records if 40 <= h["frames"] <= 60] or records
        lines.append(f"timing of hop-plan over {len(fifty)} hops of 40-60 frames (median s): " + ", ".join(
            f"{s} {np.median([h['timings_s'].get(s, 0) for h in fifty]):.1f}" for s in steps)
            + f"; whole command {np.median([h['seconds'] for h in fifty]):.1f}")
        lines.append(f"peak resident memory of the server: max {max(r['peak_memory_mib'] for r in runs):.0f} MiB")
    return "\n".join(lines)


def _conftest():
    """tests/conftest.py (ServerProcess, pairs, SIM_SPEED), also in a Dask worker that loaded this file
    by its path, whose sys.path has no tests/."""
    tests = str(REPO / "tests")
    if tests not in sys.path:
        sys.path.insert(0, tests)
    import conftest
    return conftest


# ------------------------------------------------------------------------------------ servers

WORLD = """seed = {seed}
size_m = [{size}, {size}]
[rocks]
cover = {cover}
"""


def start_server(root: Path, seed: int, size: float, cover: float, settings: str = "",
                 launch_errors: str = "") -> Any:
    """A server on a fresh data directory with the repository's configs, the scene's world, the hopper
    seeded by the scene, and hopping.toml settings (top level) and launch errors added."""
    shutil.rmtree(root, ignore_errors=True)
    configs = root / "configs"
    shutil.copytree(REPO / "configs", configs)
    shutil.copytree(REPO / "workflows", root / "workflows")   # hop-plan's workflow, beside the configs
    (configs / "world.toml").write_text(WORLD.format(seed=seed, size=size, cover=cover))
    text = (configs / "hopping.toml").read_text()
    for old, new in (("[hopper]\nseed = 5", f"[hopper]\nseed = {seed}"),
                     ("[hopper.launch_errors]", f"[hopper.launch_errors]\n{launch_errors}")):
        if old not in text:
            raise RuntimeError(f"configs/hopping.toml has no {old!r} to change")
        text = text.replace(old, new)
    for line in settings.splitlines():      # top-level keys: replace the file's own line
        key = line.split("=")[0].strip()
        text, found = re.subn(rf"^{re.escape(key)}\s*=.*$", line, text, count=1, flags=re.MULTILINE)
        if not found:
            text = line + "\n" + text
    (configs / "hopping.toml").write_text(text)
    return _conftest().ServerProcess(data_dir=root / "data", config_dir=configs).start(timeout=300)


def peak_memory_mib(server) -> float:
    for line in Path(f"/proc/{server.proc.pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def hop_and_plan(client, products: Path, hop: str, plan: str) -> dict:
    """One `hop` then `hop-plan`; what the products say of both (the plan's estimate, truth, timings)."""
    reply = client.command(hop, timeout=600)
    if " OK " not in f" {reply} ":
        raise RuntimeError(f"{hop}: {reply}")
    pairs = _conftest().pairs
    hop_name = pairs(reply)["product"]
    truth = json.loads((products / hop_name / "truth" / "hop.json").read_text())["truth"]
    started = time.perf_counter()
    reply = client.command(plan, timeout=1800)
    seconds = time.perf_counter() - started
    fields = pairs(reply)
    name = fields.get("product") or reply.split("product=")[-1].split()[0].rstrip(";")
    folder = products / name
    if not (folder / "estimate.json").exists():   # not reconstructed: the hop's truth is still known
        return {"hop": hop_name, "plan": name, "reply": reply[:300], "truth": truth, "plan_error": reply[:300],
                "seconds": seconds, "frames": truth["flight"]["frames"]}
    estimate = json.loads((folder / "estimate.json").read_text())
    comparison = json.loads((folder / "truth" / "comparison.json").read_text())
    frames = json.loads((products / hop_name / "hop.json").read_text())
    return {"hop": hop_name, "plan": name, "reply": reply[:300], "ok": " OK " in f" {reply} ", "seconds": seconds,
            "frames": estimate["frames"], "registered": estimate["registered"], "timings_s": estimate["timings_s"],
            "touchdown_m": estimate["touchdown_m"], "launch_corrected_m": estimate["launch"]["corrected_m"],
            "icp": estimate["icp"], "target_m": estimate["plan"]["target_m"] if estimate["plan"]["found"] else None,
            "launch": estimate["plan"]["launch"], "truth": truth, "comparison": comparison,
            "hop_frames_note": {k: frames[k] for k in ("frame_rate_hz",) if k in frames}}


# ------------------------------------------------------------------------------------ chains
def chain(seed: int, out: Path, hops: int, size: float, cover: float, sim_speed: float, octave: int | None) -> dict:
    conftest = _conftest()
    conftest.SIM_SPEED = sim_speed
    root = out / f"chain{seed}"
    server = start_server(root, seed, size, cover, f"sfm_first_octave = {octave}\n" if octave is not None else "")
    products = root / "data" / "products"
    heading = float(np.random.default_rng([seed, 1]).uniform(-180, 180))
    records, stopped = [], None
    try:
        with server.connect(timeout=1800) as client:
            hop = f"hop --speed {speed_for(1.0, 60):.4f} --elevation 60 --heading {heading:.2f}"
            for number in range(1, hops + 1):
                record = hop_and_plan(client, products, hop, f"hop-plan --goal-heading {heading:.2f}")
                if "plan_error" in record:     # the hops so far still count; the chain cannot go on
                    stopped = f"hop {number}: {record['plan_error']}"
                    break
                records.append(record)
                print(f"chain {seed} hop {number}: {record['plan']} {record['seconds']:.0f} s", flush=True)
                if number == hops:              # the last plan's target is for a hop not taken
                    break
                if record["launch"] is None:
                    stopped = f"no target after hop {number}: {record['reply']}"
                    break
                launch = record["launch"]
                hop = (f"hop --speed {launch['speed_mps']:.4f} --elevation {launch['elevation_deg']:.3f} "
                       f"--heading {launch['heading_deg']:.3f}")
            hop_map = conftest.pairs(client.command("hop-map", timeout=600)).get("product")
            memory = peak_memory_mib(server)
    finally:
        server.stop()
    if stopped:
        print(f"chain {seed} stopped: {stopped}", flush=True)
    return {"kind": "chain", "seed": seed, "heading_deg": heading, "hops": records, "peak_memory_mib": memory,
            "hop_map": str(products / hop_map) if hop_map else None, "stopped": stopped}


# ------------------------------------------------------------------------------------ singles
def singles(seed: int, out: Path, count: int, size: float, cover: float, sim_speed: float, spin: float,
            octave: int | None) -> dict:
    conftest = _conftest()
    conftest.SIM_SPEED = sim_speed
    root = out / f"singles{seed}"
    settings = "max_speed_mps = 6.0\n" + (f"sfm_first_octave = {octave}\n" if octave is not None else "")
    server = start_server(root, seed, size, cover, settings, f"spin_deg_s = {spin}")
    products = root / "data" / "products"
    rng = np.random.default_rng([seed, 2])
    records = []
    try:
        with server.connect(timeout=1800) as client:
            for number in range(count):
                distance, elevation = rng.uniform(1.0, 10.0), rng.uniform(45.0, 70.0)
                # Toward the world's centre, so long hops stay on it.
                hopper = records[-1]["truth"]["settled"]["centre_m"][:2] if records else [0.0, 0.0]
                toward = math.degrees(math.atan2(-hopper[1], -hopper[0])) if math.hypot(*hopper) > 2 else None
                heading = toward + rng.uniform(-60, 60) if toward is not None else rng.uniform(-180, 180)
                heading = (heading + 180) % 360 - 180
                hop = (f"hop --speed {speed_for(distance, elevation):.4f} --elevation {elevation:.2f} "
                       f"--heading {heading:.2f}")
                record = hop_and_plan(client, products, hop, "hop-plan")
                record["commanded_m"] = distance
                if "plan_error" in record:
                    print(f"singles {seed} hop {number + 1}: {record['plan_error']}", flush=True)
                    records.append(record)
                    continue
                records.append(record)
                print(f"singles {seed} hop {number + 1}: {distance:.1f} m, {record['frames']} frames, "
                      f"{record['seconds']:.0f} s", flush=True)
            memory = peak_memory_mib(server)
    finally:
        server.stop()
    return {"kind": "singles", "seed": seed, "hops": records, "peak_memory_mib": memory}


# -- campaign hooks ----------------------------------------------------------------------------------------


def runs(scenes: int = 5, first_chain_seed: int = 301, chain_hops: int = 5, hops: int = 30, jobs: int = 2,
         first_singles_seed: int = 401, size: float = 30.0, cover: float = 0.07, spin: float = 20.0,
         octave: int | None = None, kinds: list[str] | None = None) -> list[dict[str, Any]]:
    """measure_hopping.py's runs, as its command lines make them: `chains` one per scene from seed 301,
    five hops each; `singles` the 30 hops split over `jobs` servers from seed 401 (15 and 15). Each run
    holds chain()'s or singles()'s arguments (the hopper is seeded by the scene)."""
    scene: dict[str, Any] = {"size": size, "cover": cover} | ({"octave": octave} if octave is not None else {})
    made: list[dict[str, Any]] = []
    if "chains" in (kinds or ["chains", "singles"]):
        made += [{"seed": seed, "kind": "chain", "hops": chain_hops, **scene}
                 for seed in range(first_chain_seed, first_chain_seed + scenes)]
    if "singles" in (kinds or ["chains", "singles"]):
        share = [hops // jobs + (i < hops % jobs) for i in range(jobs)]
        made += [{"seed": first_singles_seed + i, "kind": "singles", "hops": n, **scene, "spin": spin}
                 for i, n in enumerate(share)]
    return made


def execute(run: dict[str, Any], run_dir: Path, sim_speed: float) -> dict[str, Any]:
    """One run of the campaign, as measure_hopping.py plays it: chain() or singles() with the run's
    arguments, its server under run_dir; the values are the script's record of the run."""
    if run["kind"] == "chain":
        return chain(run["seed"], Path(run_dir), run["hops"], run["size"], run["cover"], sim_speed, run.get("octave"))
    if run["kind"] == "singles":
        return singles(run["seed"], Path(run_dir), run["hops"], run["size"], run["cover"], sim_speed, run["spin"],
                       run.get("octave"))
    raise ValueError(f"kind {run['kind']!r}: expected chain or singles")


def report(records: list[dict[str, Any]]) -> str:
    """The summary of a campaign's runs whose values are measure_hopping.py's records of a run."""
    return summary([record["values"] for record in records if "kind" in record.get("values", {})])
