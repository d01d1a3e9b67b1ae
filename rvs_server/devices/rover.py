"""The rover: where the server believes it stands, who drives it, and its forward camera.

The pose estimate starts at the simulated rover's start pose with simulated devices (the initial
pose is given), else at 0,0; navigation corrects it from its maps, a simulated drive dead-reckons
it, and the GNC's `pose` command replaces it. Two drives sit behind one interface (`Drive`):

    simulated  the simulated rover turns, then drives straight, with its drive error
               (drivers/sim/motion.py); the estimate is dead-reckoned from what was commanded
    gnc        the waypoints or the action go out as a `navigate` event (the GNC interface is written
               here only), then the job waits for the GNC's `pose X,Y,HEADING`

Either way the estimate's roll and pitch after the move are what the rover can measure where it
stands (`RoverDevice.settle`), never the ones from before it, and its height follows the ground it
drove over (`climb` along the inclinometer's pitch, or the newest map's height under the wheels).

`RoverDevice.drive` is the one place that picks between them from a command family's setting
(auto | simulated | gnc). The simulator's truth (the true pose, the world's extent, the forward
camera's view) is reached through this device, never by a command module.

The rover is no entry of `Devices.items`: it has no driver to open or reset, and as one it would
add a line to every `status` and `reset` reply.
"""
from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any, ClassVar, Literal, Protocol

import numpy as np

from drivers.sim.forward_camera import ForwardCamera, ForwardCameraConfig
from drivers.sim.motion import dead_reckon, turn_and_distance
from drivers.sim.testbed import INCLINOMETER_NOISE_DEG
from toolbox.geometry import RoverPose
from toolbox.grid import GridSpec
from toolbox.mapping.attitude import attitude_on_ground, height_on_ground

from ..protocol import BadRequest, DeviceError, Timeout
from .sharing import DeviceSharing

if TYPE_CHECKING:
    from drivers.sim.clock import SimClock
    from drivers.sim.testbed import SimulatedTestbed

DriveMode = Literal["auto", "simulated", "gnc"]
POSE_POLL_S = 0.5
GROUND_RADIUS_M = 0.4   # the map's cells within this of the rover's centre carry its wheels (0.38 x 0.40 m apart)
NO_FORWARD_CAMERA = "the forward camera is the simulated rover's body-fixed camera and the devices are real"

__all__ = ["Drive", "DriveGuard", "DriveMode", "DriveStopped", "DrivingJob", "ForwardCamera", "ForwardCameraConfig",
           "GncDrive", "Moved", "Pace", "RoverDevice",
           "SimulatedDrive", "SunReading", "WorldEdge", "dead_reckon", "turn_and_distance"]


class JobId(Protocol):
    @property
    def id(self) -> str: ...


class DrivingJob(Protocol):
    """What a drive and its guards need of the job that moves the rover (jobs.JobContext gives it): a
    protocol, so the device layer imports nothing of the jobs."""

    @property
    def job(self) -> JobId: ...

    @property
    def clock(self) -> SimClock: ...

    def safe_point(self) -> None: ...

    def sleep(self, sim_seconds: float) -> None: ...

    def publish(self, topic: str, data: dict[str, Any]) -> None: ...


@dataclass(frozen=True)
class Pace:
    """What a command family's settings say about driving: the height above which a rock counts as
    a contact, and how long the GNC's pose is waited for. (The simulated rover's speeds are the
    rover's own: world.toml [rover_speed].)"""

    step_height_m: float
    pose_timeout_s: float


@dataclass(frozen=True)
class Moved:
    """One move done: the pose estimate after it and what the simulator saw on the way."""

    estimate: RoverPose
    commanded: tuple[float, float] | None   # (turn rad, distance m) dead-reckoned; None: the GNC's pose
    legs: int = 1                           # waypoints done by this move
    contacts: int = 0                       # simulated: samples whose footprint touched a true obstacle
    true_path: list[list[float]] = field(default_factory=list)  # simulated: true x, y, heading after the start


class WorldEdge(BadRequest):
    """The simulated rover would leave the simulated world (a real rover's ground does not end)."""


