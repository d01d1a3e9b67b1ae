"""Tests of landing target selection and hop ballistics (rvs_server/toolbox/hopping_landing.py and
hopping_ballistics.py, hopping paper "Target selection with uncertainty calculation", eqs 14-17):
the error ellipse against a Monte Carlo of the range equation, inverse ballistics that land on the
target, the masks on known scenes, the exact ellipse test against brute force, targets never on
obstacles, and the parabola collision check catching a tall obstacle on the way."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from toolbox.grid import GridSpec
from toolbox.hopping.ballistics import (
    ballistic_positions,
    elevation_for_target,
    hop_range,
    landing_error_ellipse,
    launch_to_target,
    speed_for_target,
)
from toolbox.hopping.landing import (
    LandingParams,
    NoGroundError,
    ellipse_safe_mask,
    ellipse_semi_axes,
    goal_map,
    obstacle_mask,
    plan_landing,
    protrusion_map,
    swept_height,
    top_down_maps,
    trajectory_collides,
)
from toolbox.hopping.plane import Plane

G = 1.62


# --- ballistics -------------------------------------------------------------------------------------

def monte_carlo_landing(speed, elevation, sv, st_, sp, ss, samples=400_000, seed=0):
    """(along, across) landing offsets from the nominal: the range equation with sampled launch errors."""
    rng = np.random.default_rng(seed)
    v, th, psi = rng.normal(speed, sv, samples), rng.normal(elevation, st_, samples), rng.normal(0, sp, samples)
    d = hop_range(v, th, G)
    return (d * np.cos(psi) + rng.normal(0, ss, samples) - hop_range(speed, elevation, G),
            d * np.sin(psi) + rng.normal(0, ss, samples))


@pytest.mark.parametrize("elevation_deg", [30.0, 45.0, 60.0, 70.0])
def test_error_ellipse_matches_monte_carlo_of_the_range_equation(elevation_deg):
    speed, sv, st_, sp, ss = 1.4, 0.07, math.radians(5), math.radians(4), 0.03
    along, across = monte_carlo_landing(speed, math.radians(elevation_deg), sv, st_, sp, ss)
    ellipse = landing_error_ellipse(speed, math.radians(elevation_deg), sv, st_, sp, ss, G)
    assert ellipse.distance == pytest.approx(speed ** 2 * math.sin(math.radians(2 * elevation_deg)) / G)
    assert ellipse.along_sigma == pytest.approx(along.std(), rel=0.01)
    assert ellipse.across_sigma == pytest.approx(across.std(), rel=0.01)
    assert ellipse.along_bias == pytest.approx(along.mean(), abs=0.001)
    # The paper's first order is close here too (small errors, away from 45 degrees it is the same).
    first = landing_error_ellipse(speed, math.radians(elevation_deg), sv, st_, sp, ss, G, exact=False)
    assert first.along_sigma == pytest.approx(along.std(), rel=0.03)


def test_first_order_ellipse_misses_the_elevation_error_at_45_degrees():
    """Only an elevation error, at 45 degrees: the first order sees no spread, the exact moments do."""
    along, _ = monte_carlo_landing(1.4, math.radians(45), 0.0, math.radians(6), 0.0, 0.0)
    first = landing_error_ellipse(1.4, math.radians(45), 0.0, math.radians(6), 0.0, 0.0, G, exact=False)
    exact = landing_error_ellipse(1.4, math.radians(45), 0.0, math.radians(6), 0.0, 0.0, G)
    assert first.along_sigma < 1e-12 and along.std() > 0.005
    assert exact.along_sigma == pytest.approx(along.std(), rel=0.01)
    assert exact.along_bias == pytest.approx(along.mean(), rel=0.01) and exact.along_bias < 0  # hops fall short


@settings(max_examples=100, deadline=None)
@given(dx=st.floats(-3, 3), dy=st.floats(-3, 3), dz=st.floats(-0.5, 0.5), elevation=st.floats(20, 80),
       speed=st.floats(0.5, 4.0), high=st.booleans())
def test_inverse_ballistics_lands_on_the_target(dx, dy, dz, elevation, speed, high):
    start, target = np.array([1.0, 2.0, 0.3]), np.array([1.0 + dx, 2.0 + dy, 0.3 + dz])
    if math.hypot(dx, dy) < 0.05:
        return
    for launch in (launch_to_target(start, target, G, math.radians(elevation)),
                   launch_to_target(start, target, G, elevation=None, speed=speed, high=high)):
        if launch is None:
            continue
        np.testing.assert_allclose(ballistic_positions(start, launch.velocity, [launch.flight_time], G)[0],
                                   target, atol=1e-9)
        assert math.remainder(launch.heading - math.atan2(dy, dx), 2 * math.pi) == pytest.approx(0.0, abs=1e-12)


def test_inverse_ballistics_known_answers_and_limits():
    # Flat ground: the fixed-elevation speed is the range equation's.
    v = speed_for_target(1.5, 0.0, math.radians(60), G)
    assert hop_range(v, math.radians(60), G) == pytest.approx(1.5)
    assert elevation_for_target(1.5, 0.0, v, G, high=True) == pytest.approx(math.radians(60))
    assert elevation_for_target(1.5, 0.0, v, G, high=False) == pytest.approx(math.radians(30))
    assert math.isnan(speed_for_target(1.0, 2.0, math.radians(45), G))  # at 45 degrees, no 2 m rise in 1 m
    assert math.isnan(elevation_for_target(10.0, 0.0, 1.0, G))               # too slow to reach
    assert launch_to_target([0, 0, 0], [1.0, 0, 2.0], G, math.radians(45)) is None
    with pytest.raises(ValueError, match="exactly one"):
        launch_to_target([0, 0, 0], [1, 0, 0], G, elevation=None, speed=None)


# --- the maps -------------------------------------------------------------------------------------

def test_top_down_maps_known_answer():
    spec = GridSpec(0.0, 0.0, 1.0, 2, 3)
    points = np.array([[0.5, 0.5, 1.0], [0.2, 0.7, 3.0], [2.5, 1.5, -1.0], [9.0, 9.0, 5.0]])
    colours = np.array([[10.0, 0, 0], [20.0, 0, 0], [0, 0, 30.0], [1, 1, 1]])
    top = top_down_maps(points, spec, colours)
    assert top.height[0, 0] == 3.0 and top.height[1, 2] == -1.0 and np.isnan(top.height[0, 1])
    np.testing.assert_array_equal(top.count, [[2, 0, 0], [0, 0, 1]])
    np.testing.assert_allclose(top.colour[0, 0], [15.0, 0, 0])
    np.testing.assert_allclose(top.colour[1, 2], [0, 0, 30.0])


def test_obstacles_are_protrusion_above_a_threshold_cleaned_by_median_and_closing():
    spec = GridSpec(0.0, 0.0, 0.02, 60, 60)
    xs, ys = spec.centres()
    gx, gy = np.meshgrid(xs, ys)
    z = 0.05 * gx  # a slope: the plane follows it, height alone would not
    z = np.where((np.abs(gx - 0.4) < 0.1) & (np.abs(gy - 0.6) < 0.1), z + 0.10, z)   # 10 cm box: obstacle
    z = np.where((np.abs(gx - 0.9) < 0.1) & (np.abs(gy - 0.6) < 0.1), z + 0.05, z)   # 5 cm box: not
    z[10, 10] += 0.3                                                                    # one stray spike: noise
    points = np.column_stack([gx.ravel(), gy.ravel(), z.ravel()])
    plane = Plane(np.array([-0.05, 0.0, 1.0]) / math.hypot(0.05, 1.0), 0.0)
    protrusion = protrusion_map(points, spec, plane)
    mask = obstacle_mask(protrusion, 0.08, median_px=5, closing_px=5)
    row, col, _ = spec.cell_of(np.array([0.4, 0.9]), np.array([0.6, 0.6]))
    assert mask[row[0], col[0]] and not mask[row[1], col[1]]
    assert not mask[10, 10]
    assert mask.sum() == pytest.approx(100, abs=12)  # the 10 x 10-cell box, corners rounded by the median


def test_goal_map_is_eq_17():
    spec = GridSpec(-3.0, -3.0, 0.1, 60, 60)
    goal = goal_map(spec, np.zeros(2), 0.5, 2.0, math.pi / 2, goal_heading=math.pi / 2)
    xs, ys = spec.centres()
    gx, gy = np.meshgrid(xs, ys)
    distance = np.hypot(gx, gy)
    expected = np.where((distance >= 0.5) & (distance <= 2.0) & (gy >= 0), gy / distance, 0.0)
    np.testing.assert_allclose(goal, expected, atol=1e-12)
    # Towards a goal point in reach: the goal itself scores 1, and shorter hops less.
    towards = goal_map(spec, np.zeros(2), 0.5, 2.0, goal_xy=np.array([1.05, 0.05]))
    row, col, _ = spec.cell_of(np.array([1.05, 0.65]), np.array([0.05, 0.05]))
    assert towards[row[0], col[0]] == pytest.approx(1.0) and towards[row[1], col[1]] < 0.7


def test_ellipse_safe_mask_equals_brute_force():
    rng = np.random.default_rng(3)
    spec = GridSpec(-2.0, -2.0, 0.05, 80, 80)
    params = LandingParams(cell=0.05, min_distance=0.4, max_distance=1.8)
    for _ in range(3):
        hazard = rng.random(spec.shape) < 0.004
        hazard[rng.integers(0, 80):, rng.integers(0, 80):] |= rng.random() < 0.5  # a big unknown block
        candidates = goal_map(spec, np.zeros(2), 0.4, 1.8, math.pi, goal_heading=0.0) > -1
        safe, axes = ellipse_safe_mask(hazard, spec, np.zeros(2), candidates, params)
        xs, ys = spec.centres()
        gx, gy = np.meshgrid(xs, ys)
        hx, hy = gx[hazard], gy[hazard]
        rows, cols = np.nonzero(candidates)
        semi = ellipse_semi_axes(np.hypot(gx[rows, cols], gy[rows, cols]), params)
        for k, (r, c) in enumerate(zip(rows, cols, strict=True)):
            heading = math.atan2(gy[r, c], gx[r, c])
            # Every hazard cell and every cell just outside the grid (unknown) must be outside the ellipse.
            ring_x = np.concatenate([hx, xs[0] - 0.05 + 0 * ys, xs[-1] + 0.05 + 0 * ys, xs, xs])
            ring_y = np.concatenate([hy, ys, ys, ys[0] - 0.05 + 0 * xs, ys[-1] + 0.05 + 0 * xs])
            dx, dy = ring_x - gx[r, c], ring_y - gy[r, c]
            a = dx * math.cos(heading) + dy * math.sin(heading)
            b = -dx * math.sin(heading) + dy * math.cos(heading)
            clear = not np.any((a / semi[k, 0]) ** 2 + (b / semi[k, 1]) ** 2 <= 1.0) and not hazard[r, c]
            assert safe[r, c] == clear, (r, c)


def test_swept_height_and_collision_check():
    spec = GridSpec(-0.5, -1.0, 0.02, 100, 200)  # x -0.5 .. 3.5, y -1 .. 1
    height = np.zeros(spec.shape)
    row, col, _ = spec.cell_of(np.array([1.0]), np.array([0.0]))
    height[row[0] - 2:row[0] + 3, col[0] - 2:col[0] + 3] = 1.0                 # a 10 cm wide, 1 m tall pillar
    swept = swept_height(height, spec, 0.1)
    assert swept[row[0] + 7, col[0]] == 1.0 and swept[row[0] + 10, col[0]] == 0.0  # grown by the 0.1 m radius
    start, target = np.array([0.0, 0.0, 0.1]), np.array([2.0, 0.0, 0.1])
    launch = launch_to_target(start, target, G, math.radians(60))
    path = ballistic_positions(start, launch.velocity, np.linspace(0, launch.flight_time, 200), G)
    collides, hits = trajectory_collides(path, swept, spec, 0.1, (start, target))
    assert collides and np.all(np.abs(path[hits, 0] - 1.0) < 0.2)
    # A short pillar the hop clears (apex 0.87 m above the pillar at 1 m), and the ground at both ends.
    low = swept_height(np.where(height > 0, 0.5, 0.0), spec, 0.1)
    assert not trajectory_collides(path, low, spec, 0.1, (start, target))[0]
    # A hop passing beside the pillar, more than the rover's radius away.
    side = ballistic_positions(np.array([0.0, 0.25, 0.1]), launch.velocity,
                               np.linspace(0, launch.flight_time, 200), G)
    assert not trajectory_collides(side, swept, spec, 0.1, (side[0], side[-1]))[0]


# --- the method on synthetic scenes -------------------------------------------------------------------

def rocky_scene(seed: int, rocks: int = 30, half: float = 3.2, density: float = 3000.0, slope=(0.03, -0.02)):
    """A dense cloud of sloping ground with hemispherical rocks (none under the start): (points, rocks)."""
    rng = np.random.default_rng(seed)
    n = int(density * (2 * half) ** 2)
    xy = rng.uniform(-half, half, (n, 2))
    centres = rng.uniform(-half, half, (rocks, 2))
    radius, height = rng.uniform(0.1, 0.35, rocks), rng.uniform(0.12, 0.4, rocks)
    keep = np.hypot(*centres.T) > radius + 0.3
    centres, radius, height = centres[keep], radius[keep], height[keep]
    d = np.hypot(xy[:, None, 0] - centres[:, 0], xy[:, None, 1] - centres[:, 1])
    dome = height * np.sqrt(np.clip(1 - (d / radius) ** 2, 0, 1))
    bump = np.max(np.where(d < radius, dome, 0.0), axis=1, initial=0.0)
    z = slope[0] * xy[:, 0] + slope[1] * xy[:, 1] + bump + rng.normal(0, 0.004, n)
    return np.column_stack([xy, z]), (centres, radius, height)


@pytest.mark.parametrize("seed", range(10))
def test_landing_target_is_never_on_an_obstacle(seed):
    points, (centres, radius, height) = rocky_scene(seed)
    params = LandingParams(cell=0.04, max_distance=2.0)
    plan = plan_landing(points, np.array([0.0, 0.0, 0.1]), goal_heading=seed * 1.1, params=params)
    assert plan.found, plan.reason
    target = plan.target[:2]
    # The rover's footprint at the target misses every rock, with the ellipse's margin in hand.
    edge = np.hypot(*(centres - target).T) - radius
    assert edge.min() > params.rover_radius
    # The whole drawn ellipse is clear of the obstacle mask and of unknown cells.
    xs, ys = plan.spec.centres()
    gx, gy = np.meshgrid(xs, ys)
    heading = plan.launch.heading
    a = (gx - target[0]) * math.cos(heading) + (gy - target[1]) * math.sin(heading)
    b = -(gx - target[0]) * math.sin(heading) + (gy - target[1]) * math.cos(heading)
    inside = (a / plan.ellipse_axes[0]) ** 2 + (b / plan.ellipse_axes[1]) ** 2 <= 1
    assert not plan.obstacle[inside].any() and plan.known[inside].all()
    # The launch reaches the target within the hop limits and the allowed deviation.
    distance = math.hypot(*(target))
    assert params.min_distance <= distance <= params.max_distance
    assert abs(math.remainder(plan.launch.heading - seed * 1.1, 2 * math.pi)) <= math.pi / 2 + 1e-9
    np.testing.assert_allclose(plan.trajectory[-1], plan.target, atol=1e-9)
    # The maps for the product share the grid.
    for layer in (plan.top_down.height, plan.protrusion, plan.obstacle, plan.safe, plan.clearance, plan.goal,
                  plan.score):
        assert layer.shape == plan.spec.shape
    assert np.isfinite(plan.score[plan.safe]).all() and np.isnan(plan.score[~plan.safe]).all()


def test_plan_avoids_targets_behind_a_tall_wall():
    """A 1.5 m wall across the goal direction: the best-scored cells lie beyond it, every parabola
    there hits it, so the chosen target is short of it and the rejections say why."""
    points, _ = rocky_scene(0, rocks=0, slope=(0.0, 0.0))
    wall = (np.abs(points[:, 0] - 0.8) < 0.05) & (np.abs(points[:, 1]) < 2.8)
    points[wall, 2] = 1.5
    params = LandingParams(cell=0.04, min_distance=0.3, max_distance=2.0, max_candidates=400)
    plan = plan_landing(points, np.array([0.0, 0.0, 0.1]), goal_heading=0.0, params=params)
    assert plan.found
    assert plan.target[0] < 0.8 - params.rover_radius
    assert any(reason == "collision" for _, _, reason in plan.rejected)
    assert all(x > 0.8 for x, _, reason in plan.rejected if reason == "collision")
    best_safe = np.unravel_index(np.nanargmax(plan.score), plan.score.shape)
    assert plan.spec.centre_of(*best_safe)[0] > 0.8  # the selection image alone would have jumped the wall


def test_plan_with_fixed_speed_and_goal_point():
    points, (centres, radius, _) = rocky_scene(7)
    params = LandingParams(cell=0.04, elevation=None, speed=1.6)
    plan = plan_landing(points, np.array([0.0, 0.0, 0.1]), goal_xy=np.array([1.0, 0.8]), params=params)
    assert plan.found and plan.launch.speed == pytest.approx(1.6)
    assert plan.launch.elevation > math.radians(45)  # the steep solution
    assert (np.hypot(*(centres - plan.target[:2]).T) - radius).min() > params.rover_radius


def test_no_safe_cell_is_reported_not_invented():
    rng = np.random.default_rng(0)
    xy = rng.uniform(-0.6, 0.6, (20000, 2))  # the cloud covers only the start's surroundings
    plan = plan_landing(np.column_stack([xy, np.zeros(len(xy))]), np.array([0.0, 0.0, 0.1]), goal_heading=0.0,
                        params=LandingParams(cell=0.04))
    assert not plan.found and plan.reason == "no_candidate" and not plan.safe.any()
    assert np.isnan(plan.target).all() and plan.launch is None


def test_a_start_off_the_cloud_is_refused_by_name():
    """A wrong scale puts the estimated touchdown metres away from the cloud: say so, don't plan on nothing."""
    rng = np.random.default_rng(0)
    xy = rng.uniform(-2.0, 2.0, (5000, 2))
    cloud = np.column_stack([xy, np.zeros(len(xy))])
    with pytest.raises(NoGroundError, match=r"0 points within [\d.]+ m of the estimated touchdown \(40.00, 0.00\)"):
        plan_landing(cloud, np.array([40.0, 0.0, 0.1]), goal_heading=0.0, params=LandingParams(cell=0.04))
