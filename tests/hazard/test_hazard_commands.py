"""hazard-start / hazard-stop against a real server on the simulated test bed: the activity's replies
and its 409s, its events and product, what it does beside a job (the job's sensors make its frames
unknown, never the job fail), break leaves it running and quit stops it; and it rides along on
route-follow and navigate over clean ground without stopping either."""
from __future__ import annotations

import csv
import json
import math
import re
import time
import tomllib
from pathlib import Path

import numpy as np
import pytest

from drivers.sim.config import WorldConfig
from drivers.sim.world import World

from conftest import SMALL_WORLD, WIDE_WORLD, pairs

WORLD = WIDE_WORLD
EVENT = re.compile(r"^\* EVENT hazard seq=(\d+) state=(clear|hazard|unknown) distance=(\S+) x=(\S+) y=(\S+) "
                   r"latency_ms=(\S+)")


def product_dir(server, reply: str) -> Path:
    return server.data_dir / "products" / pairs(reply)["product"]


def hazard_events(client) -> list[re.Match]:
    return [m for m in (EVENT.match(e) for e in client.events) if m]


@pytest.fixture(scope="module")
def small_world() -> World:
    return World.build(WorldConfig(**tomllib.loads(SMALL_WORLD)))


def test_start_stop_status_events_and_the_409s(server, small_world):
    with server.connect() as c:
        assert pairs(c.command("status"))["hazard"] == "off" and pairs(c.command("status"))["track"] == "off"
        stop = c.command("hazard-stop")
        assert "ERR 409 wrong-mode" in stop and "no hazard activity is running" in stop
        assert "ERR 400" in c.command("hazard-start --rate 0") and "--rate" in c.command("hazard-start --rate 0")
        assert "ERR 400" in c.command("hazard-start --sensor lidar")
        assert "ERR 400" in c.command("hazard-start --stop-distance 9")
        assert pairs(c.command("status"))["hazard"] == "off"          # refused starts change nothing
        c.command("subscribe hazard")
        started = c.command("hazard-start --rate 4 --stop-distance 0.6")
        assert pairs(started) == {"activity": "hazard", "sensor": "tof", "rate": "4", "stop_distance": "0.6"}, started
        again = c.command("hazard-start")
        assert "ERR 409 wrong-mode" in again and "already running" in again
        assert pairs(c.command("status"))["hazard"] == "on"
        deadline = time.monotonic() + 60
        while len(hazard_events(c)) < 5 and time.monotonic() < deadline:
            c.command("status")
        events = hazard_events(c)
        assert [int(m.group(1)) for m in events[:5]] == [1, 2, 3, 4, 5]
        # A 30 cm rock lies 2.1-2.7 m ahead of the start: every frame finds it where the truth has it.
        assert all(m.group(2) == "hazard" for m in events), [m.group(0) for m in events]
        for m in events:
            x, y = float(m.group(4)), float(m.group(5))
            near = np.mgrid[x - 0.1:x + 0.1:0.01, y - 0.1:y + 0.1:0.01]
            assert np.nanmax(small_world.protrusion_at(near[0], near[1])) > 0.10, m.group(0)
            assert float(m.group(3)) == pytest.approx(x - 0.275, abs=0.1)   # from the front bumper, heading east
        assert all(float(m.group(6)) < 100 for m in events)
        reply = c.command("hazard-stop", timeout=60)
        summary = pairs(reply)
        assert summary["activity"] == "hazard" and int(summary["frames"]) >= 5 and summary["stops"] == "0", reply
        assert pairs(c.command("status"))["hazard"] == "off"
    product = product_dir(server, reply)
    rows = list(csv.DictReader(open(product / "frames.csv")))
    assert len(rows) == int(summary["frames"]) and {r["state"] for r in rows} == {"hazard"}
    assert all(float(r["tilt_deg"]) == pytest.approx(-40.0, abs=0.1) for r in rows)
    assert (product / "corridor.png").stat().st_size > 1000 and (product / "stops.csv").exists()
    manifest = json.loads((product / "product.json").read_text())
    assert manifest["status"] == "complete" and manifest["summary"]["states"]["hazard"] == len(rows)


