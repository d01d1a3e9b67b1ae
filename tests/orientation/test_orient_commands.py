"""orient against a real server on the simulated test bed: the keyframe reply, the motion measured
after real drives (stereo and TOF) against the simulator's truth, the sun in its sources, --no-apply,
a new chain after `pose`, the refusal on a blank view, bad input, and break / continue."""
from __future__ import annotations

import json
import math
import time
from pathlib import Path

import pytest

from conftest import WIDE_WORLD, pairs

# Flat, untextured, rockless ground: nothing for interest points to hold on to.
BLANK_WORLD = """seed = 4
size_m = [12.0, 12.0]
[terrain]
slope_deg = 0.0
undulation_rms_m = 0.0
relief_rms_m = 0.0
[rocks]
cover = 0.0
[craters]
count = 0
[albedo]
regolith_contrast = 0.0
grain_fraction = 0.0
grain_contrast = 0.0
rock_contrast = 0.0
detail_contrast = 0.0
"""


def product(server, reply: str) -> Path:
    return server.data_dir / "products" / pairs(reply)["product"]


def look_record(server, reply: str) -> tuple[dict, dict]:
    folder = product(server, reply)
    return (json.loads((folder / "orient.json").read_text()),
            json.loads((folder / "truth" / "state.json").read_text())["rover"])


def test_keyframe_then_measured_motion_no_apply_and_a_new_chain_after_pose(server_factory):
    server = server_factory(configs={"world.toml": WIDE_WORLD})   # 10 m of ground ahead: no edge in view
    with server.connect(timeout=120) as c:
        bad = c.command("orient --sensor lidar")
        assert bad.split()[1:3] == ["ERR", "400"] and "sensor" in bad and "lidar" in bad
        first = pairs(c.command("orient", timeout=300))
        assert first["keyframe"] == "1" and first["dx"] == first["dy"] == "0.000" and first["dheading"] == "0.00"
        assert first["sources"] == "none" and first["matches"] == "0"

        assert " OK " in c.command("drive --forward 1.0", timeout=120)
        reply = c.command("orient", timeout=300)
        moved = pairs(reply)
        record, truth = look_record(server, reply)
        assert "keyframe" not in moved and record["keyframe_number"] == 1
        assert moved["sources"] == "stereo,sun" and int(moved["matches"]) >= 50
        error = math.hypot(float(moved["x"]) - truth["x"], float(moved["y"]) - truth["y"])
        assert error < 0.03, (moved, truth)
        assert abs(float(moved["heading"]) - math.degrees(truth["heading_rad"])) < 0.5
        assert float(moved["dx"]) == pytest.approx(1.0, abs=0.1) and abs(float(moved["dy"])) < 0.1
        assert 0 < float(moved["sigma_xy"]) < 0.1 and float(moved["sigma_heading"]) > 0
        assert (product(server, reply) / "look.png").exists()

        # --no-apply: measured and answered, the estimate untouched (the next look starts from it).
        assert " OK " in c.command("drive --forward 0.8", timeout=120)
        before = look_record(server, c.command("orient --no-apply", timeout=300))[0]
        after = look_record(server, c.command("orient", timeout=300))[0]
        assert after["look"]["estimate_before"] == before["look"]["estimate_before"]
        assert before["applied"] is False and after["applied"] is True

        # A pose from the GNC starts a new chain: keyframe, zero motion.
        assert " OK " in c.command("pose 0.5,0.2,10")
        again = pairs(c.command("orient", timeout=300))
        assert again["keyframe"] == "1" and (again["x"], again["y"], again["heading"]) == ("0.500", "0.200", "10.00")

        # TOF: a chain of its own.
        assert pairs(c.command("orient --sensor tof", timeout=300))["keyframe"] == "1"
        assert " OK " in c.command("drive --forward 0.7", timeout=120)
        reply = c.command("orient --sensor tof", timeout=300)
        tof = pairs(reply)
        record, truth = look_record(server, reply)
        assert tof["sources"].startswith("tof") and "keyframe" not in tof
        # The chain started at the GNC's pose, not the true one: compare the motion, not the position.
        assert float(tof["dx"]) ** 2 + float(tof["dy"]) ** 2 == pytest.approx(0.7 ** 2, abs=0.1)


def test_a_blank_view_is_refused_by_name_and_changes_nothing(server_factory):
    server = server_factory(configs={"world.toml": BLANK_WORLD})
    with server.connect(timeout=120) as c:
        reply = c.command("orient", timeout=300)
        assert reply.split()[1:3] == ["ERR", "400"] and "orient failed: few-features:" in reply, reply
        name = reply.rsplit("product=", 1)[1].strip()
        record = json.loads((server.data_dir / "products" / name / "orient.json").read_text())
        assert record["failed"]["reason"] == "few-features"
        # Still no keyframe: the next look tries again, and fails the same way.
        assert "orient failed: few-features" in c.command("orient", timeout=300)


def test_break_and_continue_an_orient_job(server_factory):
    # The tilt to -20 degrees at 2 deg/s takes 10 simulated seconds, 2 s of wall time at --sim-speed 5.
    server = server_factory(configs={"ptu.toml": "default_speed_deg_s = 2.0\n"}, args=["--sim-speed", "5"])
    with server.connect(timeout=120) as c:
        c.send("@o orient --output looked")
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            if c.read_line(timeout=60).startswith("o PROGRESS 10"):
                break
        brk = pairs(c.command("break", timeout=120))
        reply, _ = c.reply("o", timeout=120)
        assert "ERR 499 interrupted" in reply and brk["recovery"] == brk["job"]
        done = pairs(c.command("continue", timeout=300))
        assert done["product"] == "looked" and done["keyframe"] == "1"
        assert (server.data_dir / "products" / "looked" / "orient.json").exists()
