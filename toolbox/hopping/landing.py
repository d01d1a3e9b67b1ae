"""Landing target selection for the next hop on a top-down image of the dense cloud (hopping paper,
"Target selection with uncertainty calculation": obstacle detection, error ellipse, landing point
selection, collision check).

`plan_landing` is the method, step by step, each a small function:
    top_down_maps          the cloud projected to a grid: highest point, mean colour, point count
    ground_plane           RANSAC plane under the cloud (plane)
    protrusion_map         each cell's highest point above that plane
    obstacle_mask          protrusion over a threshold, then median filter and closing (paper: 8 cm)
    known_mask             cells with data, small holes closed by a median filter
    ellipse_safe_mask      cells whose whole landing error ellipse (+ rover radius) avoids hazards
    clearance_map          distance to the nearest hazard (obstacle or unknown)
    goal_map               eq 17: cos of the deviation from the goal heading inside the reach annulus;
                           towards a goal point: the progress made towards it
    selection_score        the weighted blend of clearance and goal maps on the safe cells
    trajectory_collides    the planned parabola against the height map, the rover's radius around it
    launch_to_target       the launch speed, elevation and heading (hopping_ballistics)

Frame: metres, gravity-aligned, z up (the hop frame of hopping_parabola or the world frame); grids are
GridSpec grids (rows northwards = +y). The rover's position is its centre, which rests rover_radius
above the ground. Choices the paper leaves open, documented where they are made:
  - the safe test is exact for every cell (circle bounds from a distance transform decide most cells,
    an exact ellipse test against hazard boundary cells the rest), not a per-pixel mask stamp;
  - the ellipse is computed per candidate from its own distance (a longer hop spreads more) with the
    exact moments of the range equation, and grown by the rover's radius;
  - the clearance map measures distance from hazards, not from the edge of the reachable annulus;
  - cells the cloud never saw count as hazards for landing but not for the collision check (the
    rocks that hide them are in the cloud and are checked);
  - a rejected candidate takes its ellipse with it (paper), and at most max_candidates are examined.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from scipy.ndimage import binary_erosion, distance_transform_edt
from scipy.spatial import cKDTree

from toolbox.grid import GridSpec
from toolbox.hopping.ballistics import (
    CHI2_2D_95,
    LandingEllipse,
    Launch,
    ballistic_positions,
    landing_error_ellipse,
    launch_to_target,
    speed_for_target,
)
from toolbox.hopping.parabola import MOON_GRAVITY
from toolbox.hopping.plane import Plane, ransac_plane


class NoGroundError(ValueError):
    """The cloud holds no ground around the start: the start (the estimated touchdown) or the cloud is wrong."""


@dataclass(frozen=True)
class LandingParams:
    cell: float = 0.025                    # grid cell, m (paper: 1.2 cm)
    gravity: float = MOON_GRAVITY
    ground_tolerance: float = 0.02         # RANSAC inlier distance for the ground plane, m
    obstacle_threshold: float = 0.08       # protrusion above the ground that makes an obstacle (paper: 8 cm)
    median_px: int = 5                     # median filter on the masks, pixels (odd)
    closing_px: int = 5                    # closing of the obstacle mask, pixels
    min_distance: float = 0.5              # hop distance limits, m
    max_distance: float = 2.0
    max_heading_deviation: float = np.pi / 2  # from the goal direction (paper: 90 degrees)
    elevation: float | None = np.radians(60.0)  # fixed elevation (paper prefers 60 degrees) ...
    speed: float | None = None             # ... or a fixed launch speed (set elevation=None)
    sigma_speed: float = 0.05              # launch errors, 1-sigma: m/s, rad, rad, m
    sigma_elevation: float = np.radians(3.0)
    sigma_heading: float = np.radians(3.0)
    sigma_position: float = 0.05
    ellipse_sigmas: float = CHI2_2D_95     # the ellipse drawn is this many sigmas (95 % by default)
    rover_radius: float = 0.1              # largest protrusion of the body from its centre, m
    safety_weight: float = 0.5             # blend of the clearance and goal maps
    goal_weight: float = 0.5
    clearance_saturation: float | None = None  # clearance counted up to this, m; None: the best candidate's
    collision_samples: int = 200           # points along the parabola
    collision_min_hits: int = 2            # samples in collision before a trajectory is refused (outliers)
    max_candidates: int = 50

    def __post_init__(self) -> None:
        if (self.elevation is None) == (self.speed is None):
            raise ValueError("set exactly one of elevation and speed")
        if not 0 < self.min_distance < self.max_distance:
            raise ValueError(f"need 0 < min_distance < max_distance, got {self.min_distance}, {self.max_distance}")
        for name in ("median_px", "closing_px"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0")


@dataclass(frozen=True)
class TopDown:
    height: np.ndarray       # highest point per cell, NaN where no point fell
    colour: np.ndarray | None  # mean colour per cell (rows, cols, channels), NaN where no point fell
    count: np.ndarray        # points per cell


@dataclass(frozen=True)
class LandingPlan:
    found: bool
    reason: str                       # "" when found; no_candidate or all_candidates_rejected
    spec: GridSpec
    top_down: TopDown = field(repr=False)
    ground: Plane
    protrusion: np.ndarray = field(repr=False)   # highest protrusion above the ground per cell, NaN unknown
    known: np.ndarray = field(repr=False)        # bool, cells with data after the median filter
    obstacle: np.ndarray = field(repr=False)     # bool, after median filter and closing
    safe: np.ndarray = field(repr=False)         # bool, reachable cells whose whole ellipse is clear
    clearance: np.ndarray = field(repr=False)    # m to the nearest hazard (obstacle or unknown)
    goal: np.ndarray = field(repr=False)         # goal map in [0, 1]
    score: np.ndarray = field(repr=False)        # selection score on safe cells, NaN elsewhere
    target: np.ndarray                # (3,) the chosen landing centre; NaN if none
    target_cell: tuple[int, int] | None
    ellipse: LandingEllipse | None    # the target's error ellipse (1-sigma along / across)
    ellipse_axes: tuple[float, float] | None  # semi-axes drawn (n sigma + rover radius), m
    launch: Launch | None
    trajectory: np.ndarray = field(repr=False)   # (M, 3) the planned flight; empty if none
    rejected: list = field(default_factory=list)  # [(x, y, reason)] candidates refused on the way


# ----------------------------------------------------------------------------------- the image
def top_down_maps(points: np.ndarray, spec: GridSpec, colours: np.ndarray | None = None) -> TopDown:
    """Project the cloud onto the grid: highest z and mean colour per cell (paper: the arithmetic mean
    of each colour channel), and the point count."""
    points = np.asarray(points, dtype=np.float64)
    row, col, inside = spec.cell_of(points[:, 0], points[:, 1])
    flat = (row * spec.cols + col)[inside]
    z = points[inside, 2]
    size = spec.rows * spec.cols
    count = np.bincount(flat, minlength=size)
    height = np.full(size, -np.inf)
    np.maximum.at(height, flat, z)
    height[count == 0] = np.nan
    colour = None
    if colours is not None:
        colours = np.asarray(colours, dtype=np.float64)[inside]
        sums = np.stack([np.bincount(flat, channel, minlength=size) for channel in colours.T], axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            colour = (sums / count[:, None]).reshape(spec.rows, spec.cols, -1)
    return TopDown(height.reshape(spec.shape), colour, count.reshape(spec.shape))


def ground_plane(points: np.ndarray, tolerance: float, rng: np.random.Generator | int | None = 0) -> Plane:
    """RANSAC ground plane (rocks cannot tilt it), normal pointing up. The ground may be a slope, so the
    plane is not forced horizontal (paper)."""
    plane, _ = ransac_plane(np.asarray(points, dtype=np.float64), tolerance, rng=rng)
    return plane.oriented(np.array([0.0, 0.0, 1.0]))


def protrusion_map(points: np.ndarray, spec: GridSpec, plane: Plane) -> np.ndarray:
    """Highest distance above the ground plane of the points in each cell; NaN where none fell."""
    points = np.asarray(points, dtype=np.float64)
    row, col, inside = spec.cell_of(points[:, 0], points[:, 1])
    above = np.full(spec.rows * spec.cols, -np.inf)
    np.maximum.at(above, (row * spec.cols + col)[inside], plane.signed_distance(points[inside]))
    above[np.isneginf(above)] = np.nan
    return above.reshape(spec.shape)


def median_filter_mask(mask: np.ndarray, size: int) -> np.ndarray:
    if size <= 1:
        return mask.copy()
    return cv2.medianBlur(mask.astype(np.uint8) * 255, size | 1) > 127


def known_mask(count: np.ndarray, median_px: int) -> np.ndarray:
    """Cells with data; the median filter closes the isolated empty pixels of a sparse far field
    (paper) while large unseen areas stay unknown."""
    return median_filter_mask(count > 0, median_px)


def obstacle_mask(protrusion: np.ndarray, threshold: float, median_px: int, closing_px: int) -> np.ndarray:
    """Protrusion over the threshold, then median filter (noise) and closing (dilation then erosion)
    to make uniform areas (paper, Fig 12)."""
    mask = median_filter_mask(np.nan_to_num(protrusion, nan=-np.inf) > threshold, median_px)
    if closing_px > 1:
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (closing_px, closing_px))
        mask = cv2.morphologyEx(mask.astype(np.uint8), cv2.MORPH_CLOSE, kernel) > 0
    return mask


# ------------------------------------------------------------------------------ where to land
def clearance_map(hazard: np.ndarray, cell: float) -> np.ndarray:
    """Metres from each cell centre to the nearest hazard cell centre; beyond the grid counts as hazard."""
    padded = np.pad(hazard, 1, constant_values=True)
    return distance_transform_edt(~padded)[1:-1, 1:-1] * cell


def reach_geometry(spec: GridSpec, start_xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(distance, direction angle) from the start to every cell centre."""
    xs, ys = spec.centres()
    dx, dy = xs[None, :] - start_xy[0], ys[:, None] - start_xy[1]
    return np.hypot(dx, dy), np.arctan2(dy, dx)


