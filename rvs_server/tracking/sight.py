"""Where the tracking sensor looks: its field of view, the PTU angles that point it at a place, and
one frame of it as world points with what the rover knew at that instant."""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any

import numpy as np

from rvs_server.devices.cameras import nominal_intrinsics
from rvs_server.devices.frame_points import FramePoints, FrameSettings
from toolbox.geometry import RoverPose, direction_of
from toolbox.mapping import dem as dem_tools
from toolbox.tracking.standing import Plane

from .settings import TrackingSettings

if TYPE_CHECKING:
    from rvs_server.host import Host

SENSOR_NAME = {"tof": "tof", "stereo": "left"}    # the simulator's name of the sensor that sees


@dataclass(frozen=True)
class Seen:
    """One frame in the world: its points, the sensor's place, the rover's ground plane, when."""

    points: np.ndarray            # (N, 3) world
    sensor_xy: np.ndarray         # (2,)
    sensor_z: float
    plane: Plane
    pose: RoverPose
    pan_deg: float
    tilt_deg: float
    sim_s: float
    grab_ms: float                # wall: the PTU read and the grab, devices held
    process_ms: float             # wall: points made of the frame, devices given back
    truth: dict | None = None     # simulated: the astronaut's true place and how much of it was in view


class Sight:
    """One tracking sensor on the PTU, for the search and the tracker."""

    def __init__(self, server: Host, settings: TrackingSettings, sensor: str, resolution: str | None = None):
        """`resolution`: the stereo pair's mode for these frames (default the search's, settings'
        stereo_resolution)."""
        self.server, self.settings, self.sensor = server, settings, sensor
        self.resolution = resolution or settings.stereo_resolution
        self.frames = FramePoints(server, FrameSettings(
            sensor, settings.max_range_m, self.resolution, settings.stereo_disparities,
            tof_max_distance_m=settings.tof_max_distance_m if sensor == "tof" else None,
            min_confidence=settings.tof_min_confidence, tof_max_integration=settings.tof_max_integration))
        calibration = server.calibration()
        self.mount = calibration.mounts["tof" if sensor == "tof" else "left"]
        self.half_fov_deg = self._half_fov(server, calibration)

    def _half_fov(self, server: Host, calibration: Any) -> tuple[float, float]:
        if self.sensor == "tof":
            k = calibration.tof_intrinsics
        else:
            cameras = server.devices.cameras
            k = cameras.ready_driver().camera("left").intrinsics(self.resolution) \
                if cameras.driver is not None else None
            if k is None:              # the Pike F-210B with its 12 mm lens
                k = nominal_intrinsics(self.resolution)
        return (math.degrees(math.atan2(k.width / 2, k.fx)), math.degrees(math.atan2(k.height / 2, k.fy)))

    def aim(self, pose: RoverPose, target: np.ndarray) -> tuple[float, float]:
        """PTU (pan, tilt) in degrees that point the sensor's axis at a world point (3,)."""
        world_to_rover = np.linalg.inv(pose.to_world())
        local = world_to_rover[:3, :3] @ np.asarray(target, dtype=float) + world_to_rover[:3, 3]
        d = local - np.asarray(self.mount.ptu_position, dtype=float)
        return -math.degrees(math.atan2(d[1], d[0])), math.degrees(math.atan2(d[2], math.hypot(d[0], d[1])))

    def cut_by_view(self, seen: Seen, points: np.ndarray, margin_deg: float = 1.5) -> bool:
        """Whether a cluster (N, 3 world) reaches within `margin_deg` of the frame's left or right edge:
        the view cut it, and its shape there is not its own."""
        world_to_rover = np.linalg.inv(seen.pose.to_world())
        local = points @ world_to_rover[:3, :3].T + world_to_rover[:3, 3] - np.asarray(self.mount.ptu_position)
        azimuth = -np.degrees(np.arctan2(local[:, 1], local[:, 0]))      # positive right, as the pan
        off = np.abs((azimuth - seen.pan_deg + 180.0) % 360.0 - 180.0)
        return bool(off.max(initial=0.0) >= self.half_fov_deg[0] - margin_deg)

    def sees_top_of(self, seen: Seen, top: np.ndarray, margin_deg: float = 2.0) -> bool:
        """Whether a world point (3,) lies inside the frame's vertical view by `margin_deg`: then a
        cluster whose highest point it is was not cut by the top of the image."""
        elevation = math.degrees(math.atan2(top[2] - seen.sensor_z, math.hypot(*(top[:2] - seen.sensor_xy))))
        return elevation < seen.tilt_deg + self.half_fov_deg[1] - margin_deg

    def bearing_range(self, pose: RoverPose, xy: np.ndarray) -> tuple[float, float]:
        """Bearing (degrees from the rover's heading, positive right, as the PTU's pan) and ground range
        from the PTU's axis to a world place."""
        pan, _ = self.aim(pose, np.array([xy[0], xy[1], pose.z]))
        axis = pose.to_world() @ np.array([*self.mount.ptu_position, 1.0])
        return pan, float(math.hypot(xy[0] - axis[0], xy[1] - axis[1]))

    def grab(self, devices: Any, ptu_speed_deg_s: float | None = None
             ) -> tuple[Any, RoverPose, float, float, float, dict | None, float]:
        """One frame where the PTU stands, with the devices held: the PTU read before and after the
        grab and the angles of the frame's exposure taken between them (the tracker may have the unit
        still turning, at `ptu_speed_deg_s`, the speed it last set), the rover's estimate with the
        inclinometer's attitude of the instant, the frame's own time (the middle of its exposure, not
        when it was asked for) and the truth at that time (simulated)."""
        rover = devices.rover
        started = time.perf_counter()
        before = self._read_ptu(devices)
        pose = rover.pose_estimate
        if rover.simulated:
            roll, pitch = rover.inclination()
            pose = replace(pose, roll=roll, pitch=pitch)
        frame = self.frames.grab(devices)
        after = self._read_ptu(devices)
        shown = self.frames.timestamp(frame)
        sim_s = self.server.clock.now() if shown is None else shown
        truth = self._truth(devices, sim_s)
        pan, tilt = angles_at(before, after, sim_s, ptu_speed_deg_s)
        return frame, pose, pan, tilt, sim_s, truth, (time.perf_counter() - started) * 1000.0

    def _read_ptu(self, devices: Any) -> tuple[float, float, float]:
        """The PTU's (pan, tilt) and the clock time of the reading (the middle of its round trip)."""
        asked = self.server.clock.now()
        pan, tilt = devices.ptu.read_position()
        return pan, tilt, (asked + self.server.clock.now()) / 2

    def seen(self, grabbed: tuple) -> Seen:
        """The frame's world points (run with the devices given back)."""
        frame, pose, pan, tilt, sim_s, truth, grab_ms = grabbed
        started = time.perf_counter()
        points_camera, valid, camera_pose = self.frames.points(frame, pose, pan, tilt)
        points = dem_tools.view_points(points_camera, valid, camera_pose)
        axis = camera_pose[:3, 3]
        return Seen(points, np.array([axis[0], axis[1]]), float(axis[2]), Plane.of_rover(pose.to_world()), pose,
                    pan, tilt, sim_s,
                    grab_ms, (time.perf_counter() - started) * 1000.0, truth)

    def _truth(self, devices: Any, at_s: float) -> dict | None:
        truth = devices.truth
        if truth is None:
            return None
        return truth.person(SENSOR_NAME[self.sensor], self.half_fov_deg, self.settings.max_range_m, at_s)


