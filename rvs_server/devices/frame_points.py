"""One frame of either 3-D sensor, for the background activities (hazard detection, tracking).

Taking the frame and making points of it are two calls: `grab` runs while the activity holds the
devices; `points` turns the frame into points in the camera frame, the pixels to trust and the
camera's pose once the devices are given back (a job waits for the grab, never for the processing),
for the PTU angles of the frame (a unit that turned during the grab: the mean of before and after).
- TOF: one SR4000 frame, pixels below mapping.toml `min_confidence` or beyond `max_range_m` dropped;
  with `tof_max_distance_m` the camera's modulation is switched to the shortest non-ambiguity range
  that covers it (15 MHz: 10 m), with `tof_max_integration` its exposure capped (the frame time is
  four exposures): the activity's settings stay in force between its frames and the device gives a
  job the camera's own back when it takes the camera (devices/tof.py).
- Stereo: one triggered pair in a binned resolution mode (fewer pixels to read out, match and,
  simulated, render), the cameras' own mode given back after the frame.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from toolbox.colour import grey
from toolbox.geometry import RoverPose, camera_to_world, relative_pose
from toolbox.mapping.stereo import SgbmConfig, StereoCalibration, rectification, stereo_points

if TYPE_CHECKING:
    from rvs_server.host import Host

SENSOR_DEVICE = {"tof": "tof", "stereo": "cameras"}


@dataclass(frozen=True)
class FrameSettings:
    sensor: str                          # tof | stereo
    max_range_m: float                   # points farther from the camera are dropped
    stereo_resolution: str = "low"
    stereo_disparities: int = 64
    stereo_min_disparity: int = 0             # the matcher's search starts here (pixels)
    tof_max_distance_m: float | None = None   # None: the camera's own modulation
    min_confidence: int | None = None         # TOF; None: mapping.toml's
    tof_max_integration: int | None = None    # TOF: the exposure (register) auto exposure may reach


class FramePoints:
    """Grabs one frame of `settings.sensor` for an activity and makes points of it; rectification made once."""

    def __init__(self, server: Host, settings: FrameSettings):
        self.settings = settings
        self.device = SENSOR_DEVICE[settings.sensor]
        mapping = server.settings_of("mapping")
        self.min_confidence = mapping.min_confidence if settings.min_confidence is None else settings.min_confidence
        self.max_range_m = settings.max_range_m if settings.sensor == "stereo" else min(
            settings.max_range_m, settings.tof_max_distance_m or mapping.max_range_m)
        self.mounts = server.calibration().mounts
        self._rectified: tuple | None = None

    def grab(self, devices: Any) -> Any:
        """The frame (run while the devices are held): a TOF grab result or the stereo pair's images."""
        if self.settings.sensor == "tof":
            return self._tof(devices)
        pair = devices.cameras.ready_driver()
        if self._rectified is None:
            self._rectified = self._rectification(pair)
        return binned_grab(pair, self.settings.stereo_resolution, devices.cameras.grab_timeout_s)

    def timestamp(self, frame: Any) -> float | None:
        """The clock time the frame shows (TOF: the middle of its exposure; stereo: the trigger pulse)."""
        if self.settings.sensor == "tof":
            return frame.frame.timestamp
        left = frame["left"]
        return left.trigger_time_s if left.trigger_time_s is not None else left.timestamp_s

    def points(self, frame: Any, pose: RoverPose, pan_deg: float,
               tilt_deg: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Points in the camera frame (H, W, 3), the pixels to trust and the camera-to-world pose, for
        the PTU angles and the rover pose of the frame (run once the devices are given back)."""
        pan, tilt = math.radians(pan_deg), math.radians(tilt_deg)
        if self.settings.sensor == "tof":
            points = frame.frame.xyz()
            valid = frame.defined & (np.linalg.norm(np.nan_to_num(points, nan=np.inf), axis=-1) <= self.max_range_m)
            return points, valid, camera_to_world(pose, self.mounts["tof"], pan, tilt)
        rect, config = self._rectified
        left, right = (grey(frame[role].image) for role in ("left", "right"))
        points, valid = stereo_points(left, right, rect, config)
        return (points, valid & (points[..., 2] < self.max_range_m),
                camera_to_world(pose, self.mounts["left"], pan, tilt))

    def _tof(self, devices: Any) -> Any:
        tof = devices.tof
        camera = tof.ready_driver()
        if self.settings.tof_max_distance_m is not None or self.settings.tof_max_integration is not None:
            own = tof.own_settings()
            wanted = own.model_copy(update=self._tof_changes(own))
            if camera.settings().model_copy(update={"integration_time": wanted.integration_time}) != wanted:
                tof.use_settings(wanted)
        return tof.grab(frames=1, min_confidence=self.min_confidence, settle_frames=0, camera=camera)

    def _tof_changes(self, own: Any) -> dict[str, Any]:
        from drivers.sr4000 import frequency_for_range
        changes: dict[str, Any] = {}
        if self.settings.tof_max_distance_m is not None:
            changes["modulation_frequency"] = frequency_for_range(self.settings.tof_max_distance_m, True)
        if self.settings.tof_max_integration is not None:
            changes["auto_exposure_max"] = min(own.auto_exposure_max, self.settings.tof_max_integration)
            changes["integration_time"] = min(own.integration_time, self.settings.tof_max_integration)
        return changes

    def release(self, devices: Any) -> None:
        """The activity ends: the sensor's own settings back."""
        if self.settings.sensor == "tof":
            devices.tof.restore_settings()

    def _rectification(self, pair: Any):
        """The pair's rectification in the binned mode, from the calibrated mounts (they do not move
        with the PTU, so the pan and tilt do not matter)."""
        mode = self.settings.stereo_resolution
        left, right = (pair.camera(role).intrinsics(mode) for role in ("left", "right"))
        level = RoverPose(0.0, 0.0)
        left_pose = camera_to_world(level, self.mounts["left"], 0.0, 0.0)
        right_pose = camera_to_world(level, self.mounts["right"], 0.0, 0.0)
        rect = rectification(StereoCalibration(left, right, relative_pose(left_pose, right_pose)))
        return rect, SgbmConfig(min_disparity=self.settings.stereo_min_disparity,
                                num_disparities=self.settings.stereo_disparities, block_size=5)


def binned_grab(pair: Any, mode: str, timeout_s: float) -> dict:
    """One triggered pair in the resolution mode `mode`, the cameras' own mode given back afterwards
    for the job's next images."""
    own = pair.settings
    if own.resolution == mode:
        return pair.grab("both", timeout_s=timeout_s)
    pair.apply(own.with_changes(resolution=mode))
    try:
        return pair.grab("both", timeout_s=timeout_s)
    finally:
        pair.apply(own)
