"""plan-path and pose against a real server on the simulated test bed."""
from __future__ import annotations

import csv
import json

import numpy as np
from scipy.ndimage import distance_transform_edt

from rvs_server.products.rasters import read_geotiff

from conftest import pairs


def clear_goal(product, max_y: float = np.inf) -> tuple[float, float]:
    """A known cell 2-3 m away (y at most max_y), at least 0.8 m from any hazard or unknown cell."""
    code, spec = read_geotiff(product / "hazard.tif")
    clearance = distance_transform_edt(code == 0) * spec.cell
    xs, ys = spec.centres()
    x, y = np.meshgrid(xs, ys)
    ok = (clearance > 0.8) & (np.hypot(x, y) > 2.0) & (np.hypot(x, y) < 3.0) & (y <= max_y)
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
        # The default operating area is the simulated world (12 m square, whole mesh blocks).
        assert "ERR 400 bad-request --to 500,500 is outside the operating area: x -6" in reply, reply
        assert "(navigation.toml operating_area)" in reply
        assert "is outside the operating area" in c.command("navigate --to 0,150")
        # A map file removed by hand while the server runs: named, and the server carries on.
        (server.data_dir / "products" / "arc" / "hazard.tif").unlink()
        reply = c.command("plan-path --to 2,0 --output gone", timeout=120)
        assert "ERR 409 wrong-mode products/arc/hazard.tif was removed while" in reply and "plan-path" in reply
        assert c.command("status").split()[1] == "OK"
    assert not (server.data_dir / "products" / "nowhere").exists()
    assert "internal error" not in "".join(p.read_text() for p in (server.data_dir / "logs").iterdir())


def test_without_an_operating_area_the_planner_reach_still_bounds_goals(server_factory):
    server = server_factory(configs={"navigation.toml": 'operating_area = "none"\n'})
    with server.connect() as c:
        reply = c.command("plan-path --from 0,0 --to 500,500")
        assert "ERR 400 bad-request --to 500,500 is 707.1 m from the start; the planner reaches 100 m" in reply
        assert "reaches 100 m" in c.command("navigate --to 0,150")


def test_plan_path_keeps_inside_the_operating_area(server_factory):
    server = server_factory(configs={"navigation.toml": "operating_area = { x = [-6, 6], y = [-6, 0.8] }\n"})
    with server.connect() as c:
        assert "--to 2,1 is outside the operating area: x -6:6, y -6:0.8" in c.command("plan-path --to 2,1")
        assert "--from 0,3 is outside the operating area" in c.command("plan-path --from 0,3 --to 0,0")
        c.command("dem-full-tof --pan -60:60 --output arc", timeout=300)
        goal = clear_goal(server.data_dir / "products" / "arc", max_y=0.4)
        reply = pairs(c.command(f"plan-path --to {goal[0]:.2f},{goal[1]:.2f}", timeout=120))
    product = server.data_dir / "products" / reply["product"]
    cost, spec = read_geotiff(product / "cost.tif")
    _, ys = spec.centres()
    # North of y = 0.8 is a hazard, grown by the rover's clearance (0.4 m) like a rock.
    assert np.isnan(cost[ys > 0.8 - 0.4 + spec.cell]).all()
    waypoints = json.loads((product / "waypoints.json").read_text())["waypoints"]
    assert max(w["y"] for w in waypoints) <= 0.4 + spec.cell