class DriveStopped(BadRequest):
    """A guard stopped the rover short of a hazard (PROTOCOL.md: `drive stopped: hazard: SENTENCE`).
    `moved` is the part of the move that was done; the pose estimate is where the rover stopped."""

    def __init__(self, guard: str, sentence: str, moved: Moved):
        super().__init__(f"drive stopped: {guard}: {sentence}")
        self.guard, self.sentence, self.moved = guard, sentence, moved


class DriveGuard(ABC):
    """What may stop a simulated drive between two of its samples: hazard detection installs one
    on the rover device while it runs (RoverDevice.guard)."""

    name: ClassVar[str]

    @abstractmethod
    def check(self, job: DrivingJob, pose: RoverPose, direction: int, remaining_m: float, speed_m_s: float,
              started_s: float) -> str | None:
        """Before the rover drives on from `pose` (direction +1 forward, -1 backward, remaining_m of
        this leg left, at speed_m_s, in a move begun at simulated time started_s): None to go on, or
        the sentence why it stops. May wait, in simulated time, for a fresh look ahead."""

    def stopped(self, sentence: str, estimate: RoverPose, truth: dict | None) -> None:  # noqa: B027  optional hook
        """The rover stopped for this guard: `truth` is the simulator's view of the stop, if any."""

    def swept(self, job: DrivingJob, pose: RoverPose, turn: float, distance: float,
              unguarded: bool) -> tuple[str | None, dict[str, Any]]:
        """Before a turn on the spot or a backward drive (`drive`): the sentence why it is refused, or
        None, and what the reply says of the swept ground. Default: nothing to say."""
        return None, {}


def climb(distance: float, pitch_before: float, pitch_after: float) -> float:
    """The rise (metres) of the rover's origin over one drive segment of `distance` metres along
    its heading (negative: backward), with the body's pitch read before and after it (radians, nose
    down positive, as RoverPose: the body's x axis climbs at -tan(pitch) per horizontal metre).

    Why: dead reckoning carries x, y and heading only, and every map places its points through the
    estimate's height; a drive up a 12-degree slope kept the height from before it and built the
    next map 0.21 m low per metre driven. The segments are short (sample_m, a few cm), so the mean
    of the two readings follows curved ground; the distance is horizontal, as dead_reckon's is."""
    return -distance * math.tan(0.5 * (pitch_before + pitch_after))


def action_motion(kind: str, value: float) -> tuple[float, float]:
    """(turn rad, distance m) of an action: turn by value, forward or backward value metres."""
    turn = value if kind == "turn" else 0.0
    distance = 0.0 if kind == "turn" else (value if kind == "forward" else -value)
    return turn, distance


class Drive(ABC):
    """How the rover carries out motion. Both take one action (route teaching and repeating) or a
    list of waypoints (navigate); either way the rover device's pose estimate follows."""

    simulated: ClassVar[bool]

    def __init__(self, rover: RoverDevice):
        self.rover = rover

    @abstractmethod
    def act(self, job: DrivingJob, kind: str, value: float, pace: Pace) -> Moved:
        """One action: kind turn (value radians, counter-clockwise), forward or backward (metres)."""

    @abstractmethod
    def waypoints(self, job: DrivingJob, waypoints: Sequence[Sequence[float]], start: RoverPose, pace: Pace,
                  goal: tuple[float, float], cycle: int,
                  announce: Callable[[Sequence[float] | None], None]) -> Iterator[Moved]:
        """Drive to the waypoints from start, one Moved per part done; between two, the caller may
        checkpoint. announce(target) comes before each leg a simulated rover drives, announce(None)
        once the GNC has them all."""

    def true_pose(self) -> list[float] | None:
        """The simulated rover's true x, y, heading for truth records; None when no simulator drives."""
        return None

    def resume_at(self, x: float, y: float, heading: float) -> None:  # noqa: B027  optional hook, a no-op here
        """A resumed job's rover stands where it stopped (a real one stays there): nothing to do."""


