"""track3d-detect / track3d-start / track3d-stop against a real server on the simulated test bed: the
search finds the suited astronaut and not a standing boulder of its height, with its candidates and
picture; the tracker follows it at frame rate, publishes its events, keeps PTU jobs out while it
runs, answers its summary and writes its track; the 409s; and a walker followed across the view."""
from __future__ import annotations

import csv
import math
import re
import time
from pathlib import Path

import numpy as np
import pytest

from conftest import pairs

EVENT = re.compile(r"^\* EVENT track seq=(\d+) state=(tracking|lost) x=(\S+) y=(\S+) z=(\S+) vx=(\S+) vy=(\S+) "
                   r"range=(\S+) bearing=(\S+)")
PERSON, BOULDER = (4.0, 1.0), (4.0, -1.5)


def product_dir(server, reply: str) -> Path:
    return server.data_dir / "products" / pairs(reply)["product"]


def rows(path: Path) -> list[dict]:
    with open(path) as f:
        return list(csv.DictReader(f))


def test_detect_finds_the_astronaut_not_the_boulder_and_tracking_keeps_ptu_jobs_out(server_factory):
    # The tracker's rate is in simulation time and its work in wall time: at the suite's sim-speed a
    # frame would span seconds of a turning PTU. Tracking is tested at 1.
    server = server_factory(args=["--sim-speed", "1"])
    with server.connect() as c:
        assert "409 wrong-mode track3d-start: no target" in c.command("track3d-start")
        assert "409 wrong-mode" in c.command("track3d-stop")
        assert "400 bad-request" in c.command("track3d-detect --pan 10:-10")   # a range runs low to high
        assert "400 bad-request" in c.command("track3d-start --rate 0")
        assert " OK " in c.command(f"sim-rock --at {BOULDER[0]},{BOULDER[1]} --height 1.8 --diameter 0.7",
                                   timeout=120)
        nobody = c.command("track3d-detect --pan -45:45", timeout=300)
        assert pairs(nobody)["found"] == "0", nobody                   # a boulder of a person's height is not one
        candidates = rows(product_dir(server, nobody) / "candidates.csv")
        boulder = [r for r in candidates if math.dist((float(r["x"]), float(r["y"])), BOULDER) < 0.6]
        assert boulder and all(r["person"] == "0" for r in boulder), candidates
        assert "409 wrong-mode track3d-start: no target" in c.command("track3d-start")

        assert " OK " in c.command(f"astronaut --at {PERSON[0]},{PERSON[1]}")
        found = c.command("track3d-detect --pan -45:45", timeout=300)
        got = pairs(found)
        assert got["found"] == "1", found
        assert math.dist((float(got["x"]), float(got["y"])), PERSON) < 0.08, found
        assert float(got["confidence"]) >= 0.6 and 1.6 < float(got["height"]) < 2.0
        assert float(got["bearing"]) == pytest.approx(-math.degrees(math.atan2(PERSON[1], PERSON[0])), abs=2.0)
        folder = product_dir(server, found)
        assert (folder / "detect.png").stat().st_size > 10_000 and (folder / "truth" / "state.json").exists()
        people = [r for r in rows(folder / "candidates.csv") if r["person"] == "1"]
        assert len(people) == 1 and float(people[0]["confidence"]) >= 0.6

        c.command("subscribe track")
        started = c.command("track3d-start --rate 5")
        assert pairs(started) == {"activity": "track", "sensor": "tof", "rate": "5"}, started
        assert "409 wrong-mode" in c.command("track3d-start") and "already running" in c.command("track3d-start")
        assert pairs(c.command("status"))["track"] == "on"
        busy = c.command("move-ptu --pan 40 --tilt 0")
        assert "ERR 409 busy" in busy and "track" in busy and "track3d-stop" in busy, busy
        def tracking_events() -> list[re.Match]:
            return [m for m in (EVENT.match(e) for e in c.events) if m and m.group(2) == "tracking"]
        deadline = time.monotonic() + 90
        while len(tracking_events()) < 8 and time.monotonic() < deadline:
            c.command("status")
        events = [m for m in (EVENT.match(e) for e in c.events) if m]
        seqs = [int(m.group(1)) for m in events]
        assert seqs == list(range(1, len(seqs) + 1))
        # lost until the PTU, turned from where the search ended, first sees the person; then on it
        states = [m.group(2) for m in events]
        assert "lost" not in states[states.index("tracking"):], states
        assert len(tracking_events()) >= 8
        for m in tracking_events():   # each estimate near the person (one ran 0.11 m off in a loaded suite, the
            # first frames after the PTU turned onto it); the RMSE below holds the accuracy to 5 cm
            assert math.dist((float(m.group(3)), float(m.group(4))), PERSON) < 0.15, m.group(0)
        stopped = c.command("track3d-stop", timeout=120)
        summary = pairs(stopped)
        assert summary["activity"] == "track" and int(summary["frames"]) >= 8 and float(summary["tracked"]) >= 0.5
        track = rows(product_dir(server, stopped) / "track.csv")
        seen = [r for r in track if r["state"] == "tracking" and r["seen"] == "1"]
        errors = [math.dist((float(r["x"]), float(r["y"])), (float(r["true_x"]), float(r["true_y"]))) for r in seen]
        assert len(seen) >= 6 and np.sqrt(np.mean(np.square(errors))) < 0.05, errors
        aims = [float(r["pan_deg"]) for r in track[3:]]                 # the PTU was turned onto the person
        assert np.median(np.abs(np.array(aims) - got_bearing(got))) < 3.0, aims
        assert (product_dir(server, stopped) / "track.png").stat().st_size > 10_000
        assert pairs(c.command("status"))["track"] == "off"
        assert " OK " in c.command("move-ptu --pan 0 --tilt 0", timeout=120)  # the PTU is free again


