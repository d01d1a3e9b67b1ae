"""The ground rover's forward camera, for image-based routes: fixed to the body, looking ahead.

The route paper's robot saw the way with one forward-looking camera. Here it is a 640 x 480 camera
with a 60 degree horizontal field of view, 1.0 m above the ground on the mast, tilted 20 degrees
down (the place matchers' thresholds were chosen on this view: tests/bench/bench_route_matchers.py).
Every grab renders the world under its current sun with cast shadows, then the sensor model of the
AVT emulator (shot and read noise, 8 bits) at an auto exposure that brings the mean grey level of
the ground (the lower two thirds of the image) to its target, as a real camera's metering would: a dimmer
sun makes the image no darker on average,
but the shadows move and change length with the sun, which is what defeats a brightness-threshold
matcher.
"""
from __future__ import annotations

import math

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from drivers.avt import CameraSettings
from drivers.avt_sensor import auto_exposure_us, sensor_image
from drivers.sim.render import render
from drivers.sim.rover import Rover
from toolbox.camera import Intrinsics
from toolbox.geometry import CAMERA_AXES_IN_HEAD, rotation_y


class ForwardCameraConfig(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    width: int = Field(640, ge=64, le=4096)
    height: int = Field(480, ge=48, le=4096)
    horizontal_fov_deg: float = Field(60.0, gt=10, lt=170)
    position_m: tuple[float, float, float] = Field((0.20, 0.0, 1.0), description="optical centre in the body "
                                                   "frame (x forward, y left, z up from the ground)")
    tilt_deg: float = Field(-20.0, ge=-80, le=30, description="pitch of the view, negative looks down")
    target_grey_level: int = Field(100, ge=1, le=254, description="auto exposure's mean grey level")
    gain_db: float = Field(0.0, ge=0, le=24)
    seed: int = 11

    @property
    def intrinsics(self) -> Intrinsics:
        return Intrinsics.from_fov(self.width, self.height, math.radians(self.horizontal_fov_deg))

    def camera_to_body(self) -> np.ndarray:
        """4x4 camera (OpenCV axes: x right, y down, z ahead) to body transform."""
        pose = np.eye(4)
        # Tilting down is a positive rotation about the body's y (left) axis.
        pose[:3, :3] = rotation_y(-math.radians(self.tilt_deg)) @ CAMERA_AXES_IN_HEAD
        pose[:3, 3] = self.position_m
        return pose


class ForwardCamera:
    """Grabs what the rover's forward camera sees now, under the world's current sun."""

    def __init__(self, rover: Rover, config: ForwardCameraConfig | None = None):
        self.rover = rover
        self.config = config or ForwardCameraConfig()
        self.camera = self.config.intrinsics
        self._mount = self.config.camera_to_body()
        self._settings = CameraSettings(gain_db=self.config.gain_db, target_grey_level=self.config.target_grey_level)
        self._rng = np.random.default_rng(self.config.seed)

    def pose(self) -> np.ndarray:
        """The camera-to-world pose now (the truth: the rover as it really stands)."""
        return self.rover.body_to_world @ self._mount

    def grab(self) -> np.ndarray:
        """A grey (height, width) uint8 image."""
        view = render(self.rover.world, self.pose(), self.camera, shadows=True)
        radiance = view.intensity
        # Metered on the lower two thirds, the ground: the black sky above the horizon would
        # otherwise push the exposure up until the ground saturates.
        exposure = auto_exposure_us(radiance[radiance.shape[0] // 3:], self._settings)
        return sensor_image(radiance, exposure, self.config.gain_db, self._rng)