class SimulatedDrive(Drive):
    """The simulated rover turns, then drives straight, with its drive error; the estimate is
    dead-reckoned from what was commanded."""

    simulated = True

    def act(self, job: DrivingJob, kind: str, value: float, pace: Pace) -> Moved:
        turn, distance = action_motion(kind, value)
        return self.move(job, turn, distance, pace)

    def waypoints(self, job: DrivingJob, waypoints: Sequence[Sequence[float]], start: RoverPose, pace: Pace,
                  goal: tuple[float, float], cycle: int,
                  announce: Callable[[Sequence[float] | None], None]) -> Iterator[Moved]:
        for target in list(waypoints):
            job.safe_point()
            turn, distance = turn_and_distance((start.x, start.y, start.heading), target)
            announce(target)
            moved = self.move(job, turn, distance, pace, start=start, incline=True)
            yield moved
            start = self.rover.pose_estimate   # the caller may have corrected it (an orient look between legs)

    def move(self, job: DrivingJob, turn: float, distance: float, pace: Pace, start: RoverPose | None = None,
             incline: bool = False) -> Moved:
        """Turn, then drive (negative: backward), sample by sample in simulated time, so a guard can
        stop the rover between two samples (DriveStopped). The estimate is dead-reckoned from start
        (default: the estimate now) as the samples go, its height climbing along the pitch the
        inclinometer reads at each sample (climb), and takes roll and pitch from the inclinometer at
        the end (incline: on the drive's noise stream, as navigate's legs do)."""
        rover, testbed = self.rover, self.rover.testbed
        rover.hand_over_sensors()
        start = start or rover.pose_estimate
        planned = testbed.plan_drive(turn, distance)
        edge = testbed.leaves_world(planned.poses)
        if edge is not None:   # refused before it moves: the simulated world ends (a real rover's ground does not)
            raise WorldEdge(f"the simulated rover would leave the simulated world: {edge}")
        direction = 1 if distance >= 0 else -1
        drive_steps = planned.samples - planned.turn_steps
        speed = testbed.world_config.rover_speed
        turn_s = abs(math.degrees(turn)) / speed.turn_deg_s / planned.turn_steps
        drive_s = abs(distance) / speed.drive_m_s / max(1, drive_steps)
        done_turn, done_distance, contacts = 0.0, 0.0, 0
        z, pitch = start.z, None   # pitch: the inclinometer's last reading while driving (its own stream)
        started_s = job.clock.now() if rover.guard is not None else 0.0
        true_path: list[list[float]] = []
        for k, true in enumerate(planned.poses[1:], start=1):
            driving = k > planned.turn_steps
            if driving and rover.guard is not None and distance != 0:
                here = self._estimate(start, done_turn, done_distance, z)
                why = rover.guard.check(job, here, direction, abs(distance - done_distance), speed.drive_m_s,
                                        started_s)
                if why is not None:
                    here = rover.pose_estimate = rover.settle(here)
                    moved = Moved(here, (done_turn, done_distance), 1, contacts, true_path)
                    rover.guard.stopped(why, here, rover.stop_truth(direction, pace.step_height_m))
                    raise DriveStopped(rover.guard.name, why, moved)
            # navigate's legs (incline) take the height from its own map after the leg; reading the
            # inclinometer here would shift its stream, and with it every later reading, away from
            # where a restarted server's stream stands (tests/core/test_kill_restart.py)
            climbing = driving and not incline
            if climbing and pitch is None:
                pitch = testbed.inclinometer()[1]
            job.sleep(drive_s if driving else turn_s)
            try:
                contacts += int(testbed.step_rover(tuple(true), pace.step_height_m))
            except ValueError as exc:   # the simulated world ends (a real rover's ground does not)
                rover.pose_estimate = rover.settle(self._estimate(start, done_turn, done_distance, z))
                raise WorldEdge(f"the simulated rover would leave the simulated world: {exc}") from None
            true_path.append([float(v) for v in true])
            if climbing:
                now = testbed.inclinometer()[1]
                z += climb(distance / drive_steps, pitch, now)
                pitch = now
            if driving:
                done_distance = distance * (k - planned.turn_steps) / drive_steps
            else:
                done_turn = turn * k / planned.turn_steps
            rover.pose_estimate = self._estimate(start, done_turn, done_distance, z)
        # The attitude where it stopped, as measured (navigate's legs read the inclinometer on the
        # drive's own noise stream, as always; other moves on the inclinometer's, so drive errors stay).
        estimate = rover.settle(self._estimate(start, turn, distance, z), drive_stream=incline)
        rover.pose_estimate = estimate
        return Moved(estimate, (turn, distance), 1, contacts, true_path)

    @staticmethod
    def _estimate(start: RoverPose, turn: float, distance: float, z: float) -> RoverPose:
        """Dead-reckoned from start at height z; roll and pitch from before until settle."""
        x, y, heading = dead_reckon((start.x, start.y, start.heading), turn, distance)
        return RoverPose(x, y, z, heading, start.roll, start.pitch)

    def true_pose(self) -> list[float] | None:
        return self.rover.true_pose()

    def resume_at(self, x: float, y: float, heading: float) -> None:
        """A restarted server's simulated world starts with the rover at its start: put it back."""
        rover = self.rover.testbed.rover
        if not np.allclose(rover.pose, (x, y, heading)):
            rover.place(x, y, heading)


