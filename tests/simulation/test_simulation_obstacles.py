"""astronaut and sim-rock against a real server on the simulated test bed (12 m world): replies,
refusals, removal, that a product's truth lists the obstacles and that the time-of-flight camera sees a
dropped rock; with real devices both are 409 wrong-mode."""
from __future__ import annotations

import json

import numpy as np
import tifffile

from conftest import pairs


def grab_tof(c, server, name: str) -> tuple[dict, np.ndarray]:
    reply = pairs(c.command(f"grab-tof --output {name} --frames 1", timeout=120))
    product = server.data_dir / "products" / reply["product"]
    return (json.loads((product / "truth" / "state.json").read_text()),
            tifffile.imread(product / "truth" / "range.tif"))


def test_sim_rock_drops_removes_and_clears_rocks_the_camera_sees(server):
    with server.connect() as c:
        assert c.command("move-ptu --tilt -35 --speed 50").split()[1] == "OK"
        before_state, before = grab_tof(c, server, "bare")
        assert before_state["obstacles"] == []
        rock = pairs(c.command("sim-rock --at 2.2,0 --height 0.3 --seed 4", timeout=60))
        assert (rock["rock"], rock["x"], rock["y"], rock["height"], rock["diameter"]) == \
            ("1", "2.200", "0.000", "0.300", "0.450")
        state, seen = grab_tof(c, server, "rock")
        [record] = state["obstacles"]
        assert (record["id"], record["kind"], record["seed"]) == (1, "rock", 4)
        assert abs(record["height_m"] - 0.3) < 1e-9 and len(record["footprint"]) >= 6
        nearer = np.isfinite(before) & (seen < before - 0.05)
        assert nearer.sum() > 50, "the camera looking at the rock sees it closer than the bare ground"
        second = pairs(c.command("sim-rock --at -3,3 --height 0.1 --diameter 0.3"))
        assert (second["rock"], second["diameter"]) == ("2", "0.300")
        refused = {
            "sim-rock --remove 9": "400 bad-request sim-rock: --remove = 9: no dropped rock has that id "
                                   "(dropped rocks: 1, 2)",
            "sim-rock --at 0.1,0": "would land on the rover",
            "sim-rock --at 6.2,0 --height 0.5": "its bounds are x -",
            "sim-rock --at 1,1 --height 2.6": "--height = '2.6'",
            "sim-rock --at 1,1 --diameter 0.01": "--diameter = '0.01'",
            "sim-rock --at 1": "--at",
            "sim-rock": "give one of --at X,Y",
            "sim-rock --clear --remove 1": "not --remove and --clear",
        }
        for line, expected in refused.items():
            assert expected in c.command(line), line
        assert pairs(c.command("sim-rock --remove 1")) == {"removed": "1"}
        assert pairs(c.command("sim-rock --clear")) == {"removed": "1"}
        state, after = grab_tof(c, server, "cleared")
        assert state["obstacles"] == []
        assert np.array_equal(after, before, equal_nan=True), "removal restores the view exactly"


def test_astronaut_stands_moves_walks_and_goes(server):
    with server.connect() as c:
        assert "400 bad-request astronaut: give --at" in c.command("astronaut")
        assert "409 wrong-mode astronaut: there is no astronaut" in c.command("astronaut --remove")
        person = pairs(c.command("astronaut --at 2.5,0.5", timeout=60))
        assert (person["x"], person["y"], person["height"]) == ("2.500", "0.500", "1.800")
        moved = pairs(c.command("astronaut --at 3,-1"))
        assert moved["astronaut"] == person["astronaut"] and moved["x"] == "3.000"  # one person in the world
        assert "would land on the rover" in c.command("astronaut --at 0.2,0")
        assert "its bounds are" in c.command("astronaut --at 0,6.3")
        state, _ = grab_tof(c, server, "person")
        [record] = state["obstacles"]
        assert (record["kind"], record["x"], record["y"]) == ("astronaut", 3.0, -1.0)
        walking = pairs(c.command("astronaut --at 2,-2 --to 2,2 --speed 1"))
        assert (walking["to"], walking["speed"]) == ("2.000,2.000", "1.000")
        first, _ = grab_tof(c, server, "walk1")
        [walker] = first["obstacles"]
        assert walker["walk"] == {"from": [2.0, -2.0], "to": [2.0, 2.0], "via": [], "speed_m_s": 1.0, "pause_s": 0.0}
        assert walker["x"] == 2.0 and -2.0 <= walker["y"] <= 2.0
        second, _ = grab_tof(c, server, "walk2")   # later on the simulation clock: elsewhere on the walk
        assert second["time_s"] > first["time_s"] and second["obstacles"][0]["y"] != walker["y"]
        assert pairs(c.command("astronaut --remove")) == {"removed": person["astronaut"]}
        state, _ = grab_tof(c, server, "gone")
        assert state["obstacles"] == []


def test_obstacles_are_for_the_simulated_world_only(server_factory):
    server = server_factory(configs={"devices.toml": "[tof]\nenabled = false\n[cameras]\nenabled = false\n"})
    with server.connect() as c:
        assert "409 wrong-mode astronaut: the devices are real" in c.command("astronaut --at 1,1")
        assert "409 wrong-mode sim-rock: the devices are real" in c.command("sim-rock --at 1,1")
        assert "sim-rock" in pairs(c.command("help"))["commands"].split()
