"""Configuration of the simulated hopping rover: body, camera, launch errors, bounces and sensors.

Small frozen pydantic models, one per part, with the defaults in the code (see hopper.py for the
simulation that uses them). Lengths in metres, times in seconds, angles in degrees (these are
human-facing settings); the simulation converts to radians where it computes.

Defaults follow the hopping paper's simulation: Moon gravity, a wide-angle camera looking 45 degrees
down in the direction of travel, hops of about 1 m recorded in about 50 frames, secondary bounces
that move the rover by an amount it cannot see.
"""
from __future__ import annotations

import math

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from toolbox.camera import Intrinsics
from toolbox.geometry import CAMERA_AXES_IN_HEAD, rotation_y

MOON_GRAVITY = 1.62  # m/s^2; the same value as toolbox.hopping.parabola (drivers never import it)


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class HopperCamera(_Model):
    """The hopper's one camera: a wide-angle pinhole fixed to the body, and its exposure.

    The optical axis lies in the body's x-z plane (x forward, y left, z up), `depression_deg` below
    x, so with the body level it looks 45 degrees down along the direction of travel.

    Frame rate: the planner's default launch is 60 degrees up; a 1 m hop at 1.62 m/s^2 then lasts
    2 v sin(60) / g = 1.46 s, which at 34 Hz gives 50 frames, the paper's compromise between
    reconstruction quality and cost (its simulation: 49 frames in 1.6 s, about 31 Hz).

    Exposure: set once on the ground before launch (auto exposure to `target_grey_level`, as the
    stereo emulator does), at most `max_exposure_ms` so the flight's motion blur stays small, and
    kept for the whole hop. With `motion_blur` each frame averages `blur_samples` renders spread over
    the exposure, centred on the frame's timestamp.
    """

    width: int = Field(640, gt=0)
    height: int = Field(480, gt=0)
    vertical_fov_deg: float = Field(94.4, gt=0.0, lt=180.0)
    depression_deg: float = Field(45.0, ge=-90.0, le=90.0)
    # Optical centre in the body frame, from the centre of mass (the body's origin).
    position_m: tuple[float, float, float] = (0.12, 0.0, 0.05)
    k1: float = 0.0
    k2: float = 0.0
    frame_rate_hz: float = Field(34.0, gt=0.0, le=1000.0)
    max_exposure_ms: float = Field(8.0, gt=0.0, le=100.0)
    target_grey_level: int = Field(100, ge=1, le=254)
    gain_db: float = Field(0.0, ge=0.0, le=24.0)
    motion_blur: bool = True
    blur_samples: int = Field(3, ge=1, le=16)

    def intrinsics(self) -> Intrinsics:
        """Square pixels, principal point at the image centre, the configured vertical field of view."""
        f = (self.height / 2) / math.tan(math.radians(self.vertical_fov_deg) / 2)
        return Intrinsics(width=self.width, height=self.height, fx=f, fy=f, cx=(self.width - 1) / 2,
                             cy=(self.height - 1) / 2, k1=self.k1, k2=self.k2)

    def to_body(self) -> np.ndarray:
        """4x4 camera (OpenCV axes) to body transform."""
        pose = np.eye(4)
        # Positive rotation about body y (left) tips the forward axis down.
        pose[:3, :3] = rotation_y(math.radians(self.depression_deg)) @ CAMERA_AXES_IN_HEAD
        pose[:3, 3] = self.position_m
        return pose


class LaunchErrors(_Model):
    """One-sigma errors of the spring launch (the paper's sigma_v and sigma_theta; independent, Gaussian).

    Speed error as a fraction of the commanded speed; the elevation and heading errors come from an
    uneven take-off surface and misalignment. A launch force that misses the centre of mass sets the
    body spinning: `spin_deg_s` is the one-sigma spin rate about each body axis (the paper's
    simulation had none, so 0 by default).
    """

    speed_fraction: float = Field(0.03, ge=0.0, le=0.5)
    elevation_deg: float = Field(2.0, ge=0.0, le=30.0)
    heading_deg: float = Field(3.0, ge=0.0, le=90.0)
    spin_deg_s: float = Field(0.0, ge=0.0)


class BounceModel(_Model):
    """Secondary hops after the first touchdown: the displacement the rover cannot see.

    Each bounce leaves with `restitution` times the speed it arrived with, toward a heading drawn
    uniformly within +-spread_deg of the arrival heading, at an elevation drawn uniformly from the
    range; the body turns by a N(0, yaw_deg) yaw per bounce.
    """

    count: int = Field(2, ge=0, le=10)
    restitution: float = Field(0.35, ge=0.0, le=1.0)
    spread_deg: float = Field(90.0, ge=0.0, le=180.0)
    elevation_range_deg: tuple[float, float] = (30.0, 70.0)
    yaw_deg: float = Field(20.0, ge=0.0)

    @model_validator(mode="after")
    def _check(self) -> BounceModel:
        low, high = self.elevation_range_deg
        if not 0.0 < low <= high < 90.0:
            raise ValueError(f"elevation_range_deg must be (low, high) with 0 < low <= high < 90, "
                             f"got {self.elevation_range_deg}")
        return self


class HopperSensors(_Model):
    """Noise of the attitude sensors: accelerometer gravity direction and sun-sensor heading (1 sigma)."""

    gravity_deg: float = Field(0.5, ge=0.0, le=45.0)
    sun_heading_deg: float = Field(1.0, ge=0.0, le=90.0)


class HopperConfig(_Model):
    """Everything that decides the simulated hopper. The body is a sphere centred on the centre of mass."""

    seed: int = 5
    gravity_mps2: float = Field(MOON_GRAVITY, gt=0.0)
    body_radius_m: float = Field(0.15, gt=0.0, le=1.0)
    camera: HopperCamera = HopperCamera()
    launch_errors: LaunchErrors = LaunchErrors()
    bounce: BounceModel = BounceModel()
    sensors: HopperSensors = HopperSensors()
    # Time step of the touchdown search along the arc (then bisected to microseconds): at hop speeds
    # of a few m/s the body moves about a centimetre per step, far less than its radius.
    contact_step_s: float = Field(0.004, gt=0.0, le=0.05)