class GncDrive(Drive):
    """The GNC drives: what to do goes out as a `navigate` event, and the job waits (in simulated
    time; `break` ends it) for the GNC's `pose`, the new estimate."""

    simulated = False

    def act(self, job: DrivingJob, kind: str, value: float, pace: Pace) -> Moved:
        reports = self.rover.reports
        self.rover.hand_over_sensors()
        shown = math.degrees(value) if kind == "turn" else value
        job.publish("navigate", {"job": job.job.id, "action": kind, "value": f"{shown:.4f}",
                                 "unit": "deg" if kind == "turn" else "m"})
        self.rover.wait_for_pose(job, reports, pace.pose_timeout_s, f"the route action {kind} {shown:g}")
        return Moved(self.rover.pose_estimate, None)

    def waypoints(self, job: DrivingJob, waypoints: Sequence[Sequence[float]], start: RoverPose, pace: Pace,
                  goal: tuple[float, float], cycle: int,
                  announce: Callable[[Sequence[float] | None], None]) -> Iterator[Moved]:
        reports = self.rover.reports
        self.rover.hand_over_sensors()
        job.publish("navigate", {"job": job.job.id, "cycle": cycle,
                                 "waypoints": " ".join(f"{x:.3f},{y:.3f}" for x, y in waypoints),
                                 "goal": f"{goal[0]:.3f},{goal[1]:.3f}"})
        announce(None)
        self.rover.wait_for_pose(job, reports, pace.pose_timeout_s, f"navigate handing out cycle {cycle}'s waypoints")
        yield Moved(self.rover.pose_estimate, None, legs=len(waypoints))


@dataclass
class _Pose:
    """The estimate and the count of the GNC's reports; outlives a reinit (see take_over)."""

    estimate: RoverPose | None = None   # None: not asked for yet
    reports: int = 0                    # pose commands received: a GNC drive waits for the next one
    epoch: int = 0                      # a pose given or a reset: what odometry measured before is void


@dataclass(frozen=True)
class SunReading:
    """The sun sensor's reading and what it is measured against (toolbox/odometry/sun.py)."""

    body: np.ndarray       # unit vector toward the sun in the rover's body frame, as read
    world: np.ndarray      # the sun's unit vector in the world frame, from the ephemeris
    sigma: float           # the sensor's 1-sigma angular error, radians
    tilt_sigma: float      # the inclinometer's 1-sigma roll and pitch error, radians


