"""The sun sensor's heading and the odometry chain's belief: exact cases and first-order spreads."""
import math

import numpy as np
import pytest

from toolbox.geometry import RoverPose, rotation_rpy
from toolbox.odometry.chain import PlanarBelief, carry, fuse_heading, planar, with_drift
from toolbox.odometry.estimate import exp_se3
from toolbox.odometry.sun import sun_heading, sun_heading_sigma, sun_world_vector


@pytest.mark.parametrize("heading_deg, roll_deg, pitch_deg", [(0, 0, 0), (73, 4, -6), (-170, -8, 3), (179, 0, 10)])
def test_sun_heading_recovers_the_heading_on_a_slope(heading_deg, roll_deg, pitch_deg):
    sun = sun_world_vector(135.0, 35.0)
    roll, pitch, heading = (math.radians(v) for v in (roll_deg, pitch_deg, heading_deg))
    body = rotation_rpy(roll, pitch, heading).T @ sun
    assert math.degrees(sun_heading(body, roll, pitch, sun)) == pytest.approx(heading_deg, abs=1e-9)


def test_sun_heading_error_matches_its_sigma():
    """Monte Carlo of sensor and inclinometer noise against the first-order sigma."""
    rng = np.random.default_rng(3)
    sun, elevation = sun_world_vector(200.0, 50.0), math.radians(50.0)
    sensor, tilt = math.radians(0.2), math.radians(0.1)
    errors = []
    for _ in range(4000):
        roll, pitch, heading = rng.uniform(-0.1, 0.1), rng.uniform(-0.1, 0.1), rng.uniform(-3, 3)
        body = rotation_rpy(roll, pitch, heading).T @ sun
        noisy = body + rng.normal(0, sensor, 3)
        noisy -= (noisy - body) @ body * body       # angular noise only: across the sun direction
        estimate = sun_heading(noisy / np.linalg.norm(noisy), roll + rng.normal(0, tilt),
                               pitch + rng.normal(0, tilt), sun)
        errors.append(math.atan2(math.sin(estimate - heading), math.cos(estimate - heading)))
    assert np.std(errors) == pytest.approx(sun_heading_sigma(sensor, tilt, elevation), rel=0.15)


def test_carry_composes_camera_motion_into_rover_motion():
    # A camera looking forward along the rover's x (OpenCV axes: z forward, x right, y down).
    camera_to_rover = np.eye(4)
    camera_to_rover[:3, :3] = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]])
    camera_to_rover[:3, 3] = [0.2, 0.0, 1.4]
    key = PlanarBelief(RoverPose(2.0, 3.0, 0.0, math.radians(90)).to_world(), np.zeros((3, 3)))
    forward = np.eye(4)
    forward[2, 3] = 1.5                       # 1.5 m along the camera's z
    moved = carry(key, camera_to_rover, forward, np.zeros((6, 6)), camera_to_rover)
    assert planar(moved.rover_to_world) == pytest.approx([2.0, 4.5, math.radians(90)], abs=1e-9)


def test_carry_propagates_the_motion_covariance_to_first_order():
    camera_to_rover = np.eye(4)
    camera_to_rover[:3, :3] = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]])
    key = PlanarBelief(RoverPose(0.0, 0.0).to_world(), np.diag([1e-4, 1e-4, 1e-6]))
    motion = np.eye(4)
    motion[2, 3] = 2.0
    sigma = np.diag([1e-6, 4e-6, 1e-6, 1e-4, 1e-4, 4e-4])
    carried = carry(key, camera_to_rover, motion, sigma, camera_to_rover)
    rng = np.random.default_rng(5)
    samples = []
    for _ in range(3000):
        start = RoverPose(*rng.multivariate_normal([0, 0], key.covariance[:2, :2]), 0.0,
                          rng.normal(0, 1e-3)).to_world()
        new = (start @ camera_to_rover @ motion @ exp_se3(rng.multivariate_normal(np.zeros(6), sigma))
               @ np.linalg.inv(camera_to_rover))
        samples.append(planar(new))
    sampled = np.cov(np.array(samples).T)
    assert np.diag(sampled) == pytest.approx(np.diag(carried.covariance), rel=0.1)
    scale = np.sqrt(np.outer(np.diag(sampled), np.diag(sampled)))
    assert sampled / scale == pytest.approx(carried.covariance / scale, abs=0.1)   # correlations


def test_fuse_heading_pulls_by_the_ratio_of_variances_and_gates_outliers():
    belief = PlanarBelief(RoverPose(0.0, 0.0, 0.0, 0.0).to_world(), np.diag([1e-2, 1e-2, 4e-4]))
    fused, fix = fuse_heading(belief, 0.01, 0.02)        # equal variances: half-way
    assert fix.used and planar(fused.rover_to_world)[2] == pytest.approx(0.005)
    assert fused.covariance[2, 2] == pytest.approx(2e-4)
    same, refused = fuse_heading(belief, 1.0, 0.02, gate=5.0)
    assert not refused.used and same is belief


def drifting_chain(drift_sigma: float, steps: int = 60, seed: int = 3) -> tuple[float, PlanarBelief]:
    """A chain of 1 m motions whose measured heading each gains 0.02 deg more than the rover turned
    (stereo's systematic error, exaggerated), re-keyed at every look and fused with a sun heading of
    0.12 deg sigma: the heading error at the end (deg), and the last belief."""
    camera_to_rover = np.eye(4)
    camera_to_rover[:3, :3] = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]])
    rng = np.random.default_rng(seed)
    motion_sigma, sun_sigma = math.radians(0.005), math.radians(0.12)
    motion_covariance = np.diag([motion_sigma ** 2] * 3 + [1e-6] * 3)
    belief = PlanarBelief(RoverPose(0.0, 0.0).to_world(), np.diag([1e-4, 1e-4, math.radians(0.1) ** 2]))
    if drift_sigma > 0:
        belief = with_drift(belief, math.radians(drift_sigma))
    true_heading = 0.0
    for _ in range(steps):
        rover_motion = RoverPose(1.0, 0.0, 0.0, math.radians(0.02) + rng.normal(0, motion_sigma)).to_world()
        key_from_new = np.linalg.inv(camera_to_rover) @ rover_motion @ camera_to_rover
        belief = carry(belief, camera_to_rover, key_from_new, motion_covariance, camera_to_rover,
                       drift_walk=math.radians(0.0005))
        belief, _ = fuse_heading(belief, true_heading + rng.normal(0, sun_sigma), sun_sigma)
    return math.degrees(abs(planar(belief.rover_to_world)[2] - true_heading)), belief


def test_a_heading_drift_state_learns_the_odometrys_drift_from_the_sun():
    """Stereo's heading errors run the same way for tens of metres: believed independent, the chain
    grows sure of its heading and the sun barely moves it; with a drift state the sun's readings
    teach the drift and the heading follows the sun."""
    without = [drifting_chain(0.0, seed=seed)[0] for seed in range(8)]
    learnt = [drifting_chain(0.05, seed=seed) for seed in range(8)]
    assert np.median([error for error, _ in learnt]) < 0.5 * np.median(without), (learnt, without)
    drifts = [math.degrees(belief.drift) for _, belief in learnt]
    assert np.median(drifts) == pytest.approx(0.02, abs=0.008)
    assert all(belief.covariance.shape == (4, 4) for _, belief in learnt)
