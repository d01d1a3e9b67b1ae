"""Stereo visual odometry: interest points of the keyframe, found again in a new stereo pair, give
the left camera's motion since the keyframe (the thesis' localisation update from two consecutive
overlapping images).

    key = stereo_keyframe(left, right, rig, params)            # features, their 3D from the right image
    estimate, new_key = stereo_motion(key, left2, right2, rig, params, guess)

stereo_motion's steps, each a small function below:
  1. the new pair as a keyframe: ORB features bucketed over the left image, their depth by a
     correlation search along the rectified row of the right image, refined by Lucas-Kanade
  2. a coarse motion: keyframe descriptors matched to the new ones (ratio, mutual; in a window
     around the guess's predictions if there is a guess), PnP in RANSAC
  3. every keyframe point the coarse motion puts in view tracked into the new left image from its
     prediction (Lucas-Kanade, forward-backward checked), PnP in RANSAC on these tracks
  4. Gauss-Newton on the inliers' reprojection errors both ways (keyframe points in the new
     image, the new pair's points of the same tracks in the keyframe image), with the rig's
     disparity offset, and the covariance from the Jacobian
With `warp` (a look after a manoeuvre: the head turned back to ground it saw from elsewhere), steps
2 and 3 match in the new left image warped into the keyframe's view by the ground plane's homography
under the guess (the plane fitted to the keyframe's points): seen from 1.5 m away and 45 degrees
round, the grazing ground's patches shear and turn past what descriptors and patch fits follow, and
the warp undoes most of it (rocks stand out of the plane, by a few pixels the patch fit takes up).
Matches found there are carried back to the new image's own pixels through the same homography.
Frames and covariance follow toolbox.odometry.estimate (key_from_new, right perturbation). Pixels
are raw (distorted) image pixels; toolbox.camera.project and cv2's distortion vector handle k1, k2.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from toolbox.camera import Intrinsics, project
from toolbox.geometry import invert
from toolbox.odometry.estimate import MotionEstimate, OdometryFailure, exp_se3
from toolbox.odometry.features import bucketed_features, match_descriptors, refine_positions

__all__ = ["StereoRig", "StereoOdometryParams", "StereoKeyframe", "stereo_keyframe", "stereo_motion",
           "match_picture"]


@dataclass(frozen=True, eq=False)
class StereoRig:
    """The calibrated pair: p_right = right_from_left @ p_left (4 x 4, metres). Compared by identity:
    keep one per calibration, and its rectification is computed once (see rectifying)."""

    left: Intrinsics
    right: Intrinsics
    right_from_left: np.ndarray


class StereoOdometryParams(BaseModel):
    """How stereo odometry finds, matches and trusts its features."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    features: int = Field(1500, gt=0, description="features wanted in each left image")
    grid: tuple[int, int] = Field((12, 8),
                                  description="detection buckets (columns, rows): features spread over the view")
    fast_threshold: int = Field(7, ge=1,
                                description="FAST corner threshold (grey levels); low, the grid keeps the best")
    ratio: float = Field(0.9, gt=0, le=1,
                         description="Lowe's ratio: best match distance below this share of the second")
    max_hamming: int = Field(64, gt=0, description="largest descriptor distance (of 256 bits) accepted as a match")
    stereo_row_px: float = Field(1.5, gt=0, description="rectified row difference allowed between left and right")
    max_depth_m: float = Field(25.0, gt=0, description="farther points carry too little depth to place the camera")
    min_depth_m: float = Field(0.5, gt=0, description="nearer points are closer than the ground can be")
    search_radius_px: float = Field(40.0, gt=0, description="window around the guess's prediction of each feature")
    coarse_threshold_px: float = Field(4.0, gt=0, description="RANSAC's threshold on descriptor matches (to a "
                                       "pyramid level's pixel, and the depth not yet refined)")
    coarse_min_inliers: int = Field(12, gt=5, description="fewest descriptor-match inliers a coarse motion is "
                                                          "taken from (the tracks then have to confirm it)")
    ransac_threshold_px: float = Field(2.0, gt=0, description="RANSAC's reprojection error threshold on the tracks")
    ransac_iterations: int = Field(500, gt=0, description="RANSAC draws")
    refine_threshold_px: float = Field(1.0, gt=0, description="inliers kept for the refined pose: residual below this")
    both_ways: bool = Field(True, description="refine with the new frame's 3D points seen in the keyframe too")
    min_inliers: int = Field(30, gt=5, description="fewest inliers (and features) a pose is trusted from")
    min_overlap: float = Field(0.05, ge=0, le=1, description="share of the keyframe's 3D features that must match")
    max_rms_px: float = Field(1.5, gt=0, description="refined inliers' rms beyond this: the fit went wrong")
    stereo_patch: int = Field(11, ge=5, description="patch side (px, odd) correlated along the right image's row")
    stereo_min_correlation: float = Field(0.8, gt=0, le=1, description="weakest normalised correlation accepted")
    stereo_margin: float = Field(0.05, ge=0, description="best correlation above any other disparity's by this")
    prior_depth_share: float = Field(0.25, gt=0, lt=1, description="a tracked point's depth searched within this "
                                     "share of where the coarse motion puts its keyframe point")
    prior_disparity_px: float = Field(3.0, ge=0, description="and this many pixels of disparity either side")
    track_window: int = Field(15, ge=5, description="patch side (px) fitted when tracking keyframe points")
    track_shift_px: float = Field(8.0, gt=0, description="farthest a track may end from the coarse prediction")
    disparity_offset: bool = Field(True, description="fit the rig's disparity offset (its yaw error) with the pose")
    disparity_offset_prior_px: float = Field(0.3, gt=0, description="the offset's prior spread (px): what the "
                                             "calibration is trusted to, 0.3 px ~ 0.02 deg of yaw at 810 px")


