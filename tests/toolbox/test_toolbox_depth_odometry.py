"""Tests of the time-of-flight odometry (toolbox/odometry/depth.py) on emulated SR4000 frames from a
rover in a small simulated world: known steps and turns recovered, the refusals by reason, the
covariance's shape, and each small step on its own."""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import open3d as o3d
import pytest

from drivers.sim.clock import SimClock
from drivers.sim.rover import Rover
from drivers.sim.world import World, WorldConfig
from drivers.sr4000 import CONFIDENCE_FULL, wait_for_exposure
from drivers.sr4000_emulator import MRPT_INTRINSICS, Sr4000Emulator
from toolbox.geometry import apply
from toolbox.odometry.depth import (
    DepthFrame,
    DepthOdometryParams,
    check_plausible,
    depth_motion,
    depth_picture,
    depth_turn,
    information_condition,
    motion_error,
    pinhole_depth,
    point_to_plane_covariance,
    point_to_plane_jacobian,
    refine_guess,
    register,
    register_rotation,
    rotate_about,
    seen_share,
    usable_points,
    voxel_cloud,
)
from toolbox.odometry.estimate import OdometryFailure, exp_se3

TILT_DEG = -30.0              # the TOF looks along the heading, this far down: the best of -15..-40 (bench)
PINHOLE_SCALE = 0.8           # the points carry the lens' barrel distortion: a shorter pinhole holds them all
MIN_CONFIDENCE = 0.3


class TofRig:
    """A rover with its SR4000 on the mast (pan 0, tilted down): place it, take a DepthFrame, and get
    the true and the calibrated camera-to-world poses of that look."""

    def __init__(self, world: World, seed: int = 0, tilt_deg: float = TILT_DEG):
        self.rover, self.tilt_deg = Rover(world), tilt_deg
        self.camera = Sr4000Emulator(world, lambda: self.rover.sensor_to_world("tof", 0.0, self.tilt_deg),
                                     SimClock(1e4), seed=seed).open()

    def look(self, x: float, y: float, heading_rad: float) -> tuple[DepthFrame, np.ndarray, np.ndarray]:
        self.rover.place(x, y, heading_rad)
        wait_for_exposure(self.camera, 10)
        frame = self.camera.acquire()
        i = MRPT_INTRINSICS
        depth = DepthFrame.from_arrays(frame.xyz(), frame.amplitude, PINHOLE_SCALE * i.fx, PINHOLE_SCALE * i.fy,
                                       i.cx, i.cy, frame.confidence / CONFIDENCE_FULL, MIN_CONFIDENCE)
        return (depth, self.rover.sensor_to_world("tof", 0.0, self.tilt_deg),
                self.rover.sensor_to_world("tof", 0.0, self.tilt_deg, calibrated=True))

    def body(self) -> np.ndarray:
        return self.rover.body_to_world.copy()


def _rotation_zyx(yaw: float, pitch: float, roll: float) -> np.ndarray:
    cy, sy = math.cos(yaw), math.sin(yaw)
    cp, sp, cr, sr = math.cos(pitch), math.sin(pitch), math.cos(roll), math.sin(roll)
    return np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]]) @ np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]]) \
        @ np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])


def dead_reckoning(key_body: np.ndarray, key_calibrated: np.ndarray, forward_m: float, turn_deg: float,
                   new_roll_pitch: tuple[float, float] | None = None, rng: np.random.Generator | None = None,
                   distance_error: float = 0.05, heading_error_deg: float = 1.0,
                   attitude_error_deg: float = 0.2) -> np.ndarray:
    """key_from_new guess as the rover has it: the commanded planar step (forward, then turned) in the
    keyframe's body axes, the new roll and pitch from the inclinometer when given (else the keyframe's
    attitude kept), through the calibrated mount; with rng, a seeded drive error (distance_error of the
    step, heading_error_deg) and inclinometer error (attitude_error_deg)."""
    if rng is not None:
        forward_m *= 1 + rng.normal(0, distance_error)
        turn_deg += rng.normal(0, heading_error_deg)
    step = np.eye(4)
    c, s = math.cos(math.radians(turn_deg)), math.sin(math.radians(turn_deg))
    step[:2, :2] = [[c, -s], [s, c]]
    step[0, 3] = forward_m
    new_body = key_body @ step
    if new_roll_pitch is not None:
        roll, pitch = new_roll_pitch
        if rng is not None:
            roll, pitch = np.add((roll, pitch), rng.normal(0, math.radians(attitude_error_deg), 2))
        yaw = math.atan2(new_body[1, 0], new_body[0, 0])
        new_body[:3, :3] = _rotation_zyx(yaw, pitch, roll)
    body_from_camera = np.linalg.inv(key_body) @ key_calibrated
    return np.linalg.inv(key_calibrated) @ new_body @ body_from_camera


