"""Where the rover stands after a look: the keyframe's pose carried through the odometry's motion,
the uncertainty carried with it, and absolute headings fused in.

The planar state (x, y, heading) and its 3 x 3 covariance are what navigation needs; the full 6-DoF
pose is kept for composing camera motions (the rover stands on slopes):

    new_rover_to_world = key_rover_to_world @ key_camera_to_rover @ key_from_new @ inv(new_camera_to_rover)

The covariance goes through the same function to first order (numerical Jacobians over the
keyframe's planar state and the motion's 6-vector perturbation). A heading measurement (the sun
sensor) is a scalar Kalman update of the planar state, gated: a reading that disagrees by more than
`gate` sigmas is refused rather than believed.

A belief may carry a fourth state, the odometry's heading drift (rad per metre driven; covariance
4 x 4, `with_drift`). Stereo odometry's heading errors are not independent from motion to motion:
on the orient campaign a chain gained about 0.01 deg per look, always the same way, for tens of
metres, and a filter that takes each motion's error as independent grows so sure of its heading
(0.03 deg believed, 0.2 deg off) that the sun moves it by 6 % a look. Each motion's heading is
corrected by the drift times its length, and the drift, correlated with the heading through that
correction, is learnt from the sun's readings; it may wander by `drift_walk` per root metre.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from toolbox.geometry import RoverPose, invert

from .estimate import exp_se3

__all__ = ["HeadingFix", "PlanarBelief", "carry", "fuse_heading", "planar", "with_drift", "wrap"]


def wrap(angle: float) -> float:
    return math.atan2(math.sin(angle), math.cos(angle))


@dataclass(frozen=True)
class PlanarBelief:
    """A 6-DoF rover pose and the covariance of its planar part (x m, y m, heading rad), and with a
    4 x 4 covariance the odometry's heading drift (rad per metre) as a fourth state."""

    rover_to_world: np.ndarray     # 4 x 4
    covariance: np.ndarray         # 3 x 3, or 4 x 4 with the drift
    drift: float = 0.0             # rad per metre driven: what each motion's heading is corrected by

    @property
    def drifts(self) -> bool:
        return self.covariance.shape[0] == 4

    def moved(self, rover_to_world: np.ndarray) -> PlanarBelief:
        """The same belief at another pose (a correction, a level from the inclinometer)."""
        return replace(self, rover_to_world=rover_to_world)

    @property
    def pose(self) -> RoverPose:
        return RoverPose.from_matrix(self.rover_to_world)

    def sigmas(self) -> tuple[float, float]:
        """(position sigma m: the root of the larger eigenvalue of the x, y block; heading sigma rad)."""
        xy = np.linalg.eigvalsh(self.covariance[:2, :2])
        return math.sqrt(max(float(xy[-1]), 0.0)), math.sqrt(max(float(self.covariance[2, 2]), 0.0))


def planar(rover_to_world: np.ndarray) -> np.ndarray:
    pose = RoverPose.from_matrix(rover_to_world)
    return np.array([pose.x, pose.y, pose.heading])


def _with_planar(rover_to_world: np.ndarray, state: np.ndarray) -> np.ndarray:
    """The pose moved to planar state (x, y, heading), height, roll and pitch kept."""
    pose = RoverPose.from_matrix(rover_to_world)
    return RoverPose(float(state[0]), float(state[1]), pose.z, float(state[2]), pose.roll, pose.pitch).to_world()


def _compose(key_rover: np.ndarray, key_camera_to_rover: np.ndarray, key_from_new: np.ndarray,
             new_camera_to_rover: np.ndarray) -> np.ndarray:
    return key_rover @ key_camera_to_rover @ key_from_new @ invert(new_camera_to_rover)


def with_drift(belief: PlanarBelief, sigma: float) -> PlanarBelief:
    """The belief with a heading drift state of 0 +- `sigma` rad per metre (unchanged if it has one)."""
    if belief.drifts:
        return belief
    covariance = np.zeros((4, 4))
    covariance[:3, :3] = belief.covariance
    covariance[3, 3] = sigma ** 2
    return PlanarBelief(belief.rover_to_world, covariance, 0.0)