def goal_map(spec: GridSpec, start_xy: np.ndarray, min_distance: float, max_distance: float,
             max_heading_deviation: float = np.pi / 2, goal_heading: float | None = None,
             goal_xy: np.ndarray | None = None) -> np.ndarray:
    """Eq 17: cos(deviation from the goal heading) on cells within [d_min, d_max] and the allowed
    deviation, 0 elsewhere. With a goal point instead, the progress towards it, (D0 - |cell - goal|) /
    min(D0, d_max) in [0, 1], so a reachable goal itself scores 1 and longer useful hops score higher."""
    distance, angle = reach_geometry(spec, start_xy)
    if goal_xy is not None:
        goal_xy = np.asarray(goal_xy, dtype=np.float64)
        goal_heading = float(np.arctan2(goal_xy[1] - start_xy[1], goal_xy[0] - start_xy[0]))
    if goal_heading is None:
        raise ValueError("give a goal heading or a goal point")
    deviation = np.abs(np.angle(np.exp(1j * (angle - goal_heading))))
    reachable = (distance >= min_distance) & (distance <= max_distance) & (deviation <= max_heading_deviation)
    if goal_xy is None:
        value = np.cos(deviation)
    else:
        xs, ys = spec.centres()
        d0 = float(np.hypot(*(goal_xy - start_xy)))
        left = np.hypot(xs[None, :] - goal_xy[0], ys[:, None] - goal_xy[1])
        value = (d0 - left) / max(min(d0, max_distance), 1e-9)
    return np.where(reachable, np.clip(value, 0.0, 1.0), 0.0)


