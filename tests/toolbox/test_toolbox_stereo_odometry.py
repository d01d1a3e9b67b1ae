"""toolbox.odometry.stereo and .features: each step on synthetic data, then the pipeline on emulated
stereo pairs of one small simulated world (forward step, turn, standing still, blank image, no overlap)."""
from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from drivers.avt import CameraSettings
from drivers.avt_emulator import emulated_stereo_pair
from drivers.sim.clock import SimClock
from drivers.sim.config import WorldConfig
from drivers.sim.rover import Rover
from drivers.sim.world import World
from toolbox import geometry as g
from toolbox.camera import Intrinsics, project
from toolbox.odometry import features as F
from toolbox.odometry import stereo as S
from toolbox.odometry.estimate import OdometryFailure, exp_se3

CAMERA = Intrinsics(640, 480, 500.0, 500.0, 319.5, 239.5, k1=-0.05, k2=0.01)
PARAMS = S.StereoOdometryParams()


def texture(seed: int = 0, shape=(480, 640)) -> np.ndarray:
    """Blurred noise: corners everywhere, as the ground's texture has them."""
    noise = np.random.default_rng(seed).uniform(0, 255, shape).astype(np.float32)
    return cv2.normalize(cv2.GaussianBlur(noise, (0, 0), 2.0), None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)


def shifted(image: np.ndarray, du: float, dv: float = 0.0) -> np.ndarray:
    """The image moved by (du, dv) pixels (content at u appears at u + du)."""
    return cv2.warpAffine(image, np.float32([[1, 0, du], [0, 1, dv]]), image.shape[::-1], flags=cv2.INTER_CUBIC,
                          borderMode=cv2.BORDER_REFLECT)


def scene_points(rng, n: int) -> np.ndarray:
    """Points 2-12 m ahead spread over the view."""
    z = rng.uniform(2.0, 12.0, n)
    return np.stack([rng.uniform(-0.5, 0.5, n) * z, rng.uniform(-0.35, 0.35, n) * z, z], axis=1)


# ---------------------------------------------------------------------------------- features
def test_strongest_per_cell_keeps_the_best_of_each_cell():
    keypoints = [cv2.KeyPoint(10.0, 10.0, 31, response=r) for r in (1.0, 5.0, 3.0)]
    keypoints += [cv2.KeyPoint(90.0, 90.0, 31, response=2.0)]
    kept = F.strongest_per_cell(keypoints, (100, 100), wanted=8, grid=(2, 2))   # 2 per cell
    assert sorted(k.response for k in kept) == [2.0, 3.0, 5.0]


