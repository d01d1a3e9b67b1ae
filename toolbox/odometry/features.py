"""Interest points for visual odometry: detected spread over the image, described, matched between
two images, and refined to a fraction of a pixel. Pure functions on 8-bit grey images.

    points, descriptors = bucketed_features(image, wanted=1500, grid=(12, 8))
    pairs = match_descriptors(descriptors_a, descriptors_b, allowed, ratio=0.8, max_distance=64)
    refined, ok = refine_positions(image_a, points_a, image_b, points_b)

Positions are pixel centres at integer (u, v), as toolbox.camera has them, float32 (N, 2).
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import cv2
import numpy as np

# ORB's descriptor needs a 31-pixel patch (plus its rotation) inside the image.
ORB_BORDER_PX = 20


def bucketed_features(image: np.ndarray, wanted: int, grid: tuple[int, int],
                      fast_threshold: int = 7) -> tuple[np.ndarray, np.ndarray]:
    """Up to `wanted` ORB features (points (N, 2) float32, descriptors (N, 32) uint8), at most an
    equal share per cell of a grid (columns, rows) over the image, the strongest in each cell.

    ORB alone puts most of its features on the few strongest textures (near rocks); bucketing
    spreads them over the whole view, and a pose from points all over the image is better
    conditioned than one from a cluster."""
    image = _grey_uint8(image)
    orb = cv2.ORB_create(nfeatures=4 * wanted, scaleFactor=1.2, nlevels=6, edgeThreshold=ORB_BORDER_PX,
                         patchSize=31, fastThreshold=fast_threshold)
    keypoints = orb.detect(image, None)
    keypoints = strongest_per_cell(keypoints, image.shape, wanted, grid)
    if not keypoints:
        return np.empty((0, 2), np.float32), np.empty((0, 32), np.uint8)
    keypoints, descriptors = orb.compute(image, keypoints)
    if descriptors is None or not keypoints:
        return np.empty((0, 2), np.float32), np.empty((0, 32), np.uint8)
    return np.array([k.pt for k in keypoints], np.float32), descriptors


def strongest_per_cell(keypoints: Sequence[Any], shape: tuple[int, ...], wanted: int,
                       grid: tuple[int, int]) -> list[Any]:
    """The keypoints with the highest response in each grid cell, at most ceil(wanted / cells)
    per cell (cells with fewer keep what they have; the shortfall is not moved elsewhere)."""
    columns, rows = grid
    height, width = shape[:2]
    per_cell = math.ceil(wanted / (columns * rows))
    cells: dict[tuple[int, int], list] = {}
    for keypoint in sorted(keypoints, key=lambda k: -k.response):
        u, v = keypoint.pt
        cell = (min(int(u * columns / width), columns - 1), min(int(v * rows / height), rows - 1))
        kept = cells.setdefault(cell, [])
        if len(kept) < per_cell:
            kept.append(keypoint)
    return [k for kept in cells.values() for k in kept]


def match_descriptors(a: np.ndarray, b: np.ndarray, allowed: np.ndarray | None = None,
                      ratio: float = 0.8, max_distance: int = 64) -> np.ndarray:
    """(M, 2) index pairs (i in a, j in b): each a's nearest allowed descriptor in b, kept if it is
    clearly nearer than the second nearest (Lowe's ratio), near enough, and a's nearest the other
    way too (mutual). `allowed` (len(a), len(b)) bool restricts the candidates (a search window,
    an epipolar band); None allows all."""
    if len(a) == 0 or len(b) == 0:
        return np.empty((0, 2), np.int64)
    matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
    mask = None if allowed is None else np.ascontiguousarray(np.broadcast_to(allowed, (len(a), len(b))), np.uint8)
    forward = matcher.knnMatch(a, b, k=2, mask=mask)
    backward = matcher.knnMatch(b, a, k=1, mask=None if mask is None else np.ascontiguousarray(mask.T))
    nearest_a = np.full(len(b), -1)
    for candidates in backward:
        if candidates:
            nearest_a[candidates[0].queryIdx] = candidates[0].trainIdx
    pairs = []
    for candidates in forward:
        if not candidates:
            continue
        best = candidates[0]
        second = candidates[1].distance if len(candidates) > 1 else np.inf
        if (best.distance <= max_distance and best.distance < ratio * second
                and nearest_a[best.trainIdx] == best.queryIdx):
            pairs.append((best.queryIdx, best.trainIdx))
    return np.array(pairs, np.int64).reshape(-1, 2)


def refine_positions(image_a: np.ndarray, points_a: np.ndarray, image_b: np.ndarray, points_b: np.ndarray,
                     window: int = 15, max_error: float = 0.5, max_shift: float = 3.0,
                     levels: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """points_b moved to where the patch around each points_a best fits in image_b (pyramidal
    Lucas-Kanade over `levels` pyramid levels above the image, started at points_b), and which
    did: converged, back-tracked to points_a within max_error pixels, and moved less than
    max_shift from where they started.

    A correlation peak or a descriptor match only places a feature to a pixel (ORB's coarse levels
    to 2-3); the photometric fit of the same patch finds it to a tenth of a pixel, which is what
    depth from a 0.25 m baseline and a pose good to 0.5 % need."""
    if len(points_a) == 0:
        return np.asarray(points_b, np.float32).reshape(-1, 2), np.zeros(0, bool)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01)
    a = np.ascontiguousarray(points_a, np.float32).reshape(-1, 1, 2)
    b0 = np.ascontiguousarray(points_b, np.float32).reshape(-1, 1, 2)
    lk = dict(winSize=(window, window), maxLevel=levels, criteria=criteria, flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
    b, status, _ = cv2.calcOpticalFlowPyrLK(_grey_uint8(image_a), _grey_uint8(image_b), a, b0.copy(), **lk)
    back, status_back, _ = cv2.calcOpticalFlowPyrLK(_grey_uint8(image_b), _grey_uint8(image_a), b, a.copy(), **lk)
    b, back = b.reshape(-1, 2), back.reshape(-1, 2)
    ok = ((status.ravel() == 1) & (status_back.ravel() == 1)
          & (np.linalg.norm(back - points_a, axis=1) <= max_error)
          & (np.linalg.norm(b - points_b, axis=1) <= max_shift))
    return b, ok


def _grey_uint8(image: np.ndarray) -> np.ndarray:
    image = np.asarray(image)
    if image.dtype != np.uint8 or image.ndim != 2:
        raise ValueError(f"expected an 8-bit grey image (H, W) uint8, got {image.dtype} {image.shape}")
    return image
