"""Every transform of RVS: rigid 4x4 poses, rotations and the sensor chain (the pinhole projection is
toolbox/camera.py's).

Frames (metres, radians; DESIGN.md "Frames and units"):
- world: x east, y north, z up.
- rover: x forward, y left, z up; origin on the ground between the wheels. Its pose in the world is
  (x, y, z, heading, roll, pitch): heading is the yaw of rover x counter-clockwise from east, and the
  rotation is Rz(heading) @ Ry(pitch) @ Rx(roll), so pitch > 0 puts the nose down and roll > 0 the
  left side up.
- head: the pan-tilt unit's moving frame, origin where the pan and tilt axes meet (at `ptu_position`
  in the rover frame), equal to the rover axes at pan = tilt = 0. Positive pan turns the head right
  (clockwise seen from above), positive tilt raises the view: head-to-rover = Rz(-pan) @ Ry(-tilt).
- camera: OpenCV, x right, y down, z forward. A sensor's mount is its calibrated 4x4 camera-to-head pose.

The chain is camera -> head (mount) -> pan/tilt -> rover (mast) -> world (rover pose), exactly the
simulator's (drivers/sim/rover.py); tests hold the two together to 1e-9.

A pose named `a_to_b` maps points in frame a to frame b: p_b = a_to_b @ p_a.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

# OpenCV camera axes expressed in the head frame: x right = -y, y down = -z, z forward = +x.
CAMERA_AXES_IN_HEAD = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


# ---------------------------------------------------------------------------------- rotations
def rotation_x(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rotation_y(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rotation_z(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rotation_rpy(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Rz(yaw) @ Ry(pitch) @ Rx(roll): roll about x first, then pitch about y, then yaw about z."""
    return rotation_z(yaw) @ rotation_y(pitch) @ rotation_x(roll)


def rpy_of(rotation: np.ndarray) -> tuple[float, float, float]:
    """(roll, pitch, yaw) with rotation_rpy(roll, pitch, yaw) == rotation (pitch within +-90 degrees)."""
    r = np.asarray(rotation, dtype=np.float64)
    pitch = -math.asin(float(np.clip(r[2, 0], -1.0, 1.0)))
    return math.atan2(r[2, 1], r[2, 2]), pitch, math.atan2(r[1, 0], r[0, 0])


# ---------------------------------------------------------------------------------- rigid poses
def rigid(rotation: np.ndarray | None = None,
          translation: Sequence[float] | np.ndarray = (0.0, 0.0, 0.0)) -> np.ndarray:
    """4x4 pose from a 3x3 rotation (identity if None) and a translation."""
    pose = np.eye(4)
    if rotation is not None:
        pose[:3, :3] = rotation
    pose[:3, 3] = translation
    return pose


def compose(*poses: np.ndarray) -> np.ndarray:
    """The product of 4x4 poses, left to right: compose(b_to_c, a_to_b) is a_to_c."""
    result = np.eye(4)
    for pose in poses:
        result = result @ pose
    return result


def invert(pose: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 pose (transposed rotation; exact, unlike a general inverse)."""
    rotation_t = pose[:3, :3].T
    return rigid(rotation_t, -rotation_t @ pose[:3, 3])


def apply(pose: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Points (..., 3) mapped by a 4x4 pose; NaN points stay NaN."""
    points = np.asarray(points, dtype=np.float64)
    return points @ pose[:3, :3].T + pose[:3, 3]


def relative_pose(a_to_world: np.ndarray, b_to_world: np.ndarray) -> np.ndarray:
    """a_to_b from two poses in a common frame."""
    return invert(b_to_world) @ a_to_world


# ---------------------------------------------------------------------------------- the chain
@dataclass(frozen=True)
class RoverPose:
    """Where the rover stands: position of its frame origin and its attitude (radians)."""

    x: float
    y: float
    z: float = 0.0
    heading: float = 0.0
    roll: float = 0.0
    pitch: float = 0.0

    def to_world(self) -> np.ndarray:
        """4x4 rover-to-world pose."""
        return rigid(rotation_rpy(self.roll, self.pitch, self.heading), (self.x, self.y, self.z))

    @classmethod
    def from_matrix(cls, rover_to_world: np.ndarray) -> RoverPose:
        roll, pitch, heading = rpy_of(rover_to_world[:3, :3])
        x, y, z = (float(v) for v in rover_to_world[:3, 3])
        return cls(x, y, z, heading, roll, pitch)


@dataclass(frozen=True)
class SensorMount:
    """A sensor on the PTU: the mast (where pan and tilt axes meet, in the rover frame) and the
    calibrated camera-to-head pose. The server fills it from configuration; nothing here is a default."""

    ptu_position: tuple[float, float, float]
    camera_to_head: np.ndarray

    @classmethod
    def from_offsets(cls, ptu_position: Sequence[float], position: Sequence[float],
                     rotation_rpy_deg: Sequence[float] = (0.0, 0.0, 0.0)) -> SensorMount:
        """From a calibration's position (head frame, m) and small rotation (roll, pitch, yaw in
        degrees, applied about the head axes) away from looking straight along head x."""
        rotation = rotation_rpy(*np.radians(rotation_rpy_deg)) @ CAMERA_AXES_IN_HEAD
        x, y, z = (float(v) for v in ptu_position)
        return cls((x, y, z), rigid(rotation, position))


def head_to_rover(pan: float, tilt: float, ptu_position: Sequence[float] | np.ndarray) -> np.ndarray:
    """4x4 head-to-rover pose for PTU angles (radians): positive pan right, positive tilt up."""
    return rigid(rotation_z(-pan) @ rotation_y(-tilt), ptu_position)


def camera_to_rover(mount: SensorMount, pan: float, tilt: float) -> np.ndarray:
    return head_to_rover(pan, tilt, mount.ptu_position) @ mount.camera_to_head


def camera_to_world(pose: RoverPose, mount: SensorMount, pan: float, tilt: float) -> np.ndarray:
    """4x4 camera-to-world pose: camera -> head -> pan/tilt -> rover -> world."""
    return pose.to_world() @ camera_to_rover(mount, pan, tilt)


def direction_of(pan: float | np.ndarray, tilt: float | np.ndarray) -> np.ndarray:
    """Unit vectors (..., 3), in the frame the PTU is mounted in, that the head's x axis points
    along at these PTU angles (radians)."""
    pan, tilt = np.broadcast_arrays(np.asarray(pan, np.float64), np.asarray(tilt, np.float64))
    return np.stack([np.cos(tilt) * np.cos(pan), -np.cos(tilt) * np.sin(pan), np.sin(tilt)], axis=-1)


def footprint_polygon(pose: RoverPose, length: float, width: float, margin: float = 0.0) -> np.ndarray:
    """World (x, y) of the rover body's corners (4, 2), counter-clockwise from front-left, grown by
    `margin` on every side. Level-ground approximation: roll and pitch are ignored."""
    half_l, half_w = length / 2 + margin, width / 2 + margin
    local = np.array([[half_l, half_w], [-half_l, half_w], [-half_l, -half_w], [half_l, -half_w]])
    c, s = math.cos(pose.heading), math.sin(pose.heading)
    return np.array([pose.x, pose.y]) + local @ np.array([[c, -s], [s, c]]).T
