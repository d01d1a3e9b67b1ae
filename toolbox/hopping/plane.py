"""Planes for the hopping rover: the flight plane through a hop's camera centres and the ground plane
under its dense cloud (hopping paper, "Trajectory and scale estimation" and "Obstacle detection").

Both are RANSAC planes [paper ref. 14] refined by least squares on their inliers: RANSAC keeps badly
placed cameras and rocks from tilting the plane, the refit removes the noise of a 3-point sample.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Plane:
    normal: np.ndarray  # (3,) unit normal
    offset: float       # points p on the plane satisfy normal . p + offset = 0

    def signed_distance(self, points: np.ndarray) -> np.ndarray:
        return np.asarray(points, dtype=np.float64) @ self.normal + self.offset

    def project(self, points: np.ndarray) -> np.ndarray:
        points = np.asarray(points, dtype=np.float64)
        return points - np.outer(self.signed_distance(points), self.normal)

    def oriented(self, up: np.ndarray) -> Plane:
        """The same plane with its normal on the side of `up` (so signed distance is height above it)."""
        return self if float(self.normal @ up) >= 0 else Plane(-self.normal, -self.offset)


def fit_plane_lsq(points: np.ndarray) -> Plane:
    """Total least-squares plane: through the centroid, normal = direction of least spread (SVD)."""
    points = np.asarray(points, dtype=np.float64)
    if len(points) < 3:
        raise ValueError(f"a plane needs at least 3 points, got {len(points)}")
    centroid = points.mean(axis=0)
    normal = np.linalg.svd(points - centroid, full_matrices=False)[2][-1]
    return Plane(normal, -float(normal @ centroid))


def ransac_plane(points: np.ndarray, threshold: float, iterations: int = 300,
                 rng: np.random.Generator | int | None = 0, score_points: int = 8000) -> tuple[Plane, np.ndarray]:
    """RANSAC plane with a least-squares refit on the consensus set; returns (plane, inlier mask).

    Samples are scored in vectorised batches on at most score_points random points (a dense cloud's
    consensus is just as clear on a subset); ties in the inlier count go to the smaller sum of
    inlier distances (MSAC-like). The refit and the returned inliers use every point."""
    points = np.asarray(points, dtype=np.float64)
    if len(points) < 3:
        raise ValueError(f"a plane needs at least 3 points, got {len(points)}")
    if not threshold > 0:
        raise ValueError(f"threshold must be > 0, got {threshold!r}")
    rng = np.random.default_rng(rng)
    scored = points
    if len(points) > score_points:
        scored = points[rng.choice(len(points), score_points, replace=False)]
    triples = np.array([rng.choice(len(scored), 3, replace=False) for _ in range(iterations)])
    a, b, c = scored[triples[:, 0]], scored[triples[:, 1]], scored[triples[:, 2]]
    normals = np.cross(b - a, c - a)
    norms = np.linalg.norm(normals, axis=1)
    good = norms > 1e-12 * max(1.0, float(np.ptp(points, axis=0).max()) ** 2)
    if not good.any():
        raise ValueError("the points are collinear: no plane through them")
    normals, a = normals[good] / norms[good, None], a[good]
    best_score, best = None, None
    # Score in chunks so a big cloud does not build an (iterations x points) matrix at once.
    for start in range(0, len(normals), 32):
        n, p0 = normals[start:start + 32], a[start:start + 32]
        dist = np.abs(scored @ n.T - np.sum(n * p0, axis=1))  # (points, samples)
        inside = dist < threshold
        counts = inside.sum(axis=0)
        cost = np.where(inside, dist, threshold).sum(axis=0)
        for k in range(len(n)):
            score = (counts[k], -cost[k])
            if best_score is None or score > best_score:
                best_score, best = score, Plane(n[k], -float(n[k] @ p0[k]))
    assert best is not None   # at least one non-degenerate sample was scored
    inliers = np.abs(best.signed_distance(points)) < threshold
    # Refit on the consensus set, then take the consensus of the refined plane.
    if inliers.sum() >= 3:
        refined = fit_plane_lsq(points[inliers])
        refined_inliers = np.abs(refined.signed_distance(points)) < threshold
        if refined_inliers.sum() >= inliers.sum():
            best, inliers = refined, refined_inliers
    return best, inliers


def plane_basis(normal: np.ndarray, first_axis_hint: np.ndarray | None = None) -> np.ndarray:
    """3x3 rotation whose rows are (e1, e2, normal): a right-handed basis with e1, e2 in the plane.

    e1 follows the hint projected into the plane when one is given (e.g. the direction of flight)."""
    normal = np.asarray(normal, dtype=np.float64)
    normal = normal / np.linalg.norm(normal)
    hint = np.asarray(first_axis_hint, dtype=np.float64) if first_axis_hint is not None else None
    if hint is None or np.linalg.norm(hint - (hint @ normal) * normal) < 1e-9 * max(1.0, float(np.linalg.norm(hint))):
        hint = np.eye(3)[int(np.argmin(np.abs(normal)))]
    e1 = hint - (hint @ normal) * normal
    e1 /= np.linalg.norm(e1)
    return np.array([e1, np.cross(normal, e1), normal])
