"""The hopping campaign's scenes and scores: the hopping paper's chains (Table 1) and single hops, scored
against the simulator's truth from what hop and hop-plan wrote (measure_hopping.py's records of a run).

chains   per hop: the estimated touchdown's error with and without ICP as a percentage of the true
         touchdown's distance from the start, the launch corrections' errors, each chosen target
         against the true obstacles and how far the next hop truly touched down from it;
singles  the hop's reconstructed displacement against the true one, as a percentage of its length;
timing   hop-plan's steps for hops of 40-60 frames and the servers' peak memory.

Used by tests/bench/measure_hopping.py (its runs, then `summary`), and by a campaign file through the
hooks `runs` and `report` below. A hopping run is not a fixed mission: each chain hop is launched as
the previous hop-plan chose, and each single hop heads from where the last one came to rest, so the
campaign engine needs a hook that plays a run itself (see the issue 28 notes) before
tests/bench/campaigns/hopping.toml can exist.
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np

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




# -- campaign hooks ----------------------------------------------------------------------------------------


def runs(scenes: int = 5, first_chain_seed: int = 301, chain_hops: int = 5, hops: int = 30, jobs: int = 2,
         first_singles_seed: int = 401, size: float = 30.0, cover: float = 0.07, spin: float = 20.0,
         kinds: list[str] | None = None) -> list[dict[str, Any]]:
    """measure_hopping.py's runs: `chains` one per scene from seed 301, five hops each; `singles` the 30
    hops split over `jobs` servers from seed 401 (15 and 15). The hopper is seeded by the scene."""
    world = {"size_m": [size, size], "rocks": {"cover": cover}}
    made: list[dict[str, Any]] = []
    if "chains" in (kinds or ["chains", "singles"]):
        made += [{"seed": seed, "KIND": "chain", "HOPS": chain_hops, "world": world,
                  "configs": {"hopping.toml": {"hopper": {"seed": seed}}},
                  "HEADING": f"{float(np.random.default_rng([seed, 1]).uniform(-180, 180)):.2f}",
                  "SPEED": f"{speed_for(1.0, 60):.4f}"}
                 for seed in range(first_chain_seed, first_chain_seed + scenes)]
    if "singles" in (kinds or ["chains", "singles"]):
        share = [hops // jobs + (i < hops % jobs) for i in range(jobs)]
        made += [{"seed": first_singles_seed + i, "KIND": "singles", "HOPS": n, "world": world,
                  "configs": {"hopping.toml": {"max_speed_mps": 6.0,
                                               "hopper": {"seed": first_singles_seed + i,
                                                          "launch_errors": {"spin_deg_s": spin}}}}}
                 for i, n in enumerate(share)]
    return made


def report(records: list[dict[str, Any]]) -> str:
    """The summary of a campaign's runs whose values are measure_hopping.py's records of a run."""
    return summary([record["values"] for record in records if "kind" in record.get("values", {})])
