"""End-to-end test of one hop through rvs_server/toolbox/hopping.py (process_hop): an SfM-frame
reconstruction of a hop (noisy camera centres with outliers, the dense cloud) over rocky terrain the
previous hop mapped, launched from a position known only to 15 cm. The chain must recover the metric
scale and gravity, correct the position by ICP against the previous cloud and plan the next hop."""
from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation

from toolbox import hopping
from toolbox.geometry import rotation_z

G = 1.62


def terrain(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    rng = np.random.default_rng(11)
    centres = np.column_stack([rng.uniform(-2, 7, 50), rng.uniform(-3, 3, 50)])
    radius, height = rng.uniform(0.1, 0.3, 50), rng.uniform(0.05, 0.3, 50)
    d2 = (x[:, None] - centres[:, 0]) ** 2 + (y[:, None] - centres[:, 1]) ** 2
    rocks = np.sum(height * np.exp(-d2 / (2 * radius ** 2)), axis=1)
    return 0.1 * np.sin(0.6 * x) + 0.05 * np.cos(0.9 * y) + rocks


def ground_cloud(x_range, y_range, points: int, rng) -> np.ndarray:
    x, y = rng.uniform(*x_range, points), rng.uniform(*y_range, points)
    return np.column_stack([x, y, terrain(x, y)]) + rng.normal(0, 0.003, (points, 3))


def test_process_hop_recovers_scale_position_and_plans_the_next_hop():
    rng = np.random.default_rng(5)
    previous = ground_cloud((-1.5, 3.0), (-2.5, 2.5), 30_000, rng)
    # The true hop: from `launch`, heading 0.2 rad, 60 degrees, 1.5 m on flat-ish ground.
    heading, elevation, distance = 0.2, math.radians(60), 1.5
    launch = np.array([0.5, 0.1, 0.0])
    launch[2] = terrain(launch[:1], launch[1:2])[0] + 0.1
    speed = math.sqrt(G * distance / math.sin(2 * elevation))
    t = np.linspace(0, 2 * speed * math.sin(elevation) / G, 50)
    hop = np.column_stack([speed * math.cos(elevation) * t, 0 * t,
                           speed * math.sin(elevation) * t - G * t * t / 2])
    hop_to_world = np.eye(4)
    hop_to_world[:3, :3], hop_to_world[:3, 3] = rotation_z(heading), launch
    # What SfM makes of it: an arbitrary frame and scale, noisy centres, a few gross outliers.
    sfm_rotation, sfm_scale = Rotation.random(random_state=3).as_matrix(), 2.5
    sfm_origin = np.array([3.0, 1.0, -2.0])

    def world_to_sfm(points: np.ndarray) -> np.ndarray:
        in_hop = (points - launch) @ rotation_z(heading)
        return in_hop @ sfm_rotation.T / sfm_scale + sfm_origin

    centres = hop @ rotation_z(heading).T + launch + rng.normal(0, 0.003, hop.shape)
    centres[[7, 23, 31, 40]] += np.array([[0.3, 0, 0], [0, -0.25, 0.1], [0, 0, 0.3], [-0.2, 0.2, 0]])
    cloud = ground_cloud((0.5, 5.0), (-2.0, 2.5), 30_000, rng)
    # The launch position is the previous estimate: 15 cm off after the last landing's bounce.
    guess = launch + np.array([0.12, -0.09, 0.02])
    result = hopping.process_hop(world_to_sfm(centres), t + 100.0, world_to_sfm(cloud), guess, heading,
                                 previous_cloud=previous, goal_heading=0.0,
                                 landing=hopping.LandingParams(cell=0.04, max_distance=1.8))
    assert abs(result.flight.scale / sfm_scale - 1) < 0.01
    assert result.flight.inliers.sum() >= 44 and not result.flight.inliers[[7, 23, 31, 40]].any()
    assert result.alignment is not None and result.alignment.good
    # ICP took the launch error out: launch and landing within 2 cm of the truth.
    assert np.linalg.norm(result.launch_point - launch) < 0.02
    true_landing = hop[-1] @ rotation_z(heading).T + launch
    assert np.linalg.norm(result.landing_point - true_landing) < 0.03
    np.testing.assert_allclose(result.cloud[:5], cloud[:5], atol=0.03)
    # And the next hop is planned from there.
    assert result.plan is not None and result.plan.found
    assert np.linalg.norm(result.plan.trajectory[0] - result.landing_point) < 1e-9