@dataclass(frozen=True, eq=False)
class Rectified:
    """cv2.stereoRectify's rotations (R1, R2: camera to rectified frame) and projections, and the
    remap tables of both images."""

    r1: np.ndarray
    p1: np.ndarray
    r2: np.ndarray
    p2: np.ndarray
    left_maps: tuple
    right_maps: tuple

    @property
    def baseline(self) -> float:
        return float(-self.p2[0, 3] / self.p2[0, 0])

    def disparity_range(self, params: StereoOdometryParams) -> tuple[float, float]:
        """The disparities (px) of the depths the parameters accept."""
        fb = self.p1[0, 0] * self.baseline
        return fb / params.max_depth_m, fb / params.min_depth_m


@dataclass(frozen=True, eq=False)
class StereoKeyframe:
    """What a look keeps to be found again later: its left image's features (raw pixels, ORB
    descriptors), their 3D points in its left camera frame (NaN where the right image gave no depth)
    and the left image itself, for sub-pixel refinement of the matches (half a megabyte at 960 x 540)."""

    pixels: np.ndarray        # (N, 2) float32, raw (distorted) left image
    descriptors: np.ndarray   # (N, 32) uint8
    points: np.ndarray        # (N, 3) float64, left camera frame, NaN: no depth
    camera: Intrinsics        # the left camera
    image: np.ndarray         # (H, W) uint8, the left image

    @property
    def image_size(self) -> tuple[int, int]:
        return self.camera.width, self.camera.height

    @property
    def with_depth(self) -> np.ndarray:
        return np.isfinite(self.points).all(axis=1)


# ---------------------------------------------------------------------------------- the method
def stereo_keyframe(left: np.ndarray, right: np.ndarray, rig: StereoRig,
                    params: StereoOdometryParams = StereoOdometryParams()) -> StereoKeyframe:
    """The features of a stereo pair's left image and their 3D points from the right image."""
    for name, image, camera in (("left", left, rig.left), ("right", right, rig.right)):
        if np.shape(image) != (camera.height, camera.width):
            raise ValueError(f"{name} image is {np.shape(image)}, the rig's {name} camera "
                             f"{camera.height} x {camera.width}: another resolution mode?")
    # Features over the whole left image.
    pixels, descriptors = bucketed_features(left, params.features, params.grid, params.fast_threshold)
    if len(pixels) < params.min_inliers:
        raise OdometryFailure("few-features", f"{len(pixels)} features in the left image: "
                                              f"at least {params.min_inliers} needed")
    # Their depth by the rectified row search in the right image.
    points = stereo_points(pixels, left, right, rig, params)
    usable = int(np.isfinite(points).all(axis=1).sum())
    if usable < params.min_inliers:
        raise OdometryFailure("few-features", f"{len(pixels)} features in the left image, {usable} with a depth "
                                              f"from the right image: at least {params.min_inliers} needed")
    return StereoKeyframe(pixels, descriptors, points, rig.left, np.asarray(left))