def step_pair(rig: TofRig, x: float, y: float, heading_rad: float, forward_m: float, turn_deg: float):
    """(key, new, true key_from_new, key body pose, key calibrated TOF pose, new (roll, pitch)) for a
    step forward then a turn."""
    key, key_true, key_cal = rig.look(x, y, heading_rad)
    body = rig.body()
    new_heading = heading_rad + math.radians(turn_deg)
    new, new_true, _ = rig.look(x + forward_m * math.cos(heading_rad), y + forward_m * math.sin(heading_rad),
                                new_heading)
    return key, new, np.linalg.inv(key_true) @ new_true, body, key_cal, rig.rover.roll_pitch()


# --------------------------------------------------------------------------------------------
# The method on emulated frames
# --------------------------------------------------------------------------------------------

HEADING = math.radians(200.0)     # open rolling ground ahead in this world (at 30 deg the rover climbs a rock)


@pytest.fixture(scope="module")
def rig() -> TofRig:
    return TofRig(World.build(WorldConfig(seed=5, size_m=(10.0, 10.0))), seed=5)


def recovered(rig: TofRig, forward_m: float, turn_deg: float, seed: int):
    key, new, truth, body, key_cal, attitude = step_pair(rig, 0.0, 0.0, HEADING, forward_m, turn_deg)
    guess = dead_reckoning(body, key_cal, forward_m, turn_deg, attitude, np.random.default_rng(seed))
    estimate = depth_motion(key, new, DepthOdometryParams(), guess)
    return estimate, truth, guess


def test_a_forward_step_is_recovered(rig):
    estimate, truth, guess = recovered(rig, 1.0, 0.0, seed=1)
    moved, turned = motion_error(truth, estimate.key_from_new)
    assert moved < 0.02 * np.linalg.norm(truth[:3, 3]) and turned < 0.3
    assert moved < motion_error(truth, guess)[0]
    assert estimate.overlap > 0.4 and estimate.inliers > 1000 and estimate.rms < 0.03


def test_a_step_with_a_turn_is_recovered(rig):
    estimate, truth, _ = recovered(rig, 0.5, 10.0, seed=2)
    moved, turned = motion_error(truth, estimate.key_from_new)
    assert moved < 0.02 * np.linalg.norm(truth[:3, 3]) + 0.005 and turned < 0.3


def test_standing_still_gives_identity_without_a_guess(rig):
    key, _, _ = rig.look(0.0, 0.0, HEADING)
    new, _, _ = rig.look(0.0, 0.0, HEADING)          # another frame: other noise, same place
    estimate = depth_motion(key, new, DepthOdometryParams())
    moved, turned = motion_error(np.eye(4), estimate.key_from_new)
    assert moved < 0.005 and turned < 0.1 and estimate.overlap > 0.9


def test_the_covariance_is_symmetric_positive_definite_and_near_the_error(rig):
    estimate, truth, _ = recovered(rig, 1.0, 5.0, seed=3)
    c = estimate.covariance
    assert c.shape == (6, 6) and np.allclose(c, c.T) and np.linalg.eigvalsh(c).min() > 0
    sigma = math.sqrt(np.trace(c[3:, 3:]))
    assert 0.1e-3 < sigma < 0.05                     # mm to cm, as the errors are


def test_an_empty_frame_is_no_depth(rig):
    key, _, _ = rig.look(0.0, 0.0, HEADING)
    empty = DepthFrame(np.full_like(key.points, np.nan), np.zeros_like(key.valid), key.amplitude,
                       key.fx, key.fy, key.cx, key.cy)
    with pytest.raises(OdometryFailure) as caught:
        depth_motion(key, empty, DepthOdometryParams())
    assert caught.value.reason == "no-depth" and "new frame has 0 usable points" in caught.value.sentence


