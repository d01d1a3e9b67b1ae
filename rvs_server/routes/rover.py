"""The rover as the route commands see it: a camera to look with and actions to take.

Camera (routes.toml `camera`):
    forward  the body-fixed forward camera (the rover device's, rvs_server/devices/rover.py); the test
             bed has no such camera yet, so it exists on the simulated rover only
    left     the left stereo camera through the PTU at pan 0 and `left_tilt_deg`, one triggered grab,
             grey and resized to `image_width`: works on the real test bed and (slowly) on the simulator
Actions (routes.toml `actions`, as navigation's `drive`; the rover device picks the drive):
    simulated  the simulated rover executes them with its drive error
    gnc        each action goes out as a `navigate` event (action=forward|backward|turn value=...) and
               the job waits for the GNC's `pose X,Y,HEADING` that says it is done
"""
from __future__ import annotations

from typing import TYPE_CHECKING, Any

import cv2
import numpy as np

from rvs_server.devices.rover import Pace
from rvs_server.jobs import JobContext
from rvs_server.mapping import point_ptu, stereo_intrinsics
from rvs_server.protocol import DeviceError
from toolbox.routes.match import PlaceMatcher, grey_image

if TYPE_CHECKING:
    from rvs_server.host import Host

FORWARD_CAMERA_MISSING = ("routes: camera \"forward\" is the simulated rover's body-fixed camera and the devices are "
                          "real; set camera = \"left\" (routes.toml) to use the left stereo camera")


def check_rover(server: Host, settings: Any) -> None:
    """Refuse, before anything moves, a set-up that cannot work."""
    rover = server.devices.rover
    if settings.camera == "forward" and not rover.has_forward_camera:
        raise DeviceError(FORWARD_CAMERA_MISSING)
    if settings.camera == "left":
        server.devices["cameras"].require_healthy()
    rover.drive(settings.actions, "routes.actions")   # refuses a simulated drive with real devices


class RouteRover:
    """Look (grab and describe) and act (drive or turn) for one job; keeps the true path simulated."""

    def __init__(self, ctx: JobContext, settings: Any, matcher: PlaceMatcher | None = None):
        self.ctx, self.settings, self.matcher = ctx, settings, matcher
        self.device = ctx.devices.rover
        self.drive = self.device.drive(settings.actions, "routes.actions")
        self.pace = Pace(settings.truth_step_m, settings.pose_timeout_s)
        self.true_path: list[list[float]] = []
        self.images = 0
        self.device.wait_for_world()
        true = self.device.true_pose()
        if true is not None:
            self.true_path.append(true)
        if settings.camera == "forward":
            self._forward = self.device.forward_camera(settings.forward_camera)
            self.focal_px = float(self._forward.camera.fx)
        else:
            self._forward = None
            self.focal_px = left_focal_px(ctx, settings)

    # ---------------------------------------------------------------------------------- looking
    def grab(self) -> np.ndarray:
        self.ctx.safe_point()
        self.images += 1
        if self._forward is not None:
            return self._forward.grab()
        return grab_left(self.ctx, self.settings)

    def look(self) -> Any:
        return self.matcher.describe(self.grab())

    # ---------------------------------------------------------------------------------- acting
    def act(self, kind: str, value: float) -> None:
        self.ctx.safe_point()
        self.true_path.extend(self.drive.act(self.ctx, kind, value, self.pace).true_path)


def grab_left(ctx: JobContext, settings: Any) -> np.ndarray:
    """One left-camera image at pan 0 and the route tilt, grey, at the route image width."""
    point_ptu(ctx, 0.0, settings.left_tilt_deg)
    frames = ctx.devices.cameras.require().grab("left", timeout_s=ctx.devices.cameras.grab_timeout_s)
    grey = grey_image(frames["left"].image)
    height = round(grey.shape[0] * settings.image_width / grey.shape[1])
    return cv2.resize(grey, (settings.image_width, height), interpolation=cv2.INTER_AREA)


def left_focal_px(ctx: JobContext, settings: Any) -> float:
    """The left camera's focal length in pixels of the resized route image."""
    left, _ = stereo_intrinsics(ctx)
    return float(left.fx) * settings.image_width / float(left.width)