def stereo_motion(key: StereoKeyframe, left: np.ndarray, right: np.ndarray, rig: StereoRig,
                  params: StereoOdometryParams = StereoOdometryParams(),
                  guess: np.ndarray | None = None, warp: bool = False) -> tuple[MotionEstimate, StereoKeyframe]:
    """The left camera's motion since the keyframe (key_from_new), and the new pair as a keyframe.
    `guess` (4 x 4 key_from_new, from dead reckoning) narrows the search; None searches everywhere.
    `warp` (with a guess): match in the new image warped into the keyframe's view by the ground."""
    # 1. The new pair as a keyframe; with `warp`, the new left image as the keyframe would see it.
    new = stereo_keyframe(left, right, rig, params)
    homography = ground_homography(key, guess) if warp and guess is not None else None
    view = new if homography is None else warped_view(left, homography, params, key.camera)
    # 2. A coarse motion from descriptor matches (in the guess's window) by PnP in RANSAC; where
    #    descriptors find too little (a rock close ahead changes every patch), the guess itself.
    descriptors_failed: OdometryFailure | None
    try:
        coarse = coarse_motion(key, view, params, guess, homography)
    except OdometryFailure as failure:
        if guess is None:
            raise
        coarse, descriptors_failed = guess, failure
    else:
        descriptors_failed = None
    # 3. Every keyframe point the coarse motion puts in view, tracked to sub-pixel (from the guess:
    #    as far as the descriptors' search window); depth of the tracked pixels from the new right
    #    image for the backward residuals.
    tracking = params if descriptors_failed is None else params.model_copy(
        update={"track_shift_px": params.search_radius_px})
    index, pixels_new = guided_tracks(key, left, coarse, tracking, homography, view.image)
    points_new = stereo_points(pixels_new, left, right, rig, params,
                               expected=apply_inverse(coarse, key.points[index]))
    key_from_new, inliers = pnp_ransac(key.points[index], pixels_new, key.camera, params,
                                       params.ransac_threshold_px)
    if inliers.sum() < params.min_inliers:
        if descriptors_failed is not None:   # neither the descriptors nor the guess found the keyframe
            raise descriptors_failed
        raise OdometryFailure("few-inliers", f"{len(index)} tracks, {int(inliers.sum())} inliers: "
                                             f"at least {params.min_inliers} needed")
    # 4. Refined on the inliers, both ways, with its covariance.
    refined, covariance, kept, rms = refine_motion(
        key_from_new, key.points[index[inliers]], pixels_new[inliers], points_new[inliers],
        key.pixels[index[inliers]].astype(np.float64), rig, params)
    if kept.sum() < params.min_inliers or not rms <= params.max_rms_px:
        raise OdometryFailure("diverged", f"refinement kept {int(kept.sum())} of {int(inliers.sum())} inliers at "
                                          f"rms {rms:.2f} px: at least {params.min_inliers} within "
                                          f"{params.max_rms_px} px needed")
    usable = int(key.with_depth.sum())
    estimate = MotionEstimate(refined, covariance, matches=len(index), inliers=int(kept.sum()),
                              overlap=min(1.0, int(kept.sum()) / max(usable, 1)), rms=rms, method="pnp")
    return estimate, new


def coarse_motion(key: StereoKeyframe, new: StereoKeyframe, params: StereoOdometryParams,
                  guess: np.ndarray | None, homography: np.ndarray | None = None) -> np.ndarray:
    """key_from_new from descriptor matches by PnP in RANSAC at the coarse threshold; OdometryFailure
    (no-overlap, few-inliers) when they are too few. With a `homography`, `new` holds the features
    of the warped view, carried back to the new image's pixels for the PnP."""
    pairs = descriptor_matches(key, new, params, guess, homography)
    usable = int(key.with_depth.sum())
    if len(pairs) < params.min_inliers or len(pairs) < params.min_overlap * usable:
        raise OdometryFailure("no-overlap", f"{len(pairs)} of the keyframe's {usable} features with a depth "
                                            f"found again ({len(pairs) / max(usable, 1):.0%}): at least "
                                            f"{params.min_inliers} and {params.min_overlap:.0%} needed")
    pixels = new.pixels[pairs[:, 1]].astype(np.float64)
    if homography is not None:
        pixels = apply_homography(homography, pixels)
    coarse, inliers = pnp_ransac(key.points[pairs[:, 0]], pixels, key.camera, params, params.coarse_threshold_px)
    if inliers.sum() < params.coarse_min_inliers:
        raise OdometryFailure("few-inliers", f"{len(pairs)} descriptor matches, {int(inliers.sum())} inliers: "
                                             f"at least {params.coarse_min_inliers} needed")
    return coarse