def test_looking_the_other_way_is_refused(rig):
    key, key_true, _ = rig.look(0.0, 0.0, HEADING)
    new, new_true, _ = rig.look(0.0, 0.0, HEADING + math.pi)
    for guess in (None, np.linalg.inv(key_true) @ new_true):   # believing it did not turn, or knowing it did
        with pytest.raises(OdometryFailure) as caught:
            depth_motion(key, new, DepthOdometryParams(), guess)
        assert caught.value.reason in ("no-overlap", "diverged")


def test_the_picture_is_the_new_amplitude_coloured_by_the_fit(rig):
    key, new, truth, *_ = step_pair(rig, 0.0, 0.0, HEADING, 0.5, 0.0)
    plain = depth_picture(key, new, None)
    assert plain.shape == (*new.valid.shape, 3) and plain.dtype == np.uint8
    assert np.all(plain[..., 0] == plain[..., 1])                          # grey
    estimate = depth_motion(key, new, DepthOdometryParams(), truth)
    coloured = depth_picture(key, new, estimate)
    green = (coloured[..., 1] > coloured[..., 2] + 20) & new.valid
    assert green.sum() > 0.3 * new.valid.sum()


# --------------------------------------------------------------------------------------------
# The small steps
# --------------------------------------------------------------------------------------------

def bumpy_surface(n: int = 60, seed: int = 0) -> np.ndarray:
    """Ground seen from a camera 1.2 m above it (y down, z forward), gently rolling, with rocks."""
    rng = np.random.default_rng(seed)
    x, z = np.meshgrid(np.linspace(-1.5, 1.5, n), np.linspace(1.0, 4.0, n))
    y = 1.2 - 0.1 * np.sin(2 * x) * np.cos(1.5 * z)
    for cx, cz in rng.uniform((-1.5, 1.0), (1.5, 4.0), (12, 2)):
        y -= 0.15 * np.exp(-((x - cx) ** 2 + (z - cz) ** 2) / 0.02)
    return np.column_stack([x.ravel(), y.ravel(), z.ravel()])


def frame_of(points: np.ndarray, shape=(40, 90)) -> DepthFrame:
    grid = np.full((*shape, 3), np.nan, np.float32)
    grid.reshape(-1, 3)[:len(points)] = points
    return DepthFrame.from_arrays(grid, np.ones(shape, np.float32), 100.0, 100.0, shape[1] / 2, shape[0] / 2)


def test_depth_frame_marks_zero_and_low_confidence_invalid():
    points = np.ones((2, 3, 3), np.float32)
    points[0, 0] = 0.0
    confidence = np.full((2, 3), 0.9)
    confidence[1, 2] = 0.1
    frame = DepthFrame.from_arrays(points, np.ones((2, 3)), 1, 1, 1, 1, confidence, 0.5)
    assert frame.valid.sum() == 4 and not frame.valid[0, 0] and not frame.valid[1, 2]
    assert np.isnan(frame.points[0, 0]).all()
    with pytest.raises(ValueError, match="share one"):
        DepthFrame(points, np.ones((3, 3), bool), np.ones((2, 3), np.float32), 1, 1, 1, 1)


def test_params_refuse_nonsense():
    with pytest.raises(ValueError, match="max_range_m"):
        DepthOdometryParams(min_range_m=5.0, max_range_m=4.0)
    with pytest.raises(ValueError, match="voxel_m"):
        DepthOdometryParams(voxel_m=0.0)
    with pytest.raises(ValueError, match="one positive distance per scale"):
        DepthOdometryParams(scales=(4.0, 2.0, 1.0), correspondence_m=(0.1, 0.05))


def test_usable_points_drop_invalid_near_and_far():
    points = np.array([[0, 0, 0.1], [0, 0, 2.0], [0, 0, 6.0], [np.nan, 0, 1.0]])
    used = usable_points(frame_of(points, (2, 2)), 0.3, 4.5)
    np.testing.assert_allclose(used, [[0, 0, 2.0]])


