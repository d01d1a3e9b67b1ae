"""The guard: while hazard detection runs, every simulated drive asks it before each 5 cm sample.

Two rules, both in the distance the rover drives rather than in time, so they hold at any
simulation speed-up and on a real rover alike:
- it never drives blind: at least one frame taken since this move began, and the newest frame taken
  no more than `blind` metres back (speed x (1/rate + the latency budget)); otherwise it stands and
  waits, and after `max_blind_s` of wall-clock time it stops rather than drive on unseen ground;
- a hazard the frames saw (HazardMemory: also ground that has since passed below the sensor's view)
  that the footprint would cover within the stop distance, and within what is left of this leg,
  stops it.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

from rvs_server.devices.rover import DriveGuard, DrivingJob
from toolbox.geometry import RoverPose
from toolbox.mapping import hazard as hazard_codes

if TYPE_CHECKING:
    from rvs_server.activities import ActivityHost
    from toolbox.mapping.corridor import Hit

    from .record import FrameLog
    from .settings import HazardSettings

WAIT_STEP_S = 0.05   # simulated seconds between two looks for a fresh frame


@dataclass(frozen=True)
class Seen:
    """The newest processed frame: when it was taken (simulated seconds) and from where."""

    sim_s: float
    pose: RoverPose


class Watch(Protocol):
    """What the guard asks of the loop that watches the path (activity.HazardActivity): a protocol, so
    the guard and the loop do not import each other."""

    @property
    def settings(self) -> HazardSettings: ...

    @property
    def rate_hz(self) -> float: ...

    @property
    def stop_distance(self) -> float: ...

    @property
    def frames(self) -> int: ...

    @property
    def newest(self) -> Seen | None: ...

    @property
    def log(self) -> FrameLog: ...

    @property
    def server(self) -> ActivityHost: ...

    def nearest(self, pose: tuple[float, float, float], direction: int, max_distance: float) -> Hit | None: ...

    def blind_reason(self, since_s: float, pose: RoverPose) -> str: ...


def causes(code: int) -> str:
    """The hazard code's causes as words: 'step', 'slope and step'."""
    words = [name for bit, name in ((hazard_codes.SLOPE, "slope"), (hazard_codes.STEP, "step"),
                                    (hazard_codes.ROUGHNESS, "rough ground")) if code & bit]
    return " and ".join(words) or "hazard"


class HazardGuard(DriveGuard):
    name = "hazard"

    def __init__(self, activity: Watch):
        self.activity = activity
        self.direction = 1          # of the drive in progress: the activity reports along it

    def check(self, job: DrivingJob, pose: RoverPose, direction: int, remaining_m: float, speed_m_s: float,
              started_s: float) -> str | None:
        self.direction = direction
        activity = self.activity
        settings = activity.settings
        blind = max(0.05, speed_m_s * (1.0 / activity.rate_hz + settings.latency_budget_s))
        # The rover stands while it waits, so waiting is safe; the limit is wall-clock time, because
        # the frames' processing is (with the simulation sped up, a 0.2 s hiccup of the host would be
        # 10 simulated seconds, and a stop for nothing).
        deadline = time.monotonic() + settings.max_blind_s
        while True:
            newest = activity.newest
            if newest is not None and newest.sim_s >= started_s and \
                    math.dist((newest.pose.x, newest.pose.y), (pose.x, pose.y)) <= blind:
                break
            if time.monotonic() >= deadline:
                why = activity.blind_reason(started_s, pose)
                return (f"no hazard frame within {blind:.2f} m for {settings.max_blind_s:.1f} s ({why}); the guard "
                        f"does not drive on unseen ground")
            job.sleep(WAIT_STEP_S)
        hit = activity.nearest((pose.x, pose.y, pose.heading), direction, min(activity.stop_distance, remaining_m))
        if hit is None:
            return None
        return (f"{causes(hit.cause)} {hit.distance:.2f} m ahead at {hit.x:.2f},{hit.y:.2f} (within the stop "
                f"distance {activity.stop_distance:.2f} m)")

    def stopped(self, sentence: str, estimate: RoverPose, truth: dict | None) -> None:
        activity = self.activity
        activity.log.stop({"seq": activity.frames, "sim_s": activity.server.clock.now(), "reason": sentence,
                           "x": estimate.x, "y": estimate.y, "heading_deg": math.degrees(estimate.heading),
                           "truth": truth})
