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
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "tests"))
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "tests" / "bench"))
from hopping_scoring import chain, singles, summary  # noqa: E402


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
