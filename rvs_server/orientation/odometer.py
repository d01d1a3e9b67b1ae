"""The server's visual odometer: a keyframe and the belief of where the rover stood when it was
taken; each look is matched against the keyframe, the rover's belief carried through the measured
motion, the sun sensor's heading fused in, and the look kept as the next keyframe only when the
keyframe is about to be lost (so small steps do not add up the error of every step).

The chain starts anew (a keyframe with zero motion) on the first look after start, a `pose`, a
`reset` (the rover device's epoch) or a change of sensor. A look that cannot be matched leaves the
belief alone and becomes the keyframe at the dead-reckoned pose, with the uncertainty of being lost.

The view is kept after any manoeuvre (`look_and_match`): before a look, the keyframe's points are
carried to where dead reckoning puts the rover, and when the view along the heading would see too
little of them the head is turned back to them (toolbox/odometry/aim.py). A look so pointed is
matched there, and then the look along the heading becomes the keyframe at once (the rover has not
moved: its belief is the same), because the next step goes that way.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from toolbox.geometry import RoverPose, apply, invert
from toolbox.odometry.aim import Aim, View, choose_aim, keyframe_points
from toolbox.odometry.chain import HeadingFix, PlanarBelief, carry, fuse_heading, planar, with_drift, wrap
from toolbox.odometry.depth import DepthOdometryParams, depth_motion, depth_picture, depth_turn
from toolbox.odometry.estimate import MotionEstimate, OdometryFailure
from toolbox.odometry.stereo import StereoOdometryParams, match_picture, stereo_keyframe, stereo_motion
from toolbox.odometry.sun import MAX_ELEVATION_DEG, sun_heading, sun_heading_sigma

from .look import Look, take_look, view_limits
from .settings import OrientSettings

if TYPE_CHECKING:
    from rvs_server.host import Host
    from rvs_server.jobs import JobContext

START_SIGMA_M = 0.05      # a chain's first keyframe: where dead reckoning or the GNC put the rover
START_SIGMA_DEG = 2.0


@dataclass
class Keyframe:
    sensor: str
    epoch: int
    data: Any                      # StereoKeyframe or DepthFrame
    belief: PlanarBelief           # the rover when it was taken
    camera_to_rover: np.ndarray
    number: int


@dataclass
class LastLook:
    """Where dead reckoning's guess for the next look starts: the last look's camera motion from
    the keyframe, its camera, and the server's estimate right after it (the belief when it was
    applied), which the drives since have dead-reckoned from."""

    key_from_camera: np.ndarray
    camera_to_rover: np.ndarray
    estimate_after: np.ndarray

    def guess(self, estimate: np.ndarray, camera_to_rover: np.ndarray) -> np.ndarray:
        """key_from_new of a look at `estimate` with `camera_to_rover`, by dead reckoning from the last."""
        return (self.key_from_camera @ invert(self.camera_to_rover) @ invert(self.estimate_after) @ estimate
                @ camera_to_rover)


@dataclass(frozen=True)
class Outcome:
    """One look's result: the belief now (fused), and how it came about."""

    belief: PlanarBelief
    previous: PlanarBelief | None        # the last orient's belief: dx, dy, dheading are against it
    keyframe: bool                       # first look of a chain: zero motion
    rekeyed: bool                        # this look is the keyframe from now on
    keyframe_number: int                 # the keyframe the motion was measured from
    motion: MotionEstimate | None
    odometry: PlanarBelief | None        # the belief before the sun was fused
    sun: HeadingFix | None
    sources: list[str]
    odometry_s: float
    picture: np.ndarray | None


class OrientFailed(Exception):
    """A look that could not be matched (OdometryFailure) with what the product shows of it."""

    def __init__(self, failure: OdometryFailure, picture: np.ndarray | None, keyframe_number: int):
        super().__init__(str(failure))
        self.failure, self.picture, self.keyframe_number = failure, picture, keyframe_number
        self.look: Look | None = None      # set by look_and_match
        self.aim: Aim | None = None


