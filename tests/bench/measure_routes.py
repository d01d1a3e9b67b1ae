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
import math
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
from routes_scoring import MOVED_SUN, ORIENTS, SIZE_M, START_OFFSET, SUN, lay_route, report, scene_routes, score_product  # noqa: E402

from conftest import ServerProcess, pairs  # noqa: E402

WORLD = """seed = {seed}
size_m = [{size}, {size}]
rover_start = [{x:.4f}, {y:.4f}, {heading:.3f}]
[sun]
azimuth_deg = {azimuth}
elevation_deg = {elevation}
"""
# The teacher steers (as a person at the controls would): the route taught is the route laid, clear
# of rocks. Repeats drive with the simulated rover's drive error.
TEACHER = """[drive_error]
turn_scale = 0.0
turn_noise_deg = 0.0
distance_scale = 0.0
heading_drift_deg_per_m = 0.0
lateral_slip_per_m = 0.0
"""


def configs_for(root: Path, seed: int, pose: tuple[float, float, float], sun: tuple[float, float],
                teacher: bool = False, orient: bool = False) -> Path:
    configs = root / "configs"
    shutil.rmtree(configs, ignore_errors=True)
    shutil.copytree(REPO / "configs", configs)
    routes = configs / "routes.toml"
    routes.write_text(routes.read_text().replace("orient = false", f"orient = {str(orient).lower()}"))
    (configs / "world.toml").write_text(WORLD.format(seed=seed, size=SIZE_M, x=pose[0], y=pose[1], heading=pose[2],
                                                     azimuth=sun[0], elevation=sun[1]) + (TEACHER if teacher else ""))
    return configs


def teach(seed: int, out: Path) -> dict:
    """Teach the main route r and, from its end, the branch b, in one session of one server."""
    root = out / f"scene{seed}"
    shutil.rmtree(root, ignore_errors=True)
    laid = scene_routes(seed)
    start = (*laid["start"], laid["heading"])
    server = ServerProcess(data_dir=root / "data", config_dir=configs_for(root, seed, start, SUN, teacher=True))
    server.start(timeout=300)
    taught = {}
    products = root / "data" / "products"
    try:
        with server.connect(timeout=600) as client:
            taught["r"] = record(client, seed, "r", laid["actions"], products)
            end = taught["r"]["taught"][-1]
            try:
                branch, _, _ = lay_route(laid["world"], laid["rng"], (end[0], end[1]), (8.0, 15.0),
                                         heading=math.degrees(end[2]))
                taught["b"] = record(client, seed, "b", branch, products)
            except RuntimeError as exc:   # the main route is still scored
                print(f"scene {seed}: no branch: {exc}", flush=True)
    finally:
        server.stop()
    return {"seed": seed, **taught["r"], "branch": taught.get("b")}


def record(client, seed: int, name: str, actions: list[tuple[str, float]], products: Path) -> dict:
    assert " OK " in f" {client.command(f'route-record start --name {name}', timeout=300)} "
    for kind, value in actions:
        reply = client.command(f"drive --{kind} {value}", timeout=300)
        if " OK " not in f" {reply} ":
            raise RuntimeError(f"scene {seed}: drive --{kind} {value}: {reply}")
    stop = pairs(client.command("route-record stop", timeout=300))
    taught = json.loads((products / stop["product"] / "truth" / "path.json").read_text())["path"]
    return {"actions": actions, "legs": int(stop["triplets"]), "length_m": float(stop["length"]),
            "bytes": int(stop["bytes"]), "bytes_per_m": float(stop["bytes_per_m"]), "taught": taught}


def repeat(seed: int, out: Path, route: dict, matcher: str, sun_moved: bool, reverse: bool,
           orient: bool = False) -> dict:
    taught = np.array(route["taught"])
    place = taught[-1] if reverse else taught[0]
    goal = taught[0] if reverse else taught[-1]
    rng = np.random.default_rng([seed, int(reverse), int(sun_moved), len(matcher)])
    name = (f"{matcher}-{'moved' if sun_moved else 'same'}-{'reverse' if reverse else 'forward'}"
            f"{'-orient' if orient else ''}")
    command = f"route-follow --name r {'--reverse ' if reverse else ''}--matcher {matcher} --output {name}"
    result = run_from(seed, out, name, near(place, rng), MOVED_SUN if sun_moved else SUN, [], command, goal, taught,
                      orient)
    return {"seed": seed, "matcher": matcher, "sun": "moved" if sun_moved else "same",
            "direction": "reverse" if reverse else "forward", "orient": orient, **result,
            "length_m": route["length_m"], "legs": route["legs"]}


