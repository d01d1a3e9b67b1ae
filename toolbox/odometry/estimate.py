"""What every odometry method answers: the motion of the sensor since the keyframe, how sure it is,
and how much of the keyframe it found again; or why it could not.

Conventions (OpenCV camera axes: x right, y down, z forward):
  key_from_new   4 x 4: the new camera's pose in the keyframe camera's frame (a point p in the new
                 camera's frame is key_from_new @ p in the keyframe's)
  covariance     6 x 6 over delta = (rotation vector rad, translation m), a right perturbation:
                 true key_from_new = key_from_new @ exp(delta); first order, from the residuals
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["MotionEstimate", "OdometryFailure", "exp_se3"]


@dataclass(frozen=True)
class MotionEstimate:
    key_from_new: np.ndarray    # 4 x 4
    covariance: np.ndarray      # 6 x 6, (rotation vector, translation) right perturbation
    matches: int                # correspondences tried (keyframe to new frame)
    inliers: int                # correspondences the estimate explains
    overlap: float              # share of the keyframe's usable features or points found again, 0..1
    rms: float                  # inliers' residual: pixels (stereo) or metres (depth)
    method: str = ""            # what measured it: pnp (stereo), icp, icp-rotation (a turn on the spot)


class OdometryFailure(Exception):
    """The two looks cannot be related. `reason` is a short token for the protocol's
    `orient failed: REASON: SENTENCE` (few-features, no-overlap, few-inliers, no-depth, diverged)."""

    def __init__(self, reason: str, sentence: str):
        super().__init__(f"{reason}: {sentence}")
        self.reason, self.sentence = reason, sentence


def exp_se3(delta: np.ndarray) -> np.ndarray:
    """4 x 4 transform of a (rotation vector, translation) perturbation (rotation by Rodrigues, the
    translation taken as is: first order is all the covariance claims)."""
    delta = np.asarray(delta, dtype=np.float64)
    omega, v = delta[:3], delta[3:]
    angle = float(np.linalg.norm(omega))
    if angle < 1e-12:
        rotation = np.eye(3)
    else:
        k = omega / angle
        kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
        rotation = np.eye(3) + np.sin(angle) * kx + (1 - np.cos(angle)) * kx @ kx
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = rotation, v
    return out
