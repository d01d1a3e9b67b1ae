"""The route follower's logic (toolbox/routes_follow.py) and the route network (toolbox/routes_network.py).

The follower runs here against a rover on a line with a matcher that sees positions, so each rule is
checked exactly: the approach by scale, the heading correction from the shift, the overshoot limit,
the scan after a turn, and recovery at a nearby place. tests/routes/test_routes_commands.py runs it on
rendered images through the server.
"""
from __future__ import annotations

import math

import pytest

from toolbox.routes.follow import FollowParams, Leg, RouteFollower
from toolbox.routes.match import MatchResult
from toolbox.routes.network import NetworkLeg, NetworkLink, Segment, segments, shortest_way

DEPTH = 4.0      # the scene depth the fake matcher's scale implies (FollowParams.scene_depth_m)
FOCAL = 500.0


class LineRover:
    """A rover on a line: position x (metres) and heading h (radians), actions exact unless told."""

    focal_px = FOCAL

    def __init__(self, x=0.0, h=0.0, drive_scale=1.0, turn_error=0.0):
        self.x, self.h, self.drive_scale, self.turn_error = x, h, drive_scale, turn_error
        self.actions = []

    def look(self):
        return (self.x, self.h)

    def act(self, kind, value):
        self.actions.append((kind, value))
        if kind == "turn":
            self.h += value + self.turn_error
            self.turn_error = 0.0
        else:
            self.x += (value if kind == "forward" else -value) * self.drive_scale

    def blind(self, kind, metres):
        self.act(kind, metres)


class PositionMatcher:
    """Same place within 0.5 m and 10 degrees; scale Z / (Z + d) with d how far short the live view is;
    shift f tan(heading error)."""

    name = "position"

    def match(self, live, stored):
        (x, h), (sx, sh) = live, stored
        if abs(x - sx) > 0.5 or abs(h - sh) > math.radians(10):
            return MatchResult(False, 0.0)
        return MatchResult(True, 1.0 - abs(x - sx), shift_px=(FOCAL * math.tan(h - sh), 0.0),
                           scale=DEPTH / (DEPTH + (sx - x)), support=50)


def line_route(*actions):
    """Legs of a taught route on the line from x = 0, heading 0; places as (x, h)."""
    legs, x, h = [], 0.0, 0.0
    for kind, value in actions:
        nx, nh = (x + value, h) if kind == "forward" else (x - value, h) if kind == "backward" else (x, h + value)
        legs.append(Leg((x, h), kind, value, (nx, nh)))
        x, h = nx, nh
    return legs, (x, h)


def test_drive_error_is_corrected_by_the_image_after():
    legs, end = line_route(("forward", 2.0), ("forward", 2.0))
    rover = LineRover(drive_scale=0.9)                    # every drive 10 % short
    report = RouteFollower(legs, PositionMatcher(), rover).run()
    assert report.success and report.last_matched == 2
    assert abs(rover.x - end[0]) < 0.13                   # scale tolerance 0.03 at 4 m depth: 0.12 m
    assert all(leg.approach_steps >= 1 for leg in report.legs)


def test_heading_error_is_turned_away():
    legs, end = line_route(("forward", 2.0), ("turn", math.radians(30)), ("forward", 1.0))
    rover = LineRover(h=math.radians(6))
    report = RouteFollower(legs, PositionMatcher(), rover).run()
    assert report.success
    assert abs(rover.h - end[1]) <= math.radians(FollowParams().heading_tolerance_deg) + 1e-9
    kind, value = rover.actions[0]                         # the start's check turned it first
    assert kind == "turn" and value == pytest.approx(-math.radians(6))


def test_a_turn_that_misses_its_view_scans_for_it():
    legs, end = line_route(("turn", math.radians(40)),)
    rover = LineRover(turn_error=math.radians(14))        # beyond the matcher's 10 degrees
    report = RouteFollower(legs, PositionMatcher(), rover).run()
    assert report.success and abs(rover.h - end[1]) < math.radians(1.01)


def test_overshoot_limit_then_lost_with_the_last_place():
    legs, _ = line_route(("forward", 2.0), ("forward", 2.0))
    rover = LineRover(drive_scale=0.3)                    # the wheels slip: never gets there
    params = FollowParams(overshoot=0.5, recovery_window=0)
    report = RouteFollower(legs, PositionMatcher(), rover, params).run()
    assert not report.success and report.reason == "lost" and report.last_matched == 0
    assert "last matched place 0" in report.message
    driven = sum(v for k, v in rover.actions if k == "forward")
    assert driven <= 1.5 * 2.0 + 1e-9                     # stopped at the overshoot limit