def candidate_ellipse(start_xy: np.ndarray, target_xy: np.ndarray | tuple[float, float],
                      params: LandingParams) -> LandingEllipse:
    """The landing error ellipse of a hop to target on flat ground (the paper's assumption)."""
    distance = float(np.hypot(*(np.asarray(target_xy) - start_xy)))
    elevation, speed = _flat_launch(distance, params)
    return landing_error_ellipse(speed, elevation, params.sigma_speed, params.sigma_elevation,
                                 params.sigma_heading, params.sigma_position, params.gravity)


def _flat_launch(distance: float, params: LandingParams) -> tuple[float, float]:
    if params.elevation is not None:
        return params.elevation, speed_for_target(distance, 0.0, params.elevation, params.gravity)
    # Fixed speed: the steep elevation for this distance, sin(2 theta) = g d / v^2.
    assert params.speed is not None   # LandingParams holds exactly one of elevation and speed
    ratio = min(1.0, params.gravity * distance / params.speed ** 2)
    return float(np.pi / 2 - 0.5 * np.arcsin(ratio)), params.speed


def ellipse_semi_axes(distances: np.ndarray, params: LandingParams) -> np.ndarray:
    """(N, 2) drawn semi-axes (along, across) for hops of these distances: the ellipse is a smooth
    function of distance, so it is tabulated on 256 distances and interpolated."""
    table_d = np.linspace(max(float(np.min(distances)), 1e-6), max(float(np.max(distances)), 1e-6) + 1e-9, 256)
    table = np.array([candidate_ellipse(np.zeros(2), (d, 0.0), params).semi_axes(params.ellipse_sigmas,
                                                                                  params.rover_radius)
                      for d in table_d])
    return np.column_stack([np.interp(distances, table_d, table[:, k]) for k in range(2)])