def network(seed: int, out: Path, route: dict) -> dict:
    """route-connect, then route-go from near the main route's start to the branch's end."""
    branch = route["branch"]
    taught = np.vstack([route["taught"], branch["taught"]])
    rng = np.random.default_rng([seed, 7])
    command = f"route-go --to b:{branch['legs']} --output network"
    result = run_from(seed, out, "network", near(route["taught"][0], rng), SUN, ["route-connect"], command,
                      np.array(branch["taught"][-1]), taught)
    return {"seed": seed, "matcher": "features", "sun": "same", "direction": "network", "orient": False, **result,
            "length_m": route["length_m"] + branch["length_m"], "legs": route["legs"] + branch["legs"]}


def near(place, rng: np.random.Generator) -> tuple[float, float, float]:
    """A start START_OFFSET off a place: metres in a random direction, degrees either way."""
    angle = rng.uniform(-math.pi, math.pi)
    return (place[0] + START_OFFSET[0] * math.cos(angle), place[1] + START_OFFSET[0] * math.sin(angle),
            math.degrees(place[2]) + rng.choice([-1, 1]) * START_OFFSET[1])


def run_from(seed: int, out: Path, name: str, pose, sun, before: list[str], command: str, goal: np.ndarray,
             taught: np.ndarray, orient: bool = False) -> dict:
    """A fresh server on the scene's data directory with the rover at pose: the commands `before`,
    then `command`, scored against the goal and the taught path."""
    root = out / f"scene{seed}"
    run = root / name
    shutil.rmtree(run, ignore_errors=True)
    server = ServerProcess(data_dir=root / "data", config_dir=configs_for(run, seed, pose, sun, orient=orient))
    started = time.perf_counter()
    server.start(timeout=300)
    try:
        with server.connect(timeout=1800) as client:
            for line in before:
                reply = client.command(line, timeout=1800)
                if " OK " not in f" {reply} ":
                    raise RuntimeError(f"scene {seed}: {line}: {reply}")
            reply = client.command(command, timeout=1800)
    finally:
        server.stop()
    seconds = time.perf_counter() - started
    return {**score_product(root / "data" / "products" / name, goal, taught, " OK " in f" {reply} "),
            "seconds": round(seconds, 1), "reply": reply[:200]}


def scene(seed: int, out: Path, matchers: tuple[str, ...] = ("features", "contour"),
          suns: tuple[str, ...] = ("same", "moved"), orients: tuple[bool, ...] = (False,),
          with_network: bool = True) -> list[dict]:
    route = teach(seed, out)
    (out / f"scene{seed}" / "route.json").write_text(json.dumps(route))
    print(f"scene {seed}: taught {route['length_m']:.1f} m in {route['legs']} legs, "
          f"{route['bytes_per_m']:.0f} bytes/m", flush=True)
    results = []
    runs = [(repeat, (seed, out, route, matcher, sun == "moved", reverse, orient))
            for matcher in matchers for sun in suns for reverse in (False, True) for orient in orients]
    if route["branch"] and with_network:
        runs.append((network, (seed, out, route)))
    for function, arguments in runs:
        result = function(*arguments)
        results.append({**result, "bytes_per_m": route["bytes_per_m"]})
        print(f"scene {seed} {result['matcher']} sun {result['sun']} {result['direction']}"
              f"{' orient' if result.get('orient') else ''}: "
              f"{'success' if result['success'] else 'FAILED'}, final {result['final_m']:.2f} m, "
              f"deviation {result['max_deviation_m']:.2f} m, {result['seconds']:.0f} s", flush=True)
    return results


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
