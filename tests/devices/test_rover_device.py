"""The rover device's two drives: the simulated one moves the simulated rover with its drive error and
dead-reckons the estimate; the GNC's sends the event and waits for the GNC's pose, or times out."""
from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from drivers.sim.clock import SimClock
from drivers.sim.config import DriveError, WorldConfig
from rvs_server.devices import Devices, DevicesConfig
from rvs_server.devices.cameras import CamerasDeviceConfig
from rvs_server.devices.rover import GncDrive, Pace, SimulatedDrive, WorldEdge
from rvs_server.devices.tof import TofDeviceConfig
from rvs_server.protocol import BadRequest, DeviceError, Timeout
from toolbox.geometry import RoverPose, rotation_rpy
from toolbox.grid import GridSpec

PACE = Pace(step_height_m=0.10, pose_timeout_s=2.0)
REAL = DevicesConfig(tof=TofDeviceConfig(backend="mesa"), cameras=CamerasDeviceConfig(backend="vimba"))


class Job:
    """What a drive uses of a job: simulated sleep, safe points, events; `on_sleep` plays the GNC."""

    def __init__(self, on_sleep=None):
        self.job = SimpleNamespace(id=7)
        self.slept: list[float] = []
        self.events: list[tuple[str, dict]] = []
        self.on_sleep = on_sleep

    def sleep(self, seconds: float) -> None:
        self.slept.append(seconds)
        if self.on_sleep is not None:
            self.on_sleep(len(self.slept))

    def safe_point(self) -> None:
        pass

    def publish(self, topic: str, data: dict) -> None:
        self.events.append((topic, data))


@pytest.fixture
def devices():
    made = []

    def make(config: DevicesConfig = DevicesConfig(), **world) -> Devices:  # noqa: B008  never changed by make
        made.append(Devices(config, SimClock(), WorldConfig(seed=2, size_m=(8.0, 8.0), **world)))
        return made[-1]

    yield make
    for d in made:
        d.testbed.close()


def test_the_simulated_drive_moves_the_rover_with_its_error_and_dead_reckons(devices):
    rover = devices(rover_start=(0.5, -1.0, 90.0)).rover
    assert rover.pose_estimate.x == pytest.approx(0.5) and rover.pose_estimate.heading == pytest.approx(math.pi / 2)
    drive = rover.drive("auto", "routes.actions")
    assert isinstance(drive, SimulatedDrive) and drive.simulated
    job = Job()
    moved = drive.act(job, "turn", -math.pi / 2, PACE)
    moved = drive.act(job, "forward", 2.0, PACE)
    # The estimate is what was commanded; the rover went a little elsewhere (world.toml drive error).
    assert (moved.estimate.x, moved.estimate.y, moved.estimate.heading) == pytest.approx((2.5, -1.0, 0.0), abs=1e-9)
    assert rover.pose_estimate == moved.estimate and moved.commanded == (0.0, 2.0)
    x, y, heading = rover.true_pose()
    assert math.dist((x, y), (2.5, -1.0)) < 0.3 and (x, y) != pytest.approx((2.5, -1.0), abs=1e-6)
    assert moved.true_path[-1] == pytest.approx([x, y, heading]) and len(moved.true_path) >= 40   # every 5 cm
    # In simulated time, sample by sample (a guard may stop it between two), at world.toml's rover
    # speeds: 90 deg at 20 deg/s, 2 m at 0.3 m/s.
    # Each action is its turn's samples (10 deg at most) then its drive's (5 cm at most), one of them empty.
    assert sum(job.slept) == pytest.approx(90.0 / 20.0 + 2.0 / 0.3, abs=1e-9) and len(job.slept) == (9 + 1) + (1 + 40)
    # The GNC said where the rover is: the next action dead-reckons from there.
    rover.report_pose(RoverPose(1.0, 1.0, 0.0, math.pi))
    assert drive.act(job, "backward", 0.5, PACE).estimate.x == pytest.approx(1.5)


def test_the_simulated_drive_takes_waypoints_one_leg_at_a_time(devices):
    rover = devices(drive_error=DriveError.none()).rover
    drive = rover.drive("simulated", "navigation.drive")
    announced = []
    legs = list(drive.waypoints(Job(), [(1.0, 0.0), (1.0, 1.0)], rover.pose_estimate, PACE, (1.0, 1.0), 1,
                                announced.append))
    assert announced == [(1.0, 0.0), (1.0, 1.0)] and [m.commanded[1] for m in legs] == pytest.approx([1.0, 1.0])
    assert rover.true_pose() == pytest.approx([1.0, 1.0, math.pi / 2])        # no drive error: exact
    # Roll and pitch from the inclinometer: the ground's, with 0.1 degree noise.
    true_roll, true_pitch = rover.testbed.rover.roll_pitch()
    estimate = legs[-1].estimate
    assert (estimate.roll, estimate.pitch) == pytest.approx((true_roll, true_pitch), abs=0.01)
    assert estimate.roll != true_roll and all(m.legs == 1 for m in legs)
    with pytest.raises(WorldEdge, match="the simulated rover would leave the simulated world") as refused:
        drive.act(Job(), "forward", 20.0, PACE)
    assert isinstance(refused.value, BadRequest)
    assert rover.true_pose() == pytest.approx([1.0, 1.0, math.pi / 2])        # stays where it was


