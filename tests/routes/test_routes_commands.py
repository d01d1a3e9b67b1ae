"""drive, route-record, route-follow, route-connect, route-list, route-go and sun against a real server on
the simulated test bed (20 m world, the forward camera), scored against the simulator's truth.

The rover teaches a route of three legs, repeats it backward and forward (once under a moved sun),
teaches a second route from the first one's end, and the two are joined by route-connect and
travelled by route-go from the start of the first to the end of the second. Routes survive a restart.
"""
from __future__ import annotations

import itertools
import json
import math
from pathlib import Path

from conftest import REPO, WIDE_WORLD, pairs

TAGS = itertools.count(1)
WORLD = WIDE_WORLD


def command(client, line: str, timeout: float = 300.0) -> tuple[str, list[str]]:
    tag = f"r{next(TAGS)}"
    client.send(f"@{tag} {line}")
    return client.reply(tag, timeout)


def true_path(products: Path, product: str) -> list[list[float]]:
    return json.loads((products / product / "truth" / "path.json").read_text())["path"]


def deviation(path: list[list[float]], taught: list[list[float]]) -> float:
    """Largest distance of a driven path's samples from the taught path's samples (both every 5 cm)."""
    return max(min(math.dist(p[:2], q[:2]) for q in taught) for p in path)


def test_teach_repeat_connect_and_go(server_factory):
    server = server_factory(configs={"world.toml": WORLD})
    products = server.data_dir / "products"
    with server.connect(timeout=600) as c:
        # Bad input names the field and changes nothing.
        assert "ERR 400" in c.command("drive --forward 1 --turn 10") and "exactly one" in c.command("drive")
        assert "ERR 400" in c.command("route-record start")                      # --name missing
        assert "ERR 409 wrong-mode" in c.command("route-record stop")
        assert "ERR 400" in c.command("route-follow --name nothing")
        assert "ERR 400" in c.command("route-record start --name ../evil")

        line, _ = command(c, "route-record start --name east")
        assert " OK " in f" {line} " and pairs(line)["state"] == "recording", line
        for action in ("--forward 2", "--turn 40", "--forward 2"):
            line, _ = command(c, f"drive {action}")
            assert pairs(line)["route"] == "east", line
        line, _ = command(c, "route-record stop")
        stop = pairs(line)
        assert stop["triplets"] == "3" and abs(float(stop["length"]) - 4.0) < 1e-6, line
        assert 0 < float(stop["bytes_per_m"]) < 200_000, line
        taught = true_path(products, stop["product"])
        start, end = taught[0], taught[-1]
        assert (products / stop["product"] / "places.png").exists()

        # Back along it, then forward again: each time within 0.25 m of the place, never far off the way.
        line, progress = command(c, "route-follow --name east --reverse")
        assert " OK " in f" {line} " and progress, line
        back = true_path(products, pairs(line)["product"])
        assert math.dist(back[-1][:2], start[:2]) < 0.25
        line, _ = command(c, "route-follow --name east")
        assert " OK " in f" {line} ", line
        forward = true_path(products, pairs(line)["product"])
        assert math.dist(forward[-1][:2], end[:2]) < 0.25
        assert deviation(forward, taught) < 0.4

        # A moved sun (shadows change) and the default matcher still finds its way back.
        assert pairs(command(c, "sun --azimuth 175 --elevation 55")[0])["azimuth"] == "175"
        line, _ = command(c, "route-follow --name east --reverse")
        assert " OK " in f" {line} ", line
        assert math.dist(true_path(products, pairs(line)["product"])[-1][:2], start[:2]) < 0.3
        command(c, "sun --azimuth 135 --elevation 35")

        # A second route from the first one's end; connect; go from the first's start to the second's end.
        line, _ = command(c, "route-follow --name east")
        assert " OK " in f" {line} ", line
        command(c, "route-record start --name north")
        for action in ("--turn 60", "--forward 2"):
            command(c, f"drive {action}")
        line, _ = command(c, "route-record stop")
        north_end = true_path(products, pairs(line)["product"])[-1]
        line, _ = command(c, "route-connect")
        assert int(pairs(line)["links"]) >= 1 and "east:3=north:0" in pairs(line)["added"], line
        listing = pairs(c.command("route-list"))
        assert listing["count"] == "2" and "links=" in listing["route.east"], listing
        for back in ("north", "east"):
            line, _ = command(c, f"route-follow --name {back} --reverse")
            assert " OK " in f" {line} ", line
        line, _ = command(c, "route-go --to north:2")
        go = pairs(line)
        assert " OK " in f" {line} " and go["from"] == "east:0" and go["segments"] == "2", line
        assert math.dist(true_path(products, go["product"])[-1][:2], north_end[:2]) < 0.3
    # The routes live in the data directory's database: a new server knows them.
    server.stop()
    again = server_factory(data_dir=server.data_dir)
    with again.connect(timeout=60) as c:
        listing = pairs(c.command("route-list"))
        assert listing["count"] == "2" and listing["route.east"].startswith("finished legs=3"), listing


def test_a_route_with_no_action_cannot_be_stopped(server_factory):
    server = server_factory(configs={"world.toml": WORLD})
    with server.connect(timeout=300) as c:
        assert " OK " in c.command("route-record start --name empty", timeout=300)
        refused = c.command("route-record stop")
        assert "ERR 409 wrong-mode" in refused and "has no action yet" in refused, refused
        assert " OK " in c.command("drive --forward 0.5", timeout=300)          # still recording
        assert pairs(c.command("route-record stop", timeout=300))["triplets"] == "1"


def test_a_drive_leg_followed_with_orient_looks_keeps_to_its_line(server_factory):
    """routes.toml orient: the drive leg is made in parts with a TOF orient look after each, each part
    aimed back at the leg's line; here backing up (the route followed in reverse from where it
    ends), so the rear is what is steered. This world's ground is smooth, where ICP may slide on a
    short part: the wheel check refuses that look (dead reckoning stands in)."""
    routes = (REPO / "configs" / "routes.toml").read_text()
    assert "orient = false" in routes
    server = server_factory(configs={"world.toml": WORLD,
                                     "routes.toml": routes.replace("orient = false", "orient = true")})
    products = server.data_dir / "products"
    with server.connect(timeout=600) as c:
        command(c, "route-record start --name line")
        command(c, "drive --forward 3")
        line, _ = command(c, "route-record stop")
        taught = true_path(products, pairs(line)["product"])
        line, _ = command(c, "route-follow --name line --reverse")
        assert " OK " in f" {line} ", line
        follow = json.loads((products / pairs(line)["product"] / "follow.json").read_text())
        # Two looks before the leg (the chain's first, then one that fuses the sun) and one after each
        # of its parts (2.4 m blind: three parts of at most 1 m).
        assert follow["orient_looks"] == 5 and len(follow["orient_refused"]) <= 1, follow
        driven = true_path(products, pairs(line)["product"])
        assert math.dist(driven[-1][:2], taught[0][:2]) < 0.25 and deviation(driven, taught) < 0.3
