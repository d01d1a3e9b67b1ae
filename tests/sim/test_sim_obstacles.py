"""Obstacles added to a built world (a dropped rock, a standing astronaut): they are part of the one
truth surface (heights, obstacle mask, rover collisions, rendered views) and leave no trace when removed.

One small world (8 x 8 m at 1 cm) built once for the module.
"""
from __future__ import annotations

import threading

import numpy as np
import pytest

from drivers.sim.config import WorldConfig
from drivers.sim.render import render
from drivers.sim.rover import Rover
from drivers.sim.world import World
from toolbox.camera import Intrinsics

from conftest import look_at

SMALL = WorldConfig(seed=5, size_m=(8.0, 8.0), cell_m=0.01)
CAMERA = Intrinsics(width=160, height=120, fx=150.0, fy=150.0, cx=80.0, cy=60.0)


@pytest.fixture(scope="module")
def world() -> World:
    return World.build(SMALL)


def view_of(world: World, x: float, y: float, back: float = 2.0, aim: float = 0.1) -> np.ndarray:
    """A camera `back` m south of (x, y), 1.2 m up, looking at `aim` m above the ground there."""
    ground = float(world.ground_height_at(x, y))
    return look_at([x, y - back, ground + 1.2], [x, y, ground + aim])


def free_spot(world: World, x: float, y: float, radius: float) -> tuple[float, float]:
    """The point nearest (x, y) (on a 5 cm lattice) with no rock of the world within `radius`: the test
    wants bare ground under what it drops."""
    dx, dy = np.meshgrid(np.arange(-30, 31) * 0.05, np.arange(-30, 31) * 0.05)
    candidates = np.column_stack([x + dx.ravel(), y + dy.ravel()])
    candidates = candidates[np.argsort(np.hypot(dx, dy).ravel(), kind="stable")]
    rocks = world.rocks
    for cx, cy in candidates:
        if not (np.hypot(rocks["x"] - cx, rocks["y"] - cy) < radius + rocks["radius"]).any():
            return float(cx), float(cy)
    raise AssertionError(f"no bare ground near ({x}, {y})")


def state_of(world: World) -> dict:
    return {"heights": world.heights.copy(), "rocks": world.rocks.copy(), "triangles": world.surface.triangles.copy(),
            "vertices": world.surface.vertices.copy(), "rock_of_triangle": world.rock_of_triangle.copy()}


def test_a_dropped_rock_is_in_every_truth_and_every_view_and_removal_restores_them(world):
    x, y = free_spot(world, 1.3, 0.0, 0.3)
    before = state_of(world)
    pose = view_of(world, x, y)
    bare = render(world, pose, CAMERA)
    rover = Rover(world, x=x - 0.2, y=y)          # its footprint over where the rock will fall
    assert not rover.collides(0.1)
    rock = world.add_rock(x, y, height=0.25, diameter=0.4, seed=11)
    [record] = world.obstacles()
    assert (record["id"], record["kind"], record["seed"], record["diameter_m"]) == (rock, "rock", 11, 0.4)
    assert record["height_m"] == pytest.approx(0.25, abs=1e-9)
    row = world.rocks[record["rock"]]
    assert record["rock"] == len(before["rocks"]) and row["height"] == pytest.approx(0.25, abs=1e-9)
    # the surface: ids consistent across its arrays, the rock's triangles after the static ones
    surface = world.surface
    assert len(surface.triangles) == len(surface.face_normals) == len(world.rock_of_triangle)
    assert surface.static_triangles == len(before["triangles"])
    assert np.array_equal(surface.triangles[:surface.static_triangles], before["triangles"])
    assert (world.rock_of_triangle[surface.static_triangles:] == record["rock"]).all()
    assert (surface.face_normals[surface.static_triangles:, 2] > 0).all()   # 2.5-D: every facet faces up
    # truth queries
    assert world.rock_at(x, y) == record["rock"]
    assert 0.1 < float(world.protrusion_at(x, y)) <= 0.25 + 1e-6
    changed = world.heights != before["heights"]
    protrusion = (world.heights - world.ground)[changed]
    assert changed.sum() > 500 and 0.2 < protrusion.max() <= 0.25 + 1e-6
    assert np.array_equal(np.maximum(before["heights"], world.heights), world.heights)  # max with what was there
    mask = world.obstacle_mask(0.1, 0.1, (x - 0.5, x + 0.5), (y - 0.5, y + 0.5))
    assert mask[5, 5] and mask.sum() >= 4
    assert rover.collides(0.1)
    assert float(world.albedo_at(x, y)) > 0
    # a rendered view: the camera meets the rock, nearer than the bare ground it hid
    view = render(world, pose, CAMERA)
    on_rock = view.rock == record["rock"]
    assert on_rock.sum() > 100
    assert (view.range[on_rock] < bare.range[on_rock]).all()
    assert (view._triangle.reshape(view.shape)[on_rock] >= surface.static_triangles).all()
    # removal: as if it had never been
    world.remove_obstacle(rock)
    assert world.obstacles() == []
    for name, value in state_of(world).items():
        assert np.array_equal(value, before[name]), name
    assert not rover.collides(0.1)
    again = render(world, pose, CAMERA)
    assert np.array_equal(again.range, bare.range) and np.array_equal(again.intensity, bare.intensity)


