"""orient keeps its view after the manoeuvres a GNC makes between looks: a turn in place of 90
degrees and a turn of 45 degrees followed by 1.5 m forward, in either direction, answer OK within a
few centimetres and a fraction of a degree of the truth because the head is turned back to the
keyframe's ground, and the look along the heading becomes the keyframe after it; beyond what any
pointing can recover, the refusal says what the rover should do."""
from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from conftest import pairs

# Open ground of its own (30 m, a few rocks, no craters): room for every manoeuvre from the centre.
WORLD = """seed = 5
size_m = [30.0, 30.0]
[rocks]
cover = 0.07
[craters]
count = 0
"""


def product(server, reply: str) -> Path:
    return server.data_dir / "products" / reply.rsplit("product=", 1)[1].split()[0]


def truth_of(server, reply: str) -> dict:
    return json.loads((product(server, reply) / "truth" / "state.json").read_text())["rover"]


def keyframe_at_the_truth(c, server, sensor: str) -> None:
    """A new chain whose keyframe is where the rover truly stands: the manoeuvre's look is then
    compared with the truth directly."""
    truth = truth_of(server, c.command(f"orient --sensor {sensor} --no-apply", timeout=300))
    assert " OK " in c.command(f"pose {truth['x']:.4f},{truth['y']:.4f},{math.degrees(truth['heading_rad']):.3f}")
    assert pairs(c.command(f"orient --sensor {sensor}", timeout=300))["keyframe"] == "1"


def manoeuvre(c, steps: list[str]) -> None:
    for step in steps:
        assert " OK " in c.command(f"drive {step}", timeout=300), step


def undo(c, steps: list[str]) -> None:
    for step in reversed(steps):
        kind, value = step.split()
        back = {"--forward": f"--backward {value}", "--turn": f"--turn {-float(value)}"}[kind]
        assert " OK " in c.command(f"drive {back}", timeout=300)


SHAPES = [["--turn 90"], ["--turn -90"], ["--turn 45", "--forward 1.5"], ["--turn -45", "--forward 1.5"]]


@pytest.mark.parametrize("sensor", ["stereo", "tof"])
def test_a_look_after_a_turn_or_a_turn_and_a_drive_points_back_at_the_keyframe(server_factory, sensor):
    server = server_factory(configs={"world.toml": WORLD})
    with server.connect(timeout=120) as c:
        for steps in SHAPES:
            keyframe_at_the_truth(c, server, sensor)
            manoeuvre(c, steps)
            reply = c.command(f"orient --sensor {sensor}", timeout=300)
            assert " OK " in reply, (steps, reply)
            got, truth = pairs(reply), truth_of(server, reply)
            record = json.loads((product(server, reply) / "orient.json").read_text())
            turn = float(steps[0].split()[1])
            # pointed back: the pan against the turn, and the look along the heading kept as keyframe
            assert record["aim"]["pointed"] and record["aim"]["pan_deg"] * turn > 0, record["aim"]
            assert record["aim"]["along_heading_share"] < 0.3 and record["rekeyed_along_heading"]
            error_m = math.hypot(float(got["x"]) - truth["x"], float(got["y"]) - truth["y"])
            error_deg = abs((float(got["heading"]) - math.degrees(truth["heading_rad"]) + 180) % 360 - 180)
            assert error_m < 0.04 and error_deg < 0.5, (steps, got, truth)
            # the next small step looks from the keyframe along the heading, not pointed again (whether
            # TOF ICP then holds on flat ground is the campaign's to count)
            manoeuvre(c, ["--forward 0.5"])
            step = c.command(f"orient --sensor {sensor}", timeout=300)
            assert json.loads((product(server, step) / "orient.json").read_text())["aim"]["pointed"] is False, step
            undo(c, steps + ["--forward 0.5"])


def test_beyond_what_pointing_can_recover_the_refusal_says_what_to_do(server_factory):
    server = server_factory(configs={"world.toml": WORLD})
    with server.connect(timeout=120) as c:
        keyframe_at_the_truth(c, server, "tof")
        manoeuvre(c, ["--turn 180", "--forward 4"])       # the keyframe's ground 6 m behind: past the SR4000's 5 m
        reply = c.command("orient --sensor tof", timeout=300)
        assert " ERR 400 " in reply and "orient failed:" in reply, reply
        assert "no view the pan-tilt unit can take would see more than" in reply
        assert ("orient after each turn of at most 90 deg and each 1.5 m driven, and before driving on after a "
                "turn of more than 45 deg") in reply
