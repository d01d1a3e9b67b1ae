"""Tests of the position correction (rvs_server/toolbox/hopping_icp.py, hopping paper "Position
correction"): two hops' clouds of the same rocky terrain overlapping by half, one moved by a known
0.3 m and 2 degrees. Plain point-to-point ICP is shown to fail on them; ICP with iterative elimination
of the non-overlapping parts recovers the offset."""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from toolbox.hopping.icp import (
    align_with_overlap_elimination,
    apply_transform,
    common_bounds,
    crop_mask,
    horizontal_bounds,
    icp_point_to_point,
    transform_change,
)


def terrain(seed: int, rocks: int = 60):
    """A height function: gentle undulation and Gaussian rocks 0.1-0.5 m across, up to 0.4 m high."""
    rng = np.random.default_rng(seed)
    centres = np.column_stack([rng.uniform(-1, 16, rocks), rng.uniform(-1, 7, rocks)])
    radius, height = rng.uniform(0.1, 0.5, rocks), rng.uniform(0.05, 0.4, rocks)

    def z(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        out = 0.15 * np.sin(0.5 * x) + 0.1 * np.cos(0.7 * y + 0.3 * x)
        d2 = (x[:, None] - centres[:, 0]) ** 2 + (y[:, None] - centres[:, 1]) ** 2
        return out + np.sum(height * np.exp(-d2 / (2 * radius ** 2)), axis=1)
    return z


def cloud(z, x_range, rng, points: int = 20_000, noise: float = 0.005) -> np.ndarray:
    """Points sampled at random over x_range x [0, 6] m (each hop samples the ground differently)."""
    x, y = rng.uniform(*x_range, points), rng.uniform(0, 6, points)
    return np.column_stack([x, y, z(x, y)]) + rng.normal(0, noise, (points, 3))


def pose(rotation: np.ndarray, translation) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = rotation, translation
    return out


@pytest.fixture(scope="module")
def half_overlap():
    """(previous hop's cloud, this hop's cloud with a known error, the error): x in [0, 10] and [5, 15]."""
    rng = np.random.default_rng(0)
    z = terrain(0)
    previous, current = cloud(z, (0, 10), rng), cloud(z, (5, 15), rng)
    axis = np.array([0.3, -0.2, 1.0]) / np.linalg.norm([0.3, -0.2, 1.0])
    error = pose(Rotation.from_rotvec(math.radians(2.0) * axis).as_matrix(),
                 0.3 * np.array([0.6, -0.7, 0.39]) / np.linalg.norm([0.6, -0.7, 0.39]))
    return previous, apply_transform(error, current), error


def residual_error(transform: np.ndarray, error: np.ndarray) -> tuple[float, float]:
    """How far the found transform is from undoing the error: (m, degrees)."""
    moved, turned = transform_change(np.linalg.inv(error), transform)
    return moved, math.degrees(turned)


def test_the_offset_is_the_briefs(half_overlap):
    _, _, error = half_overlap
    moved, turned = transform_change(np.eye(4), error)
    assert moved == pytest.approx(0.3, abs=1e-9) and math.degrees(turned) == pytest.approx(2.0, abs=1e-9)


def test_plain_point_to_point_icp_fails_on_half_overlap(half_overlap):
    previous, current, error = half_overlap
    transform, fitness, _ = icp_point_to_point(current, previous, np.eye(4), max_distance=1.0)
    moved, turned = residual_error(transform, error)
    assert moved > 0.2  # pulled towards the middle of the other cloud: worse than not aligning at all
    assert fitness > 0.5  # and it believes it has matched most points


def test_overlap_elimination_recovers_the_offset(half_overlap):
    previous, current, error = half_overlap
    result = align_with_overlap_elimination(current, previous, voxel=0.05)
    moved, turned = residual_error(result.transform, error)
    assert moved < 0.01 and turned < 0.1
    assert result.converged and result.good, result.checks
    assert 2 <= len(result.rounds) <= 6
    # The crop converged onto the true overlap, x in [5, 10].
    np.testing.assert_allclose(result.rounds[-1].bounds[0], [5.0, 10.0], atol=0.05)
    assert result.rounds[-1].bounds_change < 0.05 and result.fitness > 0.95


def test_gravity_known_variant_moves_only_yaw_and_translation(half_overlap):
    previous, current_tilted, _ = half_overlap
    rng = np.random.default_rng(1)
    current = cloud(terrain(0), (5, 15), rng)
    error = pose(Rotation.from_euler("z", 2.0, degrees=True).as_matrix(), [0.2, -0.2, 0.1])
    result = align_with_overlap_elimination(apply_transform(error, current), previous, voxel=0.05, dof="yaw")
    moved, turned = residual_error(result.transform, error)
    assert moved < 0.01 and turned < 0.1 and result.good
    # Only yaw: the transform keeps z vertical exactly.
    np.testing.assert_allclose(result.transform[:3, 2], [0, 0, 1], atol=1e-12)


def test_bounded_rounds_report_no_convergence(half_overlap):
    previous, current, _ = half_overlap
    result = align_with_overlap_elimination(current, previous, voxel=0.05, max_rounds=1)
    assert len(result.rounds) == 1 and not result.converged and not result.good
    assert not result.checks["bounds_stable"]  # one round has nothing to compare with


def test_bounds_crop_and_transform_change_known_answers():
    a = np.array([[0.0, 0, 0], [10, 6, 1], [5, 3, 9]])
    b = np.array([[4.0, -1, 0], [15, 5, 0]])
    np.testing.assert_allclose(horizontal_bounds(a), [[0, 10], [0, 6]])
    both = common_bounds(horizontal_bounds(a), horizontal_bounds(b))
    np.testing.assert_allclose(both, [[4, 10], [0, 5]])
    np.testing.assert_array_equal(crop_mask(a, both), [False, False, True])
    with pytest.raises(ValueError, match="do not overlap"):
        common_bounds(np.array([[0.0, 1], [0, 1]]), np.array([[2.0, 3], [0, 1]]))
    turn = pose(Rotation.from_euler("z", 30, degrees=True).as_matrix(), [3.0, 4.0, 0.0])
    moved, turned = transform_change(np.eye(4), turn)
    assert moved == pytest.approx(5.0) and math.degrees(turned) == pytest.approx(30.0)


def test_quantile_bounds_ignore_stray_points():
    rng = np.random.default_rng(2)
    points = np.column_stack([rng.uniform(0, 10, 5000), rng.uniform(0, 6, 5000), np.zeros(5000)])
    points[:3, 0] = [50.0, -40.0, 60.0]
    np.testing.assert_allclose(horizontal_bounds(points, 0.002), [[0, 10], [0, 6]], atol=0.05)