def test_an_astronaut_stands_upright_on_the_ground(world):
    x, y = free_spot(world, -1.5, 1.0, 0.35)
    pose = view_of(world, x, y, back=3.5, aim=0.9)
    bare = render(world, pose, CAMERA)
    heights = world.heights.copy()
    person = world.add_astronaut(x, y, heading=0.4)
    [record] = world.obstacles()
    assert record["kind"] == "astronaut" and record["height_m"] == 1.8
    assert float(world.protrusion_at(x, y)) == pytest.approx(1.8, abs=1e-6)
    footprint = np.array(record["footprint"])
    sides = np.linalg.norm(np.diff(np.vstack([footprint, footprint[:1]]), axis=0), axis=1)
    assert sorted(np.round(sides, 6)) == [0.41, 0.41, 0.5, 0.5]      # across the arms; torso and backpack
    assert world.rocks[record["rock"]]["area"] == pytest.approx(0.155, rel=0.1)
    # legs apart: a ray at knee height along the heading passes between them; at the chest it stops
    ground = float(world.ground_height_at(x, y))
    along = np.array([np.cos(0.4), np.sin(0.4), 0.0])
    for height, through in ((0.3, True), (1.1, False)):
        start = np.array([x, y, ground + height]) - 2 * along
        t_hit, ids = world.surface.cast(np.concatenate([start, along])[None].astype(np.float32))
        hit_person = np.isfinite(t_hit[0]) and t_hit[0] < 2.5 and ids[0] >= world.surface.static_triangles
        assert hit_person != through, height
    assert Rover(world, x=x, y=y - 0.3).collides(0.3)
    view = render(world, pose, CAMERA)
    on_person = view.rock == record["rock"]
    assert on_person.sum() > 500 and (view.range[on_person] < bare.range[on_person]).all()
    top = view.points[on_person][:, 2].max()
    assert top == pytest.approx(float(world.ground_height_at(x, y)) + 1.8, abs=0.01)
    world.move_obstacle(person, x + 0.5, y)
    assert float(world.protrusion_at(x, y)) < 0.01 and float(world.protrusion_at(x + 0.5, y)) > 1.7
    world.remove_obstacle(person)
    assert np.array_equal(world.heights, heights)
    assert np.array_equal(render(world, pose, CAMERA).range, bare.range)


def test_drops_are_refused_off_the_world_and_on_what_must_stay_clear(world):
    x0, x1, y0, y1 = world.bounds
    with pytest.raises(ValueError, match="its bounds are"):
        world.add_rock(x1 - 0.05, 0.0, 0.2)
    with pytest.raises(ValueError, match="its bounds are"):
        world.add_astronaut(0.0, y0 + 0.1)
    rover = Rover(world, x=0.0, y=0.0)
    with pytest.raises(ValueError, match="would land on the rover"):
        world.add_rock(0.1, 0.0, 0.2, keep_clear=rover.footprint())
    with pytest.raises(KeyError, match="no added obstacle 99"):
        world.remove_obstacle(99)
    assert world.obstacles() == []


def test_ids_are_kept_and_clear_takes_one_kind(world):
    a, b = world.add_rock(1.0, -2.0, 0.1), world.add_rock(-1.0, -2.0, 0.15, 0.3)
    person = world.add_astronaut(2.0, 2.0)
    assert (a, b) < (person,) and len({a, b, person}) == 3
    world.remove_obstacle(a)
    assert [o["id"] for o in world.obstacles()] == [b, person]
    assert world.rock_at(-1.0, -2.0) == world.obstacles()[0]["rock"]
    assert world.clear_obstacles("rock") == [b]
    assert [o["kind"] for o in world.obstacles()] == ["astronaut"]
    with pytest.raises(ValueError, match="added obstacles"):
        world.save("/tmp/never-written")
    world.clear_obstacles()
    assert world.add_rock(1.0, -2.0, 0.1) > person      # ids are never reused
    world.clear_obstacles()


def test_a_render_sees_the_world_before_or_after_a_change_never_half(world):
    x, y = free_spot(world, 1.3, 0.0, 0.3)
    pose = view_of(world, x, y)
    bare = render(world, pose, CAMERA).range
    rock = world.add_rock(x, y, 0.3, seed=2)
    with_rock = render(world, pose, CAMERA).range
    world.remove_obstacle(rock)
    stop, seen, errors = threading.Event(), [], []

    def churn():
        try:
            while not stop.is_set():
                world.remove_obstacle(world.add_rock(x, y, 0.3, seed=2))
        except Exception as exc:  # noqa: BLE001 - reported below
            errors.append(exc)
    thread = threading.Thread(target=churn)
    thread.start()
    try:
        for _ in range(30):
            view = render(world, pose, CAMERA)
            seen.append(view.range)
            _ = view.intensity   # lazily computed images use the same state as the rays
    finally:
        stop.set()
        thread.join()
    assert not errors
    assert all(np.array_equal(r, bare) or np.array_equal(r, with_rock) for r in seen)


def test_a_world_without_drops_is_as_it_was(world, tmp_path):
    assert world.surface is world.surface.static and world.obstacles() == []
    loaded = World.load(world.save(tmp_path / "scene"))
    assert np.array_equal(loaded.heights, world.heights) and loaded.rock_cover() == world.rock_cover()