@dataclass
class Odometer:
    keyframe: Keyframe | None = None
    last: PlanarBelief | None = None      # the last look's belief: dx, dy, dheading are against it
    reference: LastLook | None = None
    last_look: tuple[Keyframe, LastLook] | None = None   # the last look, when it is not the keyframe
    keyframes: int = 0
    stereo_params: StereoOdometryParams = field(default_factory=StereoOdometryParams)
    depth_params: DepthOdometryParams = field(default_factory=DepthOdometryParams)

    # ------------------------------------------------------------------------------------------
    def orient(self, look: Look, settings: OrientSettings, epoch: int, apply: bool = True) -> Outcome:
        """Match the look against the keyframe and say where the rover stands; OrientFailed when
        it cannot be matched (the belief stays where it was). `apply`: the caller makes the belief
        the server's estimate (the next look's dead reckoning starts from it)."""
        key = self.keyframe
        estimate = _level(look.estimate, look.roll, look.pitch)
        if key is None or key.epoch != epoch or key.sensor != look.sensor or self.reference is None:
            return self._start(look, estimate, epoch, settings)
        started = time.perf_counter()
        guess = self.reference.guess(estimate, look.camera_to_rover)
        try:
            motion, data = self._measure(key, look, guess, estimate, self.reference, settings)
        except OdometryFailure as failure:
            # The keyframe is too far behind: the last look, nearer, may still hold (it becomes the
            # keyframe this look was measured from).
            fallback = self._from_last_look(look, estimate, epoch, settings)
            if fallback is None:
                picture = self._picture(key, look, None)
                self._lost(look, estimate, epoch, key, guess, settings)
                raise OrientFailed(failure, picture, key.number) from None
            key, motion, data = fallback
        odometry_s = time.perf_counter() - started
        carried = carry(key.belief, key.camera_to_rover, motion.key_from_new,
                        motion.covariance * settings.covariance_scale, look.camera_to_rover,
                        heading_scale=settings.heading_sigma_scale.of(look.sensor),
                        drift_walk=math.radians(settings.heading_drift_walk.of(look.sensor)))
        carried = carried.moved(_level(RoverPose.from_matrix(carried.rover_to_world), look.roll, look.pitch))
        belief, fix = self._fuse_sun(carried, look, settings)
        sources = [look.sensor] + (["sun"] if fix is not None and fix.used else [])
        number = key.number
        rekeyed = self._wants_new_keyframe(key, motion, belief, settings)
        after = belief.rover_to_world if apply else estimate
        if rekeyed:
            self.keyframes += 1
            self.keyframe = Keyframe(look.sensor, epoch, data, belief, look.camera_to_rover, self.keyframes)
            self.reference = LastLook(np.eye(4), look.camera_to_rover, after)
            self.last_look = None
        else:
            self.reference = LastLook(motion.key_from_new, look.camera_to_rover, after)
            self.last_look = (Keyframe(look.sensor, epoch, data, belief, look.camera_to_rover, 0),
                              LastLook(np.eye(4), look.camera_to_rover, after))
        previous, self.last = self.last, belief
        return Outcome(belief, previous, False, rekeyed, number, motion, carried, fix, sources, odometry_s,
                       self._picture(key, look, motion))

    def aim(self, estimate: RoverPose, epoch: int, sensor: str, settings: OrientSettings, mount: Any,
            pan_range_deg: tuple[float, float], tilt_range_deg: tuple[float, float]) -> Aim:
        """Where the next look should point: along the heading while that view would still see
        `aim_share` of the keyframe's points, else back at them (the keyframe carried to
        `estimate` by the same dead reckoning the match starts from)."""
        home_tilt = settings.tilt_deg.of(sensor)
        key, reference = self.keyframe, self.reference
        if key is None or key.epoch != epoch or key.sensor != sensor or reference is None:
            return Aim(0.0, home_tilt, 1.0, 1.0, False)
        # key_from_rover now, by dead reckoning since the last look (LastLook.guess without the camera)
        key_from_rover = (reference.key_from_camera @ invert(reference.camera_to_rover)
                          @ invert(reference.estimate_after) @ _level(estimate, estimate.roll, estimate.pitch))
        rover_from_key = invert(key_from_rover)
        points_rover = apply(rover_from_key, keyframe_points(key.data))
        # Interest points need the ground seen from nearly where the keyframe saw it; ICP on the
        # TOF's points only needs the ground.
        key_camera = rover_from_key[:3, 3] if sensor == "stereo" else None   # the keyframe camera, here
        return choose_aim(points_rover, mount, self._view(key), home_tilt, pan_range_deg, tilt_range_deg,
                          settings.aim_share.of(sensor), key_camera_rover=key_camera)

    def rekey_here(self, look: Look, epoch: int) -> bool:
        """Make `look`, taken where the last matched look was (only the head turned), the keyframe
        with that look's belief; False (nothing changed) when it holds nothing to match."""
        if self.last is None or self.reference is None:
            return False
        try:
            data = self._frame(look)
        except OdometryFailure:
            return False
        self.keyframes += 1
        self.keyframe = Keyframe(look.sensor, epoch, data, self.last, look.camera_to_rover, self.keyframes)
        self.reference = LastLook(np.eye(4), look.camera_to_rover, self.reference.estimate_after)
        self.last_look = None
        return True

    def _view(self, key: Keyframe) -> View:
        if key.sensor == "stereo":
            c = key.data.camera
            return View(c.width, c.height, c.fx, c.fy, c.cx, c.cy, self.stereo_params.max_depth_m)
        d = key.data
        h, w = d.valid.shape
        return View(w, h, d.fx, d.fy, d.cx, d.cy, self.depth_params.max_range_m, margin_px=2.0)

    def shift(self, correction: np.ndarray) -> None:
        """Something better than odometry (navigate's alignment to its map) moved the estimate by
        `correction` (world frame, 4 x 4): move the chain with it."""
        key, reference = self.keyframe, self.reference
        if key is not None:
            key.belief = key.belief.moved(correction @ key.belief.rover_to_world)
        if reference is not None:
            reference.estimate_after = correction @ reference.estimate_after
        if self.last_look is not None:
            frame, last = self.last_look
            frame.belief = frame.belief.moved(correction @ frame.belief.rover_to_world)
            last.estimate_after = correction @ last.estimate_after
        if self.last is not None:
            self.last = self.last.moved(correction @ self.last.rover_to_world)

    # ------------------------------------------------------------------------------------------
    def _start(self, look: Look, estimate: np.ndarray, epoch: int, settings: OrientSettings) -> Outcome:
        started = time.perf_counter()
        try:
            data = self._frame(look)
        except OdometryFailure as failure:   # nothing to keep: the next look tries to start again
            raise OrientFailed(failure, None, 0) from None
        belief = PlanarBelief(estimate, np.diag([START_SIGMA_M ** 2, START_SIGMA_M ** 2,
                                                 math.radians(START_SIGMA_DEG) ** 2]))
        drift_sigma = settings.heading_drift_deg_per_m.of(look.sensor)
        if drift_sigma > 0:         # the odometry's heading drift, learnt against the sun from here on
            belief = with_drift(belief, math.radians(drift_sigma))
        self.keyframes += 1
        self.keyframe = Keyframe(look.sensor, epoch, data, belief, look.camera_to_rover, self.keyframes)
        self.reference = LastLook(np.eye(4), look.camera_to_rover, estimate)
        self.last, self.last_look = belief, None
        return Outcome(belief, None, True, True, self.keyframes, None, None, None, [], time.perf_counter() - started,
                       self._picture(self.keyframe, look, None))

    def _from_last_look(self, look: Look, estimate: np.ndarray, epoch: int,
                        settings: OrientSettings) -> tuple[Keyframe, MotionEstimate, Any] | None:
        """The look measured from the last look instead of the keyframe, the last look promoted to
        keyframe; None when there is no such look or it does not match either."""
        if self.last_look is None or self.last_look[0].epoch != epoch:
            return None
        frame, reference = self.last_look
        guess = reference.guess(estimate, look.camera_to_rover)
        try:
            motion, data = self._measure(frame, look, guess, estimate, reference, settings)
        except OdometryFailure:
            return None
        self.keyframes += 1
        frame.number = self.keyframes
        self.keyframe, self.reference, self.last_look = frame, reference, None
        return frame, motion, data

    def _lost(self, look: Look, estimate: np.ndarray, epoch: int, key: Keyframe, guess: np.ndarray,
              settings: OrientSettings) -> None:
        """The look becomes the keyframe at the dead-reckoned pose, as unsure as being lost (the
        estimate stays dead reckoning's); if even it has nothing to match, the old keyframe stays
        (the next look may find it again)."""
        try:
            data = self._frame(look)
        except OdometryFailure:
            return
        dead_reckoned = key.belief.rover_to_world @ key.camera_to_rover @ guess @ invert(look.camera_to_rover)
        lost = np.zeros_like(key.belief.covariance)      # the drift, if any, is the odometry's: it stays
        lost[:3, :3] = np.diag([settings.lost_sigma_m ** 2, settings.lost_sigma_m ** 2,
                                math.radians(settings.lost_sigma_deg) ** 2])
        belief = PlanarBelief(_level(RoverPose.from_matrix(dead_reckoned), look.roll, look.pitch),
                              key.belief.covariance + lost, key.belief.drift)
        self.keyframes += 1
        self.keyframe = Keyframe(look.sensor, epoch, data, belief, look.camera_to_rover, self.keyframes)
        self.reference, self.last_look = LastLook(np.eye(4), look.camera_to_rover, estimate), None

    def _measure(self, key: Keyframe, look: Look, guess: np.ndarray, estimate: np.ndarray, reference: LastLook,
                 settings: OrientSettings) -> tuple[MotionEstimate, Any]:
        """The look's motion from the key, checked against the wheels. Where the first try fails after
        a large turn, a second searches as wide as the wheels can be wrong: a 90 degree turn is
        dead-reckoned to within 2-5 degrees, 30-70 pixels, past the usual window. A TOF look after a
        turn on the spot that free ICP got wrong (it trades yaw for a sideways step) is registered
        again over the rotation about the rover's centre alone: the wheels know it did not step."""
        try:
            motion, data = self._match(key, look, guess)
            self._check_wheels(key, look, motion, guess, estimate, reference, settings)
            return motion, data
        except OdometryFailure:
            since = planar(invert(reference.estimate_after) @ estimate)
            driven, turned = math.hypot(since[0], since[1]), abs(math.degrees(wrap(since[2])))
            if look.sensor == "stereo" and turned >= settings.wide_search_after_deg:
                limit_deg = _wheel_limits(settings, driven, turned)[1]
                radius = look.rig.left.fx * math.tan(math.radians(limit_deg))
                motion, data = self._match(key, look, guess, max(radius, self.stereo_params.search_radius_px),
                                           warp=True)
                self._check_wheels(key, look, motion, guess, estimate, reference, settings)
                return motion, data
            if look.sensor != "tof" or driven > settings.turn_on_spot_m:
                raise
        pivot = invert(look.camera_to_rover)[:3, 3]          # the rover's centre in the camera's frame
        motion = depth_turn(key.data, look.depth, pivot, self.depth_params, guess)
        self._check_wheels(key, look, motion, guess, estimate, reference, settings)
        return motion, look.depth

    @staticmethod
    def _check_wheels(key: Keyframe, look: Look, motion: MotionEstimate, guess: np.ndarray, estimate: np.ndarray,
                      reference: LastLook, settings: OrientSettings) -> None:
        """OdometryFailure (diverged) when the measured motion departs from dead reckoning's by more
        than the wheels can be wrong by since the last look: ICP sliding along flat ground, or
        tracks locked onto a repeated pattern, would otherwise pass for a measurement."""
        since = planar(invert(reference.estimate_after) @ estimate)
        driven, turned = math.hypot(since[0], since[1]), abs(math.degrees(wrap(since[2])))
        measured, wheels = (planar(key.belief.rover_to_world @ key.camera_to_rover @ m @ invert(look.camera_to_rover))
                            for m in (motion.key_from_new, guess))
        off_m = math.hypot(*(measured[:2] - wheels[:2]))
        off_deg = abs(math.degrees(wrap(measured[2] - wheels[2])))
        limit_m, limit_deg = _wheel_limits(settings, driven, turned)
        if off_m > limit_m or off_deg > limit_deg:
            raise OdometryFailure("diverged", f"the {look.sensor} motion departs from the wheels' by {off_m:.2f} m "
                                  f"and {off_deg:.1f} deg after {driven:.2f} m and {turned:.1f} deg: at most "
                                  f"{limit_m:.2f} m and {limit_deg:.1f} deg believed (orient.toml wheels_*)")

    def _frame(self, look: Look) -> Any:
        if look.sensor == "stereo":
            return stereo_keyframe(look.left, look.right, look.rig, self.stereo_params)
        return look.depth

    def _match(self, key: Keyframe, look: Look, guess: np.ndarray, search_radius_px: float | None = None,
               warp: bool = False) -> tuple[MotionEstimate, Any]:
        if look.sensor == "stereo":
            params = self.stereo_params if search_radius_px is None else self.stereo_params.model_copy(
                update={"search_radius_px": search_radius_px})
            return stereo_motion(key.data, look.left, look.right, look.rig, params, guess=guess, warp=warp)
        return depth_motion(key.data, look.depth, self.depth_params, guess=guess), look.depth

    def _picture(self, key: Keyframe, look: Look, motion: MotionEstimate | None) -> np.ndarray | None:
        if look.sensor == "stereo":
            return match_picture(key.data, look.left, motion, self.stereo_params)
        return depth_picture(key.data, look.depth, motion)

    @staticmethod
    def _fuse_sun(belief: PlanarBelief, look: Look, settings: OrientSettings) -> tuple[PlanarBelief, HeadingFix | None]:
        sun = look.sun
        if not settings.sun or sun is None:
            return belief, None
        elevation = math.asin(float(np.clip(sun.world[2], -1.0, 1.0)))
        if math.degrees(elevation) > MAX_ELEVATION_DEG:
            return belief, None
        heading = sun_heading(sun.body, look.roll, look.pitch, sun.world)
        sigma = sun_heading_sigma(sun.sigma, sun.tilt_sigma, elevation)
        return fuse_heading(belief, heading, sigma, settings.sun_gate_sigmas)

    @staticmethod
    def _wants_new_keyframe(key: Keyframe, motion: MotionEstimate, belief: PlanarBelief,
                            settings: OrientSettings) -> bool:
        """Keep the keyframe while the next step will still find it: re-key when little of it was
        found again, or the rover is far from it or has turned away."""
        here, there = belief.pose, key.belief.pose
        return (motion.overlap < settings.rekey_overlap.of(key.sensor)
                or (key.sensor == "stereo" and motion.inliers < settings.rekey_inliers)
                or math.hypot(here.x - there.x, here.y - there.y) > settings.max_keyframe_m.of(key.sensor)
                or abs(math.degrees(wrap(here.heading - there.heading))) > settings.max_keyframe_deg)