# ---------------------------------------------------------------------------------- the ground's warp
def ground_homography(key: StereoKeyframe, key_from_new: np.ndarray, inlier_m: float = 0.15) -> np.ndarray | None:
    """3 x 3: a keyframe pixel to the new image's pixel of the same ground point under the motion,
    through the plane fitted to the keyframe's points (least squares, refitted on those within
    `inlier_m` of the first fit); None with too few points or a camera on the plane."""
    points = key.points[key.with_depth]
    if len(points) < 10:
        return None
    for _ in range(2):
        centre = points.mean(axis=0)
        normal = np.linalg.svd(points - centre, full_matrices=False)[2][2]
        near = np.abs((points - centre) @ normal) <= inlier_m
        if near.sum() >= 10:
            points = points[near]
    distance = float(normal @ centre)                 # the plane: normal . X = distance (keyframe camera)
    if abs(distance) < 0.1:
        return None
    new_from_key = invert(key_from_new)
    rotation, translation = new_from_key[:3, :3], new_from_key[:3, 3]
    k = key.camera.matrix
    homography = k @ (rotation + np.outer(translation, normal) / distance) @ np.linalg.inv(k)
    return homography / homography[2, 2]


def apply_homography(homography: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """(N, 2) pixels mapped through a 3 x 3 homography."""
    pixels = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    mapped = np.column_stack([pixels, np.ones(len(pixels))]) @ homography.T
    with np.errstate(divide="ignore", invalid="ignore"):
        return mapped[:, :2] / mapped[:, 2:3]


def warped_view(left: np.ndarray, homography: np.ndarray, params: StereoOdometryParams,
                camera: Intrinsics) -> StereoKeyframe:
    """The new left image resampled at the homography's image of each keyframe pixel (what the
    keyframe camera would have seen of the ground from here), and its features. Only pixels,
    descriptors and image are meaningful (no depth)."""
    height, width = np.shape(left)
    image = cv2.warpPerspective(np.asarray(left), homography, (width, height),
                                flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
    pixels, descriptors = bucketed_features(image, params.features, params.grid, params.fast_threshold)
    return StereoKeyframe(pixels, descriptors, np.full((len(pixels), 3), np.nan), camera, image)


# ---------------------------------------------------------------------------------- stereo depth
@lru_cache(maxsize=4)
def rectifying(rig: StereoRig) -> Rectified:
    """The rig's rectification (cv2.stereoRectify and its remap tables), kept for the few rigs in
    use: computing the tables costs more than the rest of a look."""
    size = (rig.left.width, rig.left.height)
    rotation = np.asarray(rig.right_from_left[:3, :3], np.float64)
    translation = np.asarray(rig.right_from_left[:3, 3], np.float64).reshape(3, 1)
    r1, r2, p1, p2, *_ = cv2.stereoRectify(rig.left.matrix, rig.left.distortion, rig.right.matrix,
                                           rig.right.distortion, size, rotation, translation,
                                           flags=cv2.CALIB_ZERO_DISPARITY, alpha=0.0)
    left_maps = cv2.initUndistortRectifyMap(rig.left.matrix, rig.left.distortion, r1, p1, size, cv2.CV_16SC2)
    right_maps = cv2.initUndistortRectifyMap(rig.right.matrix, rig.right.distortion, r2, p2, size, cv2.CV_16SC2)
    return Rectified(r1, p1, r2, p2, left_maps, right_maps)


def rectified_pixels(pixels: np.ndarray, camera: Intrinsics, rotation: np.ndarray,
                     projection: np.ndarray) -> np.ndarray:
    """Raw pixels (N, 2) of a camera as pixels of its rectified image (distortion removed)."""
    if len(pixels) == 0:
        return np.empty((0, 2))
    out = cv2.undistortPoints(np.asarray(pixels, np.float64).reshape(-1, 1, 2), camera.matrix, camera.distortion,
                              R=rotation, P=projection)
    return out.reshape(-1, 2)


def stereo_points(pixels: np.ndarray, left: np.ndarray, right: np.ndarray, rig: StereoRig,
                  params: StereoOdometryParams, expected: np.ndarray | None = None) -> np.ndarray:
    """3D points (N, 3) in the left camera frame of left-image pixels, NaN where the right image
    holds no clear match on the same rectified row within the depth range.

    `expected` (N, 3), the points' left-camera positions as a prior already places them (NaN: no
    prior), narrows each one's search to the disparities of depths within `prior_depth_share` of
    its prior's: the whole depth range is some 400 px of row, the prior's window a few tens."""
    rect = rectifying(rig)
    left_rect = cv2.remap(left, *rect.left_maps, cv2.INTER_LINEAR)
    right_rect = cv2.remap(right, *rect.right_maps, cv2.INTER_LINEAR)
    at = rectified_pixels(pixels, rig.left, rect.r1, rect.p1)
    low, high = rect.disparity_range(params)
    windows = np.tile([low, high], (len(at), 1))
    if expected is not None:
        windows = prior_windows(np.asarray(expected, np.float64) @ rect.r1.T, rect, params, windows)
    disparity = row_search(left_rect, right_rect, at, windows, params)
    points = np.full((len(pixels), 3), np.nan)
    found = np.isfinite(disparity)
    points[found] = triangulate_rectified(at[found], disparity[found], rect.p1, rect.baseline) @ rect.r1
    return points


def prior_windows(expected_rect: np.ndarray, rect: Rectified, params: StereoOdometryParams,
                  windows: np.ndarray) -> np.ndarray:
    """The (N, 2) disparity windows narrowed around the disparity of each prior point's depth (in
    the rectified frame), by the prior's relative depth error and a few pixels; rows without a
    usable prior keep their window."""
    depth = expected_rect[:, 2]
    with np.errstate(invalid="ignore", divide="ignore"):
        usable = np.isfinite(depth) & (depth > 0)
        fb = rect.p1[0, 0] * rect.baseline
        share = params.prior_depth_share
        near = fb / (depth * (1.0 - share)) + params.prior_disparity_px
        far = fb / (depth * (1.0 + share)) - params.prior_disparity_px
    out = windows.copy()
    out[usable, 0] = np.maximum(windows[usable, 0], far[usable])
    out[usable, 1] = np.minimum(windows[usable, 1], near[usable])
    return out


def row_search(left_rect: np.ndarray, right_rect: np.ndarray, at: np.ndarray, windows: np.ndarray,
               params: StereoOdometryParams) -> np.ndarray:
    """Disparity (N,) of rectified left pixels in the rectified right image, NaN where none is clear.

    Each left patch is correlated along its row (one row either side: a calibration is never
    exact, and its rows may be a pixel off) over its disparity window (N, 2: lowest, highest); the
    best correlation must be high and clearly above the best elsewhere in the window, and the
    Lucas-Kanade fit of the patch at it gives the sub-pixel disparity."""
    half = params.stereo_patch // 2
    height, width = left_rect.shape
    disparity = np.full(len(at), np.nan)
    start = np.full((len(at), 2), np.nan, np.float32)
    for i, (u, v) in enumerate(at):
        row = int(round(v))
        if not (half + 1 <= row < height - half - 1 and half <= u < width - half):
            continue
        low, high = int(np.floor(windows[i, 0])), int(np.ceil(windows[i, 1]))
        first, last = max(0, int(u) - high - half), min(width, int(u) - low + half + 2)
        if last - first < params.stereo_patch + 2:
            continue
        template = cv2.getRectSubPix(left_rect, (params.stereo_patch, params.stereo_patch), (float(u), float(v)))
        strip = right_rect[row - half - 1: row + half + 2, first:last]
        scores = cv2.matchTemplate(strip, template, cv2.TM_CCOEFF_NORMED)
        _, best, _, (best_column, best_row) = cv2.minMaxLoc(scores)
        if best < params.stereo_min_correlation:
            continue
        scores[:, max(0, best_column - 2): best_column + 3] = -1.0   # the rival: the best elsewhere on the row
        rival = cv2.minMaxLoc(scores)[1]
        if rival > best - params.stereo_margin:
            continue
        start[i] = (first + best_column + half + (u - int(u)), row - 1 + best_row + (v - row))
    wanted = np.isfinite(start).all(axis=1)
    if not wanted.any():
        return disparity
    refined, ok = refine_positions(left_rect, at[wanted].astype(np.float32), right_rect, start[wanted],
                                   window=params.stereo_patch, max_shift=1.5)
    d = at[wanted, 0] - refined[:, 0]
    ok &= ((np.abs(at[wanted, 1] - refined[:, 1]) <= params.stereo_row_px)
           & (d >= windows[wanted, 0]) & (d <= windows[wanted, 1]))
    disparity[np.flatnonzero(wanted)[ok]] = d[ok]
    return disparity


def triangulate_rectified(pixels: np.ndarray, disparity: np.ndarray, projection: np.ndarray,
                          baseline: float) -> np.ndarray:
    """Rectified-frame 3D points of rectified left pixels and their disparities (Z = f B / d)."""
    f, cx, cy = projection[0, 0], projection[0, 2], projection[1, 2]
    z = f * baseline / disparity
    return np.stack([(pixels[:, 0] - cx) * z / f, (pixels[:, 1] - cy) * z / f, z], axis=1)


# ---------------------------------------------------------------------------------- matching
def predicted_pixels(key: StereoKeyframe, key_from_new: np.ndarray) -> np.ndarray:
    """Where a motion puts each keyframe point in the new left image (N, 2), NaN without depth or
    behind the camera."""
    return project(apply_inverse(key_from_new, key.points), key.camera)


def predicted_window(key: StereoKeyframe, new_pixels: np.ndarray, guess: np.ndarray | None,
                     radius: float, homography: np.ndarray | None = None) -> np.ndarray | None:
    """(N_key, N_new) bool: the new features within `radius` pixels of where the guess puts each
    keyframe feature with depth (others: none); with a `homography`, in the warped view. None
    without a guess: everything is a candidate."""
    if guess is None:
        return None
    predicted = predicted_pixels(key, guess)
    if homography is not None:
        predicted = apply_homography(np.linalg.inv(homography), predicted)
    # Squared distances in float32, a component at a time: a norm over (N, M, 2) costs ten times more.
    predicted, new_pixels = predicted.astype(np.float32), np.asarray(new_pixels, np.float32)
    du = predicted[:, 0, None] - new_pixels[None, :, 0]
    dv = predicted[:, 1, None] - new_pixels[None, :, 1]
    with np.errstate(invalid="ignore"):
        return du * du + dv * dv <= np.float32(radius * radius)


def descriptor_matches(key: StereoKeyframe, new: StereoKeyframe, params: StereoOdometryParams,
                       guess: np.ndarray | None, homography: np.ndarray | None = None) -> np.ndarray:
    """(M, 2) index pairs (keyframe feature with depth, new feature) by descriptor, in the guess's
    window around each prediction if there is a guess."""
    allowed = predicted_window(key, new.pixels, guess, params.search_radius_px, homography)
    depth = key.with_depth[:, None]
    allowed = depth if allowed is None else allowed & depth
    return match_descriptors(key.descriptors, new.descriptors, allowed, params.ratio, params.max_hamming)


def guided_tracks(key: StereoKeyframe, new_left: np.ndarray, key_from_new: np.ndarray,
                  params: StereoOdometryParams, homography: np.ndarray | None = None,
                  warped: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(keyframe indices, their pixels in the new left image): every keyframe point with depth that
    the coarse motion puts inside the new image, its keyframe patch fitted there by Lucas-Kanade.

    Descriptor matches are few once the view has moved a metre (the perspective changes every
    patch, and a detector finds a different third of the corners), and each is only as exact as
    its pyramid level; started from the predictions, the patch fit finds most of the keyframe's
    points again, to a tenth of a pixel."""
    predicted = predicted_pixels(key, key_from_new)
    margin = params.track_window
    with np.errstate(invalid="ignore"):
        inside = (key.with_depth & (predicted[:, 0] >= margin) & (predicted[:, 0] < key.camera.width - margin)
                  & (predicted[:, 1] >= margin) & (predicted[:, 1] < key.camera.height - margin))
    index = np.flatnonzero(inside)
    if homography is None:
        tracked, ok = refine_positions(key.image, key.pixels[index], new_left, predicted[index].astype(np.float32),
                                       window=params.track_window, max_shift=params.track_shift_px, levels=2)
        return index[ok], tracked[ok].astype(np.float64)
    # In the warped view the patches keep their keyframe shape; the fit found there, carried back.
    if warped is None:
        raise ValueError("guided_tracks: a homography needs the warped image it made")
    start = apply_homography(np.linalg.inv(homography), predicted[index]).astype(np.float32)
    tracked, ok = refine_positions(key.image, key.pixels[index], warped, start,
                                   window=params.track_window, max_shift=params.track_shift_px, levels=2)
    return index[ok], apply_homography(homography, tracked[ok])


# ---------------------------------------------------------------------------------- pose
def pnp_ransac(points_key: np.ndarray, pixels_new: np.ndarray, camera: Intrinsics, params: StereoOdometryParams,
               threshold_px: float) -> tuple[np.ndarray, np.ndarray]:
    """(key_from_new 4 x 4, inlier mask) from keyframe 3D points and the new image's raw pixels,
    inliers within threshold_px."""
    inliers = np.zeros(len(points_key), bool)
    if len(points_key) < 6:
        return np.eye(4), inliers
    ok, rvec, tvec, found = cv2.solvePnPRansac(
        np.ascontiguousarray(points_key, np.float64), np.ascontiguousarray(pixels_new, np.float64),
        camera.matrix, camera.distortion, iterationsCount=params.ransac_iterations,
        reprojectionError=threshold_px, confidence=0.999, flags=cv2.SOLVEPNP_EPNP)
    if not ok or found is None:
        return np.eye(4), inliers
    inliers[found.ravel()] = True
    new_from_key = np.eye(4)
    new_from_key[:3, :3], new_from_key[:3, 3] = cv2.Rodrigues(rvec)[0], tvec.ravel()
    return invert(new_from_key), inliers


def reprojection_residuals(key_from_new: np.ndarray, points_key: np.ndarray, pixels_new: np.ndarray,
                           points_new: np.ndarray, pixels_key: np.ndarray, camera: Intrinsics) -> np.ndarray:
    """Stacked pixel residuals: keyframe points seen in the new image (forward) and new points
    seen in the keyframe image (backward), flattened (u, v) per point."""
    forward = project(apply_inverse(key_from_new, points_key), camera) - pixels_new
    backward = project(points_new @ key_from_new[:3, :3].T + key_from_new[:3, 3], camera) - pixels_key
    return np.concatenate([forward.ravel(), backward.ravel()])


def gauss_newton(key_from_new: np.ndarray, residuals: Callable[[np.ndarray, np.ndarray], np.ndarray], extra: int = 0,
                 iterations: int = 10) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Least squares over the right perturbation: key_from_new @ exp(delta) (and `extra` further
    parameters, starting at 0) minimising |residuals(pose, x_extra)|^2. Returns the pose, the extra
    parameters and the Jacobian at them (numerical, central differences: a few more projections of
    a few hundred points, cheaper than deriving the distortion's)."""
    steps = np.concatenate([np.full(6, 1e-6), np.full(extra, 1e-4)])
    pose, x = key_from_new, np.zeros(extra)

    def at(e: np.ndarray) -> np.ndarray:
        return residuals(pose @ exp_se3(e[:6]), x + e[6:])

    jacobian = np.zeros((0, 6 + extra))
    for _ in range(iterations):
        r = at(np.zeros(6 + extra))
        jacobian = np.stack([(at(e) - at(-e)) / (2 * h) for e, h in zip(np.diag(steps), steps, strict=True)], axis=1)
        # The normal equations (6 + extra square): an SVD of the tall Jacobian costs 20 times more,
        # most of it OpenBLAS waking its threads for a problem this small.
        delta = np.linalg.lstsq(jacobian.T @ jacobian, -(jacobian.T @ r), rcond=None)[0]
        pose, x = pose @ exp_se3(delta[:6]), x + delta[6:]
        if np.linalg.norm(delta[:6]) < 1e-9:
            break
    return pose, x, jacobian


def offset_points(points: np.ndarray, offset: float, rect: Rectified) -> np.ndarray:
    """Left-frame points re-triangulated with `offset` px added to their disparity: each slides
    along its ray to Z' = f B / (f B / Z + offset) (Z in the rectified frame)."""
    if offset == 0:
        return points
    fb = rect.p1[0, 0] * rect.baseline
    z = points @ rect.r1[2]
    return points / (1 + offset * z / fb)[:, None]


def refine_motion(key_from_new: np.ndarray, points_key: np.ndarray, pixels_new: np.ndarray,
                  points_new: np.ndarray, pixels_key: np.ndarray, rig: StereoRig,
                  params: StereoOdometryParams) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """(refined key_from_new, its 6 x 6 covariance, correspondences kept, their rms px).

    Fitted to all correspondences (points_new NaN where the new pair gave no depth: forward only),
    those beyond refine_threshold_px dropped, and fitted again. With params.disparity_offset the
    rig's disparity offset is fitted too: a calibration's small yaw error between the cameras adds
    the same few tenths of a pixel to every disparity, which bends the keyframe's and the new
    frame's point clouds alike and would otherwise show as a rotation of about 0.1 deg per metre;
    seen from two places, the bend is not rigid, so the fit can take it out.
    Covariance (J^T J)^-1 sigma^2, sigma^2 from the residuals, over the contract's right
    perturbation (J is taken in it; the offset marginalised)."""
    camera, rect = rig.left, rectifying(rig)
    forward = np.ones(len(points_key), bool)
    backward = np.isfinite(points_new).all(axis=1) & params.both_ways
    extra = 1 if params.disparity_offset and backward.sum() >= params.min_inliers else 0
    pose, offset = key_from_new, np.zeros(extra)
    for _ in range(3):
        if forward.sum() < 6:
            return pose, np.full((6, 6), np.nan), forward, float("inf")
        def residuals(p: np.ndarray, x: np.ndarray, forward: np.ndarray = forward,
                      backward: np.ndarray = backward) -> np.ndarray:
            c = float(x[0]) if len(x) else 0.0
            r = reprojection_residuals(p, offset_points(points_key[forward], c, rect), pixels_new[forward],
                                       offset_points(points_new[backward], c, rect), pixels_key[backward], camera)
            return np.append(r, x / params.disparity_offset_prior_px)
        pose, offset, jacobian = gauss_newton(pose, residuals, extra)
        r = residuals(pose, offset)
        # Drop what the fit does not explain, either way (a wrong depth in either frame).
        c = float(offset[0]) if extra else 0.0
        errors = reprojection_residuals(pose, offset_points(points_key, c, rect), pixels_new,
                                        offset_points(points_new, c, rect), pixels_key, camera).reshape(2, -1, 2)
        with np.errstate(invalid="ignore"):
            explained = np.linalg.norm(errors, axis=2) <= params.refine_threshold_px
        if (explained[0] == forward).all() and (explained[1] & backward == backward).all():
            break
        forward, backward = explained[0], explained[1] & backward
    if not np.isfinite(r).all() or not np.isfinite(pose).all():
        return pose, np.full((6, 6), np.nan), forward, float("inf")
    r = r[:len(r) - extra]
    sigma2 = float(r @ r) / max(len(r) - 6 - extra, 1)
    covariance = np.linalg.inv(jacobian.T @ jacobian)[:6, :6] * sigma2
    rms = float(np.sqrt(2 * np.mean(r * r)))
    return pose, (covariance + covariance.T) / 2, forward, rms


def apply_inverse(key_from_new: np.ndarray, points_key: np.ndarray) -> np.ndarray:
    """Keyframe points in the new camera's frame."""
    return (points_key - key_from_new[:3, 3]) @ key_from_new[:3, :3]


# ---------------------------------------------------------------------------------- picture
def match_picture(key: StereoKeyframe, new_left: np.ndarray, estimate: MotionEstimate | None,
                  params: StereoOdometryParams = StereoOdometryParams()) -> np.ndarray:
    """The new left image (BGR uint8) with the keyframe's tracks drawn from where each point was
    to where it is now. With an estimate: the keyframe points it puts in view, tracked as
    stereo_motion tracks them, green where it explains the track (within refine_threshold_px),
    red where not. Without: the descriptor matches, red (nothing explains them)."""
    picture = cv2.cvtColor(np.asarray(new_left, np.uint8), cv2.COLOR_GRAY2BGR)
    if estimate is None:
        pixels, descriptors = bucketed_features(new_left, params.features, params.grid, params.fast_threshold)
        pairs = match_descriptors(key.descriptors, descriptors, key.with_depth[:, None], params.ratio,
                                  params.max_hamming)
        start, end, explained = key.pixels[pairs[:, 0]], pixels[pairs[:, 1]], np.zeros(len(pairs), bool)
    else:
        index, end = guided_tracks(key, new_left, estimate.key_from_new, params)
        start = key.pixels[index]
        error = np.linalg.norm(predicted_pixels(key, estimate.key_from_new)[index] - end, axis=1)
        explained = error <= params.refine_threshold_px
    for a, b, good in zip(np.rint(start).astype(int), np.rint(end).astype(int), explained, strict=True):
        colour = (0, 200, 0) if good else (0, 0, 220)
        cv2.line(picture, (int(a[0]), int(a[1])), (int(b[0]), int(b[1])), colour, 1, cv2.LINE_AA)
        cv2.circle(picture, (int(b[0]), int(b[1])), 2, colour, -1, cv2.LINE_AA)
    return picture