def test_beside_a_job_break_leaves_it_and_quit_stops_it(server):
    with server.connect(timeout=600) as c:
        c.command("subscribe hazard")
        assert " OK " in c.command("hazard-start")
        c.send("@map dem-update-tof --pan -20:20")
        # Immediate while the job runs: stop and start again, not 409 busy.
        time.sleep(1.0)
        assert " OK " in c.command("hazard-stop", timeout=60)
        assert " OK " in c.command("hazard-start")
        reply, _ = c.reply("map", timeout=600)
        assert " OK " in reply, reply                                 # the job never fails for the activity
        unknown = [m for m in hazard_events(c) if m.group(2) == "unknown"]
        assert unknown and all(m.group(3) == "none" for m in unknown)
        assert any("reason=\"a job holds the" in e for e in c.events), c.events[-5:]
        # break interrupts the job, not the activity.
        c.send("@map2 dem-full-tof")
        time.sleep(1.0)
        c.command("break")
        reply, _ = c.reply("map2", timeout=300)
        assert "ERR 499" in reply, reply
        status = pairs(c.command("status"))
        assert status["hazard"] == "on" and status["mode"] == "break"
        frames = len(hazard_events(c))
        deadline = time.monotonic() + 60
        while len(hazard_events(c)) < frames + 3 and time.monotonic() < deadline:
            c.command("status")
        assert len(hazard_events(c)) >= frames + 3                    # the frames go on with the job gone
        assert " OK " in c.command("quit", timeout=120)
    assert server.proc.wait(timeout=60) == 0
    products = sorted((server.data_dir / "products").glob("hazard-start-*"))
    assert len(products) == 2                                         # the one stopped by hand, the one quit stopped
    assert all(json.loads((p / "product.json").read_text())["status"] == "complete" for p in products)


def clear_lane(world: World, start: tuple[float, float], length: float, half_width: float,
               below: float = 0.06) -> float:
    """A heading (degrees) whose straight lane from start is free of rocks taller than `below`."""
    grid = world.grid
    for heading in np.arange(0.0, 360.0, 5.0):
        c, s = math.cos(math.radians(heading)), math.sin(math.radians(heading))
        along = np.arange(-0.4, length, 0.02)
        across = np.arange(-half_width, half_width + 1e-9, 0.02)
        a, b = np.meshgrid(along, across)
        x, y = start[0] + a * c - b * s, start[1] + a * s + b * c
        inside = (np.abs(x) < grid.x_max - 1) & (np.abs(y) < grid.y_max - 1)
        if inside.all() and np.nanmax(world.protrusion_at(x, y)) < below:
            return float(heading)
    raise AssertionError("no clear lane in the test world")


@pytest.fixture(scope="module")
def wide_world() -> World:
    return World.build(WorldConfig(**tomllib.loads(WORLD)))


def test_route_follow_and_navigate_beside_it_on_clean_ground(server_factory, wide_world):
    heading = clear_lane(wide_world, (0.0, 0.0), 4.5, 0.55)
    server = server_factory(configs={"world.toml": WORLD})
    with server.connect(timeout=600) as c:
        c.command("subscribe hazard")
        assert " OK " in c.command("hazard-start")
        # No frame has seen the ground round the start: the operator turns there on their own word.
        assert " OK " in c.command(f"drive --turn {heading if heading <= 180 else heading - 360:g} --unguarded",
                                   timeout=300)
        assert " OK " in c.command("route-record start --name lane", timeout=300)
        for _ in range(2):
            assert " OK " in c.command("drive --forward 1.5", timeout=300)
        assert " OK " in c.command("route-record stop", timeout=300)
        followed = c.command("route-follow --name lane --reverse", timeout=600)
        assert " OK " in followed, followed
        goal = (3.2 * math.cos(math.radians(heading)), 3.2 * math.sin(math.radians(heading)))
        arrived = c.command(f"navigate --to {goal[0]:.2f},{goal[1]:.2f} --tolerance 0.3 --max-steps 3", timeout=900)
        assert " OK " in arrived, arrived
        reply = c.command("hazard-stop", timeout=60)
    summary = pairs(reply)
    assert summary["stops"] == "0", reply
    rows = list(csv.DictReader(open(product_dir(server, reply) / "frames.csv")))
    states = {s: sum(r["state"] == s for r in rows) for s in ("clear", "hazard", "unknown")}
    # navigate's panoramas hold the PTU and the TOF: those frames are unknown; the drives are guarded.
    assert states["clear"] > 20 and states["unknown"] > 0, states
    moved = {(r["est_x"], r["est_y"]) for r in rows if r["state"] == "clear"}
    assert len(moved) > 10                                            # frames were taken along the way


