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
from typing import TYPE_CHECKING, Any, Protocol

from rvs_server.devices.rover import DriveGuard, DrivingJob
from toolbox.geometry import RoverPose
from toolbox.mapping import hazard as hazard_codes

if TYPE_CHECKING:
    from rvs_server.activities import ActivityHost
    from toolbox.mapping.corridor import Hit, Swept

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

    def swept(self, pose: tuple[float, float, float], turn: float, distance: float) -> Swept: ...


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
        self.last_hit: Hit | None = None     # what the last check stopped for (None: blind, or nothing)
        self.last_job = ""                   # its job's id, for the guard event

    def check(self, job: DrivingJob, pose: RoverPose, direction: int, remaining_m: float, speed_m_s: float,
              started_s: float) -> str | None:
        self.direction = direction
        self.last_hit, self.last_job = None, job.job.id
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
        self.last_hit = hit
        return (f"{causes(hit.cause)} {hit.distance:.2f} m ahead at {hit.x:.2f},{hit.y:.2f} (within the stop "
                f"distance {activity.stop_distance:.2f} m)")

    def stopped(self, sentence: str, estimate: RoverPose, truth: dict | None) -> None:
        activity = self.activity
        activity.log.stop({"seq": activity.frames, "sim_s": activity.server.clock.now(), "reason": sentence,
                           "x": estimate.x, "y": estimate.y, "heading_deg": math.degrees(estimate.heading),
                           "truth": truth})
        self._tell("stop", estimate, self.last_hit, sentence)

    def swept(self, job: DrivingJob, pose: RoverPose, turn: float, distance: float,
              unguarded: bool) -> tuple[str | None, dict[str, Any]]:
        """A turn on the spot or a backward drive checked, before it moves, against the ground the
        memory holds: a remembered hazard in the swept area refuses it; so does ground no frame saw
        (more than max_unseen_share of it), unless `unguarded`."""
        activity = self.activity
        swept = activity.swept((pose.x, pose.y, pose.heading), turn, distance)
        what = "turning on the spot" if turn else "backing up"
        sentence = None
        if swept.hit is not None:
            hit = swept.hit
            sentence = (f"{what} would sweep {causes(hit.cause)} at {hit.x:.2f},{hit.y:.2f} ({hit.distance:.2f} m "
                        f"{'from the centre' if turn else 'behind the rear edge'})")
        elif swept.unseen > activity.settings.max_unseen_share and not unguarded:
            sentence = (f"{what} would sweep ground no frame saw ({swept.unseen:.0%} of it; the sensor looks ahead, "
                        f"the rear and sides have none): look there first, or drive --unguarded")
        if sentence is not None:
            self.last_job = job.job.id
            self._tell("refused", pose, swept.hit, sentence)
        return sentence, {"swept_unseen": f"{swept.unseen:.2f}"}

    def _tell(self, action: str, pose: RoverPose, hit: Hit | None, sentence: str) -> None:
        """The `guard` event (PROTOCOL.md): every subscribed client and the PUB socket, so a GNC that
        sent the drive learns why it stopped and where the obstacle is."""
        self.activity.server.publish_threadsafe("guard", {
            "action": action, "job": self.last_job, "x": f"{pose.x:.3f}", "y": f"{pose.y:.3f}",
            "heading": f"{math.degrees(pose.heading):.2f}", "distance": f"{hit.distance:.2f}" if hit else "none",
            "hazard_x": f"{hit.x:.3f}" if hit else "none", "hazard_y": f"{hit.y:.3f}" if hit else "none",
            "cause": causes(hit.cause) if hit else "unseen", "reason": sentence})
