"""Campaign: the hazard guard against obstacles no map knew, on seeded scenes, scored on the truth.

    python tests/bench/hazard_campaign.py [--sensor tof|stereo] [--cover 0.07] [--seeds 21 22 23 24 25]
        [--encounters 8] [--routes 2] [--results tests/bench/results/hazard.jsonl]
    python tests/bench/hazard_campaign.py --report tests/bench/results/hazard.jsonl

Each finished scene is appended to --results at once (clients/run_log.py: seed, sensor, settings,
every encounter and score, seconds); a rerun with the same settings skips the scenes already there,
so a campaign the clock stops is continued by running it again. --report prints the summary per
settings and sensor from the file alone.

Per scene (a 20 m seeded world with --cover rock cover, one real rvs-server at sim-speed 50,
`hazard-start --sensor SENSOR` running all along, the rover at its routes.toml speed, 0.3 m/s):
- clean runs: the rover turns onto a lane that the truth says is clear (no rock over 8 cm within
  0.5 m of its centre line, i.e. the swept footprint and 0.15 m more each side) and drives it;
  any stop there is a false stop;
- blind-drive encounters: on such a lane, after it turned, a rock of 12-30 cm (or, one time in
  five, a standing person) is dropped 1.6-3.8 m ahead of the rover's centre, up to 0.2 m off the
  line, and the rover is told to drive 5 m: it must stop before contact;
- taught-route encounters: a route of two 2 m legs is taught on a clear lane, repeated backward to
  its start, a rock is dropped on it, and the route is repeated forward: it must stop.
The rover's true pose comes from a grab-tof product's truth/state.json; the stops' true clearance
(free way from the true footprint to the nearest true obstacle over 10 cm) and contact counts from
hazard-stop's stops.csv and the products' truth. Prints one line per encounter and the summary.
"""
from __future__ import annotations

import argparse
import contextlib
import csv
import json
import math
import sys
import tempfile
import time
import tomllib
from collections.abc import Callable, Collection
from pathlib import Path

import numpy as np
from scipy import ndimage

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "tests"))
sys.path.insert(0, str(REPO))

from clients.run_log import RunLog, add_results_options, report, reported  # noqa: E402
from drivers.sim.config import WorldConfig  # noqa: E402
from drivers.sim.world import World  # noqa: E402
from toolbox.planning.costs import inflate_hazards  # noqa: E402
from toolbox.planning.paths import simplify_path  # noqa: E402
from toolbox.planning.search import astar  # noqa: E402

from conftest import ServerProcess, pairs, write_configs  # noqa: E402

LANE_HALF_WIDTH = 0.50      # 0.25 half body + 0.10 guard margin + 0.15 for drive error
PASS_HALF_WIDTH = 0.35      # driving to a lane: half the body and 0.1 m
CLEAR_BELOW = 0.08          # a lane is clean when no rock on it is taller than this
CLEAN_RUN_M = 4.0           # each clean run
STEEP_RAD = math.radians(15.0)   # nor on ground this steep (World.slope_at answers radians)
RESULTS = REPO / "tests" / "bench" / "results" / "hazard.jsonl"


def world_toml(seed: int, cover: float) -> str:
    return f"seed = {seed}\nsize_m = [20.0, 20.0]\n[rocks]\ncover = {cover:g}\n[craters]\ncount = 1\n"


def ground_slope(world: World, x: np.ndarray, y: np.ndarray, baseline: float = 0.25) -> np.ndarray:
    """The rock-free ground's slope (radians) over a patch `baseline` wide: rocks are CLEAR_BELOW's."""
    half = baseline / 2
    dz_dx = (world.ground_height_at(x + half, y) - world.ground_height_at(x - half, y)) / baseline
    dz_dy = (world.ground_height_at(x, y + half) - world.ground_height_at(x, y - half)) / baseline
    return np.arctan(np.hypot(dz_dx, dz_dy))


