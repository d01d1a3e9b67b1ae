"""The simulated hopping rover: ballistic flight against the analytic answers, touchdown on the ground
and on rocks, bounces and rest, camera geometry, images, sensors, seeds and saving.

Small worlds (8 m, 2 cm cells) built once per module; physics-only hops skip rendering, and the
rendering tests use tiny images, so the whole file runs in seconds.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
from pydantic import ValidationError

from drivers.sim.config import WorldConfig
from drivers.sim.hopper import Hopper, HopperConfig, HopRecord
from drivers.sim.hopper_flight import OffTerrain, body_samples, clearance, first_contact, launch_velocity
from drivers.sim.world import World
from toolbox.hopping.ballistics import hop_range, launch_to_target

G = 1.62
PLAIN = {"undulation_rms_m": 0.0, "relief_rms_m": 0.0}
NO_ROCKS = {"cover": 0.0}
# Launch errors and bounces off: the hop is exactly the command.
EXACT = {"launch_errors": {"speed_fraction": 0.0, "elevation_deg": 0.0, "heading_deg": 0.0},
         "bounce": {"count": 0}}
TINY_CAMERA = {"width": 64, "height": 48}


def exact_config(**changes) -> HopperConfig:
    return HopperConfig(**{**EXACT, "camera": TINY_CAMERA, **changes})


@pytest.fixture(scope="module")
def flat() -> World:
    return World.build(WorldConfig(seed=1, size_m=(8.0, 8.0), cell_m=0.02, craters={"count": 0}, rocks=NO_ROCKS,
                                   terrain={"slope_deg": 0.0, **PLAIN}))


@pytest.fixture(scope="module")
def slope() -> World:
    """A plane falling 6 degrees toward azimuth 200 (clockwise from north): downhill is heading 250
    degrees counter-clockwise from east, uphill 70."""
    return World.build(WorldConfig(seed=2, size_m=(8.0, 8.0), cell_m=0.02, craters={"count": 0}, rocks=NO_ROCKS,
                                   terrain={"slope_deg": 6.0, "slope_azimuth_deg": 200.0, **PLAIN}))


@pytest.fixture(scope="module")
def rocky() -> World:
    return World.build(WorldConfig(seed=3, size_m=(8.0, 8.0), cell_m=0.02, craters={"count": 0}))


def centres_of_mass(record: HopRecord) -> np.ndarray:
    """The centre of mass at each frame, from the true camera poses (eq 1 with the true offset)."""
    return record.camera_to_world[:, :3, :3] @ record.com_in_camera + record.camera_to_world[:, :3, 3]


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return math.degrees(math.acos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1.0, 1.0)))


# ------------------------------------------------------------------------------------ ballistics
def test_flight_on_flat_ground_is_the_analytic_parabola(flat):
    speed, elevation, heading = 1.37, math.radians(60.0), math.radians(30.0)
    record = Hopper(flat, exact_config()).hop(speed, 60.0, 30.0, render_frames=False)
    assert np.allclose(record.launch_velocity, launch_velocity(speed, elevation, heading), atol=1e-12)
    # Flight time, range and apex of a parabola landing at its launch height.
    flight_time = 2 * speed * math.sin(elevation) / G
    assert record.flight_time == pytest.approx(flight_time, abs=1e-6)
    assert record.hop_range == pytest.approx(speed ** 2 * math.sin(2 * elevation) / G, abs=1e-5)
    assert record.hop_range == pytest.approx(float(hop_range(speed, elevation)), abs=1e-5)   # the toolbox's eq 14
    assert record.landing_centre[2] == pytest.approx(record.launch_centre[2], abs=1e-6)
    travel = record.landing_centre[:2] - record.launch_centre[:2]
    assert math.atan2(travel[1], travel[0]) == pytest.approx(heading, abs=1e-9)
    # Every frame's centre of mass lies on p0 + v t - g t^2 / 2, and the highest one at the apex.
    centres = centres_of_mass(record)
    t = record.timestamps
    expected = record.launch_centre + np.outer(t, record.launch_velocity) - np.outer(0.5 * G * t ** 2, [0, 0, 1])
    assert np.allclose(centres, expected, atol=1e-9)
    apex = (speed * math.sin(elevation)) ** 2 / (2 * G)
    assert centres[:, 2].max() - record.launch_centre[2] == pytest.approx(apex, abs=1e-3)
    # One frame every 1/34 s from launch to touchdown: about 50 for this 1 m hop.
    assert len(record.timestamps) == math.floor(flight_time * 34.0) + 1
    assert abs(len(record.timestamps) - flight_time * 34.0) <= 1
    assert np.allclose(np.diff(t), 1 / 34.0) and t[0] == 0.0 and t[-1] <= record.flight_time
    # No bounces: it rests where it first touched, on the ground.
    assert np.allclose(record.bounce_displacement, 0.0, atol=1e-6) and len(record.bounce_centres) == 0
    assert record.settled_centre[2] - 0.15 == pytest.approx(0.0, abs=1e-6)
    assert record.contact_rock == -1


def test_the_toolbox_launch_to_a_target_lands_on_it(flat):
    hopper = Hopper(flat, exact_config(), x=-1.0, y=0.5)
    start = hopper.body_to_world[:3, 3]
    target = start + np.array([1.2, -0.9, 0.0])
    launch = launch_to_target(start, target, gravity=G)
    record = hopper.hop(launch.speed, math.degrees(launch.elevation), math.degrees(launch.heading),
                        render_frames=False)
    assert np.allclose(record.landing_centre, target, atol=1e-5)
    assert record.flight_time == pytest.approx(launch.flight_time, abs=1e-6)
    assert np.allclose(hopper.ground_position[:2], target[:2], atol=1e-5)    # the hopper moved there


def test_landing_on_a_slope_is_where_the_sphere_meets_the_plane(slope):
    # The ground is the plane z = a + b x + c y; the body touches it when its centre is r above it,
    # measured along the normal: z_c - (a + b x_c + c y_c) = r sqrt(1 + b^2 + c^2).
    h0, hx, hy = (float(slope.height_at(x, y)) for x, y in ((0, 0), (1, 0), (0, 1)))
    a, b, c = h0, hx - h0, hy - h0
    ranges = {}
    for heading_deg in (70.0, 250.0, 160.0):                    # uphill, downhill, across
        record = Hopper(slope, exact_config()).hop(1.5, 55.0, heading_deg, render_frames=False)
        p, v = record.launch_centre, record.launch_velocity
        height_above = p[2] - a - b * p[0] - c * p[1] - 0.15 * math.sqrt(1 + b * b + c * c)
        rate = v[2] - b * v[0] - c * v[1]
        t = (rate + math.sqrt(rate ** 2 + 2 * G * height_above)) / G    # root of height_above + rate t - g t^2 / 2
        assert record.flight_time == pytest.approx(t, abs=2e-3)
        expected = p + v * t - np.array([0, 0, 0.5 * G * t * t])
        assert np.allclose(record.landing_centre, expected, atol=2e-3)
        ranges[heading_deg] = record.hop_range
    flat_range = 1.5 ** 2 * math.sin(math.radians(110.0)) / G
    assert ranges[70.0] < flat_range < ranges[250.0]                      # short uphill, long downhill
    assert ranges[160.0] == pytest.approx(flat_range, abs=3e-3)


# ------------------------------------------------------------------------------------ obstacles
class Wall:
    """Synthetic terrain: flat ground, and a 2 m wall for x >= 1."""

    def height_at(self, x, y):
        return np.where(np.asarray(x) >= 1.0, 2.0, 0.0) + 0.0 * np.asarray(y)


def test_a_wall_stops_the_body_when_its_side_reaches_it():
    radius = 0.15
    velocity = launch_velocity(3.0, math.radians(30.0), math.radians(20.0))   # would fly 4.8 m
    contact = first_contact(Wall(), np.array([0.0, 0.0, radius]), velocity, G, body_samples(radius), 0.004)
    # The body's leading point reaches x = 1 when its centre is one radius short of the wall.
    assert contact.centre[0] == pytest.approx(1.0 - radius, abs=1e-6)
    assert contact.time == pytest.approx((1.0 - radius) / velocity[0], abs=1e-6)
    assert contact.point[0] == pytest.approx(1.0, abs=1e-6) and contact.point[2] == 2.0
    # Clear of the wall at the reported instant, in it a microsecond later.
    after = contact.centre + 1e-6 * contact.velocity
    gap, _ = clearance(Wall(), np.stack([contact.centre, after]), body_samples(radius))
    assert gap[0] >= 0.0 > gap[1]


def test_a_tall_rock_in_the_path_stops_the_flight(rocky):
    index, start, heading = _approach_to_a_tall_rock(rocky)
    rock = rocky.rocks[index]
    hopper = Hopper(rocky, exact_config(), x=start[0], y=start[1])
    elevation, flat_range = math.radians(20.0), 2.6                        # a low hop right over the rock
    speed = math.sqrt(G * flat_range / math.sin(2 * elevation))
    record = hopper.hop(speed, 20.0, math.degrees(heading), render_frames=False)
    assert record.contact_rock == index
    assert record.flight_time < 0.6 * 2 * speed * math.sin(elevation) / G
    to_rock = np.hypot(rock["x"] - start[0], rock["y"] - start[1])
    assert record.hop_range < to_rock                                      # stopped short of its centre
    assert np.hypot(*(record.contact_point[:2] - [rock["x"], rock["y"]])) <= rock["radius"] + 0.02


def _approach_to_a_tall_rock(world: World):
    """A rock at least 0.28 m tall, and a clear start 1 m before its edge with the hop heading at it."""
    rocks = world.rocks
    for index in np.argsort(rocks["height"])[::-1]:
        rock = rocks[index]
        if rock["height"] < 0.28:
            break
        for direction in np.arange(8) * (math.pi / 4):
            distance = rock["radius"] + 1.0
            start = np.array([rock["x"], rock["y"]]) - distance * np.array([math.cos(direction), math.sin(direction)])
            if np.any(np.abs(start) > 3.5):
                continue
            ring = start + 0.2 * np.stack([np.cos(np.arange(12) * 0.52), np.sin(np.arange(12) * 0.52)], axis=1)
            path = start + np.outer(np.linspace(0, 1.0, 40), [math.cos(direction), math.sin(direction)])
            if np.all(world.protrusion_at(*np.vstack([ring, path]).T) < 0.02):
                return int(index), start, direction
    pytest.fail("the rocky world has no tall rock with a clear approach")


# ------------------------------------------------------------------------------------ rest and bounces
def test_bounces_move_the_hopper_and_it_rests_on_the_terrain(slope, rocky):
    # Plain slope: the body rests with its bottom on the ground, moved by the bounces.
    hopper = Hopper(slope, HopperConfig(camera=TINY_CAMERA))
    record = hopper.hop(1.4, 60.0, 0.0, render_frames=False)
    assert len(record.bounce_centres) == 2
    moved = np.hypot(*record.bounce_displacement[:2])
    assert 0.005 < moved < 0.5
    ground = float(slope.height_at(*record.settled_centre[:2]))
    assert record.settled_centre[2] - 0.15 == pytest.approx(ground, abs=0.01)
    assert np.allclose(record.settled_ground, [*record.settled_centre[:2], ground])
    # Rocky ground: a chain of hops, each launched where the last one came to rest, touching the
    # terrain (the lowest body point exactly on it), never in it.
    samples = body_samples(0.15)
    hopper = Hopper(rocky, HopperConfig(camera=TINY_CAMERA), x=-2.0, y=-2.0)
    previous = None
    for heading in (45.0, 60.0, 30.0):
        record = hopper.hop(1.4, 60.0, heading, render_frames=False)
        if previous is not None:
            assert np.allclose(record.launch_centre[:2], previous.settled_centre[:2])
        for centre in (record.launch_centre, record.landing_centre, record.settled_centre):
            gap, _ = clearance(rocky, centre[None], samples)
            assert 0.0 <= gap[0] < 1e-4
        previous = record
    assert np.allclose(hopper.body_to_world[:3, 3], record.settled_centre)


def test_spin_turns_the_camera_at_the_spin_rate(flat):
    record = Hopper(flat, exact_config(launch_errors={"speed_fraction": 0.0, "elevation_deg": 0.0,
                                                      "heading_deg": 0.0, "spin_deg_s": 30.0})
                    ).hop(1.37, 60.0, 0.0, seed=4, render_frames=False)
    rates = np.linalg.norm(record.spin)
    assert rates > 0
    first, last = record.camera_to_world[0, :3, :3], record.camera_to_world[-1, :3, :3]
    turned = math.acos(np.clip((np.trace(first.T @ last) - 1) / 2, -1, 1))
    assert turned == pytest.approx(rates * record.timestamps[-1], abs=1e-9)
    # The centre of mass still flies the same parabola; the camera does not.
    t = record.timestamps
    expected = record.launch_centre + np.outer(t, record.launch_velocity) - np.outer(0.5 * G * t ** 2, [0, 0, 1])
    assert np.allclose(centres_of_mass(record), expected, atol=1e-9)


# ------------------------------------------------------------------------------------ camera
def test_camera_looks_45_degrees_down_along_the_travel(flat):
    hopper = Hopper(flat, exact_config())
    record = hopper.hop(1.37, 60.0, 30.0, render_frames=False)
    heading = math.radians(30.0)
    down45 = np.array([math.cos(heading), math.sin(heading), -1.0]) / math.sqrt(2)
    for pose in (record.camera_to_world[0], record.camera_to_world[-1], record.before_pose):
        assert np.allclose(pose[:3, 2], down45, atol=1e-9)                  # optical axis
        assert abs(pose[2, 0]) < 1e-9                                       # image rows level
        assert pose[2, 1] < 0                                               # image y points down
    # The configured vertical field of view; the camera sits off the centre of mass, as configured.
    camera = record.camera
    assert math.degrees(2 * math.atan(camera.height / 2 / camera.fy)) == pytest.approx(94.4)
    assert np.allclose(np.linalg.norm(record.com_in_camera), np.linalg.norm((0.12, 0.0, 0.05)))
    # At rest on flat ground the accelerometer sees gravity 45 degrees below the optical axis.
    assert np.allclose(record.true_gravity_launch, [0.0, math.sqrt(0.5), math.sqrt(0.5)], atol=1e-9)


def test_sensors_read_gravity_and_heading_with_their_noise(flat):
    noisy = Hopper(flat, exact_config(sensors={"gravity_deg": 0.5, "sun_heading_deg": 1.0}))
    errors = []
    for seed in range(6):
        record = noisy.hop(0.8, 60.0, 90.0, seed=seed, render_frames=False)
        errors.append([angle_deg(record.imu_gravity_launch, record.true_gravity_launch),
                       math.degrees(abs(record.sun_heading_launch - record.launch_yaw))])
        assert np.linalg.norm(record.imu_gravity_settled) == pytest.approx(1.0)
    errors = np.array(errors)
    assert np.all(errors[:, 0] < 2.5) and errors[:, 0].mean() > 0.05
    assert np.all(errors[:, 1] < 4.0) and errors[:, 1].mean() > 0.05
    exact = Hopper(flat, exact_config(sensors={"gravity_deg": 0.0, "sun_heading_deg": 0.0}))
    record = exact.hop(0.8, 60.0, 90.0, render_frames=False)
    assert np.allclose(record.imu_gravity_launch, record.true_gravity_launch)
    assert record.sun_heading_launch == pytest.approx(math.pi / 2)
    assert record.launch_yaw == pytest.approx(math.pi / 2)


# ------------------------------------------------------------------------------------ images
def test_frames_show_the_terrain_and_motion_blurs_them(rocky):
    config = HopperConfig(camera={"width": 96, "height": 72}, bounce={"count": 1})
    record = Hopper(rocky, config, x=-1.0, y=-1.0).hop(1.37, 60.0, 45.0, seed=7)
    assert record.frames.shape == (len(record.timestamps), 72, 96) and record.frames.dtype == np.uint8
    assert record.before.shape == record.after.shape == (72, 96)
    assert 0 < record.exposure_s <= 8e-3
    for image in (record.before, record.frames[len(record.frames) // 2], record.after):
        assert 50 < image.mean() < 160                                        # exposed for grey 100
        assert image.std() > 10 and np.mean(image == 255) < 0.01             # texture, not saturated
    sharp = Hopper(rocky, config.model_copy(update={"camera": config.camera.model_copy(update={"motion_blur": False})}),
                   x=-1.0, y=-1.0).hop(1.37, 60.0, 45.0, seed=7)
    # Fastest and lowest right after launch: there the blur smooths the image most.
    assert _sharpness(record.frames[1:4]) < 0.9 * _sharpness(sharp.frames[1:4])


def _sharpness(frames: np.ndarray) -> float:
    """Mean absolute difference of neighbouring pixels along the rows and columns."""
    images = frames.astype(np.float64)
    return float(np.abs(np.diff(images, axis=1)).mean() + np.abs(np.diff(images, axis=2)).mean())


# ------------------------------------------------------------------------------------ seeds, files, errors
def test_seeded_hops_repeat_and_other_seeds_differ(rocky):
    def run(seed=None):
        hopper = Hopper(rocky, HopperConfig(camera=TINY_CAMERA), x=-2.0, y=1.0)
        return hopper.hop(1.3, 60.0, -20.0, seed=seed), hopper

    first, hopper = run()
    again, _ = run()
    assert np.array_equal(first.frames, again.frames) and np.array_equal(first.camera_to_world, again.camera_to_world)
    assert first.truth() == again.truth()
    assert np.array_equal(run(first.seed)[0].frames, first.frames)          # the recorded seed replays it
    other, _ = run(first.seed + 1)
    assert not np.allclose(other.launch_velocity, first.launch_velocity)
    assert not np.allclose(other.settled_centre, first.settled_centre)
    assert hopper.hops == 1 and hopper.hop(1.3, 60.0, 0.0, render_frames=False).seed != first.seed


def test_save_and_load_give_back_the_record(rocky, tmp_path):
    record = Hopper(rocky, HopperConfig(camera={**TINY_CAMERA, "motion_blur": False})).hop(1.2, 60.0, 10.0)
    loaded = HopRecord.load(record.save(tmp_path / "hop-001"))
    for name in ("frames", "before", "after", "timestamps"):
        assert np.array_equal(getattr(loaded, name), getattr(record, name)), name
    assert np.allclose(loaded.camera_to_world, record.camera_to_world)
    assert loaded.camera == record.camera and loaded.config == record.config
    assert loaded.contact_rock == record.contact_rock and loaded.seed == record.seed
    _assert_close_tree(loaded.truth(), record.truth())
    with pytest.raises(FileNotFoundError):
        HopRecord.load(tmp_path / "nothing-here")


def _assert_close_tree(a, b):
    if isinstance(a, dict):
        assert a.keys() == b.keys()
        for key in a:
            _assert_close_tree(a[key], b[key])
    elif isinstance(a, list):
        assert np.allclose(np.asarray(a, float), np.asarray(b, float), atol=1e-12)
    else:
        assert a == pytest.approx(b, abs=1e-12)


def test_bad_commands_and_configs_are_refused(flat):
    hopper = Hopper(flat, exact_config())
    for speed, elevation in ((0.0, 45.0), (1.0, 90.0), (1.0, -5.0), (float("nan"), 45.0)):
        with pytest.raises(ValueError):
            hopper.hop(speed, elevation, 0.0, render_frames=False)
    with pytest.raises(ValidationError):
        HopperConfig(wheels=4)
    with pytest.raises(ValidationError):
        HopperConfig(bounce={"elevation_range_deg": (50.0, 20.0)})
    # A hop off the edge of the world fails and leaves the hopper where it stood.
    with pytest.raises(OffTerrain):
        hopper.hop(4.0, 45.0, 0.0, render_frames=False)
    assert hopper.x == 0.0 and hopper.y == 0.0 and hopper.hops == 0
