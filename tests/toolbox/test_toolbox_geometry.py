"""toolbox.geometry (transforms, the sensor chain, projection) and toolbox.views (PTU view planning)."""
from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.sim.config import WorldConfig
from drivers.sim.rover import Rover
from drivers.sim.world import World
from toolbox import geometry as g
from toolbox.camera import Intrinsics, project
from toolbox.mapping import views as v

SR4000_FOV = (math.radians(43.6), math.radians(34.6))
angles = st.floats(-math.pi, math.pi, allow_nan=False)


@pytest.fixture(scope="module")
def world() -> World:
    """A tilted, bumpy little world, so the rover stands with roll and pitch."""
    terrain = {"slope_deg": 9.0, "slope_azimuth_deg": 120.0, "undulation_rms_m": 0.1, "undulation_wavelength_m": 3.0}
    return World.build(WorldConfig(seed=4, size_m=(6.0, 6.0), terrain=terrain, craters={"count": 0},
                                   rocks={"cover": 0.02}))


def mount_of(rover: Rover, sensor: str, calibrated: bool) -> g.SensorMount:
    mounts = rover.calibrated_mounts if calibrated else rover.true_mounts
    m = mounts[sensor]
    return g.SensorMount.from_offsets(rover.config.ptu_position_m, m.position_m, m.rotation_deg)


# ---------------------------------------------------------------------------------- the chain
@pytest.mark.parametrize("calibrated", [False, True])
def test_chain_matches_the_simulator_to_1e9(world, calibrated):
    for x, y, heading in [(0.0, 0.0, 0.0), (1.2, -0.7, 2.1), (-1.5, 1.0, -2.8)]:
        rover = Rover(world, x=x, y=y, heading=heading)
        pose = g.RoverPose.from_matrix(rover.body_to_world)
        assert abs(pose.roll) + abs(pose.pitch) > math.radians(2)        # really on a slope
        for sensor in rover.sensors:
            mount = mount_of(rover, sensor, calibrated)
            for pan, tilt in [(0.0, 0.0), (35.0, -20.0), (-150.0, 25.0), (179.0, -45.0)]:
                ours = g.camera_to_world(pose, mount, math.radians(pan), math.radians(tilt))
                theirs = rover.sensor_to_world(sensor, pan, tilt, calibrated=calibrated)
                assert np.abs(ours - theirs).max() < 1e-9


def test_true_and_calibrated_mounts_differ_slightly(world):
    rover = Rover(world)
    pose = g.RoverPose.from_matrix(rover.body_to_world)
    true = g.camera_to_world(pose, mount_of(rover, "tof", False), 0.3, -0.4)
    calibrated = g.camera_to_world(pose, mount_of(rover, "tof", True), 0.3, -0.4)
    assert 0 < np.abs(true - calibrated).max() < 0.01


def test_rover_pose_round_trip_and_conventions():
    pose = g.RoverPose(1.0, 2.0, 0.5, heading=0.7, roll=0.1, pitch=-0.2)
    again = g.RoverPose.from_matrix(pose.to_world())
    assert np.allclose([again.x, again.y, again.z, again.heading, again.roll, again.pitch],
                       [1.0, 2.0, 0.5, 0.7, 0.1, -0.2], atol=1e-12)
    # Positive pitch puts the nose down, positive roll the left side up.
    assert g.RoverPose(0, 0, pitch=0.2).to_world()[2, 0] < 0
    assert g.RoverPose(0, 0, roll=0.2).to_world()[2, 1] > 0
    # Heading counter-clockwise from east: 90 degrees faces north.
    assert np.allclose(g.RoverPose(0, 0, heading=math.pi / 2).to_world()[:3, 0], [0, 1, 0], atol=1e-12)


