"""toolbox.stereo: rectification, SGBM with the left-right check, 3D points, and a simulated stereo DEM."""
from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from drivers.sim.config import WorldConfig
from drivers.sim.render import render
from drivers.sim.rover import Rover
from drivers.sim.world import World
from toolbox import geometry as g
from toolbox.camera import Intrinsics, project
from toolbox.grid import GridSpec
from toolbox.mapping import dem as D
from toolbox.mapping import stereo as S

WIDTH, HEIGHT = 320, 240
IDEAL = Intrinsics.from_fov(WIDTH, HEIGHT, math.radians(60))


def ideal_rig(baseline: float = 0.25) -> S.StereoCalibration:
    """Identical cameras, the right one `baseline` to the right (its centre at +x in the left frame)."""
    return S.StereoCalibration(IDEAL, IDEAL, g.rigid(None, (-baseline, 0.0, 0.0)))


def texture(rng, shape) -> np.ndarray:
    """Random texture with structure at a few pixels, as SGBM likes it."""
    noise = rng.random(shape).astype(np.float32)
    return cv2.GaussianBlur(noise, (0, 0), 1.2) * 255


def shifted(image: np.ndarray, disparity: np.ndarray) -> np.ndarray:
    """The right image of a scene whose left image is `image` and whose disparity is constant along
    each row: right(u) = left(u + d)."""
    rows, cols = np.mgrid[0:image.shape[0], 0:image.shape[1]].astype(np.float32)
    return cv2.remap(image, cols + disparity[:, None].astype(np.float32), rows, cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REFLECT)


def test_rectification_makes_rows_match():
    left = Intrinsics(WIDTH, HEIGHT, 300.0, 302.0, 161.0, 118.0, k1=-0.12, k2=0.03)
    right = Intrinsics(WIDTH, HEIGHT, 298.0, 299.0, 158.0, 121.0, k1=-0.10, k2=0.02)
    left_to_right = g.rigid(g.rotation_rpy(0.01, -0.02, 0.015), (-0.25, 0.004, -0.003))
    rect = S.rectification(S.StereoCalibration(left, right, left_to_right))
    assert rect.baseline == pytest.approx(0.25, rel=1e-3)
    rng = np.random.default_rng(0)
    points = np.c_[rng.uniform(-1, 1, (200, 2)), rng.uniform(2, 8, 200)]            # left camera frame
    in_left = project(points, left)
    in_right = project(g.apply(left_to_right, points), right)
    rect_left = cv2.undistortPoints(in_left[:, None], left.matrix, left.distortion, R=rect.left_rotation,
                                    P=rect.left_projection)[:, 0]
    rect_right = cv2.undistortPoints(in_right[:, None], right.matrix, right.distortion, R=rect.right_rotation,
                                     P=rect.right_projection)[:, 0]
    assert np.abs(rect_left[:, 1] - rect_right[:, 1]).max() < 1e-3
    # The disparity of each point gives it back, in the left camera frame.
    disparity = rect_left[:, 0] - rect_right[:, 0]
    homogeneous = np.c_[rect_left, disparity, np.ones(len(points))] @ rect.reprojection.T
    rectified = homogeneous[:, :3] / homogeneous[:, 3:]
    assert np.allclose(rectified @ rect.left_rotation, points, atol=1e-3)