def carry(key: PlanarBelief, key_camera_to_rover: np.ndarray, key_from_new: np.ndarray, motion_covariance: np.ndarray,
          new_camera_to_rover: np.ndarray, step: float = 1e-6, heading_scale: float = 1.0,
          drift_walk: float = 0.0) -> PlanarBelief:
    """The rover's belief at the new look: the keyframe's belief carried through the camera's motion
    key_from_new (covariance 6 x 6, right perturbation, toolbox/odometry/estimate.py). The motion's
    share of the heading sigma is multiplied by `heading_scale` (what a campaign found it short by:
    the fit's covariance knows the image noise, not the calibration's errors). With a drift state,
    the new heading is corrected by the drift times the motion's length, and the drift's variance
    grows by drift_walk^2 per metre."""
    new = _compose(key.rover_to_world, key_camera_to_rover, key_from_new, new_camera_to_rover)
    centre = planar(new)
    base = planar(key.rover_to_world)

    def difference(moved: np.ndarray) -> np.ndarray:
        d = planar(moved) - centre
        d[2] = wrap(d[2])
        return d / step

    j_key = np.column_stack([difference(_compose(_with_planar(key.rover_to_world, base + step * e),
                                                 key_camera_to_rover, key_from_new, new_camera_to_rover))
                             for e in np.eye(3)])
    j_motion = np.column_stack([difference(_compose(key.rover_to_world, key_camera_to_rover,
                                                    key_from_new @ exp_se3(step * e), new_camera_to_rover))
                                for e in np.eye(6)])
    scale = np.diag([1.0, 1.0, heading_scale])
    motion_part = scale @ j_motion @ motion_covariance @ j_motion.T @ scale
    if not key.drifts:
        covariance = j_key @ key.covariance @ j_key.T + motion_part
        return PlanarBelief(new, 0.5 * (covariance + covariance.T))
    length = float(math.hypot(centre[0] - base[0], centre[1] - base[1]))
    jacobian = np.eye(4)
    jacobian[:3, :3] = j_key
    jacobian[2, 3] = -length                       # heading = measured - drift x length
    covariance = jacobian @ key.covariance @ jacobian.T
    covariance[:3, :3] += motion_part
    covariance[3, 3] += drift_walk ** 2 * length
    corrected = centre.copy()
    corrected[2] = wrap(centre[2] - key.drift * length)
    return PlanarBelief(_with_planar(new, corrected), 0.5 * (covariance + covariance.T), key.drift)


@dataclass(frozen=True)
class HeadingFix:
    """What a heading measurement did: its value and sigma (rad), the innovation in sigmas, and
    whether it was used."""

    heading: float
    sigma: float
    innovation_sigmas: float
    used: bool


def fuse_heading(belief: PlanarBelief, heading: float, sigma: float,
                 gate: float = 5.0) -> tuple[PlanarBelief, HeadingFix]:
    """Kalman update of the planar state with an absolute heading (rad) of 1-sigma `sigma`; refused
    (belief unchanged) when the innovation exceeds `gate` sigmas of its own spread."""
    p = belief.covariance
    state = np.append(planar(belief.rover_to_world), [belief.drift] if belief.drifts else [])
    innovation = wrap(heading - state[2])
    spread = p[2, 2] + sigma ** 2
    nis = abs(innovation) / math.sqrt(spread)
    if nis > gate:
        return belief, HeadingFix(heading, sigma, nis, False)
    gain = p[:, 2] / spread
    state = state + gain * innovation
    state[2] = wrap(state[2])
    covariance = p - np.outer(gain, p[2, :])
    return (PlanarBelief(_with_planar(belief.rover_to_world, state[:3]), 0.5 * (covariance + covariance.T),
                         float(state[3]) if belief.drifts else 0.0),
            HeadingFix(heading, sigma, nis, True))