def ellipse_safe_mask(hazard: np.ndarray, spec: GridSpec, start_xy: np.ndarray, candidates: np.ndarray,
                      params: LandingParams) -> tuple[np.ndarray, np.ndarray]:
    """Candidates whose whole ellipse (n-sigma semi-axes + rover radius, major axis along the hop) lies
    clear of hazards; returns (safe mask, (rows, cols, 2) semi-axes map, NaN off the candidates).

    Exact per cell: a cell whose nearest hazard is farther than its major semi-axis is safe, nearer
    than its minor semi-axis is not; the rest are tested against the hazard boundary cells within the
    major semi-axis (the boundary suffices: the segment from a clear centre to any hazard cell inside
    the convex ellipse crosses a boundary cell that is inside too)."""
    rows, cols = np.nonzero(candidates)
    axes = np.full(spec.shape + (2,), np.nan)
    safe = np.zeros(spec.shape, dtype=bool)
    if len(rows) == 0:
        return safe, axes
    xs, ys = spec.centre_of(rows, cols)
    heading = np.arctan2(ys - start_xy[1], xs - start_xy[0])
    semi = ellipse_semi_axes(np.hypot(xs - start_xy[0], ys - start_xy[1]), params)
    axes[rows, cols] = semi
    clearance = clearance_map(hazard, spec.cell)[rows, cols]
    verdict = np.where(clearance > semi[:, 0], 1, np.where(clearance <= semi[:, 1], 0, -1))
    unsure = np.nonzero(verdict == -1)[0]
    if len(unsure):
        padded = np.pad(hazard, 1, constant_values=True)
        boundary = padded & ~binary_erosion(padded, np.ones((3, 3), dtype=bool), border_value=1)
        brow, bcol = np.nonzero(boundary)
        bx, by = spec.centre_of(brow - 1, bcol - 1)
        tree = cKDTree(np.column_stack([bx, by]))
        near = tree.query_ball_point(np.column_stack([xs[unsure], ys[unsure]]), semi[unsure, 0] + 1e-9)
        for k, hits in zip(unsure, near, strict=True):
            hx, hy = bx[hits] - xs[k], by[hits] - ys[k]
            c, s = np.cos(heading[k]), np.sin(heading[k])
            along, across = hx * c + hy * s, -hx * s + hy * c
            verdict[k] = int(not np.any((along / semi[k, 0]) ** 2 + (across / semi[k, 1]) ** 2 <= 1.0))
    safe[rows, cols] = verdict == 1
    return safe, axes