class Lanes:
    """Where the truth has clear lanes: a lane's centre line must keep LANE_HALF_WIDTH from every rock
    over CLEAR_BELOW and from ground steeper than 15 degrees, so the blocked cells are dilated by that
    half width once and a lane is then a line of look-ups (at 15-20 % cover a clear 5 m lane is seldom
    a turn away; this finds the nearest one a straight, clear drive away)."""

    def __init__(self, world: World, cell: float = 0.04):
        x0, x1, y0, y1 = world.bounds
        self.cell, self.x0, self.y0 = cell, x0 + 1.0, y0 + 1.0     # a lane keeps 1 m off the world's edge
        xs = np.arange(self.x0, x1 - 1.0, cell)
        ys = np.arange(self.y0, y1 - 1.0, cell)
        gx, gy = np.meshgrid(xs, ys)
        blocked = world.protrusion_at(gx, gy) >= CLEAR_BELOW
        coarse = ground_slope(world, gx[::3, ::3], gy[::3, ::3]) >= STEEP_RAD
        blocked |= np.repeat(np.repeat(coarse, 3, axis=0), 3, axis=1)[:len(ys), :len(xs)]
        grown = inflate_hazards(blocked, cell, LANE_HALF_WIDTH)
        self.forbidden = grown.mask
        # Where the rover's centre may pass on its way to a lane (half its width and 0.1 m clear of any
        # rock over CLEAR_BELOW); the world's edge is no way either.
        self.passable = grown.distance_m > PASS_HALF_WIDTH + 1e-9

    def clear(self, x: float, y: float, heading: float, length: float, behind: float = 0.4) -> bool:
        """Whether the centre line from `behind` back to `length` + 0.3 ahead keeps clear (as lane_clear)."""
        along = np.arange(-behind, length + 0.3, self.cell / 2)
        col = np.floor((x + along * math.cos(heading) - self.x0) / self.cell).astype(int)
        row = np.floor((y + along * math.sin(heading) - self.y0) / self.cell).astype(int)
        rows, cols = self.forbidden.shape
        if (col < 0).any() or (row < 0).any() or (col >= cols).any() or (row >= rows).any():
            return False
        return not bool(self.forbidden[row, col].any())

    def cell_of(self, x: float, y: float) -> tuple[int, int]:
        return int((y - self.y0) // self.cell), int((x - self.x0) // self.cell)

    def route(self, x: float, y: float, length: float, reach: float = 12.0,
              clear: Callable[[float, float, float, float], bool] = lambda *lane: True,
              avoid: Collection[tuple[int, int]] = ()) -> list[tuple[float, float]] | None:
        """Waypoints (world x, y) from the rover at (x, y) to the start of the nearest clear lane of
        `length` (at any heading; a lane this grid's `clear` and `clear(x, y, heading, length)` both
        pass) that it can reach by passable ground, the start last; None when no lane lies within
        `reach` along the way. Starts whose cells are in `avoid` (tried before) are not taken."""
        rows, cols = self.passable.shape
        here = self.cell_of(x, y)
        if not (0 <= here[0] < rows and 0 <= here[1] < cols):
            return None
        passable = self.passable.copy()
        # The rover may stand where its centre should not pass (it backed off a rock): its own spot
        # and a step round it count as passable, or it could never leave.
        r0, c0 = here
        passable[max(0, r0 - 3):r0 + 4, max(0, c0 - 3):c0 + 4] = True
        labels, _ = ndimage.label(passable)
        mine = labels[here] if labels[here] else None
        if mine is None:
            return None
        step = int(round(0.25 / self.cell))
        rr, cc = np.mgrid[0:rows:step, 0:cols:step]
        starts = (labels[rr, cc] == mine)
        sx, sy = self.x0 + (cc + 0.5) * self.cell, self.y0 + (rr + 0.5) * self.cell
        distance = np.hypot(sx - x, sy - y)
        starts &= distance <= reach
        headings = np.radians(np.arange(0, 360, 10))
        for index in np.argsort(np.where(starts, distance, np.inf), axis=None):
            if not starts.flat[index]:
                break
            lx, ly = float(sx.flat[index]), float(sy.flat[index])
            if self.cell_of(lx, ly) in avoid:
                continue
            # The grid's own look first (cheap), then the caller's.
            if not any(self.clear(lx, ly, float(h), length) and clear(lx, ly, float(h), length) for h in headings):
                continue
            path = astar(np.where(passable, 1.0, np.inf), here, self.cell_of(lx, ly), 1.0, self.cell)
            if not path.found:
                continue
            cells = path.cells
            keep = simplify_path(cells, ~passable, 3.0)
            points = [(self.x0 + (c + 0.5) * self.cell, self.y0 + (r + 0.5) * self.cell) for r, c in cells[keep]]
            route: list[tuple[float, float]] = []
            for index, point in enumerate(points[1:], 1):   # legs under 0.15 m are a turn's worth: merged
                if index == len(points) - 1 or math.dist(point, route[-1] if route else points[0]) >= 0.15:
                    route.append((float(point[0]), float(point[1])))
            return route
        return None


class SceneWorld:
    """A scene's seeded world and its clear lanes, without a server (tests/bench/measure_corridor.py)."""

    def __init__(self, seed: int, cover: float):
        self.seed = seed
        self.world_text = world_toml(seed, cover)
        self.world = World.build(WorldConfig(**tomllib.loads(self.world_text)))
        self.lanes = Lanes(self.world)
        self.rng = np.random.default_rng(seed)

    def lane_clear(self, x: float, y: float, heading: float, length: float) -> bool:
        along = np.arange(-0.4, length + 0.3, 0.02)
        across = np.arange(-LANE_HALF_WIDTH, LANE_HALF_WIDTH + 1e-9, 0.02)
        a, b = np.meshgrid(along, across)
        c, s = math.cos(heading), math.sin(heading)
        xs, ys = x + a * c - b * s, y + a * s + b * c
        g = self.world.grid
        if not ((xs > g.x_min + 1.0) & (xs < g.x_max - 1.0) & (ys > g.y_min + 1.0) & (ys < g.y_max - 1.0)).all():
            return False
        if np.nanmax(self.world.protrusion_at(xs, ys)) >= CLEAR_BELOW:
            return False
        return bool(np.nanmax(ground_slope(self.world, xs[::5, ::5], ys[::5, ::5])) < STEEP_RAD)


class Scene(SceneWorld):
    def __init__(self, seed: int, workdir: Path, cover: float):
        super().__init__(seed, cover)
        self.relocation_contacts = 0  # contacts while driving unguarded to a lane (not the guard's)
        self.tried_starts: set[tuple[int, int]] = set()   # lane starts relocation drove to
        config = write_configs(workdir / "configs", {"world.toml": self.world_text})
        self.server = ServerProcess(workdir / "data", config).start(timeout=180)
        self.client = self.server.connect(timeout=900)

    def command(self, line: str, timeout: float = 900) -> str:
        return self.client.command(line, timeout=timeout)

    def truth(self) -> dict:
        """The simulator's truth of this instant, from a grab-tof product."""
        reply = self.command("grab-tof --output truth")
        if " OK " not in reply:
            raise RuntimeError(f"grab-tof: {reply}")
        return json.loads((Path(pairs(reply)["path"]) / "truth" / "state.json").read_text())["rover"]

    def true_pose(self) -> tuple[float, float, float]:
        rover = self.truth()
        return rover["x"], rover["y"], rover["heading_rad"]

    def contacts(self) -> int:
        return int(self.truth()["contacts"])

    def onto_lane(self, length: float) -> tuple[float, float, float] | None:
        """Turn onto a clear lane of `length`; the true pose on it, or None when none is found."""
        for _ in range(4):
            x, y, h = self.true_pose()
            if self.lane_clear(x, y, h, length):
                return x, y, h
            towards_centre = math.atan2(-y, -x)
            options = sorted(np.radians(np.arange(0, 360, 10)), key=lambda a: abs(_wrap(a - towards_centre)))
            target = next((a for a in options if self.lane_clear(x, y, a, length)), None)
            if target is None:
                if not self.relocate(length):
                    return None
                continue
            turn = math.degrees(_wrap(target - h))
            if abs(turn) >= 1.0:
                self.command(f"drive --turn {turn:.1f} --unguarded")   # the lane is chosen on the truth
        x, y, h = self.true_pose()
        return (x, y, h) if self.lane_clear(x, y, h, length) else None

    def relocate(self, length: float = 5.0) -> bool:
        """No clear lane of `length` from here: drive to the start of the nearest one along a path the
        truth says is passable, unguarded (positioning, not measured: its distance is not clean driving
        and its contacts are counted apart). False when none is in reach."""
        x, y, h = self.true_pose()
        route = self.lanes.route(x, y, length, clear=self.lane_clear, avoid=self.tried_starts)
        if route is None:
            return False
        # A start the drive error left the rover beside, with no clear lane there, is not tried again.
        self.tried_starts.add(self.lanes.cell_of(*route[-1]))
        before = self.contacts()
        for wx, wy in route:
            x, y, h = self.true_pose()
            turn = math.degrees(_wrap(math.atan2(wy - y, wx - x) - h))
            if abs(turn) >= 1.0:
                self.command(f"drive --turn {turn:.1f} --unguarded")
            self.command(f"drive --forward {math.hypot(wx - x, wy - y):.2f} --unguarded")
        self.relocation_contacts += self.contacts() - before
        return True

    def drop(self, x: float, y: float, h: float, person: bool) -> tuple[str, str, float, float]:
        distance = float(self.rng.uniform(1.6, 3.8))
        offset = float(self.rng.uniform(-0.2, 0.2))
        px = x + distance * math.cos(h) - offset * math.sin(h)
        py = y + distance * math.sin(h) + offset * math.cos(h)
        if person:
            reply = self.command(f"astronaut --at {px:.3f},{py:.3f}")
            return "person", "astronaut --remove", distance, 1.8
        height = float(self.rng.uniform(0.12, 0.30))
        reply = pairs(self.command(f"sim-rock --at {px:.3f},{py:.3f} --height {height:.3f}"))
        return "rock", f"sim-rock --remove {reply['rock']}", distance, height

    def close(self) -> None:
        self.client.close()
        self.server.stop()


def _wrap(angle: float) -> float:
    return (angle + math.pi) % (2 * math.pi) - math.pi


def run_scene(scene: Scene, sensor: str, encounters: int, routes: int, log: list[dict]) -> dict:
    clean_m, false_stops, done = 0.0, 0, 0
    stops = 0   # guard stops so far: the row of stops.csv each encounter's stop will be
    started = scene.command(f"hazard-start --sensor {sensor}")
    assert " OK " in started, started
    contacts0 = scene.contacts()
    attempts = 0
    while done < encounters and attempts < encounters * 4:
        attempts += 1
        # A clean run first (also moves the rover to fresh ground), then an encounter on a clear lane.
        lane = scene.onto_lane(CLEAN_RUN_M + 0.5)
        if lane is not None:
            reply = scene.command(f"drive --forward {CLEAN_RUN_M}")
            if "drive stopped: hazard" in reply:
                false_stops += 1
                stops += 1
                print(f"  seed {scene.seed}: FALSE STOP on a clean lane: {reply}", flush=True)
            elif " OK " in reply:
                clean_m += CLEAN_RUN_M
        lane = scene.onto_lane(5.0)
        if lane is None:
            scene.relocate()
            continue
        person = done % 5 == 4
        kind, remove, distance, height = scene.drop(*lane, person)
        before = scene.contacts()
        reply = scene.command("drive --forward 5")
        after = scene.contacts()
        stopped = "drive stopped: hazard" in reply
        log.append({"seed": scene.seed, "kind": kind, "how": "drive", "height": height, "dropped_at": distance,
                    "stopped": stopped, "contacts": after - before, "reply": reply,
                    "stop_row": stops})
        stops += int(stopped)
        print(f"  seed {scene.seed} {kind} {height:.2f} m at {distance:.2f} m: "
              f"{'stopped' if stopped else 'NOT STOPPED'}, contacts {after - before}", flush=True)
        scene.command(remove)
        stops += back_off(scene)
        done += 1
    for index in range(routes):
        lane = scene.onto_lane(4.5)
        if lane is None:
            scene.relocate()
            lane = scene.onto_lane(4.5)
        if lane is None:
            print(f"  seed {scene.seed}: no clear 4.5 m lane for route {index}", flush=True)
            continue
        name = f"lane{index}"
        taught = [scene.command(f"route-record start --name {name}"), scene.command("drive --forward 2"),
                  scene.command("drive --forward 2"), scene.command("route-record stop")]
        if not all(" OK " in reply for reply in taught):
            print(f"  seed {scene.seed}: route {name} not taught: {taught}", flush=True)
            continue
        back = scene.command(f"route-follow --name {name} --reverse")
        x, y, h = scene.true_pose()
        if " OK " not in back or not scene.lane_clear(x, y, h, 4.0):
            print(f"  seed {scene.seed}: route {name} not back on a clear lane ({back})", flush=True)
            continue
        kind, remove, distance, height = scene.drop(x, y, h, False)
        before = scene.contacts()
        reply = scene.command(f"route-follow --name {name}")
        after = scene.contacts()
        stopped = "drive stopped: hazard" in reply
        log.append({"seed": scene.seed, "kind": kind, "how": "route-follow", "height": height,
                    "dropped_at": distance, "stopped": stopped, "contacts": after - before, "reply": reply,
                    "stop_row": stops})
        stops += int(stopped)
        print(f"  seed {scene.seed} route {kind} {height:.2f} m at {distance:.2f} m: "
              f"{'stopped' if stopped else 'NOT STOPPED'}, contacts {after - before}", flush=True)
        scene.command(remove)
        stops += back_off(scene)
    reply = scene.command("hazard-stop", timeout=120)
    rows = list(csv.DictReader(open(Path(pairs(reply)["path"]) / "stops.csv")))
    for entry in log:
        if entry["seed"] == scene.seed and entry["stopped"] and entry["stop_row"] < len(rows):
            value = rows[entry["stop_row"]]["true_clearance_m"]
            entry["clearance"] = None if value == "none" else float(value)
    summary = json.loads((Path(pairs(reply)["path"]) / "product.json").read_text()).get("summary")
    return {"clean_m": clean_m, "false_stops": false_stops, "stop_reply": pairs(reply), "summary": summary,
            "contacts": scene.contacts() - contacts0 - scene.relocation_contacts,
            "relocation_contacts": scene.relocation_contacts}


def back_off(scene: Scene) -> int:
    """After an obstacle is taken away: back up 1.5 m, so the sensor sees the ground where it stood
    (the guard remembers a hazard below its view until a frame sees that ground clear again; a rock
    does not vanish, but the campaign's does). Returns the guard stops it met (0 or 1)."""
    # --unguarded: the campaign measures the forward guard; the rear has no sensor (PROTOCOL.md)
    reply = scene.command("drive --backward 1.5 --unguarded")
    return int("drive stopped: hazard" in reply)


def summarise(records: list[dict], sensor: str) -> str:
    """The campaign's figures over scenes (each a results line with its encounters)."""
    scenes = [r for r in records if r["sensor"] == sensor]
    log = [e for r in scenes for e in r["encounters"]]
    clean_m = sum(r["clean_m"] for r in scenes)
    false_stops = sum(r["false_stops"] for r in scenes)
    # Stopped for the dropped obstacle: stopped, no contact, and the nearest true obstacle ahead is within 1 m.
    short = [e for e in log if e["stopped"] and e["contacts"] == 0 and e.get("clearance") is not None
             and e["clearance"] < 1.0]
    touched = sum(e["contacts"] > 0 for e in log)
    rates = [float(r["stop_reply"]["rate"]) for r in scenes]
    p95 = [((r.get("summary") or {}).get("latency_ms") or {}).get("p95") for r in scenes]
    p95 = [v for v in p95 if v is not None]
    lines = [f"{sensor}: scenes {len(scenes)} (seeds {' '.join(str(r['seed']) for r in scenes)}), 20 m worlds, "
             f"rover 0.3 m/s",
             f"  encounters {len(log)} (drive {sum(e['how'] == 'drive' for e in log)}, route-follow "
             f"{sum(e['how'] == 'route-follow' for e in log)}; rocks {sum(e['kind'] == 'rock' for e in log)} of "
             f"12-30 cm, persons {sum(e['kind'] == 'person' for e in log)})",
             f"  stopped short of the obstacle before contact: {len(short)}/{len(log)}; encounters with a contact: "
             f"{touched}; contacts over the campaign (truth): {sum(r['contacts'] for r in scenes)}",
             f"  clean runs: {clean_m:.1f} m, false stops {false_stops} -> "
             + (f"{100.0 * false_stops / clean_m:.2f} per 100 m" if clean_m > 0 else "no clean metre driven")]
    if rates:
        # At sim-speed 50 the guard's frames are paced by wall time (each drive step waits for a fresh
        # frame), so the rate per simulated second is not the guard's speed: its latency is.
        worst = max(p95) if p95 else math.nan
        lines.append(f"  latency per detection, p95 per scene: median {np.median(p95) if p95 else math.nan:.1f} ms, "
                     f"max {worst:.1f} ms (at most {1000.0 / worst:.1f} Hz on one core); frames per simulated "
                     f"second at sim-speed 50: median {np.median(rates):.2f}")
    margins = [e["clearance"] for e in short]
    if margins:
        m = np.array(margins)
        lines.append(f"  stop margin (true free way left, m): min {m.min():.3f} p5 {np.percentile(m, 5):.3f} "
                     f"median {np.median(m):.3f} max {m.max():.3f} over {len(m)} stops")
    others = [(e["seed"], e["kind"], e["reply"][-90:], e.get("clearance")) for e in log if e not in short]
    if others:
        lines.append(f"  other outcomes: {others}")
    return "\n".join(lines)


def scene_folder(seed: int, keep: str | None) -> contextlib.AbstractContextManager[str]:
    """A scene's data folder: a temporary one, or one kept under `keep` (made if missing) to look at."""
    prefix = f"hazard-campaign-{seed}-"
    if keep is None:
        return tempfile.TemporaryDirectory(prefix=prefix)
    Path(keep).mkdir(parents=True, exist_ok=True)
    return contextlib.nullcontext(tempfile.mkdtemp(prefix=prefix, dir=keep))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sensor", choices=("tof", "stereo"), default="tof")
    parser.add_argument("--cover", type=float, default=0.07, help="the worlds' rock cover")
    parser.add_argument("--seeds", type=int, nargs="+", default=[21, 22, 23, 24, 25])
    parser.add_argument("--encounters", type=int, default=8, help="blind-drive encounters per scene")
    parser.add_argument("--routes", type=int, default=2, help="taught-route encounters per scene")
    add_results_options(parser, RESULTS)
    parser.add_argument("--keep", help="keep each scene's data directory under this directory")
    args = parser.parse_args()
    if reported(args, summarise):
        return
    log = RunLog(args.results, {"encounters": args.encounters, "routes": args.routes, "cover": args.cover})
    planned = [{"seed": seed, "sensor": args.sensor} for seed in args.seeds]
    tasks = log.todo(planned)
    print(f"{len(planned) - len(tasks)} of {len(planned)} scenes already in {args.results}; {len(tasks)} to go",
          flush=True)
    for task in tasks:
        started = time.monotonic()
        encounters: list[dict] = []
        try:
            with scene_folder(task["seed"], args.keep) as tmp:
                scene = Scene(task["seed"], Path(tmp), args.cover)
                try:
                    result = run_scene(scene, args.sensor, args.encounters, args.routes, encounters)
                finally:
                    scene.close()
        except Exception as exc:   # one broken scene is written and reported, not the campaign's end
            log.append(task, time.monotonic() - started, error=f"{type(exc).__name__}: {exc}")
            print(f"{args.sensor} seed {task['seed']}: broke: {exc}", flush=True)
            continue
        for entry in encounters:
            entry["reply"] = entry["reply"][-300:]
        log.append(task, time.monotonic() - started, encounters=encounters, **result)
        print(f"{args.sensor} seed {task['seed']}: {result['stop_reply']}", flush=True)
    print(report(args.results, summarise))


if __name__ == "__main__":
    main()