def test_lost_at_start_and_recovery_at_a_later_place():
    legs, _ = line_route(("forward", 1.0), ("forward", 1.0), ("forward", 1.0))
    assert RouteFollower(legs, PositionMatcher(), LineRover(x=-5.0)).run().reason == "lost_at_start"
    # Starting at place 2 (2 m along): the follower finds it and does only the last leg.
    rover = LineRover(x=2.0)
    report = RouteFollower(legs, PositionMatcher(), rover).run()
    assert report.success and len(report.legs) == 1 and abs(rover.x - 3.0) < 0.13


def test_backward_legs_use_the_same_scale_rule():
    legs, _ = line_route(("forward", 2.0))
    back = [Leg(leg.after, "backward", leg.value, leg.before) for leg in reversed(legs)]
    rover = LineRover(x=2.0, drive_scale=1.1)
    report = RouteFollower(back, PositionMatcher(), rover).run()
    assert report.success and abs(rover.x) < 0.13


class PlaneRover:
    """A rover on the plane: x, y (metres) and heading h (radians CCW), actions exact."""

    focal_px = FOCAL

    def __init__(self, x=0.0, y=0.0, h=0.0):
        self.x, self.y, self.h = x, y, h
        self.actions = []

    def look(self):
        return (self.x, self.y, self.h)

    def act(self, kind, value):
        self.actions.append((kind, value))
        if kind == "turn":
            self.h += value
        else:
            step = value if kind == "forward" else -value
            self.x += step * math.cos(self.h)
            self.y += step * math.sin(self.h)

    def blind(self, kind, metres):
        self.act(kind, metres)


class ParallaxMatcher:
    """Views along +x from places on the x axis. A sideways offset e adds parallax f e / Z to the
    heading's shift: Z = 4 m for the matched points on average, 12 m for the far ones."""

    name = "parallax"

    def match(self, live, stored):
        (x, y, h), (sx, sy, sh) = live, stored
        if abs(x - sx) > 0.6 or abs(y - sy) > 1.0 or abs(h - sh) > math.radians(15):
            return MatchResult(False, 0.0)
        heading, offset = math.tan(h - sh), y - sy
        return MatchResult(True, 1.0 - abs(x - sx), shift_px=(FOCAL * (heading + offset / DEPTH), 0.0),
                           scale=DEPTH / (DEPTH + (sx - x)), support=50,
                           far_shift_px=(FOCAL * (heading + offset / 12.0), 0.0))


def test_backing_up_steers_the_rear_back_onto_the_path():
    """Backing up a straight route from 0.3 m beside its end: turning away the whole shift (as
    forward) would steer the rover off, the heading alone keeps the offset; the far points' shift
    with the parallax turned the other way brings it back."""
    places = [(2.0 * k, 0.0, 0.0) for k in range(7)]
    back = [Leg(places[k + 1], "backward", 2.0, places[k]) for k in reversed(range(6))]
    offsets = {}
    for gain in (2.0, 0.0):
        rover = PlaneRover(x=12.0, y=0.3)
        assert RouteFollower(back, ParallaxMatcher(), rover, FollowParams(backing_gain=gain)).run().success
        offsets[gain] = abs(rover.y)
    assert offsets[2.0] < 0.1 < 0.2 < offsets[0.0]
    # Forward, the whole shift steers: the same offset at the start is gone at the end.
    ahead = [Leg(places[k], "forward", 2.0, places[k + 1]) for k in range(6)]
    rover = PlaneRover(y=0.3)
    assert RouteFollower(ahead, ParallaxMatcher(), rover).run().success and abs(rover.y) < 0.1


def test_params_are_checked():
    with pytest.raises(ValueError, match="blind_fraction"):
        FollowParams(blind_fraction=1.5)


# ---------------------------------------------------------------------------------- the network
def test_shortest_way_through_a_link_and_backward_stretches():
    legs = [NetworkLeg("a", i, "forward", 2.0) for i in range(3)]
    legs += [NetworkLeg("b", 0, "turn", math.radians(90)), NetworkLeg("b", 1, "forward", 3.0)]
    links = [NetworkLink(("a", 2), ("b", 0))]
    segments_found, cost = shortest_way(legs, links, ("a", 0), ("b", 2), turn_cost_m=0.3, link_cost_m=0.5)
    assert segments_found == [Segment("a", 0, 2), Segment("b", 0, 2)]
    assert cost == pytest.approx(4.0 + 0.5 + 0.3 * math.pi / 2 + 3.0)
    back, _ = shortest_way(legs, links, ("b", 2), ("a", 1))
    assert back == [Segment("b", 2, 0), Segment("a", 2, 1)] and back[0].reverse
    assert shortest_way(legs, [], ("a", 0), ("b", 2)) is None
    assert shortest_way(legs, links, ("a", 1), ("a", 1)) == ([], 0.0)


def test_segments_split_at_links():
    assert segments([("a", 0), ("a", 1), ("b", 4), ("b", 3)]) == [Segment("a", 0, 1), Segment("b", 4, 3)]
