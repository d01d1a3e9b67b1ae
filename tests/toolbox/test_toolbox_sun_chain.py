"""The sun sensor's heading and the odometry chain's belief: exact cases and first-order spreads."""
import math

import numpy as np
import pytest

from toolbox.geometry import RoverPose, rotation_rpy
from toolbox.odometry.chain import PlanarBelief, carry, fuse_heading, planar
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
