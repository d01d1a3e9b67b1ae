"""The hopping paper's simulated experiments, through a real server on seeded worlds, scored against
the simulator's truth.

chains   (paper Table 1) per scene: a first hop of about 1 m in a random direction, then five times
         hop-plan and a hop to the target it chose (about 1 m, 60 degrees, Moon gravity; the
         paper's 640x480 wide-angle camera at 34 Hz, about 50 frames a hop, motion blur; two
         bounces after each touchdown that the rover cannot see). Per hop, the error of the
         estimated touchdown as a percentage of the true touchdown's distance from the start:
           with ICP     hop-plan's estimate (each launch corrected against the previous hop's cloud)
           without ICP the same hops' reconstructed displacements chained from the start, each hop
                       launched where the last one was believed to touch down (bounces unseen)
         and each chosen target against the true obstacles, and how far the next hop truly
         touched down from it.
singles  hops of 1-10 m at random elevations 45-70 degrees with launch errors and spin, each from
         where the last one came to rest: the hop's reconstructed displacement (touchdown less
         corrected launch) against the true one, as a percentage of the true hop length (the paper:
         under 4 % on average, never over 10 %).
timing   hop-plan's steps (sfm, dense, estimate, plan, write) for every hop, and the server's peak
         resident memory (VmHWM) over the whole run.

    .venv/bin/python tests/bench/measure_hopping.py chains [--scenes 5] [--first-seed 301] [--jobs 2]
    .venv/bin/python tests/bench/measure_hopping.py singles [--hops 30] [--first-seed 401] [--jobs 2]
    .venv/bin/python tests/bench/measure_hopping.py report [--out /tmp/rvs-hopping]
"""
from __future__ import annotations

import argparse
import json
import math
import re
import shutil
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "tests"))
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "tests" / "bench"))
from hopping_scoring import speed_for, summary  # noqa: E402

from conftest import ServerProcess, pairs  # noqa: E402

WORLD = """seed = {seed}
size_m = [{size}, {size}]
[rocks]
cover = {cover}
"""


def start_server(root: Path, seed: int, size: float, cover: float, settings: str = "",
                 launch_errors: str = "") -> ServerProcess:
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
    return ServerProcess(data_dir=root / "data", config_dir=configs).start(timeout=300)


def peak_memory_mib(server: ServerProcess) -> float:
    for line in Path(f"/proc/{server.proc.pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def hop_and_plan(client, products: Path, hop: str, plan: str) -> dict:
    """One `hop` then `hop-plan`; what the products say of both (the plan's estimate, truth, timings)."""
    reply = client.command(hop, timeout=600)
    if " OK " not in f" {reply} ":
        raise RuntimeError(f"{hop}: {reply}")
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
    import conftest
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
            hop_map = pairs(client.command("hop-map", timeout=600)).get("product")
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
    import conftest
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


def report(out: Path) -> str:
    return summary([json.loads(line) for line in (out / "results.jsonl").read_text().splitlines()])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("what", choices=["chains", "singles", "report"])
    parser.add_argument("--scenes", type=int, default=5)
    parser.add_argument("--hops", type=int, default=30, help="singles: hops in all (split over --jobs servers)")
    parser.add_argument("--chain-hops", type=int, default=5)
    parser.add_argument("--first-seed", type=int, default=None)
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--size", type=float, default=30.0)
    parser.add_argument("--cover", type=float, default=0.07)
    parser.add_argument("--spin", type=float, default=20.0, help="singles: spin, deg/s one sigma per axis")
    parser.add_argument("--octave", type=int, choices=[-1, 0], default=None,
                        help="hopping.toml sfm_first_octave for every server (0 is about 3x faster)")
    parser.add_argument("--sim-speed", type=float, default=100.0)
    parser.add_argument("--out", type=Path, default=Path("/tmp/rvs-hopping"))
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    if args.what == "report":
        print(report(args.out))
        return
    log = args.out / "results.jsonl"
    if args.what == "chains":
        first = args.first_seed or 301
        tasks = [(chain, (seed, args.out, args.chain_hops, args.size, args.cover, args.sim_speed, args.octave))
                 for seed in range(first, first + args.scenes)]
    else:
        first = args.first_seed or 401
        share = [args.hops // args.jobs + (i < args.hops % args.jobs) for i in range(args.jobs)]
        tasks = [(singles, (first + i, args.out, n, args.size, args.cover, args.sim_speed, args.spin, args.octave))
                 for i, n in enumerate(share)]
    with ProcessPoolExecutor(max_workers=args.jobs) as pool:
        futures = [pool.submit(fn, *fn_args) for fn, fn_args in tasks]
        for future in futures:
            try:
                result = future.result()
            except Exception as exc:  # a run that cannot finish is reported, not hidden
                print(f"ERROR {exc!r}"[:400], flush=True)
                continue
            with open(log, "a") as handle:
                handle.write(json.dumps(result) + "\n")
    print(report(args.out))


if __name__ == "__main__":
    main()
