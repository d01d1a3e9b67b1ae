"""Depth (time-of-flight) odometry: how the SR4000 moved between a keyframe and a new frame, from the
two point clouds alone, by robust multi-scale point-to-plane ICP seeded with dead reckoning.

The method, step by step (`depth_motion`), each step one small pure function:

    usable_points        valid, finite points inside [min_range, max_range] (beyond ~4.5 m the 30 MHz
                         SR4000 wraps and its noise grows)
    voxel_cloud          voxel-downsampled cloud with normals, per scale
    refine_guess         the guess's height and step length searched on a small grid (dead reckoning
                         does not know the terrain's height under the wheels)
    register             point-to-plane ICP (Open3D, Tukey kernel), coarse to fine, from the guess
    seen_share           the share of the new cloud the keyframe camera could have seen after the motion
    check_plausible      refuse a result that left the guess implausibly far or found too little: a
                         long step leaves the two views little in common, so a small overlap is taken
                         when most of what the keyframe could see agrees (campaign: 1.4 m steps at 19-29 %
                         overlap were right; wrong results agreed on under half of what was in view)
    point_to_plane_covariance
                         sigma^2 (J^T J)^-1 of the final correspondences, in the contract's right
                         perturbation (rotation vector, translation) of key_from_new

A turn on the spot (`depth_turn`) is registered over the rotation about the rover's centre alone:
with the SR4000's 44 deg view of gently rolling ground, free ICP after a 10-15 deg turn often explains
part of the yaw as a sideways step (the campaign's 38 of 63 refusals were that), while the wheels
know the rover did not step. `register_rotation` holds the translation the turn implies and
measures only the rotation.

Why ICP and not image-based depth odometry: tests/bench/measure_depth_odometry.py measured Open3D
point-to-plane ICP against Open3D's RGBD odometry (hybrid Jacobian, amplitude as intensity) and
cv2.Odometry (DEPTH and RGB_DEPTH) on the same 45 pairs per tilt (steps 0.5-1.5 m, turns 0-10 deg).
With the TOF tilted 30 deg down, ICP answered all 45 within 0.57 % of the step (median; p90 1.6 %,
0.13 deg; 90/90 on 10 worlds, 0.48 %, 366 ms median and 646 ms max on one core); Open3D RGBD was as
good at the median but off by 27 % at p90 without refusing, cv2.Odometry 1.7 % at the median and
unable to take 1.5 m steps.

Flat ground lets point-to-plane ICP slide: every normal points up, so forward, sideways and yaw are
unobserved. No threshold hides it: the information matrix is what it is, and its weak directions
come out as large sigmas in the covariance (`MotionEstimate.covariance`); `information_condition`
says how weak. Frames: OpenCV camera axes; key_from_new maps a point of the new frame into the keyframe's.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree

from toolbox.geometry import apply

from .estimate import MotionEstimate, OdometryFailure, exp_se3

__all__ = ["DepthFrame", "DepthOdometryParams", "depth_motion", "depth_picture", "usable_points",
           "voxel_cloud", "refine_guess", "register", "seen_share", "check_plausible", "point_to_plane_jacobian",
           "point_to_plane_covariance", "information_condition", "pinhole_depth",
           "motion_error", "depth_turn", "register_rotation", "rotate_about"]


@dataclass(frozen=True)
class DepthFrame:
    """One time-of-flight look.

    points     (H, W, 3) float32, camera frame (x right, y down, z forward), metres; NaN where invalid
    valid      (H, W) bool: a measurement the camera trusts (amplitude threshold, confidence)
    amplitude  (H, W) float32, the camera's amplitude (grey) image
    fx, fy, cx, cy
               a pinhole for the depth camera's images: the points are projected with it for
               image-based methods and pictures (the points themselves already carry any lens
               distortion, so this may be a pinhole chosen to hold them all)
    """

    points: np.ndarray
    valid: np.ndarray
    amplitude: np.ndarray
    fx: float
    fy: float
    cx: float
    cy: float

    def __post_init__(self) -> None:
        h, w = self.valid.shape
        if self.points.shape != (h, w, 3) or self.amplitude.shape != (h, w):
            raise ValueError(f"points {self.points.shape}, valid {self.valid.shape} and amplitude "
                             f"{self.amplitude.shape} must share one (H, W)")

    @classmethod
    def from_arrays(cls, points: np.ndarray, amplitude: np.ndarray, fx: float, fy: float, cx: float,
                    cy: float, confidence: np.ndarray | None = None, min_confidence: float = 0.0) -> DepthFrame:
        """A frame from a camera's x, y, z and amplitude images: invalid where z <= 0 or not finite
        (the SR4000 writes 0 for no measurement) or where confidence (0..1) is below min_confidence."""
        points = np.asarray(points, dtype=np.float32).copy()
        valid = np.all(np.isfinite(points), axis=-1) & (points[..., 2] > 0)
        if confidence is not None:
            valid &= np.asarray(confidence) >= min_confidence
        points[~valid] = np.nan
        return cls(points, valid, np.asarray(amplitude, dtype=np.float32), float(fx), float(fy), float(cx), float(cy))


@dataclass(frozen=True)
class DepthOdometryParams:
    voxel_m: float = 0.04                    # finest voxel the clouds are thinned to (the SR4000's pixel
                                             # spacing is ~1 cm at 3 m: a voxel evens the density out)
    scales: tuple[float, ...] = (2.0, 1.0)   # coarse-to-fine voxel multiples, one ICP each
    correspondence_m: tuple[float, ...] = (0.1, 0.05)  # max correspondence distance per scale: the first
                                             # covers the dead-reckoning error of a 1.5 m step (~8 cm,
                                             # 1 deg). Wider is worse: at 0.2 m (or 0.3 m) ICP turned the
                                             # new view 20-40 deg to overlap more of the keyframe (bench)
    iterations: int = 30                     # ICP iterations per scale
    tukey_ratio: float = 0.5                 # Tukey kernel width as a share of the correspondence distance
    normal_radius_voxels: float = 3.0        # normals from neighbours within this many voxels
    min_range_m: float = 0.3                 # points nearer are dropped (mast, wheels, saturation)
    max_range_m: float = 4.5                 # and farther (30 MHz non-ambiguity range is 5 m)
    min_points: int = 300                    # usable points (after cropping) each frame needs: else no-depth
    min_overlap: float = 0.3                 # share of the new frame's points matched in the keyframe: else no-overlap,
    min_seen_match: float = 0.6              # ... unless this share of the points the keyframe could see matched
    min_overlap_floor: float = 0.1           # ... and at least this share overall
    min_inliers: int = 200                   # matched points at the finest scale: else few-inliers
    max_departure_m: float = 0.5             # the result may move this far from the guess: else diverged
    max_departure_deg: float = 15.0          # and turn this far from it
    seed_span_m: float = 0.15                # the guess is first searched this far up/down and along the
    seed_step_m: float = 0.025               # step, at this spacing (0 span: no search)
    covariance_scale: float = 4.0            # sigma^2 (J^T J)^-1 times this: on the bench the errors ran
                                             # ~2x the raw sigma (neighbours' errors are correlated, the
                                             # voxel grid biases), so the variance is taken 4x
    turn_step_sigma_m: float = 0.02          # depth_turn: how far a turn on the spot may shift the rover's
                                             # centre (skid-steer scrub), added to the rotation's covariance

    def __post_init__(self) -> None:
        for name in ("voxel_m", "tukey_ratio", "normal_radius_voxels", "covariance_scale", "seed_step_m",
                     "turn_step_sigma_m",
                     "max_range_m", "max_departure_m", "max_departure_deg"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)!r}")
        if not 0 <= self.min_range_m < self.max_range_m:
            raise ValueError(f"need 0 <= min_range_m < max_range_m, got {self.min_range_m}, {self.max_range_m}")
        for name in ("min_overlap", "min_seen_match", "min_overlap_floor"):
            if not 0 <= getattr(self, name) <= 1:
                raise ValueError(f"{name} must be in [0, 1], got {getattr(self, name)!r}")
        if not self.scales or any(s <= 0 for s in self.scales) or self.iterations < 1:
            raise ValueError(f"scales must be positive and iterations >= 1, got {self.scales}, {self.iterations}")
        if len(self.correspondence_m) != len(self.scales) or any(d <= 0 for d in self.correspondence_m):
            raise ValueError(f"correspondence_m needs one positive distance per scale, got {self.correspondence_m} "
                             f"for scales {self.scales}")


@dataclass(frozen=True)
class Registration:
    key_from_new: np.ndarray     # 4 x 4
    fitness: float               # matched share of the new frame's finest cloud
    inlier_rmse: float           # m
    correspondences: np.ndarray  # (K, 2) int: (new index, key index) in the finest clouds
    max_distance: float          # correspondence distance of the last scale, m
    new_points: np.ndarray       # (N, 3) the finest new (source) cloud
    key_points: np.ndarray       # (M, 3) the finest keyframe (target) cloud
    key_normals: np.ndarray      # (M, 3) its normals


# ------------------------------------------------------------------------------ small steps
def usable_points(frame: DepthFrame, min_range_m: float, max_range_m: float) -> np.ndarray:
    """(N, 3) float64 valid, finite points with min_range <= |p| <= max_range."""
    points = frame.points[frame.valid].astype(np.float64)
    points = points[np.all(np.isfinite(points), axis=1)]
    distance = np.linalg.norm(points, axis=1)
    return points[(distance >= min_range_m) & (distance <= max_range_m)]


def voxel_cloud(points: np.ndarray, voxel_m: float, normal_radius_m: float) -> o3d.geometry.PointCloud:
    """Voxel-downsampled Open3D cloud with unit normals turned toward the camera (origin)."""
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points)).voxel_down_sample(voxel_m)
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=normal_radius_m, max_nn=30))
    cloud.orient_normals_towards_camera_location(np.zeros(3))
    return cloud


def refine_guess(new_points: np.ndarray, key_points: np.ndarray, guess: np.ndarray,
                 params: DepthOdometryParams) -> np.ndarray:
    """The guess shifted, on a grid within seed_span_m along the keyframe's ground normal (up) and
    along the step, to where the coarse new cloud lands best on the keyframe's (Tukey-weighted count
    within the first correspondence distance). Dead reckoning knows the step's length to a few per
    cent and the height of the terrain under the wheels not at all: on the bench a 12 cm height error
    left the first ICP scale with no correspondences."""
    if params.seed_span_m <= 0:
        return guess
    voxel = params.voxel_m * params.scales[0]
    key_cloud = voxel_cloud(key_points, voxel, params.normal_radius_voxels * voxel)
    up = np.median(np.asarray(key_cloud.normals), axis=0)
    up /= max(np.linalg.norm(up), 1e-12)
    along = guess[:3, 3] - up * (guess[:3, 3] @ up)
    if np.linalg.norm(along) < 1e-3:                         # no step: along the optical axis instead
        along = np.array([0.0, 0.0, 1.0]) - up * up[2]
    along /= max(np.linalg.norm(along), 1e-12)
    moved = apply(guess, np.asarray(voxel_cloud(new_points, voxel, 2 * voxel).points))
    tree, reach = cKDTree(np.asarray(key_cloud.points)), params.correspondence_m[0]
    offsets = np.arange(-params.seed_span_m, params.seed_span_m + 1e-9, params.seed_step_m)
    shifts = (offsets[:, None, None] * along + offsets[None, :, None] * up).reshape(-1, 3)
    distance, _ = tree.query((moved[None] + shifts[:, None]).reshape(-1, 3), distance_upper_bound=reach)
    weight = np.where(np.isfinite(distance), (1 - (np.minimum(distance, reach) / reach) ** 2) ** 2, 0.0)
    score = weight.reshape(len(shifts), len(moved)).sum(axis=1)
    best = shifts[np.lexsort((np.linalg.norm(shifts, axis=1), -score))[0]]   # best score, then the smallest shift
    refined = guess.copy()
    refined[:3, 3] += best
    return refined


def register(new_points: np.ndarray, key_points: np.ndarray, guess: np.ndarray,
             params: DepthOdometryParams) -> Registration:
    """Multi-scale robust point-to-plane ICP of the new cloud (source) onto the keyframe's (target)
    from the guess: the transform found is key_from_new."""
    transform = np.asarray(guess, dtype=np.float64).copy()
    criteria = o3d.pipelines.registration.ICPConvergenceCriteria(relative_fitness=1e-7, relative_rmse=1e-7,
                                                                 max_iteration=params.iterations)
    for index, scale in enumerate(params.scales):
        voxel = params.voxel_m * scale
        source = voxel_cloud(new_points, voxel, params.normal_radius_voxels * voxel)
        target = voxel_cloud(key_points, voxel, params.normal_radius_voxels * voxel)
        distance = params.correspondence_m[index]
        loss = o3d.pipelines.registration.TukeyLoss(k=params.tukey_ratio * distance)
        result = o3d.pipelines.registration.registration_icp(
            source, target, distance, transform,
            o3d.pipelines.registration.TransformationEstimationPointToPlane(loss), criteria)
        transform = np.asarray(result.transformation).copy()
    correspondences = np.asarray(result.correspondence_set, dtype=np.int64).reshape(-1, 2)
    return Registration(transform, float(result.fitness), float(result.inlier_rmse), correspondences, distance,
                        np.asarray(source.points), np.asarray(target.points), np.asarray(target.normals))


def rotate_about(pivot: np.ndarray, rotation_vector: np.ndarray) -> np.ndarray:
    """4 x 4 rotation by rotation_vector about the point pivot (not the origin)."""
    out = exp_se3(np.concatenate([rotation_vector, np.zeros(3)]))
    out[:3, 3] = pivot - out[:3, :3] @ pivot
    return out


def register_rotation(new_points: np.ndarray, key_points: np.ndarray, guess: np.ndarray, pivot: np.ndarray,
                      params: DepthOdometryParams) -> Registration:
    """Robust point-to-plane ICP over key_from_new = guess @ rotate_about(pivot, delta), delta the only
    unknown (3 rotation angles; pivot a point of the new frame): Gauss-Newton with Tukey weights,
    coarse to fine like `register`. The residual's derivative in delta is (p - pivot) x m, m the key
    normal turned into the new frame (`point_to_plane_jacobian`'s rotation columns about the pivot)."""
    transform = np.asarray(guess, dtype=np.float64).copy()
    pivot = np.asarray(pivot, dtype=np.float64)
    for index, scale in enumerate(params.scales):
        voxel = params.voxel_m * scale
        source = np.asarray(voxel_cloud(new_points, voxel, params.normal_radius_voxels * voxel).points)
        target = voxel_cloud(key_points, voxel, params.normal_radius_voxels * voxel)
        target_points, target_normals = np.asarray(target.points), np.asarray(target.normals)
        tree, distance = cKDTree(target_points), params.correspondence_m[index]
        width = params.tukey_ratio * distance
        for _ in range(params.iterations):
            gap, nearest = tree.query(apply(transform, source), distance_upper_bound=distance)
            matched = np.isfinite(gap)
            if matched.sum() < 6:
                break
            p, q, n = source[matched], target_points[nearest[matched]], target_normals[nearest[matched]]
            residual = np.sum(n * (apply(transform, p) - q), axis=1)
            weight = np.where(np.abs(residual) < width, (1 - (residual / width) ** 2) ** 2, 0.0)
            jacobian = np.cross(p - pivot, n @ transform[:3, :3])
            hessian = (jacobian * weight[:, None]).T @ jacobian
            delta = -np.linalg.solve(hessian + 1e-9 * np.eye(3), (jacobian * weight[:, None]).T @ residual)
            transform = transform @ rotate_about(pivot, delta)
            if np.linalg.norm(delta) < 1e-7:
                break
    gap, nearest = tree.query(apply(transform, source), distance_upper_bound=distance)
    matched = np.flatnonzero(np.isfinite(gap))
    correspondences = np.column_stack([matched, nearest[matched]]).astype(np.int64)
    rmse = float(np.sqrt(np.mean(gap[matched] ** 2))) if len(matched) else 0.0
    return Registration(transform, len(matched) / max(1, len(source)), rmse, correspondences, distance,
                        source, target_points, target_normals)


def motion_error(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """(translation m, rotation deg) of a^-1 b."""
    delta = np.linalg.inv(a) @ b
    angle = np.degrees(np.arccos(np.clip((np.trace(delta[:3, :3]) - 1) / 2, -1.0, 1.0)))
    return float(np.linalg.norm(delta[:3, 3])), float(angle)


def seen_share(points: np.ndarray, key: DepthFrame, key_from_new: np.ndarray, params: DepthOdometryParams) -> float:
    """Share of points (new frame) that land, moved by key_from_new, inside the keyframe camera's
    image (its pinhole) and usable range: what the keyframe could have seen of them."""
    if not len(points):
        return 0.0
    moved = apply(key_from_new, points)
    h, w = key.valid.shape
    z = moved[:, 2]
    ahead = z > 1e-6
    u = key.fx * moved[ahead, 0] / z[ahead] + key.cx
    v = key.fy * moved[ahead, 1] / z[ahead] + key.cy
    distance = np.linalg.norm(moved[ahead], axis=1)
    inside = ((u >= 0) & (u < w) & (v >= 0) & (v < h) & (distance >= params.min_range_m)
              & (distance <= params.max_range_m))
    return float(inside.sum()) / len(points)


def check_plausible(registration: Registration, guess: np.ndarray, params: DepthOdometryParams,
                    seen: float = 1.0) -> None:
    """Raise OdometryFailure when the registration found too little or left the guess too far; seen:
    the share of the new cloud the keyframe could see after the motion (`seen_share`)."""
    if not np.all(np.isfinite(registration.key_from_new)):
        raise OdometryFailure("diverged", "the ICP gave a non-finite transform")
    moved, turned = motion_error(guess, registration.key_from_new)
    if moved > params.max_departure_m or turned > params.max_departure_deg:
        raise OdometryFailure("diverged", f"the ICP result lies {moved:.2f} m and {turned:.1f} deg from the "
                              f"guess; at most {params.max_departure_m:.2f} m and {params.max_departure_deg:.1f} "
                              "deg are plausible")
    fitness = registration.fitness
    agrees = fitness >= params.min_overlap_floor and fitness >= params.min_seen_match * seen
    if fitness < params.min_overlap and not agrees:
        raise OdometryFailure("no-overlap", f"only {fitness:.0%} of the new frame's points lie within "
                              f"{registration.max_distance * 100:.0f} cm of the keyframe's "
                              f"({fitness / max(seen, 1e-9):.0%} "
                              f"of the {seen:.0%} it could see); at least {params.min_overlap:.0%}, or "
                              f"{params.min_seen_match:.0%} of what it could see, are needed")
    if len(registration.correspondences) < params.min_inliers:
        raise OdometryFailure("few-inliers", f"{len(registration.correspondences)} points matched the keyframe; "
                              f"at least {params.min_inliers} are needed")


def point_to_plane_jacobian(new_points: np.ndarray, key_normals: np.ndarray, key_from_new: np.ndarray) -> np.ndarray:
    """(K, 6) d residual / d delta of r = n . (T exp(delta) p - q), delta = (rotation vector, translation),
    right perturbation: with m = R^T n (the key normal in the new frame), the row is (p x m, m)."""
    m = key_normals @ key_from_new[:3, :3]          # row-wise R^T n
    return np.column_stack([np.cross(new_points, m), m])


def information_condition(information: np.ndarray) -> float:
    """Largest over smallest eigenvalue of a 6 x 6 information matrix (inf if singular): large on
    flat ground, where point-to-plane ICP can slide."""
    eigenvalues = np.linalg.eigvalsh(information)
    return float(eigenvalues[-1] / eigenvalues[0]) if eigenvalues[0] > 0 else float("inf")


def point_to_plane_covariance(new_points: np.ndarray, key_points: np.ndarray, key_normals: np.ndarray,
                              key_from_new: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """(covariance 6 x 6, information J^T J, residual rms m) of the final correspondences (row i of
    new_points matched to row i of key_points): sigma^2 (J^T J)^-1 with sigma^2 the residual variance.

    Our own J^T J rather than Open3D's get_information_matrix_from_point_clouds: that one is the
    point-to-point information, linearised at the target points (a left perturbation in the
    keyframe's axes), though its order is also (rotation, translation); this is point-to-plane, the
    residual the ICP minimised, and a right perturbation of key_from_new as the contract wants.

    Weak directions (flat ground) keep their tiny eigenvalues, floored only to stay finite, so they show
    as large sigmas rather than disappear. Neighbouring points' errors are correlated, so the figure is
    a lower bound on the true uncertainty (depth_motion scales it by params.covariance_scale)."""
    jacobian = point_to_plane_jacobian(new_points, key_normals, key_from_new)
    residual = np.sum(key_normals * (apply(key_from_new, new_points) - key_points), axis=1)
    information = jacobian.T @ jacobian
    variance = float(residual @ residual) / max(1, len(residual) - 6)
    eigenvalues, vectors = np.linalg.eigh(information)
    floor = max(eigenvalues[-1], 1e-12) * 1e-12
    covariance = variance * (vectors / np.maximum(eigenvalues, floor)) @ vectors.T
    return (covariance + covariance.T) / 2, information, float(np.sqrt(np.mean(residual ** 2)))


# ------------------------------------------------------------------------------ the method
def depth_motion(key: DepthFrame, new: DepthFrame, params: DepthOdometryParams | None = None,
                 guess: np.ndarray | None = None) -> MotionEstimate:
    """The new frame's pose in the keyframe camera's frame (key_from_new) and its covariance, from
    the two clouds; guess is dead reckoning's key_from_new (identity if None)."""
    params = params or DepthOdometryParams()
    guess = np.eye(4) if guess is None else np.asarray(guess, dtype=np.float64)
    # Usable points: valid, inside the range the camera measures well.
    key_points = usable_points(key, params.min_range_m, params.max_range_m)
    new_points = usable_points(new, params.min_range_m, params.max_range_m)
    for name, points in (("keyframe", key_points), ("new frame", new_points)):
        if len(points) < params.min_points:
            raise OdometryFailure("no-depth", f"the {name} has {len(points)} usable points within "
                                  f"{params.min_range_m:.1f}-{params.max_range_m:.1f} m; at least "
                                  f"{params.min_points} are needed")
    # Registration: the guess's height and step length searched, then coarse-to-fine robust
    # point-to-plane ICP.
    registration = register(new_points, key_points, refine_guess(new_points, key_points, guess, params), params)
    # Plausibility: enough overlap (of what the keyframe could see), not run away from the guess.
    check_plausible(registration, guess, params,
                    seen_share(registration.new_points, key, registration.key_from_new, params))
    # Covariance of the final correspondences.
    pairs = registration.correspondences
    covariance, _, rms = point_to_plane_covariance(registration.new_points[pairs[:, 0]],
                                                   registration.key_points[pairs[:, 1]],
                                                   registration.key_normals[pairs[:, 1]], registration.key_from_new)
    return MotionEstimate(key_from_new=registration.key_from_new, covariance=params.covariance_scale * covariance,
                          matches=len(registration.new_points), inliers=len(pairs), overlap=registration.fitness,
                          rms=rms, method="icp")


def depth_turn(key: DepthFrame, new: DepthFrame, pivot: np.ndarray, params: DepthOdometryParams | None = None,
               guess: np.ndarray | None = None) -> MotionEstimate:
    """`depth_motion` for a turn on the spot: only the rotation about pivot (the rover's centre, in
    the new camera's frame) is measured, the translation is the one that rotation implies from the
    guess. The covariance is the rotation's, carried to the 6-DoF right perturbation (rotating by
    delta about the pivot moves the camera by pivot x delta), plus turn_step_sigma_m of scrub."""
    params = params or DepthOdometryParams()
    guess = np.eye(4) if guess is None else np.asarray(guess, dtype=np.float64)
    key_points = usable_points(key, params.min_range_m, params.max_range_m)
    new_points = usable_points(new, params.min_range_m, params.max_range_m)
    for name, points in (("keyframe", key_points), ("new frame", new_points)):
        if len(points) < params.min_points:
            raise OdometryFailure("no-depth", f"the {name} has {len(points)} usable points within "
                                  f"{params.min_range_m:.1f}-{params.max_range_m:.1f} m; at least "
                                  f"{params.min_points} are needed")
    registration = register_rotation(new_points, key_points, guess, pivot, params)
    check_plausible(registration, guess, params,
                    seen_share(registration.new_points, key, registration.key_from_new, params))
    pairs = registration.correspondences
    _, information, rms = point_to_plane_covariance(registration.new_points[pairs[:, 0]],
                                                    registration.key_points[pairs[:, 1]],
                                                    registration.key_normals[pairs[:, 1]], registration.key_from_new)
    # The rotation's information about the pivot: J_pivot = J_rotation - [pivot]x-shifted, i.e. the
    # 6-DoF rows taken along (delta, pivot x delta).
    lift = np.vstack([np.eye(3), _skew(pivot)])
    rotation_information = lift.T @ information @ lift
    variance = rms ** 2 * len(pairs) / max(1, len(pairs) - 3)
    rotation_covariance = variance * np.linalg.inv(rotation_information + 1e-12 * np.eye(3))
    covariance = params.covariance_scale * lift @ rotation_covariance @ lift.T
    covariance[3:, 3:] += params.turn_step_sigma_m ** 2 * np.eye(3)
    return MotionEstimate(key_from_new=registration.key_from_new, covariance=(covariance + covariance.T) / 2,
                          matches=len(registration.new_points), inliers=len(pairs), overlap=registration.fitness,
                          rms=rms, method="icp-rotation")


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


# ------------------------------------------------------------------------------ pictures and images
def pinhole_depth(frame: DepthFrame) -> tuple[np.ndarray, np.ndarray]:
    """(depth, amplitude), (H, W) float32 images of the frame's valid points projected with its pinhole
    (depth = z in metres, 0 where no point lands), the nearest point winning a pixel: the images
    image-based depth odometry works on (the camera's own grid carries its lens distortion)."""
    points = frame.points.reshape(-1, 3).astype(np.float64)
    amplitude = frame.amplitude.reshape(-1).astype(np.float32)
    keep = frame.valid.reshape(-1) & np.all(np.isfinite(points), axis=1) & (points[:, 2] > 0)
    points, amplitude = points[keep], amplitude[keep]
    h, w = frame.valid.shape
    cols = np.round(frame.fx * points[:, 0] / points[:, 2] + frame.cx).astype(np.int64)
    rows = np.round(frame.fy * points[:, 1] / points[:, 2] + frame.cy).astype(np.int64)
    inside = (rows >= 0) & (rows < h) & (cols >= 0) & (cols < w)
    order = np.argsort(-points[inside, 2])                   # far first: the nearest is written last
    pixel = (rows[inside] * w + cols[inside])[order]
    depth, grey = np.zeros(h * w, np.float32), np.zeros(h * w, np.float32)
    depth[pixel], grey[pixel] = points[inside, 2][order], amplitude[inside][order]
    return depth.reshape(h, w), grey.reshape(h, w)


def depth_picture(key: DepthFrame, new: DepthFrame, estimate: MotionEstimate | None,
                  match_distance_m: float = 0.05) -> np.ndarray:
    """BGR uint8 picture of the new frame's amplitude (grey) with, if an estimate is given, each of its
    valid pixels coloured by how far its point lies from the keyframe's cloud after the estimated
    motion: green within match_distance_m, shading to red at 4 x, blue where the keyframe saw nothing
    near (outside the overlap). Pure: returns the array."""
    amplitude = np.nan_to_num(new.amplitude.astype(np.float64))
    top = np.percentile(amplitude[new.valid], 99) if new.valid.any() else 1.0
    grey = np.clip(amplitude / max(top, 1e-9) * 255, 0, 255).astype(np.uint8)
    picture = cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR)
    shown = new.valid & np.all(np.isfinite(new.points), axis=-1)
    key_points = key.points[key.valid].astype(np.float64)
    key_points = key_points[np.all(np.isfinite(key_points), axis=1)]
    if estimate is None or not shown.any() or not len(key_points):
        return picture
    moved = apply(estimate.key_from_new, new.points[shown].astype(np.float64))
    distance, _ = cKDTree(key_points).query(moved, distance_upper_bound=4 * match_distance_m)
    share = np.clip((distance - match_distance_m) / (3 * match_distance_m), 0, 1)
    colour = np.column_stack([np.zeros_like(share), 255 * (1 - share), 255 * share])
    colour[~np.isfinite(distance)] = (255, 0, 0)
    blended = 0.5 * picture[shown].astype(np.float64) + 0.5 * colour
    picture[shown] = np.clip(blended, 0, 255).astype(np.uint8)
    return picture