def test_sgbm_finds_a_known_disparity():
    rng = np.random.default_rng(1)
    left = texture(rng, (HEIGHT, WIDTH))
    truth = np.where(np.arange(HEIGHT) < HEIGHT // 2, 17.25, 30.5)        # two planes, fractional
    right = shifted(left, truth)
    disparity = S.sgbm_disparity(left, right, S.SgbmConfig(num_disparities=64))
    body = np.s_[8:-8, 40:-8]                 # the first 31 columns have no match in the right image
    valid = np.isfinite(disparity[body])
    assert valid.mean() > 0.95
    error = (disparity - truth[:, None])[body][valid]
    assert np.median(np.abs(error)) < 0.2          # SGBM's sub-pixel fit pulls 0.25 toward 0 by 0.19
    assert np.mean(np.abs(error) < 1.0) > 0.98


def test_left_right_check_drops_the_occluded_strip():
    rng = np.random.default_rng(2)
    left = texture(rng, (HEIGHT, WIDTH))
    background, foreground = 12.0, 36.0
    right = shifted(left, np.full(HEIGHT, background))
    # A textured square in front: in the right image it sits 36 px left of where the left image has
    # it, covering background that the left image shows just left of the square (the occluded strip).
    square = texture(rng, (80, 80))
    left[80:160, 180:260] = square
    right[80:160, 180 - 36:260 - 36] = square
    disparity = S.sgbm_disparity(left, right, S.SgbmConfig(num_disparities=64))
    on_square = disparity[90:150, 190:250]
    assert np.nanmedian(on_square) == pytest.approx(foreground, abs=0.3)
    occluded = disparity[90:150, 180 - (36 - 12) + 3:180 - 3]           # background hidden in the right image
    assert np.isfinite(occluded).mean() < 0.2
    plain = S.left_right_consistent(disparity, np.full_like(disparity, np.nan), 1.0)
    assert not plain.any()                                             # nothing to agree with: nothing valid


def test_small_featureless_patches_are_matched_and_large_areas_masked():
    """A smooth facet on a surface (a flat patch moving with it) is matched across from its edges; a
    large featureless area (sky) and a block-wide margin round it are not matched at all."""
    rng = np.random.default_rng(4)
    left = texture(rng, (HEIGHT, WIDTH))
    left[:60] = 0.0                                                   # sky: 60 x 320 px of nothing
    left[120:132, 150:162] = left[120:132, 150:162].mean()            # a smooth facet, 12 x 12 px
    right = shifted(left, np.full(HEIGHT, 20.0))
    config = S.SgbmConfig(num_disparities=64)
    usable = S.textured(left.astype(np.uint8), config)
    assert usable[120:132, 150:162].all()
    assert not usable[:60 + config.block_size // 2].any()            # every block holding some sky
    assert usable[60 + config.block_size:].all()
    disparity = np.where(usable, S.sgbm_disparity(left, right, config), np.nan)
    facet = disparity[120:132, 150:162]
    assert np.isfinite(facet).mean() > 0.9
    assert np.nanmax(np.abs(facet - 20.0)) < 0.5
    # A black facet is masked, however small the least masked area: it holds no signal at all.
    black = left.copy()
    black[120:132, 150:162] = 0.0
    assert not S.textured(black.astype(np.uint8), S.SgbmConfig(featureless_area_px=1))[120:132, 150:162].any()


def test_a_large_shadow_is_matched_across_from_its_edges():
    """A shadow is featureless but holds signal, and its edges lie on the surface: masked, every rock's
    shadow became a hole the DEM's filling made flat, and the rock with it."""
    rng = np.random.default_rng(5)
    left = texture(rng, (HEIGHT, WIDTH))
    left[100:160, 120:200] = 10.0 + rng.normal(0.0, 0.3, (60, 80))   # 4800 px at grey 10, no texture
    right = shifted(left, np.full(HEIGHT, 20.0))
    config = S.SgbmConfig(num_disparities=64)
    usable = S.textured(left.astype(np.uint8), config)
    assert usable[100:160, 120:200].all()
    disparity = np.where(usable, S.sgbm_disparity(left.astype(np.uint8), right.astype(np.uint8), config), np.nan)
    shadow = disparity[100:160, 120:200]
    assert np.isfinite(shadow).mean() > 0.8
    assert np.nanpercentile(np.abs(shadow - 20.0), 95) < 0.5


def test_disparity_to_points_on_an_ideal_rig():
    rect = S.rectification(ideal_rig())
    disparity = np.full((HEIGHT, WIDTH), 20.0, np.float32)
    disparity[:, :10] = np.nan
    disparity[:, 10:20] = 0.0                                         # infinitely far: not a point
    points, valid = S.disparity_to_points(disparity, rect)
    assert not valid[:, :20].any() and valid[:, 20:].all()
    depth = rect.focal_px * 0.25 / 20.0
    assert np.allclose(points[valid][:, 2], depth)
    v, u = np.mgrid[0:HEIGHT, 0:WIDTH]
    cx, cy = rect.left_projection[0, 2], rect.left_projection[1, 2]
    assert np.allclose(points[..., 0][valid], ((u - cx) * depth / rect.focal_px)[valid])
    assert np.allclose(points[..., 1][valid], ((v - cy) * depth / rect.focal_px)[valid])
    assert np.isnan(points[~valid]).all()


def test_simulated_stereo_dem():
    """Render the rover's stereo pair (true mounts), rectify with the calibrated ones, and take the
    points through the same DEM chain as the TOF's: the DEM agrees with the truth to stereo accuracy
    (a quarter pixel of disparity is 2 cm of range at 3 m for this 0.25 m rig)."""
    world = World.build(WorldConfig(seed=3, size_m=(8.0, 8.0), craters={"count": 0}))
    rover = Rover(world, heading=0.3)
    camera = intrinsics = Intrinsics.from_fov(480, 360, math.radians(60.0))
    views = [render(world, rover.sensor_to_world(side, 0.0, -35.0), camera) for side in ("left", "right")]
    images = [view.intensity for view in views]
    left_pose, right_pose = (rover.sensor_to_world(side, 0.0, -35.0, calibrated=True) for side in ("left", "right"))
    rect = S.rectification(S.StereoCalibration(intrinsics, intrinsics, g.relative_pose(left_pose, right_pose)))
    points, valid = S.stereo_points(*images, rect)
    # The top of the view looks past the 8 m world's edge into black, and this noise-free render
    # leaves shadows a flat grey: neither has anything to match.
    assert valid.mean() > 0.75 * views[0].hit.mean()
    dem = D.dem_from_points(D.view_points(points, valid, left_pose), GridSpec.covering((-4, 4), (-4, 4), 0.03))
    truth = world.height_map(0.03, dem.spec.x_range, dem.spec.y_range)
    xs, ys = dem.spec.centres()
    near = np.hypot(xs[None, :] - left_pose[0, 3], ys[:, None] - left_pose[1, 3]) < 3.0
    measured = dem.counts > 0
    error = (dem.heights - truth)[measured & near]
    assert error.size > 3000
    assert np.sqrt(np.mean(error ** 2)) < 0.025      # farther out the error grows with range squared
    assert abs(np.median(error)) < 0.01
