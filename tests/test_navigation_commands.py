"""plan-path and pose against a real server on the simulated test bed."""
from __future__ import annotations

import csv
import json

import numpy as np
from scipy.ndimage import distance_transform_edt

from conftest import pairs
from rvs_server.rasters import read_geotiff


def clear_goal(product) -> tuple[float, float]:
    """A known cell 2-3 m ahead, at least 0.8 m from any hazard or unknown cell."""
    code, spec = read_geotiff(product / "hazard.tif")
    clearance = distance_transform_edt(code == 0) * spec.cell
    xs, ys = spec.centres()
    x, y = np.meshgrid(xs, ys)
    ok = (clearance > 0.8) & (np.hypot(x, y) > 2.0) & (np.hypot(x, y) < 3.0)
    row, col = np.argwhere(ok)[0]
    return float(xs[col]), float(ys[row])


def test_plan_path_needs_a_map_then_plans_on_it(server):
    with server.connect() as c:
        assert "ERR 409 wrong-mode no tof map yet" in c.command("plan-path --to 2,0")
        c.command("dem-full-tof --pan -60:60 --output arc", timeout=300)
        goal = clear_goal(server.data_dir / "products" / "arc")
        line = c.command(f"plan-path --to {goal[0]:.2f},{goal[1]:.2f} --output route", timeout=120)
    reply = pairs(line)
    assert reply["map"] == "arc" and int(reply["waypoints"]) >= 2 and int(reply["drivable"]) >= 2
    product = server.data_dir / "products" / reply["product"]
    data = json.loads((product / "waypoints.json").read_text())
    assert data["found"] and abs(data["waypoints"][-1]["x"] - goal[0]) < 0.1
    with open(product / "waypoints.csv") as handle:
        assert len(list(csv.DictReader(handle))) == int(reply["waypoints"])
    for name in ("plan.png", "plan-ortho.png", "cost.tif", "product.json"):
        assert (product / name).exists()


def test_bad_goals_are_refused_before_anything_is_planned(server):
    with server.connect() as c:
        c.command("dem-full-tof --pan -60:60 --output arc", timeout=300)
        reply = c.command("plan-path --to 2,0 --weight 1.5")
        assert "ERR 400" in reply and "--weight" in reply
        reply = c.command("plan-path --to 500,500 --output nowhere", timeout=120)
        assert "ERR 400 bad-request --to 500,500 is 707.1 m from the start; the planner reaches 100 m" in reply
        assert "ERR 400" in c.command("navigate --to 0,150") and "reaches 100 m" in c.command("navigate --to 0,150")
    assert not (server.data_dir / "products" / "nowhere").exists()


def test_pose_sets_the_estimate(server):
    with server.connect() as c:
        assert pairs(c.command("pose 1.5,-2,45")) == {"x": "1.500", "y": "-2.000", "heading": "45.00"}
        assert "ERR 400" in c.command("pose 1,2")
        assert "ERR 400" in c.command("pose 1,2,nan")