def test_voxel_cloud_thins_and_turns_normals_to_the_camera():
    cloud = voxel_cloud(bumpy_surface(100), 0.1, 0.3)
    normals, points = np.asarray(cloud.normals), np.asarray(cloud.points)
    assert len(points) < 100 * 100 / 2
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-6)
    assert np.all(np.sum(normals * points, axis=1) <= 1e-9)             # facing the origin
    assert np.median(-normals[:, 1]) > 0.9                               # ground: normals point up (-y)


def test_register_recovers_a_known_motion():
    key = bumpy_surface()
    truth = exp_se3(np.r_[np.radians([0.5, 2.0, -0.5]), 0.03, -0.02, 0.08])
    new = apply(np.linalg.inv(truth), key)
    found = register(new, key, np.eye(4), DepthOdometryParams())
    moved, turned = motion_error(truth, found.key_from_new)
    assert moved < 0.005 and turned < 0.1 and found.fitness > 0.9


def test_refine_guess_finds_the_height_dead_reckoning_missed():
    key = bumpy_surface()
    truth = exp_se3(np.r_[0, 0, 0, 0.0, -0.05, 0.6])
    new = apply(np.linalg.inv(truth), key)
    guess = truth.copy()
    guess[:3, 3] += (0.0, 0.12, -0.06)                                     # 12 cm too low, 6 cm short
    refined = refine_guess(new, key, guess, DepthOdometryParams())
    assert motion_error(truth, refined)[0] < 0.03
    np.testing.assert_allclose(refined[:3, :3], guess[:3, :3])             # only the translation moves
    assert refine_guess(new, key, guess, DepthOdometryParams(seed_span_m=0.0)) is guess


def test_check_plausible_refuses_by_reason():
    key = bumpy_surface()
    found = register(key, key, np.eye(4), DepthOdometryParams())
    check_plausible(found, np.eye(4), DepthOdometryParams())             # fine
    with pytest.raises(OdometryFailure, match="diverged: the ICP result lies 1.00 m"):
        check_plausible(found, exp_se3(np.r_[0, 0, 0, 1.0, 0, 0]), DepthOdometryParams())
    with pytest.raises(OdometryFailure, match="no-overlap"):
        check_plausible(replace(found, fitness=0.1), np.eye(4), DepthOdometryParams())
    with pytest.raises(OdometryFailure, match="few-inliers"):
        check_plausible(found, np.eye(4), DepthOdometryParams(min_inliers=10 ** 6))
    # A long step leaves little in common: a small overlap passes when most of what was in view agrees.
    check_plausible(replace(found, fitness=0.2), np.eye(4), DepthOdometryParams(), seen=0.25)
    with pytest.raises(OdometryFailure, match="no-overlap: only 20% .* \\(40% of the 50% it could see\\)"):
        check_plausible(replace(found, fitness=0.2), np.eye(4), DepthOdometryParams(), seen=0.5)
    with pytest.raises(OdometryFailure, match="no-overlap"):
        check_plausible(replace(found, fitness=0.05), np.eye(4), DepthOdometryParams(), seen=0.05)


def test_seen_share_is_what_the_keyframe_camera_could_see():
    points = bumpy_surface()
    key = frame_of(points, (60, 60))
    key = replace(key, fx=15.0, fy=15.0, cx=30.0, cy=30.0)     # a pinhole that holds the surface
    params = DepthOdometryParams(max_range_m=10.0)
    assert seen_share(points, key, np.eye(4), params) > 0.95
    behind = exp_se3(np.r_[0.0, np.pi, 0.0, 0.0, 0.0, 0.0])    # turned round: nothing in front of it
    assert seen_share(points, key, behind, params) == 0.0
    ahead = exp_se3(np.r_[0.0, 0.0, 0.0, 0.0, 0.0, 2.0])       # seen from 2 m farther back: the far part
    assert 0.2 < seen_share(points, key, ahead, DepthOdometryParams(max_range_m=4.5)) < 0.7   # is out of range