def selection_score(clearance: np.ndarray, goal: np.ndarray, safe: np.ndarray,
                    params: LandingParams) -> np.ndarray:
    """Pixel-wise weighted average of the normalised clearance map and the goal map on safe cells (paper:
    the blend of the distance and gradient maps); NaN where landing is not allowed."""
    if not safe.any():
        return np.full(safe.shape, np.nan)
    saturation = params.clearance_saturation or float(clearance[safe].max())
    safety = np.clip(clearance / max(saturation, 1e-9), 0.0, 1.0)
    weights = params.safety_weight + params.goal_weight
    blend = (params.safety_weight * safety + params.goal_weight * goal) / weights
    return np.where(safe, blend, np.nan)


# --------------------------------------------------------------------------- the flight
def swept_height(height: np.ndarray, spec: GridSpec, radius: float) -> np.ndarray:
    """Highest terrain within `radius` horizontally of each cell (a disk-shaped grey dilation);
    cells with no data count as -inf, so they never collide."""
    terrain = np.nan_to_num(height, nan=-1e6).astype(np.float32)
    r = max(0, int(np.ceil(radius / spec.cell)))
    if r == 0:
        return terrain.astype(np.float64)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    return cv2.dilate(terrain, kernel, borderType=cv2.BORDER_CONSTANT, borderValue=-1e6).astype(np.float64)


def trajectory_collides(trajectory: np.ndarray, swept: np.ndarray, spec: GridSpec, rover_radius: float,
                        ignore_near: tuple[np.ndarray, ...] = (), tolerance: float = 0.02,
                        min_hits: int = 2) -> tuple[bool, np.ndarray]:
    """Collision check along the planned parabola (paper: points closer to the trajectory than the rover's
    largest protrusion, at least a few of them): the rover's underside, rover_radius below its centre,
    must clear the highest terrain within rover_radius (swept height) by `tolerance`. Samples within
    2 rover radii of the points in ignore_near (start and target, where the rover touches the ground
    by design) are skipped. Returns (collides, per-sample hit mask)."""
    trajectory = np.asarray(trajectory, dtype=np.float64)
    row, col, inside = spec.cell_of(trajectory[:, 0], trajectory[:, 1])
    terrain = np.full(len(trajectory), -np.inf)
    terrain[inside] = swept[row[inside], col[inside]]
    hits = terrain > trajectory[:, 2] - rover_radius + tolerance
    for point in ignore_near:
        hits &= np.hypot(*(trajectory[:, :2] - np.asarray(point)[:2]).T) > 2 * rover_radius
    return bool(hits.sum() >= min_hits), hits