class RoverDevice:
    """The rover as the commands see it: its pose estimate and the GNC's reports of it, the drive,
    the simulator's truth about it, and (simulated only) its forward camera."""

    name = "rover"

    def __init__(self, testbed: SimulatedTestbed, simulated: Callable[[], bool],
                 sharing: DeviceSharing | None = None):
        self.testbed = testbed
        self._simulated = simulated
        self._sharing = sharing
        self._pose = _Pose()
        self._forward: ForwardCamera | None = None
        self.guard: DriveGuard | None = None   # set while hazard detection runs

    @property
    def simulated(self) -> bool:
        return self._simulated()

    def take_over(self, previous: RoverDevice) -> None:
        """reinit builds the devices anew, and the rover has not moved: share the previous device's
        estimate and reports (a `pose` sent meanwhile lands in both), and keep the forward camera
        (its noise stream continues on the same world)."""
        self._pose, self._forward, self.guard = previous._pose, previous._forward, previous.guard

    # ---------------------------------------------------------------------------------- the pose
    @property
    def pose_estimate(self) -> RoverPose:
        """Where the server believes the rover stands."""
        if self._pose.estimate is None:
            if self.simulated:
                self._pose.estimate = RoverPose.from_matrix(self.testbed.rover.body_to_world)
            else:
                self._pose.estimate = RoverPose(0.0, 0.0)
        return self._pose.estimate

    @pose_estimate.setter
    def pose_estimate(self, pose: RoverPose) -> None:
        self._pose.estimate = pose

    @property
    def reports(self) -> int:
        """How many poses the GNC has reported."""
        return self._pose.reports

    def report_pose(self, pose: RoverPose) -> None:
        """The GNC says where the rover stands: the new estimate, and the end of a GNC drive's wait."""
        self._pose.estimate = pose
        self._pose.reports += 1
        self._pose.epoch += 1

    @property
    def epoch(self) -> int:
        """Changes when a pose is given or the devices are reset: a visual odometry keyframe taken
        in an earlier epoch no longer ties to the estimate."""
        return self._pose.epoch

    def new_epoch(self) -> None:
        self._pose.epoch += 1

    def wait_for_pose(self, job: DrivingJob, reports: int, timeout_s: float, after: str) -> None:
        """Wait (in simulated time; `break` ends it) until the GNC reports a pose after the count of
        reports was `reports`; Timeout after timeout_s, naming what it waited `after`."""
        waited = 0.0
        while self.reports == reports:
            if waited >= timeout_s:
                raise Timeout(f"no pose from the GNC within {timeout_s:.0f} s of {after}")
            job.sleep(POSE_POLL_S)
            waited += POSE_POLL_S

    # ---------------------------------------------------------------------------------- driving
    def drive(self, mode: DriveMode, option: str) -> Drive:
        """The drive a setting (`option`, e.g. navigation.drive) picks: simulated or gnc, or auto:
        simulated when the devices are. A simulated drive with real devices is refused."""
        simulated = self.simulated
        if mode == "simulated" and not simulated:
            raise BadRequest(f"{option} is simulated but the devices are real: set {option.rpartition('.')[2]} "
                             "= \"gnc\"")
        if mode == "simulated" or (mode == "auto" and simulated):
            return SimulatedDrive(self)
        return GncDrive(self)

    def settle(self, estimate: RoverPose, ground: Callable[[], tuple[np.ndarray, GridSpec] | None] | None = None,
               drive_stream: bool = False) -> RoverPose:
        """`estimate` (a pose a drive just reached, or the GNC's report) with the roll and pitch the
        rover can measure where it stands: the inclinometer when it has one (the simulated rover;
        drive_stream: read on the drive's noise stream, as navigate's legs always have); with none,
        the plane of the terrain under its wheels in `ground` (the newest DEM's heights, or None);
        else the old ones. Its height is the ground's under the wheels when `ground` is given and
        knows it (a pose whose drive the server did not see); a simulated drive climbed it (climb).

        Why: dead reckoning and the GNC's `pose` carry x, y and heading only, yet every map places
        its points through the estimate's whole pose (mapping/steps.py camera_to_world), so the
        roll, pitch and height from before a move tilt and shift the next map (dem-update-tof) by
        their change: a turn on a slope swaps roll into pitch, driving onto a slope tilts the body
        and lifts it."""
        dem = ground() if ground is not None else None
        if self.simulated:
            roll, pitch = self.testbed.inclination() if drive_stream else self.testbed.inclinometer()
            estimate = replace(estimate, roll=roll, pitch=pitch)
        elif dem is not None and (tilt := attitude_on_ground(*dem, estimate.x, estimate.y, estimate.heading,
                                                             GROUND_RADIUS_M)) is not None:
            estimate = replace(estimate, roll=tilt[0], pitch=tilt[1])
        z = None if dem is None else height_on_ground(*dem, estimate.x, estimate.y, GROUND_RADIUS_M)
        return estimate if z is None else replace(estimate, z=z)

    def inclination(self) -> tuple[float, float]:
        """Roll and pitch now: the simulated rover's inclinometer; else the estimate's (settled after
        every drive and every `pose` of the GNC: see settle)."""
        if self.simulated:
            return self.testbed.inclinometer()
        pose = self.pose_estimate
        return pose.roll, pose.pitch

    def sun_reading(self, samples: int = 1) -> SunReading | None:
        """Simulated: the rover's sun sensor, `samples` readings averaged (the rover stands still
        while it looks), and the world's sun (the ephemeris); None when the sun is outside the
        sensor's view, and with real devices (the test bed has no sun sensor yet)."""
        if not self.simulated:
            return None
        readings = [self.testbed.sun_sensor() for _ in range(samples)]
        if any(r is None for r in readings):
            return None
        mean = np.mean(readings, axis=0)
        sensor = self.testbed.world_config.sun_sensor   # its data sheet
        sigma = math.hypot(math.radians(sensor.noise_deg) / math.sqrt(samples), math.radians(sensor.bias_deg))
        return SunReading(mean / np.linalg.norm(mean), np.asarray(self.testbed.world.sun.direction(), dtype=np.float64),
                          sigma, math.radians(INCLINOMETER_NOISE_DEG))

    def hand_over_sensors(self) -> None:
        """A rover that starts to move gives the job's PTU and sensors to the activities that guard
        it (devices/sharing.py); the job takes them back when it looks again."""
        if self._sharing is not None:
            self._sharing.release_job("ptu", "tof", "cameras")

    def stop_truth(self, direction: int, step_height: float) -> dict | None:
        """Simulated: the true pose where a guard stopped the rover and the true free way left
        before its footprint would touch a rock taller than step_height (metres, None: none within
        5 m); None with real devices."""
        if not self.simulated:
            return None
        rover = self.testbed.rover
        clearance = rover.clearance(step_height, 5.0, direction)
        return {"x": rover.x, "y": rover.y, "heading_rad": rover.heading, "contacts": self.testbed.contacts,
                "clearance_m": None if math.isinf(clearance) else clearance}

    # ---------------------------------------------------------------------------------- the truth
    def wait_for_world(self) -> None:
        """Simulated: wait for the world being built, before the rover drives or looks on it."""
        if self.simulated:
            self.testbed.wait_for_build()

    def true_pose(self) -> list[float] | None:
        """The simulated rover's true x, y, heading (radians); None with real devices."""
        return list(self.testbed.rover.pose) if self.simulated else None

    def true_body_m(self) -> tuple[float, float]:
        """The simulated rover's body length and width, metres, as its footprint on the truth."""
        config = self.testbed.rover.config
        return config.body_length_m, config.body_width_m

    def truly_touches(self, x: float, y: float, heading: float, step: float) -> bool:
        """Whether the simulated rover's footprint at this pose covers a true obstacle taller than
        step (the rover is put back where it stands)."""
        rover = self.testbed.rover
        saved = rover.pose
        try:
            rover.place(x, y, heading)
            return rover.collides(step)
        finally:
            rover.place(*saved)

    def world_extent(self) -> tuple[float, float, float, float] | None:
        """(x_min, x_max, y_min, y_max) of the simulated world's ground; None with real devices, or
        before a world file is loaded."""
        return self.testbed.extent() if self.simulated else None

    # ---------------------------------------------------------------------------------- the camera
    @property
    def has_forward_camera(self) -> bool:
        """The test bed has no forward camera yet: only the simulated rover has one."""
        return self.simulated

    def forward_camera(self, config: ForwardCameraConfig) -> ForwardCamera:
        """The simulated forward camera, one per server and rover (its noise stream continues)."""
        if not self.has_forward_camera:
            raise DeviceError(NO_FORWARD_CAMERA)
        rover = self.testbed.rover
        camera = self._forward
        if camera is None or camera.rover is not rover or camera.config != config:
            camera = self._forward = ForwardCamera(rover, config)
        return camera
