"""Image-based routes on seeded scenes, taught once and repeated forwards and backwards, with the sun
unchanged and moved, with both matchers, through real servers; scored against the simulator's truth.

Per scene (50 m worlds, 7 % rock cover, three craters): a route of 20-50 m is laid on the true map
(rocks over 0.10 m grown by 0.5 m avoided) from a start within 8 m of the centre toward a random
goal, cut into straight legs of at most 2.5 m that keep 0.45 m from every rock, with a turn wherever
it bends, and taught once (route-record, drive ..., route-record stop) by a teacher who steers: the
drive error is off while teaching (world.toml drive_error), as a person at the controls keeps the
rover where they mean it to go. A branch of 8-15 m is taught the same way from the route's end.
The route database then serves every repeat: each repeat is a fresh server on the same data
directory (the routes survive the restart) whose rover, with its drive error, starts near the
route's start (forward) or end (reverse), 0.2 m and 5 degrees off, under the teaching sun or under
one moved 40 degrees in azimuth and 20 degrees up, and runs `route-follow --name r [--reverse]
--matcher M`. Last, the network: route-connect, then route-go from near the route's start to the
branch's end. Scored per run:

- success: the reply is OK and the rover truly stands within 0.5 m of the goal place;
- final distance: from the goal place's true position;
- deviation: the largest distance of the run's true path from the taught true path;
- images grabbed (each approach step and heading check is one) and, with routes.toml orient, the
  orient looks and how many were refused.

`--orient both` repeats each route with routes.toml orient off and on (drive legs in parts with a TOF
orient look after each, aimed back at the leg's line), on the same taught routes and start poses.

    .venv/bin/python tests/bench/measure_routes.py [--scenes 10] [--first-seed 501] [--jobs 2]
        [--matchers features contour] [--suns same moved] [--orient off|on|both]
    .venv/bin/python tests/bench/measure_routes.py --report [--out /tmp/rvs-routes]
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
from routes_scoring import ORIENTS, report, scene  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scenes", type=int, default=10)
    parser.add_argument("--first-seed", type=int, default=501)
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--matchers", nargs="+", default=["features", "contour"], choices=["features", "contour"])
    parser.add_argument("--suns", nargs="+", default=["same", "moved"], choices=["same", "moved"])
    parser.add_argument("--orient", choices=["off", "on", "both"], default="off",
                        help="routes.toml orient for the repeats (both: each repeat with and without)")
    parser.add_argument("--no-network", action="store_true", help="skip route-connect and route-go")
    parser.add_argument("--report", action="store_true", help="only summarise --out's results")
    parser.add_argument("--out", type=Path, default=Path("/tmp/rvs-routes"))
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    log = args.out / "results.jsonl"
    results = [json.loads(line) for line in log.read_text().splitlines()] if log.exists() else []
    if not args.report:
        done = {r["seed"] for r in results}
        seeds = [s for s in range(args.first_seed, args.first_seed + args.scenes) if s not in done]
        with ProcessPoolExecutor(max_workers=args.jobs) as pool:
            for seed, future in [(s, pool.submit(scene, s, args.out, tuple(args.matchers), tuple(args.suns),
                                                           ORIENTS[args.orient], not args.no_network)) for s in seeds]:
                try:
                    rows = future.result()
                except Exception as exc:  # a scene that cannot run is reported, not hidden
                    print(f"scene {seed}: ERROR {exc!r}"[:400], flush=True)
                    continue
                results.extend(rows)
                with open(log, "a") as handle:
                    handle.writelines(json.dumps(r) + "\n" for r in rows)
    print(report(results))


if __name__ == "__main__":
    main()
