"""One look: the PTU turned along the rover's heading (pan 0, the orient tilt) or where the odometer
aims it (back at its keyframe's ground after a manoeuvre), one stereo pair or SR4000 frame, and what the
rover's other sensors read at that instant (inclinometer, sun sensor), with the dead-reckoned estimate the look
is taken from."""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from rvs_server.devices.rover import SunReading
from toolbox.colour import grey
from toolbox.geometry import RoverPose, camera_to_rover, relative_pose
from toolbox.odometry.depth import DepthFrame
from toolbox.odometry.stereo import StereoRig

from .settings import OrientSettings

if TYPE_CHECKING:
    from rvs_server.jobs import JobContext


@dataclass(frozen=True)
class Look:
    sensor: str
    pan_tilt_deg: tuple[float, float]       # as the PTU reported it
    camera_to_rover: np.ndarray             # 4 x 4, calibrated: the left camera's or the SR4000's
    estimate: RoverPose                      # where the server believed the rover stood
    roll: float                              # the inclinometer's, radians
    pitch: float
    sun: SunReading | None
    acquire_s: float                         # wall seconds the PTU and the grab took
    left: np.ndarray | None = None           # stereo: grey images
    right: np.ndarray | None = None
    rig: StereoRig | None = None
    depth: DepthFrame | None = None          # tof


def point_head(ctx: JobContext, pan_deg: float, tilt_deg: float) -> tuple[float, float]:
    """Turn the PTU to the angles and wait until it stands; the angles it reports."""
    device = ctx.devices.ptu
    driver = device.require()
    driver.move_to(pan_deg, tilt_deg, speed_deg_s=ctx.settings_of("ptu").default_speed_deg_s)
    driver.wait_until_stopped(timeout_s=120.0)
    return device.read_position()


def view_limits(ctx: JobContext, keep_off_deg: float = 1.0) -> tuple[tuple[float, float], tuple[float, float]]:
    """The pan and tilt ranges (degrees) a look may point in: the unit's own, a little inside."""
    limits = ctx.devices.ptu.require().limits
    (pan_lo, pan_hi), (tilt_lo, tilt_hi) = limits.range_deg("pan"), limits.range_deg("tilt")
    return (pan_lo + keep_off_deg, pan_hi - keep_off_deg), (tilt_lo + keep_off_deg, min(tilt_hi - keep_off_deg, 0.0))


def take_look(ctx: JobContext, sensor: str, settings: OrientSettings, pan_deg: float = 0.0,
              tilt_deg: float | None = None) -> Look:
    """One look: the head turned to (pan, tilt), default along the heading at the orient tilt."""
    started = time.perf_counter()
    tilt = settings.tilt_deg.of(sensor) if tilt_deg is None else tilt_deg
    pan_deg, tilt_deg = point_head(ctx, pan_deg, tilt)
    ctx.safe_point()
    rover = ctx.devices.rover
    calibration = ctx.server.calibration()
    pan, tilt_rad = math.radians(pan_deg), math.radians(tilt_deg)
    estimate = rover.pose_estimate
    roll, pitch = rover.inclination() if rover.simulated else (estimate.roll, estimate.pitch)
    common = dict(sensor=sensor, pan_tilt_deg=(pan_deg, tilt_deg), estimate=estimate, roll=roll, pitch=pitch,
                  sun=rover.sun_reading(settings.sun_samples))
    if sensor == "stereo":
        pair = ctx.devices.cameras.require()
        frames = pair.grab("both", timeout_s=ctx.devices.cameras.grab_timeout_s)
        mode = ctx.devices.cameras.config.resolution
        left_k, right_k = (pair.camera(role).intrinsics(mode) for role in ("left", "right"))
        left_to_rover = camera_to_rover(calibration.mounts["left"], pan, tilt_rad)
        right_to_rover = camera_to_rover(calibration.mounts["right"], pan, tilt_rad)
        rig = StereoRig(left_k, right_k, relative_pose(left_to_rover, right_to_rover))
        return Look(**common, camera_to_rover=left_to_rover, acquire_s=time.perf_counter() - started,
                    left=grey(frames["left"].image), right=grey(frames["right"].image), rig=rig)
    result = ctx.devices.tof.grab(frames=settings.tof_frames)
    frame, k = result.frame, calibration.tof_intrinsics
    points = frame.xyz().astype(np.float32)
    valid = np.asarray(result.defined, dtype=bool) & np.isfinite(points).all(axis=-1)
    points[~valid] = np.nan
    depth = DepthFrame(points=points, valid=valid, amplitude=frame.amplitude.astype(np.float32),
                       fx=k.fx, fy=k.fy, cx=k.cx, cy=k.cy)
    return Look(**common, camera_to_rover=camera_to_rover(calibration.mounts["tof"], pan, tilt_rad),
                acquire_s=time.perf_counter() - started, depth=depth)
