"""The rover as the route commands see it: a camera to look with and actions to take.

Camera (routes.toml `camera`):
    forward  the body-fixed forward camera (drivers/sim/forward_camera.py); the test bed has no such
             camera yet, so it exists on the simulated rover only
    left     the left stereo camera through the PTU at pan 0 and `left_tilt_deg`, one triggered grab,
             grey and resized to `image_width`: works on the real test bed and (slowly) on the simulator
Actions (routes.toml `actions`, as navigation's `drive`):
    simulated  the simulated rover executes them with its drive error (drivers/sim/motion.py)
    gnc        each action goes out as a `navigate` event (action=forward|backward|turn value=...) and
               the job waits for the GNC's `pose X,Y,HEADING` that says it is done
"""
from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np

from drivers.sim.forward_camera import ForwardCamera
from drivers.sim.motion import dead_reckon

from rvs_server.jobs import JobContext
from rvs_server.mapping.steps import point_ptu, stereo_intrinsics
from rvs_server.protocol import BadRequest, DeviceError
from toolbox.geometry import RoverPose
from toolbox.routes.match import PlaceMatcher, grey_image
from rvs_server.navigation.commands import wait_for_pose

if TYPE_CHECKING:
    from rvs_server.host import Host

FORWARD_CAMERA_MISSING = ("routes: camera \"forward\" is the simulated rover's body-fixed camera and the devices are "
                          "real; set camera = \"left\" (routes.toml) to use the left stereo camera")


def check_rover(server: Host, settings: Any) -> None:
    """Refuse, before anything moves, a set-up that cannot work."""
    simulated = server.devices.simulated
    if settings.camera == "forward" and not simulated:
        raise DeviceError(FORWARD_CAMERA_MISSING)
    if settings.camera == "left":
        server.devices["cameras"].require_healthy()
    if settings.actions == "simulated" and not simulated:
        raise BadRequest("routes.actions is simulated but the devices are real: set actions = \"gnc\"")


class RouteRover:
    """Look (grab and describe) and act (drive or turn) for one job; keeps the true path simulated."""

    def __init__(self, ctx: JobContext, settings: Any, matcher: PlaceMatcher | None = None):
        self.ctx, self.settings, self.matcher = ctx, settings, matcher
        self.server = ctx.server
        self.simulated_drive = settings.actions == "simulated" or (settings.actions == "auto" and ctx.devices.simulated)
        self.true_path: list[list[float]] = []
        self.images = 0
        if ctx.devices.simulated:
            self.testbed = ctx.devices.testbed
            self.testbed.wait_for_build()
            self.true_path.append(list(self.testbed.rover.pose))
        if settings.camera == "forward":
            self._forward = forward_camera(ctx.server, settings)
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
        turn = value if kind == "turn" else 0.0
        distance = 0.0 if kind == "turn" else (value if kind == "forward" else -value)
        if self.simulated_drive:
            self._act_simulated(turn, distance)
        else:
            self._act_with_gnc(kind, value)

    def _act_simulated(self, turn: float, distance: float) -> None:
        s = self.settings
        self.ctx.sleep(abs(math.degrees(turn)) / s.turn_rate_deg_s + abs(distance) / s.drive_speed_m_s)
        try:
            motion = self.testbed.drive(turn, distance, s.truth_step_m)
        except ValueError as exc:   # the simulated world ends (a real rover's ground does not)
            raise BadRequest(f"the simulated rover would leave the simulated world: {exc}") from None
        self.true_path.extend(motion.poses[1:].tolist())
        pose = self.server.pose_estimate
        x, y, heading = dead_reckon((pose.x, pose.y, pose.heading), turn, distance)
        self.server.pose_estimate = RoverPose(x, y, pose.z, heading, pose.roll, pose.pitch)

    def _act_with_gnc(self, kind: str, value: float) -> None:
        reports = self.server.pose_reports
        shown = math.degrees(value) if kind == "turn" else value
        self.ctx.publish("navigate", {"job": self.ctx.job.id, "action": kind, "value": f"{shown:.4f}",
                                      "unit": "deg" if kind == "turn" else "m"})
        wait_for_pose(self.ctx, reports, self.settings.pose_timeout_s, f"the route action {kind} {shown:g}")


def forward_camera(server: Host, settings: Any) -> ForwardCamera:
    """The simulated forward camera, one per server and rover (its noise stream continues)."""
    testbed = server.devices.testbed
    camera = getattr(server, "_routes_forward_camera", None)
    if camera is None or camera.rover is not testbed.rover or camera.config != settings.forward_camera:
        camera = ForwardCamera(testbed.rover, settings.forward_camera)
        server._routes_forward_camera = camera
    return camera


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
