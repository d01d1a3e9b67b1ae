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
With routes.toml `orient` a simulated drive leg is made in parts with an orient look after each
(rvs_server/orientation), each part aimed back at the leg's straight line: the wheels' heading creep
and slip over the leg are measured and taken out instead of carried to its end. A GNC's drives are
its own to steer.
"""
from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np

from rvs_server.devices.rover import Pace, turn_and_distance
from rvs_server.jobs import JobContext
from rvs_server.mapping import point_ptu, stereo_intrinsics
from rvs_server.orientation import OrientFailed, orient_here
from rvs_server.protocol import DeviceError
from toolbox.geometry import RoverPose
from toolbox.routes.match import PlaceMatcher, grey_image

if TYPE_CHECKING:
    from rvs_server.host import Host

MIN_PART_M = 0.02          # a drive leg's rest shorter than this is left to the image approach
MIN_TURN_RAD = math.radians(0.05)
LOOKAHEAD_M = 1.0          # a drive leg's parts steer toward its line this far ahead
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
        self.orient_looks: list[dict[str, Any]] = []
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

    def blind(self, kind: str, metres: float) -> None:
        if self.settings.orient and self.drive.simulated:
            self._drive_looking(kind, metres)
        else:
            self.act(kind, metres)

    def _drive_looking(self, kind: str, metres: float) -> None:
        """A drive of `metres` along the heading the rover has now, in parts of at most orient_step_m:
        each part turns toward that line's point LOOKAHEAD_M ahead of where the last look put the
        rover (backing up: its rear toward it), and a look after each says how far along it is."""
        sign = 1.0 if kind == "forward" else -1.0
        start, fused = self._orient()
        if not fused:   # a new chain (or a refused look): its heading is dead reckoning's; a second look
            start, _ = self._orient()    # where it stands fuses the sun, so the line is the true heading's
        ux, uy = math.cos(start.heading), math.sin(start.heading)
        step, done = self.settings.orient_step_m, 0.0
        for _ in range(math.ceil(metres / step) + 2):      # + 2: a part may fall short
            if metres - done < MIN_PART_M:
                break
            part = min(metres, done + step) - done
            ahead = done + max(part, LOOKAHEAD_M)       # steer at a point well ahead: a short part aimed
            aim = (start.x + sign * ahead * ux, start.y + sign * ahead * uy)   # at its own end would swerve
            here = self.device.pose_estimate
            facing = here.heading + (math.pi if sign < 0 else 0.0)
            turn, _ = turn_and_distance((here.x, here.y, facing), aim)
            if abs(turn) > MIN_TURN_RAD:
                self.act("turn", turn)
            self.act(kind, part)
            here, _ = self._orient()
            done = sign * ((here.x - start.x) * ux + (here.y - start.y) * uy)

    def _orient(self) -> tuple[RoverPose, bool]:
        """An orient look: the pose estimate it leaves (dead reckoning's if the look was refused), and
        whether it was measured and fused (not the first look of a chain, not refused)."""
        self.ctx.safe_point()
        try:
            outcome = orient_here(self.ctx, self.settings.orient_sensor, self.ctx.settings_of("orientation"))
        except OrientFailed as failed:
            self.orient_looks.append({"failed": failed.failure.reason, "sentence": failed.failure.sentence})
            return self.device.pose_estimate, False
        self.orient_looks.append({"failed": None, "sources": outcome.sources})
        return self.device.pose_estimate, not outcome.keyframe


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