def test_a_drive_stops_short_of_a_dropped_rock_and_of_a_person(server_factory, wide_world):
    heading = clear_lane(wide_world, (0.0, 0.0), 4.5, 0.55)
    c_, s_ = math.cos(math.radians(heading)), math.sin(math.radians(heading))
    server = server_factory(configs={"world.toml": WORLD})
    with server.connect(timeout=600) as c:
        assert " OK " in c.command(f"drive --turn {heading if heading <= 180 else heading - 360:g}", timeout=300)
        # Without the activity, a drive over the rock's place is not stopped (the maps never saw it).
        assert " OK " in c.command("hazard-start --stop-distance 0.5")
        rock = pairs(c.command(f"sim-rock --at {2.6 * c_:.3f},{2.6 * s_:.3f} --height 0.15"))
        stopped = c.command("drive --forward 4", timeout=300)
        assert "ERR 400 bad-request drive stopped: hazard: step" in stopped, stopped
        assert " OK " in c.command(f"sim-rock --remove {rock['rock']}")
        assert " OK " in c.command("drive --turn 180", timeout=300)
        assert " OK " in c.command("drive --forward 1.0", timeout=300)   # back along the clear lane
        assert " OK " in c.command("drive --turn 180", timeout=300)
        c.command(f"astronaut --at {2.8 * c_:.3f},{2.8 * s_:.3f}")
        stopped = c.command("drive --forward 4", timeout=300)
        assert "drive stopped: hazard:" in stopped, stopped
        reply = c.command("hazard-stop", timeout=60)
    assert pairs(reply)["stops"] == "2", reply
    stops = list(csv.DictReader(open(product_dir(server, reply) / "stops.csv")))
    for stop in stops:
        # Stopped before contact, about the stop distance short of the obstacle.
        assert stop["contacts_so_far"] == "0" and 0.2 < float(stop["true_clearance_m"]) < 0.75, stop


def test_navigate_plans_round_a_rock_the_guard_saw_while_it_drives(server_factory, wide_world):
    heading = clear_lane(wide_world, (0.0, 0.0), 4.5, 0.55)
    c_, s_ = math.cos(math.radians(heading)), math.sin(math.radians(heading))
    # Slower simulated time: the rock lands while the first leg has barely begun.
    server = server_factory(configs={"world.toml": WORLD}, args=["--sim-speed", "10"])
    with server.connect(timeout=900) as c:
        assert " OK " in c.command("hazard-start")
        goal = (4.0 * c_, 4.0 * s_)
        c.send(f"@nav navigate --to {goal[0]:.2f},{goal[1]:.2f} --tolerance 0.3 --max-steps 6")
        deadline = time.monotonic() + 600
        while time.monotonic() < deadline:
            line = c.read_line(timeout=600)
            if line.startswith("* EVENT"):
                continue
            c.pending.append(line)
            if line.startswith("nav PROGRESS") and "driving" in line:
                break
        dropped = c.command(f"sim-rock --at {1.9 * c_:.3f},{1.9 * s_:.3f} --height 0.2")
        assert " OK " in dropped, dropped
        reply, progress = c.reply("nav", timeout=900)
        stop = c.command("hazard-stop", timeout=60)
    assert " OK " in reply, reply
    assert any("drive stopped: hazard" in p and "mapping again" in p for p in progress), progress
    traverse = json.loads((product_dir(server, reply) / "traverse.json").read_text())
    truth = json.loads((product_dir(server, reply) / "truth" / "traverse.json").read_text())
    assert traverse["hazard_stops"] >= 1 and truth["contacts"] == 0, (traverse["hazard_stops"], truth["contacts"])
    assert int(pairs(stop)["stops"]) >= 1
    # The plans after the stop had the guard's own detections in their map, not only the next scan's.
    stopped_at = next(i for i, c in enumerate(traverse["cycles"]) if c.get("hazard_stop"))
    assert any(c.get("guard_hazard_cells", 0) > 0 for c in traverse["cycles"][stopped_at + 1:]), traverse["cycles"]


def test_the_frame_log_is_on_disk_as_it_goes_and_survives_a_kill(server_factory):
    """frames.csv gets a flushed row per frame: after kill -9, every frame the events announced is there."""
    server = server_factory()
    with server.connect() as c:
        c.command("subscribe hazard")
        started = c.command("hazard-start --rate 5 --output kept")
        assert " OK " in started, started
        deadline = time.monotonic() + 60
        while len(hazard_events(c)) < 6 and time.monotonic() < deadline:
            c.command("status")
        announced = max(int(m.group(1)) for m in hazard_events(c))
    server.proc.kill()
    server.proc.wait(30)
    rows = list(csv.DictReader(open(server.data_dir / "products" / "kept" / "frames.csv")))
    assert len(rows) >= announced >= 6 and [int(r["seq"]) for r in rows] == list(range(1, len(rows) + 1))
    assert (server.data_dir / "products" / "kept" / "stops.csv").read_text().startswith("seq,sim_s,")