def test_pan_right_tilt_up():
    mount = g.SensorMount.from_offsets((0.1, 0.0, 1.4), (0.0, 0.0, 0.0))
    facing_north = g.RoverPose(0.0, 0.0, heading=math.pi / 2)
    view = g.camera_to_world(facing_north, mount, math.radians(90), 0.0)[:3, 2]
    assert np.allclose(view, [1, 0, 0], atol=1e-12)           # pan +90 from north looks east
    up = g.camera_to_world(facing_north, mount, 0.0, math.radians(30))[:3, 2]
    assert up[2] == pytest.approx(0.5)
    # direction_of gives the head's forward axis in the frame the PTU sits in.
    for pan, tilt in [(0.4, -0.3), (-2.0, 0.5)]:
        assert np.allclose(g.camera_to_rover(mount, pan, tilt)[:3, 2], g.direction_of(pan, tilt), atol=1e-12)


@settings(max_examples=50, deadline=None)
@given(angles, st.floats(-1.5, 1.5), angles, st.floats(-5, 5), st.floats(-5, 5))
def test_rigid_helpers(roll, pitch, yaw, tx, ty):
    rotation = g.rotation_rpy(roll, pitch, yaw)
    assert np.allclose(g.rotation_rpy(*g.rpy_of(rotation)), rotation, atol=1e-9)
    pose = g.rigid(rotation, (tx, ty, 1.0))
    other = g.rigid(g.rotation_z(0.3), (1.0, 0.0, -2.0))
    assert np.allclose(g.compose(pose, g.invert(pose)), np.eye(4), atol=1e-12)
    assert np.allclose(g.compose(pose, other), pose @ other)
    points = np.array([[1.0, 2.0, 3.0], [-1.0, 0.5, 0.0]])
    homogeneous = (pose @ np.c_[points, np.ones(2)].T).T[:, :3]
    assert np.allclose(g.apply(pose, points), homogeneous)
    assert np.allclose(g.relative_pose(pose, other), np.linalg.inv(other) @ pose)


def test_projection_matches_opencv_and_the_rays_the_simulator_casts():
    intrinsics = Intrinsics(176, 144, 262.9, 262.9, 88.0, 69.0, k1=-0.3, k2=0.1)
    rng = np.random.default_rng(0)
    points = np.c_[rng.uniform(-1, 1, (50, 2)), rng.uniform(1, 5, 50)]
    ours = project(points, intrinsics)
    opencv, _ = cv2.projectPoints(points, np.zeros(3), np.zeros(3), intrinsics.matrix, intrinsics.distortion)
    assert np.allclose(ours, opencv[:, 0], atol=1e-6)
    # the renderer casts ray_directions(): each pixel's ray must project back onto that pixel
    rays = intrinsics.ray_directions().astype(np.float64)
    v, u = np.mgrid[0:intrinsics.height, 0:intrinsics.width]
    assert np.allclose(project(rays, intrinsics), np.stack([u, v], axis=-1), atol=1e-3)
    assert np.isnan(project(np.array([[0.0, 0.0, -1.0]]), intrinsics)).all()


def test_footprint_matches_the_simulator(world):
    rover = Rover(world, x=0.5, y=-0.4, heading=1.1)
    ours = g.footprint_polygon(g.RoverPose(rover.x, rover.y, heading=rover.heading), rover.config.body_length_m,
                               rover.config.body_width_m)
    assert np.allclose(ours, rover.footprint(), atol=1e-12)