def test_bucketed_features_spread_over_the_image():
    points, descriptors = F.bucketed_features(texture(), 400, (4, 4))
    assert 200 <= len(points) <= 400 and descriptors.shape == (len(points), 32)
    cells = np.unique((points[:, 0] * 4 // 640) * 4 + points[:, 1] * 4 // 480)
    assert len(cells) == 16


def test_bucketed_features_none_on_a_blank_image():
    points, descriptors = F.bucketed_features(np.full((480, 640), 128, np.uint8), 400, (4, 4))
    assert len(points) == 0 and descriptors.shape == (0, 32)


def test_match_descriptors_ratio_mutual_and_mask():
    rng = np.random.default_rng(1)
    a = rng.integers(0, 256, (50, 32), dtype=np.uint8)
    order = rng.permutation(50)
    pairs = F.match_descriptors(a, a[order])
    assert len(pairs) == 50 and (order[pairs[:, 1]] == pairs[:, 0]).all()
    # A twin in b makes the match ambiguous: the ratio test drops it.
    pairs = F.match_descriptors(a[:1], np.concatenate([a[:1], a[:1]]))
    assert len(pairs) == 0
    # A mask that forbids the true partner leaves only far (rejected) candidates.
    assert len(F.match_descriptors(a, a, allowed=~np.eye(50, dtype=bool))) == 0


def test_refine_positions_finds_a_subpixel_shift():
    image = texture(2)
    moved = shifted(image, 3.3, -1.6)
    points = np.array([[100.0, 100.0], [300.0, 200.0], [500.0, 400.0]], np.float32)
    refined, ok = F.refine_positions(image, points, moved, points + np.float32([3.0, -2.0]))
    assert ok.all()
    np.testing.assert_allclose(refined - points, [[3.3, -1.6]] * 3, atol=0.08)


# ---------------------------------------------------------------------------------- stereo depth
def ideal_rig(baseline: float = 0.25) -> S.StereoRig:
    camera = Intrinsics(640, 480, 500.0, 500.0, 319.5, 239.5)
    return S.StereoRig(camera, camera, g.rigid(None, (-baseline, 0.0, 0.0)))


def test_triangulate_rectified_inverts_projection():
    projection = np.array([[500.0, 0, 320, 0], [0, 500.0, 240, 0], [0, 0, 1, 0]])
    points = S.triangulate_rectified(np.array([[420.0, 140.0]]), np.array([25.0]), projection, 0.25)
    np.testing.assert_allclose(points, [[1.0, -1.0, 5.0]])


def test_stereo_points_of_a_plane_at_known_depth():
    rig, image = ideal_rig(), texture(3)
    disparity = 25.0                                           # 500 px * 0.25 m / 5 m
    pixels, _ = F.bucketed_features(image, 300, (4, 4))
    points = S.stereo_points(pixels, image, shifted(image, -disparity), rig, PARAMS)
    found = np.isfinite(points).all(axis=1)
    assert found.mean() > 0.7
    np.testing.assert_allclose(points[found, 2], 5.0, rtol=0.01)
    np.testing.assert_allclose(project(points[found], rig.left), pixels[found], atol=0.05)


def test_a_depth_prior_narrows_the_row_search_to_its_window():
    """Near the prior the same depths are found; a prior twice as far searches where the match is not."""
    rig, image = ideal_rig(), texture(3)
    pixels, _ = F.bucketed_features(image, 300, (4, 4))
    right = shifted(image, -25.0)                               # 5 m
    unguided = S.stereo_points(pixels, image, right, rig, PARAMS)
    near = np.where(np.isfinite(unguided), unguided * 1.1, np.nan)
    guided = S.stereo_points(pixels, image, right, rig, PARAMS, expected=near)
    both = np.isfinite(unguided).all(axis=1) & np.isfinite(guided).all(axis=1)
    assert both.sum() >= 0.95 * np.isfinite(unguided).all(axis=1).sum()
    np.testing.assert_allclose(guided[both], unguided[both], atol=1e-9)
    far = S.stereo_points(pixels, image, right, rig, PARAMS, expected=unguided * 2.0)
    assert not np.isfinite(far).any()


def test_row_search_refuses_a_textureless_right_image():
    rig, image = ideal_rig(), texture(4)
    pixels, _ = F.bucketed_features(image, 200, (4, 4))
    points = S.stereo_points(pixels, image, np.full_like(image, 128), rig, PARAMS)
    assert not np.isfinite(points).any()


def test_offset_points_slide_along_the_ray():
    rect = S.rectifying(ideal_rig())
    points = np.array([[1.0, -1.0, 5.0]])
    np.testing.assert_array_equal(S.offset_points(points, 0.0, rect), points)
    moved = S.offset_points(points, 5.0, rect)               # 25 px disparity + 5: Z = 125 / 30
    np.testing.assert_allclose(moved, points * (125 / 30) / 5.0)


# ---------------------------------------------------------------------------------- pose
def synthetic_motion(seed: int = 5, n: int = 200):
    rng = np.random.default_rng(seed)
    key_from_new = g.rigid(g.rotation_y(math.radians(3)) @ g.rotation_x(math.radians(1)), (0.1, 0.02, 0.8))
    points_key = scene_points(rng, n)
    pixels_new = project(S.apply_inverse(key_from_new, points_key), CAMERA)
    return key_from_new, points_key, pixels_new, rng


def test_predicted_pixels_of_the_identity_are_the_projections():
    points = scene_points(np.random.default_rng(6), 20)
    key = S.StereoKeyframe(project(points, CAMERA).astype(np.float32), np.zeros((20, 32), np.uint8), points,
                           CAMERA, np.zeros((480, 640), np.uint8))
    np.testing.assert_allclose(S.predicted_pixels(key, np.eye(4)), key.pixels, atol=1e-3)
    window = S.predicted_window(key, key.pixels, np.eye(4), 1.0)
    assert (window == np.eye(20, dtype=bool)).all() and S.predicted_window(key, key.pixels, None, 1.0) is None


def test_guided_tracks_follow_the_predicted_motion():
    camera = ideal_rig().left
    image = texture(7)
    pixels, descriptors = F.bucketed_features(image, 300, (4, 4))
    rays = np.column_stack([(pixels[:, 0] - camera.cx) / camera.fx, (pixels[:, 1] - camera.cy) / camera.fy,
                            np.ones(len(pixels))])
    key = S.StereoKeyframe(pixels, descriptors, 5.0 * rays, camera, image)   # a wall 5 m ahead
    # The camera 0.04 m to the right: the wall moves 500 * 0.04 / 5 = 4 px to the left; the
    # prediction is started 2 px off (a coarse motion) and the patch fit finds the rest.
    index, tracked = S.guided_tracks(key, shifted(image, -4.0), g.rigid(None, (0.04 - 0.02, 0, 0)), PARAMS)
    assert len(index) > 0.8 * len(pixels)
    np.testing.assert_allclose(tracked - pixels[index], [[-4.0, 0.0]] * len(index), atol=0.1)


def test_a_warped_view_is_seen_by_the_keyframe_camera():
    """The type checker found the warped view's keyframe made with no camera (None where Intrinsics
    belongs), so anything that asked it for its camera or its image size would have failed."""
    camera = ideal_rig().left
    view = S.warped_view(texture(7), np.eye(3), PARAMS, camera)
    assert view.camera == camera and view.image_size == (640, 480) and len(view.pixels) > 0


def test_guided_tracks_through_a_homography_need_the_warped_image():
    """A homography without the warped image it made is a caller's mistake, said as such (it reached
    OpenCV as None before)."""
    camera = ideal_rig().left
    image = texture(7)
    pixels, descriptors = F.bucketed_features(image, 300, (4, 4))
    rays = np.column_stack([(pixels[:, 0] - camera.cx) / camera.fx, (pixels[:, 1] - camera.cy) / camera.fy,
                            np.ones(len(pixels))])
    key = S.StereoKeyframe(pixels, descriptors, 5.0 * rays, camera, image)
    with pytest.raises(ValueError, match="warped image"):
        S.guided_tracks(key, image, np.eye(4), PARAMS, homography=np.eye(3))


def test_pnp_ransac_recovers_the_motion_despite_outliers():
    truth, points_key, pixels_new, rng = synthetic_motion()
    pixels_new = pixels_new + rng.normal(0, 0.2, pixels_new.shape)
    pixels_new[:40] += rng.uniform(20, 80, (40, 2))           # a fifth are wrong matches
    estimate, inliers = S.pnp_ransac(points_key, pixels_new, CAMERA, PARAMS, 2.0)
    assert not inliers[:40].any() and inliers[40:].mean() > 0.95
    np.testing.assert_allclose(estimate[:3, 3], truth[:3, 3], atol=0.01)


def test_reprojection_residuals_vanish_at_the_truth():
    truth, points_key, pixels_new, _ = synthetic_motion()
    points_new = S.apply_inverse(truth, points_key)
    r = S.reprojection_residuals(truth, points_key, pixels_new, points_new, project(points_key, CAMERA), CAMERA)
    assert np.abs(r).max() < 1e-9


def test_gauss_newton_converges_from_a_perturbed_start():
    truth, points_key, pixels_new, _ = synthetic_motion()
    start = truth @ exp_se3([0.01, -0.01, 0.005, 0.03, -0.02, 0.05])
    pose, extra, jacobian = S.gauss_newton(start, lambda p, x: S.reprojection_residuals(
        p, points_key, pixels_new, np.empty((0, 3)), np.empty((0, 2)), CAMERA))
    np.testing.assert_allclose(pose, truth, atol=1e-7)
    assert jacobian.shape == (2 * len(points_key), 6) and extra.shape == (0,)


def test_refine_motion_covariance_matches_the_scatter():
    truth, points_key, pixels_new, rng = synthetic_motion(n=300)
    rig = S.StereoRig(CAMERA, CAMERA, g.rigid(None, (-0.25, 0, 0)))
    params = S.StereoOdometryParams(both_ways=False, disparity_offset=False)
    deltas, covariances = [], []
    for _ in range(30):
        noisy = pixels_new + rng.normal(0, 0.3, pixels_new.shape)
        pose, covariance, kept, rms = S.refine_motion(truth, points_key, noisy, np.full_like(points_key, np.nan),
                                                      project(points_key, CAMERA), rig, params)
        deltas.append(np.concatenate([cv2.Rodrigues(truth[:3, :3].T @ pose[:3, :3])[0].ravel(),
                                      truth[:3, :3].T @ (pose[:3, 3] - truth[:3, 3])]))
        covariances.append(covariance)
        assert kept.mean() > 0.98 and 0.3 < rms < 0.55       # per point: sqrt(2) * 0.3 px
    scatter, predicted = np.var(deltas, axis=0), np.diag(np.mean(covariances, axis=0))
    assert ((scatter / predicted > 0.4) & (scatter / predicted < 2.5)).all()


# ---------------------------------------------------------------------------------- the pipeline
class Look:
    """One small world, a rover on it and its emulated stereo pair, grabbed where the rover is put."""

    TILT = -25.0

    def __init__(self):
        self.world = World.build(WorldConfig(seed=3, size_m=(12.0, 12.0)))
        self.rover = Rover(self.world, x=-1.5, y=0.0, heading=0.0)
        self.poses = {}
        self.pair = emulated_stereo_pair(self.world, lambda t: self.poses["left"], lambda t: self.poses["right"],
                                         clock=SimClock(1.0), seed=3,
                                         default_settings=CameraSettings(resolution="medium"))
        self.pair.open()
        k = self.pair.camera("left").intrinsics("medium")
        camera = Intrinsics(k.width, k.height, k.fx, k.fy, k.cx, k.cy, k.k1, k.k2)
        calibrated = [self.rover.sensor_to_world(s, 0, self.TILT, calibrated=True) for s in ("left", "right")]
        self.rig = S.StereoRig(camera, camera, g.relative_pose(*calibrated))

    def grab(self, x: float, y: float, heading_deg: float):
        self.rover.place(x, y, math.radians(heading_deg))
        self.poses = {s: self.rover.sensor_to_world(s, 0, self.TILT) for s in ("left", "right")}
        frames = self.pair.grab(timeout_s=60)
        return frames["left"].image, frames["right"].image, self.poses["left"]


@pytest.fixture(scope="module")
def look():
    look = Look()
    left, right, pose = look.grab(-1.5, 0.0, 0.0)
    look.key = S.stereo_keyframe(left, right, look.rig)
    look.key_pose = pose
    yield look
    look.pair.close()


def motion_error(estimate, truth) -> tuple[float, float]:
    rotation = estimate.key_from_new[:3, :3].T @ truth[:3, :3]
    angle = math.degrees(math.acos(np.clip((np.trace(rotation) - 1) / 2, -1, 1)))
    return float(np.linalg.norm(estimate.key_from_new[:3, 3] - truth[:3, 3])), angle


def test_keyframe_has_depth_for_most_features(look):
    assert len(look.key.pixels) > 500 and look.key.with_depth.mean() > 0.5
    depth = look.key.points[look.key.with_depth, 2]
    assert depth.min() > 1.0 and np.median(depth) < 8.0


def test_a_forward_step_is_recovered(look):
    left, right, pose = look.grab(-0.8, 0.0, 0.0)
    truth = g.relative_pose(pose, look.key_pose)
    estimate, new = S.stereo_motion(look.key, left, right, look.rig)
    dt, dr = motion_error(estimate, truth)
    assert dt < 0.02 * 0.7 and dr < 0.15
    assert estimate.inliers >= PARAMS.min_inliers and 0 < estimate.overlap <= 1 and estimate.rms < 1.0
    assert isinstance(new, S.StereoKeyframe) and new.with_depth.sum() > 100
    # Symmetric positive definite covariance, and it grows with fewer features.
    cov = estimate.covariance
    assert np.allclose(cov, cov.T) and np.linalg.eigvalsh(cov).min() > 0
    few = S.StereoOdometryParams(features=500)
    sparse, _ = S.stereo_motion(S.stereo_keyframe(*look.grab(-1.5, 0.0, 0.0)[:2], look.rig, few),
                                left, right, look.rig, few, guess=estimate.key_from_new)
    assert np.trace(sparse.covariance[3:, 3:]) > 1.5 * np.trace(cov[3:, 3:])
    # The picture of the tracks, green where the estimate explains them.
    picture = S.match_picture(look.key, left, estimate)
    assert picture.shape == left.shape + (3,) and picture.dtype == np.uint8
    green = picture[..., 1].astype(int) - picture[..., 2] > 100
    assert green.sum() > 2 * estimate.inliers


def test_a_turn_is_recovered(look):
    left, right, pose = look.grab(-1.1, 0.03, 8.0)
    truth = g.relative_pose(pose, look.key_pose)
    estimate, _ = S.stereo_motion(look.key, left, right, look.rig, guess=None)
    dt, dr = motion_error(estimate, truth)
    assert dt < 0.01 and dr < 0.2      # the calibrated rig's own error: about 0.1 deg per metre


def test_standing_still_gives_no_motion(look):
    left, right, _ = look.grab(-1.5, 0.0, 0.0)
    estimate, _ = S.stereo_motion(look.key, left, right, look.rig, guess=np.eye(4))
    dt, dr = motion_error(estimate, np.eye(4))
    assert dt < 0.001 and dr < 0.01 and estimate.overlap > 0.8


def test_a_blank_image_has_few_features(look):
    blank = np.full((look.rig.left.height, look.rig.left.width), 128, np.uint8)
    with pytest.raises(OdometryFailure) as failure:
        S.stereo_keyframe(blank, blank, look.rig)
    assert failure.value.reason == "few-features" and "0 features" in failure.value.sentence


def test_an_image_of_another_size_is_refused(look):
    small = np.zeros((look.rig.left.height // 2, look.rig.left.width // 2), np.uint8)
    with pytest.raises(ValueError, match="another resolution mode"):
        S.stereo_keyframe(small, small, look.rig)


def test_looking_the_other_way_does_not_overlap(look):
    left, right, _ = look.grab(-1.5, 0.0, 180.0)
    with pytest.raises(OdometryFailure) as failure:
        S.stereo_motion(look.key, left, right, look.rig)
    assert failure.value.reason in ("no-overlap", "few-inliers")