def test_a_sensor_fault_mid_run_makes_frames_unknown_stops_drives_and_a_reset_mends_it(server_factory):
    """The activity outlives a broken sensor: its frames say unknown and why, the guard will not drive
    on unseen ground, and after the fault is cleared and the devices reset, frames are measured again."""
    server = server_factory()
    with server.connect(timeout=300) as c:
        c.command("subscribe hazard")
        assert " OK " in c.command("hazard-start --rate 5")
        assert " OK " in c.command("sim-fault --device tof")
        deadline = time.monotonic() + 60
        while not any(m.group(2) == "unknown" for m in hazard_events(c)) and time.monotonic() < deadline:
            c.command("status")
        unknown = next(e for e in c.events if "state=unknown" in e)
        assert "reason=" in unknown and "sr4000" in unknown.lower(), unknown
        assert pairs(c.command("status"))["hazard"] == "on"
        refused = c.command("drive --forward 0.5", timeout=300)
        assert "drive stopped: hazard: no hazard frame" in refused and "unknown" in refused, refused
        assert " OK " in c.command("sim-fault --device tof --clear")
        assert " OK " in c.command("reset", timeout=120)
        seen = len(c.events)
        deadline = time.monotonic() + 60
        while not any("state=clear" in e or "state=hazard" in e for e in c.events[seen:]) \
                and time.monotonic() < deadline:
            c.command("status")
        assert any("state=clear" in e or "state=hazard" in e for e in c.events[seen:])
        summary = pairs(c.command("hazard-stop", timeout=60))
    assert summary["activity"] == "hazard" and int(summary["frames"]) > 2
    rows = list(csv.DictReader(open(server.data_dir / "products" / summary["product"] / "frames.csv")))
    assert {"unknown", "clear"} <= {r["state"] for r in rows} or {"unknown", "hazard"} <= {r["state"] for r in rows}


def test_a_gnc_drive_over_zeromq_is_stopped_and_told_and_turns_and_backing_up_are_checked(server_factory,
                                                                                           wide_world):
    """The GNC's own `drive` over ZeroMQ stops short of a rock like a manual one, and the GNC's PUB
    subscription hears the `guard` event with the rover's and the rock's places; a turn on the spot or a
    backward drive is checked before it moves against what the frames saw."""
    from clients.gnc import RvsBadRequest, ZmqClient
    heading = clear_lane(wide_world, (0.0, 0.0), 4.5, 0.55)
    c_, s_ = math.cos(math.radians(heading)), math.sin(math.radians(heading))
    server = server_factory(configs={"world.toml": WORLD})
    events: list = []
    with server.connect(timeout=600) as c, \
            ZmqClient(server.zmq, timeout=300, pub=server.pub, on_event=events.append, topics=("guard",)) as gnc:
        assert " OK " in c.command(f"drive --turn {heading if heading <= 180 else heading - 360:g}", timeout=300)
        assert " OK " in c.command("hazard-start --stop-distance 0.5")
        # Where the rover stands, no frame has seen its sides or its back: a turn is refused by name.
        refused = c.command("drive --turn 90", timeout=300)
        assert "ERR 400 bad-request drive refused: hazard: turning on the spot would sweep ground no frame saw" \
            in refused and "--unguarded" in refused, refused
        rock = (2.6 * c_, 2.6 * s_)
        assert " OK " in c.command(f"sim-rock --at {rock[0]:.3f},{rock[1]:.3f} --height 0.15")
        with pytest.raises(RvsBadRequest) as stopped:
            gnc.call("drive", forward=4)
        assert "drive stopped: hazard: step" in stopped.value.message
        deadline = time.monotonic() + 30
        while not any(e.data.get("action") == "stop" for e in events) and time.monotonic() < deadline:
            gnc.poll_events(0.5)
        told = next(e.data for e in events if e.data.get("action") == "stop")
        assert told["cause"] == "step" and float(told["distance"]) <= 0.55, told
        assert math.dist((float(told["hazard_x"]), float(told["hazard_y"])), rock) < 0.4, told
        where = np.array([float(told["x"]), float(told["y"])])      # on the lane, short of the rock
        assert abs(where @ (-s_, c_)) < 0.1 and 1.2 < where @ (c_, s_) < 2.4, told
        # Backing up over the lane the frames saw on the way is allowed, and says how much was unseen.
        back = pairs(c.command("drive --backward 0.4", timeout=300))
        assert float(back["swept_unseen"]) <= 0.25, back
        # The unguarded turn goes, and the reply says how much of its circle no frame saw.
        turned = pairs(c.command("drive --turn 90 --unguarded", timeout=300))
        assert turned["action"] == "turn" and 0.0 <= float(turned["swept_unseen"]) <= 1.0, turned
        c.command("hazard-stop", timeout=60)
    assert any(e.data.get("action") == "refused" for e in events)
