"""Following an image-based route (seeds/image-based-route-maps.txt, sec. 3.2-3.3), I/O free.

A route is a chain of legs (image before, action, image after). The paper's rover repeats each
action until the live view matches the image after, and makes small "adjust" actions when the view
is close but off; it reports two weak spots: adjustment fails for large differences, and a lost
rover stays lost. Here each leg is followed as

    1. heading check  the live view against the leg's image before; the matcher's horizontal shift
                      is a heading error (heading_offset) that a turn removes (the paper's adjust);
    2. the action     a turn is made whole (and if its image after is not seen, the rover looks a
                      few degrees left and right for it); a drive is made blind for most of its length (odometry
                      is good over a leg), then
    3. approach       the live view against the image after: heading corrected as in 1, and the
                      scale of the match (live over stored size: < 1 means still short of the
                      place) converted into the remaining distance with the scene's typical depth,
                      until the scale is within tolerance; a leg whose image after is not seen is
                      driven on in small steps up to an overshoot limit;
    4. recovery       a leg that ends without a match is not yet lost: the live view is ranked
                      against the nearby places of the route, and following resumes from the one
                      it matches (so a skipped or repeated leg is caught). Only then does it fail,
                      with the last place matched.

The rover is anything with `look()` (the matcher's descriptor of the live view), `act(kind, value)`
(kind forward / backward in metres >= 0, turn in radians CCW), `blind(kind, metres)` (the blind part
of a drive leg) and `focal_px`. The follower is the
same for a simulated and a real rover, for either matcher, and for routes followed backward (the
store reverses a route's legs: actions reversed, images swapped, the camera still facing forward,
so the scale rule holds unchanged).
"""
from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

from toolbox.routes.match import MatchResult, PlaceMatcher, heading_offset


class RouteRover(Protocol):
    focal_px: float

    def look(self) -> Any: ...

    def act(self, kind: str, value: float) -> None: ...

    def blind(self, kind: str, metres: float) -> None:
        """The blind part of a drive leg (forward or backward, metres >= 0): a rover that measures its
        own motion (visual odometry) keeps it on the leg's line; plain act otherwise."""


@dataclass(frozen=True)
class Leg:
    """One triplet as the follower needs it: the descriptors of its two images and its action."""

    before: Any
    kind: str           # forward | backward | turn
    value: float        # metres (>= 0) or radians (CCW)
    after: Any


@dataclass(frozen=True)
class FollowParams:
    blind_fraction: float = 0.8        # of a drive made before looking for the image after
    scene_depth_m: float = 4.0         # typical depth of matched features: scale error -> distance
    scale_tolerance: float = 0.03      # arrived when |scale - 1| is below this ...
    min_step_m: float = 0.03           # ... or the step it asks for is shorter than this
    max_step_m: float = 0.4            # longest single approach step
    search_step_fraction: float = 0.1  # of the leg, driven per step while the image after is not seen
    overshoot: float = 0.5             # ... up to this fraction of the leg beyond its length
    heading_tolerance_deg: float = 1.0
    max_heading_corrections: int = 3
    max_approach_steps: int = 10
    recovery_window: int = 3           # places before and after the expected one ranked when lost
    scan_deg: tuple[float, ...] = (8.0, -8.0, 16.0, -16.0)   # looked at when a turn's image after is not seen
    backing_gain: float = 2.0          # backing up, the parallax (near minus far shift) steers this much the other way

    def __post_init__(self) -> None:
        if not 0.0 <= self.blind_fraction <= 1.0:
            raise ValueError(f"blind_fraction must be in [0, 1], got {self.blind_fraction!r}")
        for name in ("scene_depth_m", "scale_tolerance", "max_step_m", "search_step_fraction"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)!r}")


@dataclass
class LegReport:
    index: int
    kind: str
    value: float
    matched: bool
    similarity: float
    approach_steps: int = 0
    heading_corrections: int = 0
    travelled_m: float = 0.0
    resumed_at: int | None = None      # recovery: the place the live view matched instead


@dataclass
class FollowReport:
    success: bool
    reason: str                        # "" on success; lost_at_start, lost
    last_matched: int | None           # the last place (0..n) the live view matched
    legs: list[LegReport] = field(default_factory=list)

    @property
    def message(self) -> str:
        if self.success:
            return ""
        where = "no place" if self.last_matched is None else f"place {self.last_matched}"
        return f"{self.reason}: the live view matched no image near the expected one; last matched {where}"


Progress = Callable[[int, int, str], None]


