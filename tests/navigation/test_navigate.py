"""navigate against a real server on the simulated test bed: it arrives without touching a rock,
knows where it is better than dead reckoning, stops and resumes on break / continue, refuses a goal
on a rock with its pictures, and hands its waypoints to a GNC that answers with pose."""
from __future__ import annotations

import json
import math
import re
import time
import tomllib

import numpy as np
import pytest
from scipy.ndimage import distance_transform_edt

from drivers.sim.config import WorldConfig
from drivers.sim.world import World

from conftest import REPO, SMALL_WORLD, pairs

CELL = 0.05


@pytest.fixture(scope="module")
def world() -> World:
    return World.build(WorldConfig(**tomllib.loads(SMALL_WORLD)))


def obstacles(world: World, half: float = 5.5) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    mask = world.obstacle_mask(0.10, CELL, (-half, half), (-half, half))
    centres = -half + (np.arange(mask.shape[0]) + 0.5) * CELL
    return mask, centres, centres


def open_goal(world: World, distance: tuple[float, float]) -> tuple[float, float]:
    """A point at the given distance from the start with at least 1 m of clear ground around it."""
    mask, xs, ys = obstacles(world)
    clearance = distance_transform_edt(~mask) * CELL
    x, y = np.meshgrid(xs, ys)
    r = np.hypot(x, y)
    ok = (clearance > 1.0) & (r > distance[0]) & (r < distance[1]) & (x > 0)
    row, col = np.argwhere(ok)[len(np.argwhere(ok)) // 2]
    return round(float(xs[col]), 2), round(float(ys[row]), 2)


def rock_goal(world: World) -> tuple[float, float]:
    """The centre of the tallest rock 2-2.8 m from the start."""
    mask, xs, ys = obstacles(world)
    x, y = np.meshgrid(xs, ys)
    r = np.hypot(x, y)
    height = np.where((r > 2.0) & (r < 2.8), world.protrusion_at(x, y), 0.0)
    row, col = np.unravel_index(np.argmax(height), height.shape)
    assert height[row, col] > 0.15, "the test world needs a rock near the start"
    return round(float(xs[col]), 2), round(float(ys[row]), 2)


def product_of(server, reply: str):
    return server.data_dir / "products" / re.search(r"product=(\S+)", reply).group(1)


def path_length(path: list[list[float]]) -> float:
    return float(np.sum(np.linalg.norm(np.diff(np.asarray(path)[:, :2], axis=0), axis=1))) if len(path) > 1 else 0.0


def test_navigate_arrives_without_touching_a_rock(server_factory, world):
    """... and with navigation.toml orient, looks along the heading between its maps (the other
    navigate tests run without)."""
    navigation = (REPO / "configs" / "navigation.toml").read_text()
    navigation, count = re.subn(r"^orient = .*$", "orient = true", navigation, flags=re.M)
    assert count == 1
    server = server_factory(configs={"navigation.toml": navigation})
    goal = open_goal(world, (4.0, 4.6))
    with server.connect() as c:
        tag = "nav"
        # Two drives of at most 3 m reach the goal; the look after the last one says so.
        c.send(f"@{tag} navigate --to {goal[0]},{goal[1]} --tolerance 0.3 --max-steps 2")
        reply, progress = c.reply(tag, timeout=600)
        # plan-path then plans on what navigate saw last, not on an older map (or none).
        back = pairs(c.command("plan-path --to 0,0", timeout=120))
    assert " OK " in reply, reply
    assert back["map"].startswith(product_of(server, reply).name + "/cycle-"), back
    fields = pairs(reply)
    assert int(fields["cycles"]) >= 2 and float(fields["remaining"]) <= 0.3
    # PROGRESS names the cycle and what it does.
    assert any("cycle 1: mapping" in line for line in progress) and any("driving" in line for line in progress)
    product = product_of(server, reply)
    for name in ("overview.png", "traverse.json", "path.csv", "truth/traverse.json", "cycle-01/hazard.tif",
                 "cycle-01/plan.png", "cycle-01/map-cloud.npy", "cycle-02/dem.tif"):
        assert (product / name).exists(), name
    traverse = json.loads((product / "traverse.json").read_text())
    truth = json.loads((product / "truth" / "traverse.json").read_text())
    assert traverse["outcome"] == "arrived" and truth["contacts"] == 0
    true_end = np.array(truth["path"][-1][:2])
    assert np.linalg.norm(true_end - goal) < 0.45
    # The map-corrected estimate is where the rover really is, within a few centimetres.
    assert np.linalg.norm(np.array(traverse["pose"][:2]) - true_end) < 0.12
    # The maps of the later cycles were aligned to the earlier ones.
    assert all(c["alignment"]["accepted"] for c in traverse["cycles"][1:])
    # An orient look began each cycle and came whenever the drive would take the rover more than a
    # metre (orient_step_m) from the last one, and after every part of a large turn: a keyframe
    # first, then visual odometry and the sun, where the next map found the rover. Looks within a
    # cycle are no more than the step apart (plus the drive error), and short legs share one.
    looks = traverse["orients"]
    assert {o["cycle"] for o in looks} == {c["cycle"] for c in traverse["cycles"]}
    assert len(looks) > len(traverse["cycles"])
    gaps = [math.dist((a["x"], a["y"]), (b["x"], b["y"])) for a, b in zip(looks[:-1], looks[1:], strict=True)
            if a["cycle"] == b["cycle"] and "x" in a and "x" in b]    # a refused look has no place
    assert gaps and max(gaps) < 1.1, looks
    assert len(looks) < len(traverse["cycles"]) + 2 * path_length(traverse["estimated_path"]) + 4, looks
    assert looks[0]["keyframe"] and any("cycle 2: orienting along the heading" in line for line in progress)
    measured = [o for o in looks[1:] if "sources" in o]
    assert len(measured) >= 0.7 * len(looks[1:]) and all(o["sources"][0] == "tof" for o in measured), looks
    # The sun's heading is fused unless the gate refuses it (a chain that went wrong disagrees with it).
    assert sum("sun" in o["sources"] for o in measured) >= 0.7 * len(measured), looks
    for cycle in traverse["cycles"][1:]:
        assert np.linalg.norm(np.array(cycle["pose_odometry"][:2]) - cycle["pose_true"][:2]) < 0.1, cycle


def test_break_stops_the_traverse_and_continue_finishes_it(server, world):
    goal = open_goal(world, (4.0, 4.6))
    with server.connect() as c:
        c.send(f"@nav navigate --to {goal[0]},{goal[1]}")
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline:  # wait until the rover drives
            line = c.read_line(timeout=60)
            if line.startswith("nav PROGRESS") and "driving" in line:
                break
        assert " ERR " not in line
        with server.connect() as other:
            assert " OK " in other.command("break")
        stopped, _ = c.reply("nav", timeout=300)
        assert "ERR 499" in stopped and "recovery=" in stopped
        reply = c.command("continue", timeout=600)
    assert " OK " in reply, reply
    truth = json.loads((product_of(server, reply) / "truth" / "traverse.json").read_text())
    path = np.array(truth["path"])[:, :2]
    # One continuous drive: no jump where the job stopped, no leg driven twice.
    assert np.max(np.linalg.norm(np.diff(path, axis=0), axis=1)) < 0.1
    assert np.linalg.norm(path[-1] - goal) < 0.45 and truth["contacts"] == 0


def test_a_goal_on_a_rock_is_refused_with_the_pictures(server, world):
    goal = rock_goal(world)
    with server.connect() as c:
        reply = c.command(f"navigate --to {goal[0]},{goal[1]} --tolerance 0.2", timeout=600)
        # The refused run's maps are whole: plan-path plans on them.
        back = pairs(c.command("plan-path --to 0,0", timeout=120))
    assert "ERR 400 bad-request navigate stopped: goal_blocked" in reply, reply
    product = product_of(server, reply)
    assert back["map"].startswith(product.name + "/cycle-"), back
    traverse = json.loads((product / "traverse.json").read_text())
    assert traverse["outcome"] == "goal_blocked" and (product / "overview.png").exists()
    assert (product / "cycle-01" / "plan.png").exists()


def test_with_a_real_rover_the_waypoints_go_to_the_gnc(server_factory, world):
    server = server_factory(configs={"navigation.toml": "drive = \"gnc\"\n"})
    goal = open_goal(world, (4.0, 4.6))
    with server.connect() as gnc, server.connect() as c:
        assert " OK " in gnc.command("subscribe navigate")
        c.send(f"@nav navigate --to {goal[0]},{goal[1]}")
        deadline = time.monotonic() + 300
        event = ""
        while not event.startswith("* EVENT navigate") and time.monotonic() < deadline:
            event = gnc.read_line(timeout=300)
        assert "cycle=1" in event, event
        waypoints = re.search(r'waypoints="?([^"]+)"?', event).group(1).split()
        x, y = (float(v) for v in waypoints[-1].split(","))
        # The GNC drove there (here: it says so) and reports; navigate maps again from that pose.
        assert " OK " in gnc.command(f"pose {x},{y},0")
        while time.monotonic() < deadline:
            line = c.read_line(timeout=300)
            if "cycle 2: mapping" in line:
                break
        assert "cycle 2: mapping" in line
        # The first cycle's workflow checkpoints go once the second maps: its maps are in the product.
        working = server.data_dir / "recovery" / re.search(r"job=(\S+)", event).group(1)
        while ((working / "cycle-01").exists() or not (working / "cycle-02").exists()) \
                and time.monotonic() < deadline:
            time.sleep(0.2)
        assert not (working / "cycle-01").exists() and (working / "cycle-02").exists()
        assert " OK " in gnc.command("break")
        assert "ERR 499" in c.reply("nav", timeout=300)[0]


@pytest.mark.parametrize("options, field", [("--to 1", "to"), ("--to 1,2 --tolerance 0", "tolerance"),
                                            ("--to 1,2 --sensor lidar", "sensor"),
                                            ("--to 1,2 --max-steps 0", "max_steps")])
def test_bad_options_name_the_field(shared_server, options, field):
    """Refused before anything runs, so the four cases ask one server."""
    with shared_server.connect() as c:
        reply = c.command(f"navigate {options}")
    assert reply.split()[1:3] == ["ERR", "400"] and (field in reply or field.replace("_", "-") in reply), reply


def first_drive(server, goal) -> tuple[float, dict, list[str], dict]:
    """navigate for one cycle: the length driven, the cycle's record, PROGRESS, and the truth."""
    with server.connect() as c:
        c.send(f"@nav navigate --to {goal[0]},{goal[1]} --max-steps 1")
        reply, progress = c.reply("nav", timeout=600)
    product = product_of(server, reply)
    cycle = json.loads((product / "traverse.json").read_text())["cycles"][0]
    driven = float(np.linalg.norm(np.diff(np.array(cycle["drive"]), axis=0), axis=1).sum())
    return driven, cycle, progress, json.loads((product / "truth" / "traverse.json").read_text())


def test_a_sloppy_rover_drives_less_before_it_maps_again(server_factory, world):
    """A rover whose turns are off by 10 degrees (as its GNC states in navigation.toml) is sent only as
    far as that error keeps its body off the hazards, and told why; without the cut it is sent 3 m."""
    goal = open_goal(world, (4.0, 4.6))
    holes = "look_first = { tof = false, stereo = false }\n"    # that cut has a test of its own (below)
    uncut, cycle, progress, _ = first_drive(server_factory(configs={"navigation.toml": "drive_error_sigmas = 0\n"
                                                                    + holes}), goal)
    assert uncut == pytest.approx(3.0) and "drive_error_cut_m" not in cycle
    assert not any("mapping again" in line for line in progress)
    sloppy = server_factory(configs={"navigation.toml": "drive_error = { turn_noise_deg = 10.0 }\n" + holes})
    driven, cycle, progress, truth = first_drive(sloppy, goal)
    assert 0.15 <= driven < uncut - 0.5 and cycle["drive_error_cut_m"] > 0.1, cycle
    assert any(f"cycle 1: driving {driven:.2f} m and mapping again: farther, the drive error" in line
               for line in progress), progress
    assert truth["contacts"] == 0


def test_the_rover_stops_to_look_at_unknown_ground_before_it_drives_there(server_factory):
    """Once the rover stands beside ground (in the 0.9 m ring round the mast the TOF camera cannot see)
    no look can show what is there, and a rock's shadow can hide another rock: the first drive ends
    1.4 m (the blind ring and the border margin) short of the unknown ground its way crosses, and
    PROGRESS says why."""
    from rvs_server.navigation.commands import NavigationSettings
    from rvs_server.products.rasters import read_geotiff
    from toolbox.mapping.hazard import UNKNOWN
    goal = (-4.3, 0.0)
    server = server_factory(configs={"navigation.toml": "drive_error_sigmas = 0\n",
                                     "world.toml": "seed = 3\nsize_m = [12.0, 12.0]\n[rocks]\ncover = 0.16\n"})
    driven, cycle, progress, truth = first_drive(server, goal)
    assert 0.15 < driven < 2.9 and cycle["looks_first"], cycle
    assert any(f"cycle 1: driving {driven:.2f} m and mapping again: the path crosses ground no look has seen" in line
               for line in progress), progress
    folder = server.data_dir / "products" / cycle_product(server) / "cycle-01"
    code, spec = read_geotiff(folder / "hazard.tif")
    xs, ys = spec.centres()
    from_start = np.hypot(xs[None, :], ys[:, None])
    unlooked = (code == UNKNOWN) & (from_start > 2.0)          # no look from within close_look_m
    plan = json.loads((folder / "waypoints.json").read_text())
    route = np.array([[w["x"], w["y"]] for w in plan["waypoints"]])
    rows, cols = np.nonzero(unlooked)
    cells = np.column_stack([xs[cols], ys[rows]])
    # The waypoints stay within max_deviation_m of the A* cells, which the cut measures from.
    settings = NavigationSettings()
    clearance, deviation = settings.rover_radius_m + settings.hazard_margin_m.tof, settings.max_deviation_m
    off_route = distance_to_polyline(cells, route)
    end = np.array(cycle["drive"][-1])
    surely_crossed = cells[off_route <= clearance - deviation]
    maybe_crossed = cells[off_route <= clearance + deviation + spec.cell]
    assert len(surely_crossed), "the planned way should cross unknown ground"
    # 1.4 m short, to a cell or two (this map's grid and the fused one differ by up to a cell): outside the
    # 0.9 m blind ring round where the rover stops, with room.
    assert np.linalg.norm(surely_crossed - end, axis=1).min() >= 1.4 - 2 * spec.cell
    assert np.linalg.norm(maybe_crossed - end, axis=1).min() <= 1.4 + 2 * spec.cell
    assert truth["contacts"] == 0


def cycle_product(server) -> str:
    return max((p for p in (server.data_dir / "products").iterdir() if p.name.startswith("navigate-")),
               key=lambda p: p.stat().st_mtime).name


def distance_to_polyline(points: np.ndarray, line: np.ndarray) -> np.ndarray:
    best = np.full(len(points), np.inf)
    for a, b in zip(line[:-1], line[1:], strict=True):
        t = np.clip(((points - a) @ (b - a)) / max(float((b - a) @ (b - a)), 1e-12), 0.0, 1.0)
        best = np.minimum(best, np.linalg.norm(points - (a + t[:, None] * (b - a)), axis=1))
    return best


def test_navigate_fused_arrives_on_one_map_of_both_sensors(server, world):
    """--sensor fused: each cycle maps with the SR4000 and the stereo pair at the same views
    (workflows/navigate-fused.yaml), the TOF's cloud aligned to the map and the stereo's following it."""
    goal = open_goal(world, (4.0, 4.6))
    with server.connect() as c:
        c.send(f"@nav navigate --to {goal[0]},{goal[1]} --sensor fused --tolerance 0.3 --max-steps 3")
        reply, _ = c.reply("nav", timeout=900)
        plan = pairs(c.command("plan-path --to 0,0 --sensor fused", timeout=120))
    assert " OK " in reply, reply
    product = product_of(server, reply)
    assert plan["map"].startswith(product.name + "/cycle-"), plan
    traverse = json.loads((product / "traverse.json").read_text())
    truth = json.loads((product / "truth" / "traverse.json").read_text())
    assert traverse["outcome"] == "arrived" and truth["contacts"] == 0
    assert np.linalg.norm(np.array(truth["path"][-1][:2]) - goal) < 0.45
    assert all(c["alignment"]["accepted"] for c in traverse["cycles"][1:])
    for cycle in traverse["cycles"]:      # both sensors in every cycle's map, the stereo bias measured
        assert {"grid_tof", "aligned_stereo", "grid_stereo", "fused"} <= set(cycle["steps"]), cycle["steps"]
        assert cycle["fusion"]["bias_measured"] and cycle["fusion"]["stereo_only"] > 0, cycle["fusion"]