def test_the_jacobian_is_the_right_perturbation_of_key_from_new():
    rng = np.random.default_rng(1)
    p, q = rng.normal(size=(5, 3)), rng.normal(size=(5, 3))
    n = rng.normal(size=(5, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    t = exp_se3(np.r_[0.3, -0.2, 0.5, 1.0, 2.0, -0.5])
    def residual(T):
        return np.sum(n * (apply(T, p) - q), axis=1)

    numeric = np.column_stack([(residual(t @ exp_se3(e)) - residual(t @ exp_se3(-e))) / 2e-6
                               for e in np.eye(6) * 1e-6])
    np.testing.assert_allclose(point_to_plane_jacobian(p, n, t), numeric, atol=1e-6)


def test_flat_ground_shows_as_large_sigmas_not_as_certainty():
    x, z = np.meshgrid(np.linspace(-1.5, 1.5, 40), np.linspace(1.0, 4.0, 40))
    flat = np.column_stack([x.ravel(), np.full(x.size, 1.2), z.ravel()])
    up = np.tile([0.0, -1.0, 0.0], (len(flat), 1))
    noisy = flat + np.outer(np.random.default_rng(2).normal(0, 0.005, len(flat)), up[0])
    covariance, information, rms = point_to_plane_covariance(noisy, flat, up, np.eye(4))
    assert information_condition(information) > 1e6
    sigma = np.sqrt(np.diag(covariance))
    assert sigma[3] > 1.0 and sigma[5] > 1.0 and sigma[1] > 1.0         # x, z and yaw slide freely
    assert sigma[4] < 0.001 and rms == pytest.approx(0.005, rel=0.2)    # height is known
    rocky = bumpy_surface()
    _, information, _ = point_to_plane_covariance(rocky, rocky, voxel_normals(rocky), np.eye(4))
    assert information_condition(information) < 1e4


def voxel_normals(points: np.ndarray) -> np.ndarray:
    """Normals of every point (no thinning), turned to the camera."""
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=0.2, max_nn=30))
    cloud.orient_normals_towards_camera_location(np.zeros(3))
    return np.asarray(cloud.normals)


def test_pinhole_depth_puts_points_where_the_pinhole_sees_them():
    frame = frame_of(np.array([[0.0, 0.0, 2.0], [0.4, -0.2, 2.0], [0.2, -0.1, 1.0]]), (40, 90))
    depth, amplitude = pinhole_depth(frame)
    assert depth[20, 45] == pytest.approx(2.0)
    assert depth[10, 65] == pytest.approx(1.0)                           # the nearer of two on one pixel
    assert np.count_nonzero(depth) == 2 and amplitude[10, 65] == 1.0


def test_register_rotation_finds_a_turn_about_the_pivot_and_keeps_its_translation():
    key, pivot = bumpy_surface(), np.array([0.1, 1.0, -0.6])    # the rover's centre: below, behind the camera
    truth = rotate_about(pivot, np.radians([0.3, 12.0, -0.2]))   # y is up-down: a turn is about y
    new = apply(np.linalg.inv(truth), key)
    guess = rotate_about(pivot, np.radians([0.0, 10.5, 0.0]))    # the wheels' turn, 1.5 deg short
    found = register_rotation(new, key, guess, pivot, DepthOdometryParams())
    moved, turned = motion_error(truth, found.key_from_new)
    assert turned < 0.05 and moved < 0.002 and found.fitness > 0.9
    np.testing.assert_allclose(apply(found.key_from_new, pivot[None])[0], pivot, atol=1e-9)   # the pivot stays


def test_a_turn_on_the_spot_is_measured_as_a_turn(rig):
    key, new, truth, body, key_cal, attitude = step_pair(rig, 0.0, 0.0, HEADING, 0.0, 12.0)
    guess = dead_reckoning(body, key_cal, 0.0, 12.0, attitude, np.random.default_rng(3), heading_error_deg=1.5)
    new_cal = rig.rover.sensor_to_world("tof", 0.0, TILT_DEG, calibrated=True)
    pivot = apply(np.linalg.inv(new_cal), rig.body()[:3, 3][None])[0]
    estimate = depth_turn(key, new, pivot, DepthOdometryParams(), guess)
    moved, turned = motion_error(truth, estimate.key_from_new)
    assert turned < 0.3 and moved < 0.02
    sigmas = np.sqrt(np.diag(estimate.covariance))
    assert np.all(np.linalg.eigvalsh(estimate.covariance) > 0)
    assert sigmas[3:].min() >= DepthOdometryParams().turn_step_sigma_m and np.degrees(sigmas[:3]).max() < 1.0