# ------------------------------------------------------------------------------ the method
def plan_landing(points: np.ndarray, start: np.ndarray, goal_heading: float | None = None,
                 goal_xy: np.ndarray | None = None, params: LandingParams = LandingParams(),
                 colours: np.ndarray | None = None, rng: np.random.Generator | int | None = 0) -> LandingPlan:
    """Choose the next landing target around `start` (the rover's centre, 3-D) on the dense cloud
    (metric, z up) towards a goal heading (rad, counter-clockwise from +x) or a goal point."""
    start = np.asarray(start, dtype=np.float64)
    # Half the map is a little more than the longest hop plus its ellipse (paper: "somewhat bigger").
    far = candidate_ellipse(start[:2], start[:2] + [params.max_distance, 0], params)
    half = params.max_distance + far.semi_axes(params.ellipse_sigmas, params.rover_radius)[0] + 2 * params.cell
    spec = GridSpec.covering((start[0] - half, start[0] + half), (start[1] - half, start[1] + half), params.cell)
    points = np.asarray(points, dtype=np.float64)
    _, _, inside = spec.cell_of(points[:, 0], points[:, 1])
    points = points[inside]
    if len(points) < 3:
        raise NoGroundError(f"the dense cloud has {len(points)} points within {half:.1f} m of the estimated "
                            f"touchdown ({start[0]:.2f}, {start[1]:.2f}): the two disagree")
    # Project the cloud to a top-down image.
    top = top_down_maps(points, spec, None if colours is None else np.asarray(colours)[inside])
    # RANSAC ground plane; protrusion above it makes obstacles (median filter, closing).
    plane = ground_plane(points, params.ground_tolerance, rng)
    protrusion = protrusion_map(points, spec, plane)
    obstacle = obstacle_mask(protrusion, params.obstacle_threshold, params.median_px, params.closing_px)
    known = known_mask(top.count, params.median_px)
    hazard = obstacle | ~known
    # Goal map (eq 17) on the reachable annulus; the cells where the whole error ellipse is clear.
    goal = goal_map(spec, start[:2], params.min_distance, params.max_distance, params.max_heading_deviation,
                    goal_heading, goal_xy)
    reachable = goal > 0
    safe, _ = ellipse_safe_mask(hazard, spec, start[:2], reachable, params)
    # Clearance (distance transform) blended with the goal map: the selection image.
    clearance = clearance_map(hazard, spec.cell)
    score = selection_score(clearance, goal, safe, params)
    # Best candidates first: launch to reach it, parabola against the terrain, else drop its ellipse.
    swept = swept_height(top.height, spec, params.rover_radius)
    open_score = np.nan_to_num(score, nan=-np.inf)
    rejected: list = []
    maps: dict[str, Any] = dict(spec=spec, top_down=top, ground=plane, protrusion=protrusion, known=known,
                                obstacle=obstacle, safe=safe, clearance=clearance, goal=goal, score=score)
    for _ in range(params.max_candidates):
        flat = int(np.argmax(open_score))
        if not np.isfinite(open_score.flat[flat]):
            break
        row, col = divmod(flat, spec.cols)
        x, y = spec.centre_of(row, col)
        target = np.array([x, y, _plane_height(plane, x, y) + params.rover_radius])
        launch = launch_to_target(start, target, params.gravity, params.elevation, params.speed)
        ellipse = candidate_ellipse(start[:2], target[:2], params)
        axes = ellipse.semi_axes(params.ellipse_sigmas, params.rover_radius)
        if launch is None:
            reason = "out_of_reach"
        else:
            trajectory = ballistic_positions(start, launch.velocity,
                                             np.linspace(0, launch.flight_time, params.collision_samples),
                                             params.gravity)
            collides, _ = trajectory_collides(trajectory, swept, spec, params.rover_radius, (start, target),
                                              params.ground_tolerance, params.collision_min_hits)
            if not collides:
                return LandingPlan(True, "", target=target, target_cell=(row, col), ellipse=ellipse,
                                   ellipse_axes=axes, launch=launch, trajectory=trajectory, rejected=rejected,
                                   **maps)
            reason = "collision"
        rejected.append((float(x), float(y), reason))
        open_score[_ellipse_cells(spec, target[:2], start[:2], axes)] = -np.inf
    reason = "all_candidates_rejected" if rejected else "no_candidate"
    return LandingPlan(False, reason, target=np.full(3, np.nan), target_cell=None, ellipse=None, ellipse_axes=None,
                       launch=None, trajectory=np.empty((0, 3)), rejected=rejected, **maps)


def _plane_height(plane: Plane, x: float, y: float) -> float:
    n = plane.normal
    return float(-(plane.offset + n[0] * x + n[1] * y) / n[2])


def _ellipse_cells(spec: GridSpec, centre: np.ndarray, start_xy: np.ndarray,
                   axes: tuple[float, float]) -> np.ndarray:
    """Mask of the cells inside an ellipse whose major axis points along the hop from start_xy."""
    xs, ys = spec.centres()
    heading = np.arctan2(centre[1] - start_xy[1], centre[0] - start_xy[0])
    dx, dy = xs[None, :] - centre[0], ys[:, None] - centre[1]
    along = dx * np.cos(heading) + dy * np.sin(heading)
    across = -dx * np.sin(heading) + dy * np.cos(heading)
    return (along / axes[0]) ** 2 + (across / axes[1]) ** 2 <= 1.0
