"""The attitude a rover takes on mapped ground: the plane of the heights under its wheels, and
their height."""
from __future__ import annotations

import math

import numpy as np

from toolbox.grid import GridSpec


def attitude_on_ground(heights: np.ndarray, spec: GridSpec, x: float, y: float, heading: float,
                       radius: float, min_cells: int = 12) -> tuple[float, float] | None:
    """Roll and pitch (radians; roll left side up positive, pitch nose down positive, as RoverPose)
    of a body at (x, y) facing `heading` that rests on the plane fitted by least squares to the known
    heights within `radius` of (x, y). None when fewer than min_cells are known there or they lie
    along a line (no plane)."""
    xs, ys = spec.centres()
    near = (np.hypot(xs[None, :] - x, ys[:, None] - y) <= radius) & np.isfinite(heights)
    if int(near.sum()) < min_cells:
        return None
    rows, cols = np.nonzero(near)
    dx, dy = xs[cols] - x, ys[rows] - y
    design = np.column_stack([dx, dy, np.ones_like(dx)])
    (a, b, _), _, rank, _ = np.linalg.lstsq(design, heights[rows, cols].astype(np.float64), rcond=None)
    if rank < 3:
        return None
    # The plane's normal (-a, -b, 1) seen from the body's heading: forward and left components.
    normal = np.array([-a, -b, 1.0]) / math.sqrt(a * a + b * b + 1.0)
    cos_h, sin_h = math.cos(heading), math.sin(heading)
    forward = normal[0] * cos_h + normal[1] * sin_h
    left = -normal[0] * sin_h + normal[1] * cos_h
    # The body's z axis is the normal: (sin p cos r, -sin r, cos p cos r) in the heading frame.
    roll = math.asin(float(np.clip(-left, -1.0, 1.0)))
    pitch = math.atan2(forward, normal[2])
    return roll, pitch


def height_on_ground(heights: np.ndarray, spec: GridSpec, x: float, y: float, radius: float) -> float | None:
    """The median of the known heights within `radius` of (x, y): where a rover's origin (the mean
    of its wheel contacts) stands on the map; None when none is known there."""
    xs, ys = spec.centres()
    near = (np.hypot(xs[None, :] - x, ys[:, None] - y) <= radius) & np.isfinite(heights)
    return float(np.median(heights[near])) if near.any() else None