class RouteFollower:
    def __init__(self, legs: Sequence[Leg], matcher: PlaceMatcher, rover: RouteRover,
                 params: FollowParams = FollowParams(), progress: Progress | None = None):
        self.legs, self.matcher, self.rover, self.params = list(legs), matcher, rover, params
        self.progress = progress or (lambda done, total, message: None)
        self.places = [leg.before for leg in self.legs] + ([self.legs[-1].after] if self.legs else [])

    # ---------------------------------------------------------------------------------- the route
    def run(self) -> FollowReport:
        report = FollowReport(True, "", None)
        if not self.legs:
            return report
        start = self.find_place(0, 0, len(self.places) - 1)
        if start is None:
            return FollowReport(False, "lost_at_start", None)
        report.last_matched = start
        index = start
        while index < len(self.legs):
            leg = self.legs[index]
            self.progress(index, len(self.legs), f"leg {index + 1}/{len(self.legs)}: {leg.kind} "
                          f"{math.degrees(leg.value) if leg.kind == 'turn' else leg.value:.2f}"
                          f"{' deg' if leg.kind == 'turn' else ' m'}")
            leg_report = self.follow_leg(index, leg)
            report.legs.append(leg_report)
            if leg_report.matched:
                index += 1
                report.last_matched = index
                continue
            resumed = self.find_place(index + 1, max(0, index + 1 - self.params.recovery_window),
                                      min(len(self.places) - 1, index + 1 + self.params.recovery_window))
            if resumed is None:
                return FollowReport(False, "lost", report.last_matched, report.legs)
            leg_report.resumed_at = resumed
            report.last_matched = index = resumed
        return report

    def follow_leg(self, index: int, leg: Leg) -> LegReport:
        report = LegReport(index, leg.kind, leg.value, False, 0.0)
        if leg.kind == "turn":
            backing = self.backing_from(index + 1)   # corrected as the drive after it will be made
            self.rover.act("turn", leg.value)
            result = self.settle(leg.after, report, backing)
            result = self.scan(leg.after, result, report, backing)
        else:
            result = self.approach(leg, report)
        report.matched, report.similarity = bool(result.same_place), float(result.similarity)
        return report

    # ---------------------------------------------------------------------------------- steps
    def settle(self, target: Any, report: LegReport | None = None, backing: bool = False) -> MatchResult:
        """The live view against a target, turning away the heading error the match shows.

        A shift is the heading error plus the parallax of a sideways offset, larger on near points.
        Driving forward, turning the whole shift away points the rover back onto the path, as in
        teach and repeat. Backing up, that turn would steer it farther off: then the far points'
        shift (mostly heading) is turned away and the parallax turns the other way, so the rear
        points back onto the path instead (backing_gain, since the far points are not at infinity)."""
        result = self.matcher.match(self.rover.look(), target)
        for _ in range(self.params.max_heading_corrections):
            if not result.same_place or result.shift_px is None:
                break
            shift = result.shift_px[0]
            if backing and result.far_shift_px is not None:
                far = result.far_shift_px[0]
                shift = far + self.params.backing_gain * (far - shift)
            error = heading_offset(shift, self.rover.focal_px)
            if abs(math.degrees(error)) <= self.params.heading_tolerance_deg:
                break
            self.rover.act("turn", -error)
            if report is not None:
                report.heading_corrections += 1
            result = self.matcher.match(self.rover.look(), target)
        return result

    def scan(self, target: Any, result: MatchResult, report: LegReport, backing: bool = False) -> MatchResult:
        """Not seen after a turn: look left and right in growing steps (a turn made from a place a
        little off, or with a slipping wheel, ends a few degrees away), back where it was if not."""
        if result.same_place:
            return result
        at = 0.0
        for offset in self.params.scan_deg:
            self.rover.act("turn", math.radians(offset - at))
            at = offset
            result = self.settle(target, report, backing)
            if result.same_place:
                return result
        self.rover.act("turn", math.radians(-at))
        return result

    def approach(self, leg: Leg, report: LegReport) -> MatchResult:
        """Drive the leg: blind for most of it, then until the image after is matched at its scale."""
        p = self.params
        sign = 1.0 if leg.kind == "forward" else -1.0      # along the body's x axis
        backing = sign < 0
        self.settle(leg.before, report, backing)
        blind = p.blind_fraction * leg.value
        if blind > 1e-6:
            self.rover.blind(leg.kind, blind)
            report.travelled_m += blind
        along = blind                                       # along the leg's own direction
        search_step = max(p.min_step_m, p.search_step_fraction * leg.value)
        fine_steps = 0
        while True:
            result = self.settle(leg.after, report, backing)
            if result.same_place:
                if result.scale is None:                    # a matcher without scale: seen is arrived
                    return result
                # Scale s = Z / (Z + d): still d short of the place (d < 0: past it).
                step = p.scene_depth_m * (1.0 / result.scale - 1.0)
                if (abs(result.scale - 1.0) <= p.scale_tolerance or abs(step) < p.min_step_m
                        or fine_steps >= p.max_approach_steps):
                    return result
                step = max(-p.max_step_m, min(p.max_step_m, step))
                fine_steps += 1
            elif along < (1.0 + p.overshoot) * leg.value - 1e-9:
                step = sign * search_step                   # not seen yet: on along the leg
            else:
                return result
            self.drive(step, report)
            along += step * sign
            report.approach_steps += 1

    def drive(self, metres: float, report: LegReport) -> None:
        """Body-frame drive: positive forward."""
        if abs(metres) < 1e-6:
            return
        self.rover.act("forward" if metres > 0 else "backward", abs(metres))
        report.travelled_m += abs(metres)

    def backing_from(self, index: int) -> bool:
        """Is the next drive from leg `index` on a backward one?"""
        return next((leg.kind == "backward" for leg in self.legs[index:] if leg.kind != "turn"), False)

    def find_place(self, expected: int, first: int, last: int) -> int | None:
        """The place among first..last the live view matches (settling the heading on it), nearest
        the expected one on a tie; None if none."""
        live = self.rover.look()
        candidates = range(first, last + 1)
        results = {i: self.matcher.match(live, self.places[i]) for i in candidates}
        matched = [i for i, r in results.items() if r.same_place]
        if not matched:
            return None
        best = max(matched, key=lambda i: (results[i].similarity, -abs(i - expected)))
        self.settle(self.places[best], backing=self.backing_from(best))
        return best
