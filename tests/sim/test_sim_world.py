"""The simulated world: determinism, saving, rocks, exact truth, obstacles, lighting and rendering.

Most tests share one small world (10 x 10 m) built once for the module; the whole file runs in a
few seconds.
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from drivers.sim.config import Sun, WorldConfig
from drivers.sim.render import render
from drivers.sim.rover import Rover
from drivers.sim.world import World
from toolbox.camera import Intrinsics

from conftest import look_at

SMALL = WorldConfig(seed=3, size_m=(10.0, 10.0))
SR4000 = Intrinsics(width=176, height=144, fx=262.92, fy=262.92, cx=88.0, cy=69.0, k1=-0.826, k2=0.656)


@pytest.fixture(scope="module")
def world() -> World:
    return World.build(SMALL)


def ground_view_pose(world: World) -> np.ndarray:
    eye = [0.0, -1.0, float(world.height_at(0.0, -1.0)) + 1.5]
    return look_at(eye, [0.0, 3.0, float(world.height_at(0.0, 3.0))])


# ------------------------------------------------------------------------------------ determinism
def test_same_seed_builds_the_same_world(world):
    again = World.build(SMALL)
    for name in ("ground", "heights", "albedo_grid"):
        assert np.array_equal(getattr(world, name), getattr(again, name)), name
    assert np.array_equal(world.rocks, again.rocks)
    assert np.array_equal(world.surface.vertices, again.surface.vertices)
    assert np.array_equal(world.surface.triangles, again.surface.triangles)


def test_another_seed_builds_another_world(world):
    other = World.build(SMALL.model_copy(update={"seed": SMALL.seed + 1}))
    assert not np.array_equal(world.heights, other.heights)
    assert len(world.rocks) != len(other.rocks) or not np.array_equal(world.rocks, other.rocks)


def test_save_and_load_give_back_the_same_world(world, tmp_path):
    world.sun = Sun(azimuth_deg=200.0, elevation_deg=25.0)
    try:
        loaded = World.load(world.save(tmp_path / "scene"))
    finally:
        world.sun = SMALL.sun
    assert loaded.config == world.config
    assert loaded.sun == Sun(azimuth_deg=200.0, elevation_deg=25.0)
    for name in ("ground", "heights", "albedo_grid"):
        assert np.array_equal(getattr(world, name), getattr(loaded, name)), name
    assert np.array_equal(world.rocks, loaded.rocks)
    assert np.array_equal(world.surface.vertices, loaded.surface.vertices)
    assert np.array_equal(world.surface.triangles, loaded.surface.triangles)
    x, y = np.random.default_rng(0).uniform(-5, 5, (2, 2000))
    assert np.array_equal(world.height_at(x, y), loaded.height_at(x, y))
    assert np.array_equal(world.albedo_at(x, y), loaded.albedo_at(x, y))


def test_bad_configs_are_refused():
    with pytest.raises(ValueError):
        WorldConfig(rocks={"diameter_range_m": (0.5, 0.1)})
    with pytest.raises(ValueError):
        WorldConfig(rocks={"buried_fraction_range": (0.2, 0.95)})
    with pytest.raises(ValueError):
        WorldConfig(size_m=(0.0, 10.0))


# ------------------------------------------------------------------------------------ rocks
@pytest.mark.parametrize("cover", [0.07, 0.18])
def test_rocks_cover_the_requested_area_with_power_law_sizes(cover):
    config = SMALL.model_copy(update={"rocks": SMALL.rocks.model_copy(update={"cover": cover})})
    world = World.build(config)
    assert world.rock_cover() == pytest.approx(cover, abs=0.1 * cover)
    # Cumulative counts N(>D) on a log-log plot: a straight line of slope -size_exponent.
    low, high = config.rocks.diameter_range_m
    diameters = np.sort(world.rocks["diameter"])
    grid = np.geomspace(2 * low, high / 4, 8)
    counts = len(diameters) - np.searchsorted(diameters, grid)
    slope = np.polyfit(np.log(grid), np.log(counts), 1)[0]
    assert slope == pytest.approx(-config.rocks.size_exponent, abs=0.35)
    assert counts[0] > 5 * counts[-1]                       # many small rocks, few boulders
    assert diameters.min() >= low and diameters.max() <= high


def test_rock_table_describes_the_rocks(world):
    visible = np.flatnonzero(world.rocks["area"] > 0)
    rocks = world.rocks[visible]
    assert np.all((rocks["buried_fraction"] >= 0.2) & (rocks["buried_fraction"] <= 0.5))
    # Each rock's height and footprint, measured on the truth where it is the top surface.
    peaks = []
    for index in visible[np.argsort(rocks["height"])[-20:]]:
        rock = world.rocks[index]
        x, y = np.meshgrid(np.arange(rock["x"] - rock["radius"], rock["x"] + rock["radius"], 0.005),
                           np.arange(rock["y"] - rock["radius"], rock["y"] + rock["radius"], 0.005))
        own = world.rock_at(x, y) == index
        assert own.any()
        assert np.max(np.hypot(x[own] - rock["x"], y[own] - rock["y"])) <= rock["radius"] + 0.01
        highest = np.max(world.protrusion_at(x[own], y[own]))
        assert highest <= rock["height"] + SMALL.mesh_tolerance_m
        peaks.append(highest / rock["height"])
    assert np.median(peaks) > 0.9      # a 5 mm raster finds nearly the full height


def test_no_rock_in_the_clear_start_circle(world):
    gap = np.hypot(world.rocks["x"], world.rocks["y"]) - world.rocks["radius"]
    assert np.all(gap > SMALL.rocks.clear_radius_m - 0.01)


# ------------------------------------------------------------------------------------ truth
def test_rendered_hits_lie_on_the_truth_surface(world):
    for camera in (SR4000, Intrinsics.from_fov(640, 480, math.radians(60.0))):
        view = render(world, ground_view_pose(world), camera)
        points = view.points[view.hit]
        assert len(points) > 0.5 * camera.width * camera.height
        error = points[:, 2] - world.height_at(points[:, 0], points[:, 1])
        assert np.max(np.abs(error)) < 1e-3
        assert np.median(np.abs(error)) < 1e-5


def test_truth_mesh_stays_within_tolerance_of_the_height_grid(world):
    rows, cols = np.random.default_rng(1).integers(0, world.grid.rows + 1, (2, 50_000))
    truth = world.height_at(world.grid.x_of(cols), world.grid.y_of(rows))
    assert np.max(np.abs(truth - world.heights[rows, cols])) <= SMALL.mesh_tolerance_m + 1e-6


def test_slope_and_normals(world):
    x, y = np.random.default_rng(2).uniform(-4, 4, (2, 500))
    normals = world.normal_at(x, y)
    assert np.allclose(np.linalg.norm(normals, axis=-1), 1.0, atol=1e-5)
    assert np.all(normals[:, 2] > 0)
    on_ground = world.protrusion_at(x, y) <= 0
    regional = world.slope_at(x[on_ground], y[on_ground], baseline=2.0)
    assert np.median(np.degrees(regional)) < SMALL.terrain.slope_deg + 10
    assert np.all(np.isnan(world.height_at([100.0], [0.0])))


def test_obstacle_mask_holds_the_tall_rocks_and_only_them(world):
    step, cell = 0.10, 0.05
    bounds = world.bounds
    mask = world.obstacle_mask(step, cell, bounds[:2], bounds[2:])
    assert mask.shape == (round((bounds[3] - bounds[2]) / cell), round((bounds[1] - bounds[0]) / cell))
    iy, ix = np.nonzero(mask)
    centres = np.stack([bounds[0] + (ix + 0.5) * cell, bounds[2] + (iy + 0.5) * cell], axis=1)
    tall = world.rocks[world.rocks["height"] > step]
    assert len(tall) > 5
    for rock in tall[tall["height"] > step + 0.02]:
        near = np.hypot(centres[:, 0] - rock["x"], centres[:, 1] - rock["y"]) <= rock["radius"] + cell
        assert near.any(), f"tall rock at ({rock['x']:.2f}, {rock['y']:.2f}) not in the mask"
    distance = np.hypot(centres[:, None, 0] - tall["x"][None, :], centres[:, None, 1] - tall["y"][None, :])
    assert np.all(np.min(distance - tall["radius"][None, :], axis=1) <= cell)
    # The lower the step, the more cells; no rocks, no obstacles.
    assert world.obstacle_mask(0.03, cell, bounds[:2], bounds[2:]).sum() > mask.sum()
    assert not World.build(SMALL.model_copy(update={"rocks": SMALL.rocks.model_copy(update={"cover": 0.0})})
                           ).obstacle_mask(0.01, cell, bounds[:2], bounds[2:]).any()


# ------------------------------------------------------------------------------------ lighting
def test_shadows_fall_on_the_side_away_from_the_sun(world):
    sun = Sun(azimuth_deg=90.0, elevation_deg=30.0)       # in the east: shadows fall west
    tall = world.rocks[(world.rocks["height"] > 0.15) & (world.rocks["area"] > 0)]
    assert len(tall) >= 3
    lit_fraction = {}
    for side in (+1, -1):                                 # +1: east of the rock, toward the sun
        lit = []
        for rock in tall:
            y = rock["y"] + np.linspace(-0.3, 0.3, 7) * rock["radius"]
            x = np.full_like(y, rock["x"] + side * (rock["radius"] + 0.03))
            points = np.stack([x, y, world.height_at(x, y)], axis=1)
            lit.append(world.in_sunlight(points, world.normal_at(x, y), sun))
        lit_fraction[side] = np.mean(lit)
    assert lit_fraction[+1] > 0.8
    assert lit_fraction[-1] < 0.3


def test_moving_the_sun_changes_the_image_but_not_the_geometry(world):
    pose, camera = ground_view_pose(world), Intrinsics.from_fov(320, 240, math.radians(60.0))
    teach = render(world, pose, camera, sun=Sun(azimuth_deg=135.0, elevation_deg=35.0))
    repeat = render(world, pose, camera, sun=Sun(azimuth_deg=165.0, elevation_deg=20.0))
    assert np.array_equal(teach.range, repeat.range)
    hit = teach.hit
    change = np.abs(teach.intensity[hit] - repeat.intensity[hit]).mean() / teach.intensity[hit].mean()
    assert change > 0.05
    assert (teach.lit != repeat.lit)[hit].mean() > 0.01


def test_lower_sun_means_more_shadow(world):
    x, y = np.meshgrid(np.linspace(-4.5, 4.5, 200), np.linspace(-4.5, 4.5, 200))
    points = np.stack([x.ravel(), y.ravel(), world.height_at(x, y).ravel()], axis=1)
    normals = world.normal_at(x, y).reshape(-1, 3)
    high = world.in_sunlight(points, normals, Sun(elevation_deg=60.0)).mean()
    low = world.in_sunlight(points, normals, Sun(elevation_deg=10.0)).mean()
    assert high > low + 0.02


# ------------------------------------------------------------------------------------ rendering
def test_render_outputs_agree_with_each_other(world):
    pose = ground_view_pose(world)
    view = render(world, pose, SR4000)
    hit = view.hit
    camera_points = (view.points[hit] - pose[:3, 3]) @ pose[:3, :3]
    assert np.allclose(view.depth[hit], camera_points[:, 2], atol=1e-4)
    assert np.allclose(view.range[hit], np.linalg.norm(camera_points, axis=1), atol=1e-4)
    v, u = np.nonzero(hit)
    assert np.allclose(SR4000.project(camera_points), np.stack([u, v], axis=1), atol=1e-3)
    assert np.allclose(np.linalg.norm(view.normals[hit], axis=1), 1.0, atol=1e-5)
    assert np.all((view.incidence_cos[hit] >= 0) & (view.incidence_cos[hit] <= 1))
    # Rock textures are 3-D, and a hit's z carries the ray's float32 distance: agreement to 1e-3.
    truth = world.albedo_at(view.points[hit][:, 0], view.points[hit][:, 1])
    assert np.allclose(view.albedo[hit], truth, rtol=1e-3)
    assert np.all(np.isinf(view.range[~hit])) and np.all(view.intensity[~hit] == 0)
    assert (view.rock[hit] >= 0).mean() > 0.01


def test_a_camera_looking_at_the_sky_hits_nothing(world):
    view = render(world, look_at([0, 0, 2.0], [0, 10, 12.0]), Intrinsics.from_fov(64, 48, math.radians(30.0)))
    assert not view.hit.any()


def test_rover_camera_sees_the_ground_ahead(world):
    rover = Rover(world, heading=math.pi / 2)
    view = render(world, rover.sensor_to_world("left", tilt_deg=-30.0),
                  Intrinsics.from_fov(160, 120, math.radians(60.0)))
    assert view.hit.mean() > 0.9
    assert np.median(view.points[view.hit][:, 1]) > 1.0          # north of the rover, where it looks