def _wheel_limits(settings: OrientSettings, driven: float, turned: float) -> tuple[float, float]:
    """How far (m, deg) dead reckoning may be off after `driven` metres and `turned` degrees."""
    return (settings.wheels_m + settings.wheels_per_m * driven,
            settings.wheels_deg + settings.wheels_deg_per_deg * turned + settings.wheels_deg_per_m * driven)


def _level(pose: RoverPose, roll: float, pitch: float) -> np.ndarray:
    """The pose with the inclinometer's roll and pitch: those are absolute, odometry's drift."""
    return RoverPose(pose.x, pose.y, pose.z, pose.heading, roll, pitch).to_world()


def odometer_of(server: Host) -> Odometer:
    return server.state_of("orientation")


@dataclass(frozen=True)
class Sighting:
    """A look pointed where its keyframe is, matched, and (when it was pointed away from the
    heading) the look along the heading that became the keyframe after it."""

    look: Look
    aim: Aim
    outcome: Outcome
    home: Look | None


def look_and_match(ctx: JobContext, sensor: str, settings: OrientSettings, apply: bool = True) -> Sighting:
    """Aim, look, match; after a pointed look, re-key along the heading. OrientFailed (with `look`
    and `aim` set on it) when the look cannot be matched; the caller applies the belief."""
    rover, odometer = ctx.devices.rover, odometer_of(ctx.server)
    mount = ctx.server.calibration().mounts["left" if sensor == "stereo" else "tof"]
    pan_range, tilt_range = view_limits(ctx)
    aim = odometer.aim(rover.pose_estimate, rover.epoch, sensor, settings, mount, pan_range, tilt_range)
    look = take_look(ctx, sensor, settings, aim.pan_deg, aim.tilt_deg)
    try:
        outcome = odometer.orient(look, settings, rover.epoch, apply=apply)
    except OrientFailed as failed:
        failed.look, failed.aim = look, aim
        raise
    home = None
    if aim.pointed and not outcome.keyframe:
        ctx.safe_point()
        home = take_look(ctx, sensor, settings)
        if not odometer.rekey_here(home, rover.epoch):
            home = None
    return Sighting(look, aim, outcome, home)


def orient_here(ctx: JobContext, sensor: str, settings: OrientSettings) -> Outcome:
    """One look matched by the server's odometer, the belief made the rover's pose estimate: for jobs
    that orient between their moves (navigate, route-follow). OrientFailed leaves the estimate as
    dead reckoning has it."""
    outcome = look_and_match(ctx, sensor, settings).outcome
    ctx.devices.rover.pose_estimate = outcome.belief.pose
    return outcome
