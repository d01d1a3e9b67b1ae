"""Map alignment recovers a known odometry error, and refuses to invent one on featureless ground."""
from __future__ import annotations

import math

import numpy as np
import pytest

from toolbox.mapping.localisation import AlignConfig, align_to_map, apply, four_dof


def terrain(rng: np.random.Generator, rocks: int, extent: float = 5.0, spacing: float = 0.03) -> np.ndarray:
    """Points on gently rolling ground with hemispherical rocks, like a TOF view of the test bed."""
    xs = np.arange(-extent, extent, spacing)
    x, y = np.meshgrid(xs, xs)
    x = x + rng.uniform(-spacing / 2, spacing / 2, x.shape)
    y = y + rng.uniform(-spacing / 2, spacing / 2, y.shape)
    z = 0.05 * np.sin(x / 1.7) + 0.04 * np.cos(y / 2.3)
    for cx, cy, r in zip(rng.uniform(-extent, extent, rocks), rng.uniform(-extent, extent, rocks),
                         rng.uniform(0.1, 0.35, rocks), strict=True):
        d2 = (x - cx) ** 2 + (y - cy) ** 2
        z = np.where(d2 < r * r, z + np.sqrt(np.maximum(r * r - d2, 0)) * 0.8, z)
    return np.column_stack([x.ravel(), y.ravel(), z.ravel() + rng.normal(0, 0.005, x.size)])


def odometry_error(dx: float, dy: float, dyaw_deg: float, pivot: np.ndarray) -> np.ndarray:
    yaw = math.radians(dyaw_deg)
    transform = np.eye(4)
    transform[:3, :3] = [[math.cos(yaw), -math.sin(yaw), 0], [math.sin(yaw), math.cos(yaw), 0], [0, 0, 1]]
    return four_dof(transform, pivot) @ np.array([[1, 0, 0, dx], [0, 1, 0, dy], [0, 0, 1, 0], [0, 0, 0, 1.0]])


@pytest.mark.parametrize("dx, dy, dyaw", [(0.25, -0.15, 3.0), (-0.4, 0.3, -5.0), (0.05, 0.0, 0.5)])
def test_recovers_a_known_offset_between_partly_overlapping_views(dx, dy, dyaw):
    rng = np.random.default_rng(4)
    world = terrain(rng, rocks=40)
    pivot = np.array([1.0, 0.5, 0.0])
    old = world[world[:, 0] < 2.0]                       # what the last map saw
    new = world[world[:, 0] > -1.5]                      # the new view overlaps it by 3.5 of 10 m
    error = odometry_error(dx, dy, dyaw, pivot)
    seen = apply(error, new + rng.normal(0, 0.004, new.shape))
    result = align_to_map(seen, old, pivot)
    assert result.accepted, result.reason
    # The correction undoes the error: corrected points land where they truly are.
    corrected = apply(result.correction, seen)
    residual = np.linalg.norm(corrected[:, :2] - new[:, :2], axis=1)
    assert np.median(residual) < 0.02
    assert math.degrees(abs(result.dyaw + math.radians(dyaw))) < 0.2


def test_flat_ground_gives_no_position_fix():
    rng = np.random.default_rng(1)
    xs = np.arange(-4, 4, 0.04)
    x, y = np.meshgrid(xs, xs)
    flat = np.column_stack([x.ravel(), y.ravel(), rng.normal(0, 0.003, x.size)])
    result = align_to_map(flat + [0.3, 0.0, 0.0], flat, np.zeros(3))
    assert not result.accepted
    assert "featureless" in result.reason
    assert np.array_equal(result.correction, np.eye(4))


def test_refuses_a_correction_larger_than_odometry_allows():
    rng = np.random.default_rng(2)
    world = terrain(rng, rocks=40)
    seen = world + [0.6, 0.0, 0.0]
    result = align_to_map(seen, world, np.zeros(3), AlignConfig(max_translation_m=0.3))
    assert not result.accepted and "larger than odometry" in result.reason


def test_too_few_points_is_said_not_guessed():
    result = align_to_map(np.zeros((10, 3)), np.zeros((10, 3)), np.zeros(3))
    assert not result.accepted and "too few points" in result.reason


def test_four_dof_keeps_the_pivot_where_the_full_transform_puts_it():
    roll = math.radians(2)
    transform = np.eye(4)
    transform[:3, :3] = [[1, 0, 0], [0, math.cos(roll), -math.sin(roll)], [0, math.sin(roll), math.cos(roll)]]
    transform[:3, 3] = [0.1, 0.2, 0.3]
    pivot = np.array([2.0, -1.0, 0.5])
    planar = four_dof(transform, pivot)
    assert np.allclose(planar[:3, :3], np.eye(3))
    assert np.allclose(planar[:3, :3] @ pivot + planar[:3, 3], transform[:3, :3] @ pivot + transform[:3, 3])
