"""The simulated rover: settling on the terrain, PTU geometry, sensor mounts and footprint."""
from __future__ import annotations

import math

import numpy as np
import pytest

from drivers.sim.config import WorldConfig
from drivers.sim.rover import Rover, RoverConfig
from drivers.sim.world import World


@pytest.fixture(scope="module")
def world() -> World:
    """A plain 8 degree slope falling toward the east, with rocks but no hills or craters."""
    terrain = {"slope_deg": 8.0, "slope_azimuth_deg": 90.0, "undulation_rms_m": 0.0, "relief_rms_m": 0.001}
    return World.build(WorldConfig(seed=11, size_m=(6.0, 6.0), terrain=terrain, craters={"count": 0}))


def angle_between(a: np.ndarray, b: np.ndarray) -> float:
    return math.degrees(math.acos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1, 1)))


def test_rover_stands_on_the_terrain_and_tilts_with_it(world):
    # The ground falls toward the east (azimuth 90) at 8 degrees: facing east the nose points down.
    rover = Rover(world, heading=0.0)
    roll, pitch = rover.roll_pitch()
    assert math.degrees(pitch) == pytest.approx(8.0, abs=0.5)
    assert abs(math.degrees(roll)) < 0.5
    assert rover.body_to_world[2, 3] == pytest.approx(float(world.height_at(0.0, 0.0)), abs=0.03)
    north = Rover(world, heading=math.pi / 2)
    roll, pitch = north.roll_pitch()
    assert math.degrees(roll) == pytest.approx(8.0, abs=0.5)          # left (west) side up
    assert abs(math.degrees(pitch)) < 0.5


def test_cameras_sit_on_the_mast_a_baseline_apart(world):
    rover = Rover(world, x=0.5, y=-0.5, heading=1.0)
    left, right = rover.sensor_to_world("left"), rover.sensor_to_world("right")
    assert np.linalg.norm(left[:3, 3] - right[:3, 3]) == pytest.approx(0.25, abs=0.01)
    ground = float(world.height_at(0.5, -0.5))
    assert left[2, 3] - ground == pytest.approx(1.5, abs=0.1)
    # The left camera is to the left: along the camera's -x axis from the right one.
    assert (left[:3, 3] - right[:3, 3]) @ right[:3, 0] < -0.2
    for pose in (left, right, rover.sensor_to_world("tof")):
        assert np.allclose(pose[:3, :3].T @ pose[:3, :3], np.eye(3), atol=1e-12)
        assert np.linalg.det(pose[:3, :3]) == pytest.approx(1.0)


def test_pan_turns_right_and_tilt_looks_up(world):
    rover = Rover(world, heading=math.pi / 2)                     # facing north
    ahead = rover.sensor_to_world("left")[:3, 2]
    assert angle_between(ahead, np.array([0.0, 1.0, ahead[2]])) < 3.0
    right = rover.sensor_to_world("left", pan_deg=90.0)[:3, 2]
    assert right[0] > 0.95                                          # pan +90: looking east
    up = rover.sensor_to_world("left", tilt_deg=30.0)[:3, 2]
    down = rover.sensor_to_world("left", tilt_deg=-30.0)[:3, 2]
    assert up[2] > 0.4 and down[2] < -0.4
    assert angle_between(up, ahead) == pytest.approx(30.0, abs=3.0)


def test_calibrated_mounts_differ_slightly_and_repeatably(world):
    rover = Rover(world)
    for sensor in rover.sensors:
        true, calibrated = rover.sensor_to_world(sensor), rover.sensor_to_world(sensor, calibrated=True)
        offset = np.linalg.norm(true[:3, 3] - calibrated[:3, 3])
        turn = math.degrees(math.acos(np.clip((np.trace(true[:3, :3].T @ calibrated[:3, :3]) - 1) / 2, -1, 1)))
        assert 0 < offset < 0.005 and 0 < turn < 0.5
    same = Rover(world)
    assert np.array_equal(same.sensor_to_world("tof", 10, -20), rover.sensor_to_world("tof", 10, -20))
    other = Rover(world, RoverConfig(seed=8))
    assert not np.array_equal(other.sensor_to_world("tof"), rover.sensor_to_world("tof"))


def test_footprint_and_collisions(world):
    rover = Rover(world, heading=0.3)
    corners = rover.footprint()
    sides = np.linalg.norm(np.roll(corners, -1, axis=0) - corners, axis=1)
    assert sorted(sides.round(3)) == [0.5, 0.5, 0.55, 0.55]
    assert not rover.collides(0.05)                                 # the start circle is clear
    tallest = world.rocks[np.argmax(world.rocks["height"])]
    on_rock = Rover(world, x=tallest["x"], y=tallest["y"])
    assert on_rock.collides(0.05)


def test_unknown_sensor_and_off_terrain_are_refused(world):
    rover = Rover(world)
    with pytest.raises(KeyError):
        rover.sensor_to_world("thermal")
    with pytest.raises(ValueError):
        rover.place(50.0, 0.0, 0.0)