def test_the_gnc_drive_sends_the_waypoints_and_waits_for_the_pose(devices):
    rover = devices().rover
    drive = rover.drive("gnc", "navigation.drive")
    assert isinstance(drive, GncDrive) and drive.true_pose() is None
    job = Job(on_sleep=lambda n: n == 3 and rover.report_pose(RoverPose(2.0, 0.5, 0.0, 0.1)))
    announced = []
    moved = list(drive.waypoints(job, [(1.0, 0.25), (2.0, 0.5)], rover.pose_estimate, PACE, (3.0, 0.5), 4,
                                 announced.append))
    assert job.events == [("navigate", {"job": 7, "cycle": 4, "waypoints": "1.000,0.250 2.000,0.500",
                                        "goal": "3.000,0.500"})]
    assert announced == [None] and job.slept == [0.5] * 3
    assert len(moved) == 1 and moved[0].legs == 2 and moved[0].commanded is None
    assert moved[0].estimate == RoverPose(2.0, 0.5, 0.0, 0.1) == rover.pose_estimate
    assert rover.true_pose() is not None          # the devices are simulated; the GNC drove, not the simulator


def test_the_gnc_drive_times_out_naming_what_it_waited_after(devices):
    rover = devices().rover
    job = Job()
    with pytest.raises(Timeout, match=r"^no pose from the GNC within 2 s of the route action turn 30$"):
        GncDrive(rover).act(job, "turn", math.radians(30.0), PACE)
    assert job.events == [("navigate", {"job": 7, "action": "turn", "value": "30.0000", "unit": "deg"})]
    assert sum(job.slept) == pytest.approx(2.0)
    with pytest.raises(Timeout, match=r"within 2 s of navigate handing out cycle 1's waypoints"):
        list(GncDrive(rover).waypoints(Job(), [(1.0, 0.0)], rover.pose_estimate, PACE, (1.0, 0.0), 1, print))


def test_real_devices_have_no_simulated_drive_truth_or_forward_camera(devices):
    real = devices(REAL)
    rover = real.rover
    assert not real.simulated and rover.pose_estimate == RoverPose(0.0, 0.0)
    with pytest.raises(BadRequest,
                       match=r'^navigation.drive is simulated but the devices are real: set drive = "gnc"$'):
        rover.drive("simulated", "navigation.drive")
    with pytest.raises(BadRequest, match=r'^routes.actions is simulated .* set actions = "gnc"$'):
        rover.drive("simulated", "routes.actions")
    assert isinstance(rover.drive("auto", "routes.actions"), GncDrive)
    assert rover.true_pose() is None and rover.world_extent() is None and not rover.has_forward_camera
    with pytest.raises(DeviceError):
        rover.forward_camera(None)


def test_reinit_keeps_the_estimate_and_the_pose_reports(devices):
    old = devices().rover
    old.report_pose(RoverPose(1.0, 2.0))
    new = devices(REAL).rover
    new.take_over(old)
    assert new.pose_estimate == RoverPose(1.0, 2.0) and new.reports == 1
    old.report_pose(RoverPose(3.0, 4.0))     # a pose sent while the devices were being replaced
    assert new.pose_estimate == RoverPose(3.0, 4.0) and new.reports == 2


def test_settle_without_an_inclinometer_takes_the_attitude_and_height_from_the_mapped_ground_under_the_wheels(devices):
    rover = devices(REAL).rover
    spec = GridSpec.covering((-2.0, 2.0), (-2.0, 2.0), 0.05)
    xs, ys = spec.centres()
    a, b = math.tan(math.radians(8.0)), math.tan(math.radians(-5.0))     # rises east 8 deg, falls north 5 deg
    heights = (a * xs[None, :] + b * ys[:, None]).astype("float32")
    heights[:, : spec.cols // 2 - 4] = float("nan")                         # a half mapped: enough under the wheels
    old = RoverPose(0.3, -0.2, 1.0, math.radians(35.0), 0.01, -0.02)        # 1 m: the height from before
    settled = rover.settle(old, ground=lambda: (heights, spec))
    normal = np.array([-a, -b, 1.0]) / math.sqrt(a * a + b * b + 1.0)
    up = rotation_rpy(settled.roll, settled.pitch, settled.heading)[:, 2]
    assert math.degrees(math.acos(min(1.0, float(up @ normal)))) < 0.05
    assert (settled.x, settled.y, settled.heading) == (old.x, old.y, old.heading)
    assert settled.z == pytest.approx(a * old.x + b * old.y, abs=0.005)   # the ground's height under the wheels
    assert rover.settle(old, ground=lambda: None) == old                   # no map: the old attitude
    assert rover.settle(old, ground=lambda: (heights * float("nan"), spec)) == old   # nothing mapped there
    assert rover.settle(old) == old
