"""Stereo: rectification from a known calibration, SGBM disparity, and 3D points for the DEM chain.

    rect = rectification(calibration)                 # cv2.stereoRectify + undistort/rectify maps
    left_r, right_r = rectify(left, right, rect)       # rows of the two images now match
    disparity = sgbm_disparity(left_r, right_r, cfg)   # OpenCV StereoSGBM + left-right check
    points, valid = disparity_to_points(disparity, rect)   # left camera frame (not the rectified one)

`stereo_points` runs the four. The points are organized on the rectified left image's pixel grid
but expressed in the ORIGINAL left camera frame, so the left camera's camera-to-world pose from
geometry.camera_to_world takes them to the world, and dem.view_points / dem_from_points make the
DEM exactly as for the TOF camera.

Calibration convention (OpenCV's): left_to_right maps left camera points to the right camera,
x_r = R x_l + T; geometry.relative_pose(left_to_world, right_to_world) gives it from two mounts.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from toolbox.camera import Intrinsics

# StereoSGBM returns disparities in fixed point, 4 fractional bits.
DISPARITY_SCALE = 16.0


@dataclass(frozen=True)
class StereoCalibration:
    left: Intrinsics
    right: Intrinsics
    left_to_right: np.ndarray   # 4x4 rigid pose


@dataclass(frozen=True)
class Rectification:
    """stereoRectify's outputs and the remap tables for both images.

    left_rotation (R1) takes points from the left camera frame to the rectified left frame;
    reprojection (Q) takes (u, v, disparity, 1) on the rectified left image to rectified 3D points."""

    size: tuple[int, int]                 # (width, height)
    left_rotation: np.ndarray
    right_rotation: np.ndarray
    left_projection: np.ndarray
    right_projection: np.ndarray
    reprojection: np.ndarray
    left_maps: tuple[np.ndarray, np.ndarray]
    right_maps: tuple[np.ndarray, np.ndarray]

    @property
    def focal_px(self) -> float:
        return float(self.left_projection[0, 0])

    @property
    def baseline(self) -> float:
        """Metres between the optical centres (P2[0, 3] = -f * baseline)."""
        return float(-self.right_projection[0, 3] / self.right_projection[0, 0])


@dataclass(frozen=True)
class SgbmConfig:
    """StereoSGBM's parameters. Defaults: 5 x 5 blocks, OpenCV's recommended smoothness penalties
    (P1 = 8 and P2 = 32 times the block area: small disparity changes cheap, jumps dear), 128
    disparities (nearest range f * B / 128: 0.8 m for the 0.25 m rig in the 'low' mode's 405 px;
    raise it for the finer modes), the 3-way
    mode (fast, full quality), OpenCV's own speckle filter for small blobs, and our explicit
    left-right check at 1 pixel."""

    min_disparity: int = 0
    num_disparities: int = 128
    block_size: int = 5
    min_texture: float = 1.5          # grey levels of spread a block needs to be matched at all
    featureless_area_px: int = 100    # featureless areas at least this large are masked (see textured) ...
    signal_grey: tuple[float, float] = (3.0, 250.0)   # ... when their mean grey level is outside this range
    uniqueness_ratio: int = 10
    speckle_window_size: int = 100
    speckle_range: int = 2
    left_right_tolerance: float = 1.0
    mode: int = cv2.StereoSGBM_MODE_SGBM_3WAY

    def matcher(self) -> cv2.StereoSGBM:
        if self.num_disparities <= 0 or self.num_disparities % 16:
            raise ValueError(f"num_disparities must be a positive multiple of 16, got {self.num_disparities}")
        if self.block_size < 1 or self.block_size % 2 == 0:
            raise ValueError(f"block_size must be odd and >= 1, got {self.block_size}")
        area = self.block_size * self.block_size
        return cv2.StereoSGBM_create(
            minDisparity=self.min_disparity, numDisparities=self.num_disparities, blockSize=self.block_size,
            P1=8 * area, P2=32 * area, disp12MaxDiff=-1, uniquenessRatio=self.uniqueness_ratio,
            speckleWindowSize=self.speckle_window_size, speckleRange=self.speckle_range, mode=self.mode)


def stereo_points(left: np.ndarray, right: np.ndarray, rect: Rectification,
                  config: SgbmConfig = SgbmConfig()) -> tuple[np.ndarray, np.ndarray]:
    """(points (H, W, 3) in the left camera frame, valid mask) from a raw stereo pair."""
    left_rect, right_rect = to_uint8(*rectify(left, right, rect))
    disparity = sgbm_disparity(left_rect, right_rect, config)
    disparity = np.where(both_images_cover(disparity, rect, config.block_size) & textured(left_rect, config),
                         disparity, np.nan)
    # A match at the end of the search range is where SGBM puts what it cannot resolve (nearer
    # than the range allows, or no texture): its depth is the range's limit, not the surface's.
    with np.errstate(invalid="ignore"):
        disparity = np.where(disparity < config.min_disparity + config.num_disparities - 2, disparity, np.nan)
    return disparity_to_points(disparity, rect)


def textured(image: np.ndarray, config: SgbmConfig) -> np.ndarray:
    """False in and within a block of large featureless areas without signal (the black beyond the
    terrain's edge, the rectification's fill, a saturated sky): no block there has anything to match,
    and a block straddling its edge matches the edge at whatever disparity a half-pixel of
    misalignment favours.

    Featureless patches smaller than config.featureless_area_px stay: they are surface detail, such as
    a rock's smooth facet, whose edges lie on the surface and look the same to both cameras, and
    SGBM's paths carry the disparity across them from those edges. Masking them too (with the margin)
    took whole rocks out of the stereo maps, and the DEM's hole filling then made them flat ground.
    So do large dark areas that still hold some signal: shadows, whose edges lie on the surface too.
    Masked, every rock's shadowed face and cast shadow left a hole that the filling made flat: a
    17 cm rock 2.8 m away read as a 6 cm step, and the rover drove over it."""
    grey = np.asarray(image, np.float32)
    window = (config.block_size, config.block_size)
    mean = cv2.boxFilter(grey, -1, window)
    spread = np.sqrt(np.maximum(cv2.boxFilter(grey * grey, -1, window) - mean * mean, 0.0))
    count, labels, stats, _ = cv2.connectedComponentsWithStats((spread < config.min_texture).astype(np.uint8),
                                                               connectivity=8)
    level = np.bincount(labels.ravel(), weights=grey.ravel(), minlength=count) / np.maximum(
        stats[:, cv2.CC_STAT_AREA], 1)
    no_signal = (level < config.signal_grey[0]) | (level > config.signal_grey[1])
    large = (stats[:, cv2.CC_STAT_AREA] >= config.featureless_area_px) & no_signal
    large[0] = False                                   # label 0: the textured rest of the image
    size = 2 * config.block_size + 1
    return ~cv2.dilate(large[labels].astype(np.uint8), np.ones((size, size), np.uint8)).astype(bool)


def image_coverage(maps: tuple[np.ndarray, np.ndarray], size: tuple[int, int], margin: int) -> np.ndarray:
    """Where a rectified image holds real pixels (not the constant border remap fills in), at
    least `margin` pixels from the fill."""
    ones = np.ones((size[1], size[0]), np.uint8)
    covered = cv2.remap(ones, *maps, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    if margin > 0:
        covered = cv2.erode(covered, np.ones((2 * margin + 1, 2 * margin + 1), np.uint8), borderValue=0)
    return covered.astype(bool)


def both_images_cover(disparity: np.ndarray, rect: Rectification, block_size: int) -> np.ndarray:
    """True where the left pixel and the right pixel it matched both lie on real image content.

    With a calibration that is slightly off (it always is), the rectified pair's black fill differs
    by a row or two at the edges; a block that straddles it in one image matches garbage, whose
    wrong disparities put far ground (the view's top rows) a few metres too close and high."""
    margin = block_size // 2 + 1
    left = image_coverage(rect.left_maps, rect.size, margin)
    right = image_coverage(rect.right_maps, rect.size, margin)
    height, width = disparity.shape
    column = np.rint(np.arange(width)[None, :] - np.nan_to_num(disparity, nan=0.0)).astype(np.int64)
    inside = (column >= 0) & (column < width)
    right_ok = right[np.arange(height)[:, None], np.clip(column, 0, width - 1)] & inside
    return left & right_ok


def rectification(calibration: StereoCalibration, alpha: float = 0.0) -> Rectification:
    """Rectify a calibrated pair (cv2.stereoRectify). alpha 0 crops to valid pixels only; 1 keeps all."""
    left, right = calibration.left, calibration.right
    if (left.width, left.height) != (right.width, right.height):
        raise ValueError("the two cameras must have the same image size")
    size = (left.width, left.height)
    rotation = np.asarray(calibration.left_to_right[:3, :3], dtype=np.float64)
    translation = np.asarray(calibration.left_to_right[:3, 3], dtype=np.float64).reshape(3, 1)
    r1, r2, p1, p2, q, _, _ = cv2.stereoRectify(left.matrix, left.distortion, right.matrix, right.distortion,
                                                size, rotation, translation, flags=cv2.CALIB_ZERO_DISPARITY,
                                                alpha=alpha)
    left_maps = cv2.initUndistortRectifyMap(left.matrix, left.distortion, r1, p1, size, cv2.CV_32FC1)
    right_maps = cv2.initUndistortRectifyMap(right.matrix, right.distortion, r2, p2, size, cv2.CV_32FC1)
    return Rectification(size, r1, r2, p1, p2, q, tuple(left_maps), tuple(right_maps))


def rectify(left: np.ndarray, right: np.ndarray, rect: Rectification) -> tuple[np.ndarray, np.ndarray]:
    """Both images resampled (bilinear) onto the rectified grids."""
    return (cv2.remap(left, *rect.left_maps, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT),
            cv2.remap(right, *rect.right_maps, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT))


def to_uint8(left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A float pair as 8-bit for SGBM, both with the same scale (their joint 99.9th percentile to
    255), so brightness differences between the two stay as they were."""
    if left.dtype == np.uint8 and right.dtype == np.uint8:
        return left, right
    both = np.concatenate([np.ravel(left), np.ravel(right)]).astype(np.float64)
    top = np.nanpercentile(both, 99.9) or 1.0
    def scale(image: np.ndarray) -> np.ndarray:
        return np.clip(np.nan_to_num(np.asarray(image, np.float64) * (255.0 / top)), 0, 255).astype(np.uint8)
    return scale(left), scale(right)


def sgbm_disparity(left_rect: np.ndarray, right_rect: np.ndarray, config: SgbmConfig = SgbmConfig()) -> np.ndarray:
    """Disparity of the rectified left image in pixels (float32, NaN where invalid or inconsistent).

    The right image's own disparity comes from the same matcher on the mirrored pair (mirroring
    swaps the roles of the cameras and keeps disparities positive); a left pixel survives only if
    the right pixel it points at points back within left_right_tolerance (occlusions and
    mismatches fail)."""
    left_rect, right_rect = to_uint8(left_rect, right_rect)
    matcher = config.matcher()
    left_disparity = _match(matcher, left_rect, right_rect, config)
    right_mirrored, left_mirrored = (np.ascontiguousarray(image[:, ::-1]) for image in (right_rect, left_rect))
    right_disparity = _match(matcher, right_mirrored, left_mirrored, config)[:, ::-1]
    consistent = left_right_consistent(left_disparity, right_disparity, config.left_right_tolerance)
    return np.where(consistent, left_disparity, np.nan).astype(np.float32)


def left_right_consistent(left_disparity: np.ndarray, right_disparity: np.ndarray, tolerance: float) -> np.ndarray:
    """True where the left disparity d at (u, v) and the right disparity at (u - d, v) agree."""
    height, width = left_disparity.shape
    u = np.arange(width)[None, :] - np.nan_to_num(left_disparity, nan=np.inf)
    column = np.rint(np.where(np.isfinite(u), u, -1)).astype(np.int64)
    inside = (column >= 0) & (column < width)
    back = right_disparity[np.arange(height)[:, None], np.clip(column, 0, width - 1)]
    with np.errstate(invalid="ignore"):
        return inside & (np.abs(back - left_disparity) <= tolerance)


def disparity_to_points(disparity: np.ndarray, rect: Rectification) -> tuple[np.ndarray, np.ndarray]:
    """3D points (H, W, 3) in the original left camera frame and their validity (finite, positive
    disparity, in front of the camera); invalid points are NaN."""
    disparity = np.asarray(disparity, dtype=np.float32)
    valid = np.isfinite(disparity) & (disparity > 0)
    rectified = cv2.reprojectImageTo3D(np.where(valid, disparity, 0.0).astype(np.float32), rect.reprojection)
    valid &= np.isfinite(rectified).all(axis=-1) & (rectified[..., 2] > 0)
    rectified[~valid] = np.nan
    # Undo the rectifying rotation: p_left = R1^T p_rectified (row vectors: p @ R1).
    points = rectified.astype(np.float64) @ rect.left_rotation
    return points, valid


def _match(matcher: cv2.StereoSGBM, left: np.ndarray, right: np.ndarray, config: SgbmConfig) -> np.ndarray:
    """One SGBM pass (float disparities of `left`, NaN: none). SGBM leaves blank the first
    min_disparity + num_disparities columns, where the whole search range does not fit; both
    images are padded on that side so the blank band falls in the padding, and pixels whose match
    really lies outside the other image are left to the left-right check."""
    pad = max(0, config.min_disparity + config.num_disparities)
    raw = matcher.compute(*(cv2.copyMakeBorder(image, 0, 0, pad, 0, cv2.BORDER_CONSTANT, value=0)
                            for image in (left, right)))
    return _from_fixed_point(raw[:, pad:], config.min_disparity)


def _from_fixed_point(raw: np.ndarray, min_disparity: int) -> np.ndarray:
    """SGBM's int16 output as float pixels; its 'no match' value (below min_disparity) as NaN."""
    disparity = raw.astype(np.float32) / DISPARITY_SCALE
    disparity[raw < min_disparity * DISPARITY_SCALE] = np.nan
    return disparity
