"""Self-localisation by map alignment: correct the odometry pose by aligning a new cloud to the map.

The thesis' rover had no self-localisation: each map was placed where odometry said the rover was,
so wheel slip went straight into the maps and the plans. Here the new view's cloud (placed with the
odometry pose) is aligned to the cloud of everything mapped so far with point-to-plane ICP (Open3D),
coarse to fine. Roll and pitch come from the inclinometer and are kept: the correction has four
degrees of freedom (x, y, z and heading), every ICP stage is projected onto them, and it rotates
about the rover, so a heading error swings the far cloud back without dragging the rover along.

Flat ground constrains only height; rocks and slopes pin x, y and heading. The correction is accepted
only when the aligned clouds overlap well and x and y are constrained (the smallest eigenvalue of the
point-to-plane normal matrix, per point), and only when it is no larger than odometry could have
been wrong by: otherwise the odometry pose stands, and the result says why.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import open3d as o3d


@dataclass(frozen=True)
class AlignConfig:
    stages: tuple[tuple[float, float], ...] = ((0.20, 0.60), (0.10, 0.30), (0.05, 0.12))  # (voxel, max distance)
    iterations: int = 40
    max_translation_m: float = 1.0      # odometry is not wrong by more than this between two maps
    max_rotation_deg: float = 10.0
    min_fitness: float = 0.3            # share of source points with a partner within the last max distance
    min_constraint: float = 0.005       # per-point smallest eigenvalue of the x-y normal matrix
    search_margin_m: float = 1.0        # the map is cropped to the new cloud's extent plus this
    overlap_cell_m: float = 0.25        # new points count as overlapping where the map has points in this cell


@dataclass(frozen=True)
class Alignment:
    correction: np.ndarray   # 4x4 applied to the new cloud (and to the rover pose) in the world frame
    dx: float
    dy: float
    dz: float
    dyaw: float              # radians
    fitness: float
    rmse: float
    constraint: float
    accepted: bool
    reason: str              # "" when accepted; else why the odometry pose stands


def identity_alignment(reason: str) -> Alignment:
    return Alignment(np.eye(4), 0.0, 0.0, 0.0, 0.0, 0.0, math.nan, 0.0, False, reason)


def four_dof(transform: np.ndarray, pivot: np.ndarray) -> np.ndarray:
    """The x, y, z and heading part of a rigid transform: the yaw about the vertical through
    `pivot`, and the translation that moves `pivot` where the full transform moves it."""
    yaw = math.atan2(transform[1, 0], transform[0, 0])
    c, s = math.cos(yaw), math.sin(yaw)
    rotation = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    moved = transform[:3, :3] @ pivot + transform[:3, 3]
    out = np.eye(4)
    out[:3, :3] = rotation
    out[:3, 3] = moved - rotation @ pivot
    return out


def _cloud(points: np.ndarray) -> o3d.geometry.PointCloud:
    cloud = o3d.geometry.PointCloud()
    cloud.points = o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64))
    return cloud


def crop_to(points: np.ndarray, around: np.ndarray, margin: float) -> np.ndarray:
    low, high = around[:, :2].min(axis=0) - margin, around[:, :2].max(axis=0) + margin
    inside = np.all((points[:, :2] >= low) & (points[:, :2] <= high), axis=1)
    return points[inside]


def overlapping(points: np.ndarray, reference: np.ndarray, cell: float) -> np.ndarray:
    """Which points fall in an x-y cell where the reference has points: the part of a new view the
    map can say anything about (the rest is new ground, and no measure of a misfit)."""
    def keys(xy: np.ndarray) -> np.ndarray:
        ij = np.floor(xy / cell).astype(np.int64)
        return ij[:, 0] * 1_000_003 + ij[:, 1]
    return np.isin(keys(points[:, :2]), np.unique(keys(reference[:, :2])))


def xy_constraint(points: np.ndarray, normals: np.ndarray) -> float:
    """How firmly point-to-plane residuals pin x and y: the smallest eigenvalue of sum(n_xy n_xy^T)
    per point. 0 on a flat floor (it slides freely), up to 0.5 when normals point every way."""
    if len(points) == 0:
        return 0.0
    nxy = normals[:, :2]
    return float(np.linalg.eigvalsh(nxy.T @ nxy / len(points))[0])


def align_to_map(source: np.ndarray, target: np.ndarray, pivot: np.ndarray,
                 config: AlignConfig = AlignConfig()) -> Alignment:
    """The 4-DOF correction that best lays `source` (new points, world frame by odometry) on
    `target` (the map's points); `pivot` is the rover's estimated position."""
    source = np.asarray(source, dtype=np.float64).reshape(-1, 3)
    target = crop_to(np.asarray(target, dtype=np.float64).reshape(-1, 3), source, config.search_margin_m) \
        if len(source) else np.empty((0, 3))
    if len(source) >= 100 and len(target) >= 100:
        source = source[overlapping(source, target, config.overlap_cell_m)]
    if len(source) < 100 or len(target) < 100:
        return identity_alignment(f"too few points to align ({len(source)} new where the map has any, "
                                  f"{len(target)} in the map)")
    pivot = np.asarray(pivot, dtype=np.float64)
    transform = np.eye(4)
    source_full, target_full = _cloud(source), _cloud(target)
    result = None
    for voxel, distance in config.stages:
        src = source_full.voxel_down_sample(voxel)
        tgt = target_full.voxel_down_sample(voxel)
        tgt.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=3 * voxel, max_nn=30))
        tgt.orient_normals_to_align_with_direction(np.array([0.0, 0.0, 1.0]))
        result = o3d.pipelines.registration.registration_icp(
            src, tgt, distance, transform, o3d.pipelines.registration.TransformationEstimationPointToPlane(),
            o3d.pipelines.registration.ICPConvergenceCriteria(max_iteration=config.iterations))
        transform = four_dof(result.transformation, pivot)
    assert result is not None
    voxel, distance = config.stages[-1]
    final = o3d.pipelines.registration.evaluate_registration(src, tgt, distance, transform)
    matched = np.asarray(final.correspondence_set)
    normals = np.asarray(tgt.normals)[matched[:, 1]] if len(matched) else np.empty((0, 3))
    constraint = xy_constraint(matched, normals)
    dx, dy, dz = (float(v) for v in (transform[:3, :3] @ pivot + transform[:3, 3] - pivot))
    dyaw = math.atan2(transform[1, 0], transform[0, 0])
    reason = _refusal(final.fitness, constraint, math.hypot(dx, dy), dz, dyaw, config)
    return Alignment(transform if not reason else np.eye(4), dx, dy, dz, dyaw, float(final.fitness),
                     float(final.inlier_rmse), constraint, not reason, reason)


def _refusal(fitness: float, constraint: float, shift: float, dz: float, dyaw: float, config: AlignConfig) -> str:
    if fitness < config.min_fitness:
        return f"overlap too small (fitness {fitness:.2f} < {config.min_fitness})"
    if constraint < config.min_constraint:
        return f"ground too featureless to fix x and y (constraint {constraint:.3f} < {config.min_constraint})"
    if shift > config.max_translation_m or abs(dz) > config.max_translation_m:
        return f"correction of {shift:.2f} m is larger than odometry can be wrong ({config.max_translation_m} m)"
    if abs(math.degrees(dyaw)) > config.max_rotation_deg:
        return f"heading correction of {math.degrees(dyaw):.1f} deg exceeds {config.max_rotation_deg} deg"
    return ""


def apply(transform: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Points (..., 3) moved by a 4x4 transform."""
    points = np.asarray(points)
    return (points.reshape(-1, 3) @ transform[:3, :3].T + transform[:3, 3]).reshape(points.shape).astype(points.dtype)


def merge_clouds(old: np.ndarray | None, new: np.ndarray, voxel: float) -> np.ndarray:
    """The map's cloud with new points added, thinned to one point (the mean) per voxel."""
    points = new if old is None or len(old) == 0 else np.vstack([old, new])
    if len(points) == 0:
        return np.empty((0, 3), np.float32)
    return np.asarray(_cloud(points).voxel_down_sample(voxel).points, dtype=np.float32)
