"""Where a look should point so that it finds its keyframe again.

A look along the heading loses the keyframe after any real manoeuvre: a turn of more than about
15 degrees takes the keyframe's ground out of a 40-degree view, and a turn plus a metre forward
leaves little of it. The rover has a pan-tilt head, so the sensor can be turned back to that ground.
The keyframe's own points, carried into the rover's frame of now by dead reckoning, are projected
into the views the head can take; the share of them each view would see is the overlap to expect.

    matchable       the points seen from near enough the keyframe's direction and distance to match:
                    the same ground seen across a 30 degree change of view, at the grazing angles a
                    mast camera has, warps past what interest points can match, whichever way the
                    head then points (where the camera stands decides it, not where it looks)
    seen_share      the share of the points a view would see (in front, in range, inside the image)
    aim_at          pan and tilt that put a point on the sensor's axis (the head's axes meet at the
                    mast; the camera's small offset from them is left to the search)
    choose_aim      along the heading while it still sees enough; else the best of the views toward
                    the points (their middle, and a sweep of pans at two tilts), within the unit's limits

Pure: arrays and mounts in, angles out. Angles in degrees; pan positive right, tilt positive up.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from toolbox.geometry import SensorMount, apply, camera_to_rover, invert


@dataclass(frozen=True)
class View:
    """What a sensor sees of a point: its image (pinhole, pixels) and how far it measures."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    max_range_m: float
    margin_px: float = 8.0


@dataclass(frozen=True)
class Aim:
    pan_deg: float
    tilt_deg: float
    share: float            # of the keyframe's points this view should see
    along_share: float      # ... and the view along the heading
    pointed: bool           # turned away from the view along the heading


def keyframe_points(data: Any, most: int = 1500) -> np.ndarray:
    """(N, 3) points of a keyframe in its camera frame, at most `most` of them, evenly picked: a
    stereo keyframe's features with a depth, or a depth frame's valid points."""
    if hasattr(data, "with_depth"):
        points = np.asarray(data.points)[data.with_depth]
    else:
        points = np.asarray(data.points)[np.asarray(data.valid, dtype=bool)]
    points = points[np.isfinite(points).all(axis=1)]
    step = max(1, len(points) // most)
    return points[::step].astype(np.float64)


def matchable(points_rover: np.ndarray, key_camera_rover: np.ndarray, camera_rover: np.ndarray,
              max_angle_deg: float = 12.0, max_scale: float = 1.4) -> np.ndarray:
    """(N,) bool: the points whose line of sight from `camera_rover` (where the camera stands now)
    turned less than `max_angle_deg` from the keyframe camera's at `key_camera_rover`, and whose
    distance changed by less than a factor `max_scale`."""
    before = points_rover - np.asarray(key_camera_rover, dtype=float)
    after = points_rover - np.asarray(camera_rover, dtype=float)
    d_before, d_after = np.linalg.norm(before, axis=1), np.linalg.norm(after, axis=1)
    cos = np.einsum("ij,ij->i", before, after) / np.maximum(d_before * d_after, 1e-9)
    ratio = d_after / np.maximum(d_before, 1e-9)
    return (cos >= math.cos(math.radians(max_angle_deg))) & (ratio <= max_scale) & (ratio >= 1 / max_scale)


def seen_share(points_rover: np.ndarray, camera_to_rover_pose: np.ndarray, view: View) -> float:
    """The share of `points_rover` (N, 3, rover frame) a camera there would see."""
    if len(points_rover) == 0:
        return 0.0
    p = apply(invert(camera_to_rover_pose), points_rover)
    z = p[:, 2]
    in_front = (z > 0.1) & (np.linalg.norm(p, axis=1) <= view.max_range_m)
    with np.errstate(divide="ignore", invalid="ignore"):
        u = view.fx * p[:, 0] / z + view.cx
        v = view.fy * p[:, 1] / z + view.cy
    inside = ((u >= view.margin_px) & (u <= view.width - view.margin_px)
              & (v >= view.margin_px) & (v <= view.height - view.margin_px))
    return float(np.count_nonzero(in_front & inside)) / len(points_rover)


def aim_at(point_rover: np.ndarray, mount: SensorMount) -> tuple[float, float]:
    """(pan, tilt) in degrees that point the head's axis at a point of the rover frame."""
    d = np.asarray(point_rover, dtype=float) - np.asarray(mount.ptu_position, dtype=float)
    return -math.degrees(math.atan2(d[1], d[0])), math.degrees(math.atan2(d[2], math.hypot(d[0], d[1])))


def choose_aim(points_rover: np.ndarray, mount: SensorMount, view: View, home_tilt_deg: float,
               pan_range_deg: tuple[float, float], tilt_range_deg: tuple[float, float],
               enough: float, key_camera_rover: np.ndarray | None = None, pan_step_deg: float = 10.0,
               min_gain: float = 0.15) -> Aim:
    """The view to look in: along the heading (pan 0, `home_tilt_deg`) while it would see at least
    `enough` of the keyframe's points; otherwise the view toward them that would see the most, if
    it sees `min_gain` more of them than the view along the heading (a pointed look costs a
    second one along the heading afterwards). With `key_camera_rover` (where the keyframe's camera
    stood, in the rover frame now) the shares count only the points still matchable from here."""
    weights = np.ones(len(points_rover), dtype=bool)
    if key_camera_rover is not None and len(points_rover):
        weights = matchable(points_rover, key_camera_rover, np.asarray(mount.ptu_position, dtype=float))
        if not weights.any():          # nothing matchable from here: at least look where the ground is
            weights[:] = True

    def share(pan: float, tilt: float) -> float:
        pose = camera_to_rover(mount, math.radians(pan), math.radians(tilt))
        return seen_share(points_rover[weights], pose, view) * np.count_nonzero(weights) / max(len(points_rover), 1)

    along = share(0.0, home_tilt_deg)
    if along >= enough or len(points_rover) == 0:
        return Aim(0.0, home_tilt_deg, along, along, False)
    pan_lo, pan_hi = pan_range_deg
    tilt_lo, tilt_hi = tilt_range_deg
    target = points_rover[weights] if np.any(weights) else points_rover
    centre_pan, centre_tilt = aim_at(np.median(target, axis=0), mount)
    centre_tilt = float(np.clip(centre_tilt, tilt_lo, tilt_hi))
    candidates = {(float(np.clip(centre_pan, pan_lo, pan_hi)), centre_tilt)}
    for pan in np.arange(math.ceil(pan_lo / pan_step_deg) * pan_step_deg, pan_hi + 1e-9, pan_step_deg):
        candidates.update({(float(pan), home_tilt_deg), (float(pan), centre_tilt)})
    # The most seen; of equals, the nearest the heading (the next step goes that way).
    pan, tilt, best = max(((p, t, share(p, t)) for p, t in candidates), key=lambda c: (round(c[2], 3), -abs(c[0])))
    if best < along + min_gain:
        return Aim(0.0, home_tilt_deg, along, along, False)
    return Aim(round(pan, 2), round(tilt, 2), best, along, True)