def angles_at(before: tuple[float, float, float], after: tuple[float, float, float],
              at_s: float, speed_deg_s: float | None = None) -> tuple[float, float]:
    """PTU (pan, tilt) at clock time `at_s` from two timed readings (pan, tilt, time) around it.

    A stereo pair exposes at its trigger pulse, at the start of a grab whose read-out takes 0.1-0.3 s,
    and a TOF frame in the middle of its ~60 ms: the mean of the two readings put a turning head 0.4-1
    degree off. With the speed the unit was last set to (the tracker's own command), each axis runs
    from the reading before at that speed until it stands where the reading after found it: a
    2-degree hop at 47 deg/s is over in 40 ms of a 60 ms grab, and straight-line interpolation put
    the TOF frames exposed during it 0.3-0.6 degree behind. An axis that moved farther than that
    speed allows (unknown, or changed in the grab) is taken on the straight line; either way the
    angles are held at the nearer reading outside the two."""
    span = after[2] - before[2]
    share = 0.5 if span <= 0 else min(1.0, max(0.0, (at_s - before[2]) / span))
    elapsed = share * max(span, 0.0)
    angles = []
    for axis in (0, 1):
        moved = after[axis] - before[axis]
        if speed_deg_s is not None and span > 0 and abs(moved) <= speed_deg_s * span * 1.05:
            angles.append(before[axis] + math.copysign(min(abs(moved), speed_deg_s * elapsed), moved))
        else:
            angles.append(before[axis] + share * moved)
    return angles[0], angles[1]


def optical_axis(pan_deg: float, tilt_deg: float) -> np.ndarray:
    """The head's forward axis for PTU angles, rover frame (for pictures and tests)."""
    return direction_of(math.radians(pan_deg), math.radians(tilt_deg))