def got_bearing(reply: dict) -> float:
    return float(reply["bearing"])


def test_a_walker_is_followed_across_the_view_and_found_again_when_it_comes_back(server_factory):
    server = server_factory(args=["--sim-speed", "1"])
    with server.connect() as c:
        assert " OK " in c.command("astronaut --at 4,-1.5 --to 4,1.5 --speed 0.8 --pause 1", timeout=120)
        found = pairs(c.command("track3d-detect --pan -40:40", timeout=300))
        assert found["found"] == "1", found
        assert pairs(c.command("track3d-start --rate 8"))["activity"] == "track"
        time.sleep(9)
        # away behind the rover, out of every view: lost; then back in front: found again
        assert " OK " in c.command("astronaut --at -4,0")
        time.sleep(6)
        assert " OK " in c.command("astronaut --at 4,-1.0 --to 4,1.5 --speed 0.8")
        time.sleep(8)
        stopped = c.command("track3d-stop", timeout=120)
    track = rows(product_dir(server, stopped) / "track.csv")
    moving = [r for r in track if float(r["sim_s"]) < float(track[0]["sim_s"]) + 8.5]
    walked = [r for r in moving if r["state"] == "tracking" and r["seen"] == "1"]
    assert len(walked) >= 0.8 * len(moving), [r["state"] + r["seen"] for r in moving]
    errors = [math.dist((float(r["x"]), float(r["y"])), (float(r["true_x"]), float(r["true_y"]))) for r in walked]
    assert np.sqrt(np.mean(np.square(errors))) < 0.06, errors
    speeds = [math.hypot(float(r["vx"]), float(r["vy"])) for r in walked[10:]]
    assert 0.3 < np.median(speeds) < 1.2
    states = [r["state"] for r in track]
    assert "lost" in states, states                               # gone behind the rover
    after = states[states.index("lost"):]
    assert "tracking" in after                                    # and found again
    last = [r for r in track[-20:] if r["state"] == "tracking" and r["seen"] == "1"]
    assert last and all(math.dist((float(r["x"]), float(r["y"])), (float(r["true_x"]), float(r["true_y"]))) < 0.1
                        for r in last)