# ---------------------------------------------------------------------------------- view planning
def sample_directions(pan_range, tilt_range, count=120):
    pans = np.linspace(*pan_range, count)
    tilts = np.linspace(*tilt_range, count // 3)
    return np.meshgrid(pans, tilts)


def seen_by_some_view(views, fov, pans, tilts):
    seen = np.zeros(pans.shape, dtype=bool)
    for pan, tilt in views:
        seen |= v.in_view(pan, tilt, *fov, pans, tilts)
    return seen


@pytest.mark.parametrize("pan_range, tilt_range", [
    ((-math.pi, math.pi), (math.radians(-60), math.radians(10))),      # full panorama, three rows
    ((math.radians(-70), math.radians(45)), (math.radians(-45), math.radians(-30))),   # one row
    ((math.radians(-10), math.radians(10)), (math.radians(-5), math.radians(5))),      # one view
    ((0.0, 2 * math.pi), (math.radians(-80), math.radians(-50))),       # steep: wide keystones
])
def test_every_direction_in_the_range_is_seen(pan_range, tilt_range):
    views = v.plan_views(pan_range, tilt_range, *SR4000_FOV, overlap=0.1)
    pans, tilts = sample_directions(pan_range, tilt_range)
    assert seen_by_some_view(views, SR4000_FOV, pans, tilts).all()


def test_full_panorama_has_no_seam_view_and_no_spare_view():
    views = v.plan_views((-math.pi, math.pi), (0.0, 0.0), *SR4000_FOV, overlap=0.1)
    pans = np.sort(views[:, 0])
    steps = np.diff(np.r_[pans, pans[0] + 2 * math.pi])
    assert np.allclose(steps, 2 * math.pi / len(pans))             # evenly round, seam included
    assert len(pans) == math.ceil(2 * math.pi / (SR4000_FOV[0] * 0.9))
    assert pans[0] >= -math.pi and pans[-1] < math.pi              # inside the range, no duplicate


@pytest.mark.parametrize("overlap", [0.1, 0.3])
def test_neighbouring_views_overlap_by_the_fraction_asked(overlap):
    views = v.plan_views((math.radians(-90), math.radians(90)), (0.0, 0.0), *SR4000_FOV, overlap=overlap)
    spacing = np.diff(views[:, 0])
    assert (spacing <= SR4000_FOV[0] * (1 - overlap) + 1e-9).all()
    rows = v.plan_views((0.0, 0.1), (math.radians(-60), math.radians(10)), *SR4000_FOV, overlap=overlap)
    assert (np.diff(np.unique(rows[:, 1])) <= SR4000_FOV[1] * (1 - overlap) + 1e-9).all()


def test_serpentine_order_keeps_travel_short():
    views = v.plan_views((-math.pi, math.pi), (math.radians(-60), math.radians(10)), *SR4000_FOV, overlap=0.1)
    tilts = views[:, 1]
    changes = np.flatnonzero(np.diff(tilts) != 0)
    assert len(changes) == 2 and (np.diff(tilts[changes[0]:changes[0] + 2]) > 0).all()
    for end in changes:              # a row starts near the pan where the previous one ended
        assert abs(views[end + 1, 0] - views[end, 0]) < SR4000_FOV[0]
    raster = views[np.lexsort((views[:, 0], views[:, 1]))]
    assert v.travel(views) < v.travel(raster)


def test_in_view_agrees_with_the_projection():
    intrinsics = Intrinsics.from_fov(176, 144, SR4000_FOV[0])
    fov = (SR4000_FOV[0], 2 * math.atan(intrinsics.height / 2 / intrinsics.fy))
    mount = g.SensorMount(ptu_position=(0.0, 0.0, 0.0), camera_to_head=g.rigid(g.CAMERA_AXES_IN_HEAD))
    view_pan, view_tilt = 0.6, -0.5
    to_camera = g.invert(g.camera_to_rover(mount, view_pan, view_tilt))
    pans, tilts = sample_directions((0.0, 1.2), (-1.0, 0.0), 60)
    uv = project(g.apply(to_camera, g.direction_of(pans, tilts)), intrinsics)
    inside = (np.abs(uv[..., 0] - intrinsics.cx) <= intrinsics.width / 2) & \
        (np.abs(uv[..., 1] - intrinsics.cy) <= intrinsics.height / 2)
    assert np.array_equal(v.in_view(view_pan, view_tilt, *fov, pans, tilts), inside)


def test_bad_requests_are_refused():
    with pytest.raises(ValueError):
        v.plan_views((1.0, 0.0), (0.0, 0.1), *SR4000_FOV)
    with pytest.raises(ValueError):
        v.plan_views((0.0, 1.0), (0.0, 0.1), 0.0, 0.5)
    with pytest.raises(ValueError):
        v.plan_views((0.0, 1.0), (0.0, 0.1), *SR4000_FOV, overlap=1.0)
    with pytest.raises(ValueError):   # zero overlap: tilted frames would only touch at the corners
        v.plan_views((0.0, 3.0), (math.radians(-60), math.radians(-60) + 2 * SR4000_FOV[1]), *SR4000_FOV, overlap=0.0)
