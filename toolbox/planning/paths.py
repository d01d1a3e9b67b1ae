"""Paths after the search: world coordinates, straight segments for the rover, and the drivable part.

Cell paths are (K, 2) int arrays of (row, col); waypoints are (M, 2) float arrays of world (x, y)
at cell centres. Geometry on the grid works in continuous cell coordinates (row, col) where a cell's
centre is at its integer index and it spans +-0.5 around it.

Straight segments (thesis 3.3.1): the rover drives straight lines between waypoints, so the A* path
is reduced to few segments that keep every path cell within a deviation limit (Douglas-Peucker),
and a segment that would cross a blocked cell is split like one that deviates too far.

Drivable part (thesis 4.4.2): only the stretch of path inside the local map, at least a margin from
the border of its known cells, is handed out for driving.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import distance_transform_edt

from toolbox.grid import GridSpec

# Crossings of a cell shorter than this (in segment parameter) are corner touches, not crossings.
TOUCH_TOLERANCE = 1e-9


def cells_to_world(spec: GridSpec, cells: np.ndarray) -> np.ndarray:
    """World (x, y) of cell centres for (row, col) cells."""
    cells = np.asarray(cells).reshape(-1, 2)
    x, y = spec.centre_of(cells[:, 0], cells[:, 1])
    return np.stack([np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)], axis=1)


def world_to_cells(spec: GridSpec, points_xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(row, col) cells holding world points, and whether each point is on the grid at all."""
    points_xy = np.asarray(points_xy, dtype=np.float64).reshape(-1, 2)
    rows, cols, inside = spec.cell_of(points_xy[:, 0], points_xy[:, 1])
    return np.stack([rows, cols], axis=1), inside


def world_to_grid(spec: GridSpec, points_xy: np.ndarray) -> np.ndarray:
    """Continuous (row, col) coordinates of world points; cell centres fall on integers."""
    points_xy = np.asarray(points_xy, dtype=np.float64).reshape(-1, 2)
    return np.stack([(points_xy[:, 1] - spec.origin_y) / spec.cell - 0.5,
                     (points_xy[:, 0] - spec.origin_x) / spec.cell - 0.5], axis=1)


def path_length(points_xy: np.ndarray) -> float:
    """Length of a polyline in metres."""
    points_xy = np.asarray(points_xy, dtype=np.float64).reshape(-1, 2)
    return float(np.hypot(*np.diff(points_xy, axis=0).T).sum())


def point_segment_distance(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance from each point to the segment a-b (to the nearer end beyond its ends)."""
    ab = b - a
    length_sq = float(ab @ ab)
    t = np.zeros(len(points)) if length_sq == 0 else np.clip((points - a) @ ab / length_sq, 0.0, 1.0)
    return np.hypot(*(points - (a + t[:, None] * ab)).T)


def douglas_peucker(points: np.ndarray, tolerance: float,
                    segment_ok: Callable[[int, int], bool] | None = None) -> np.ndarray:
    """Indices of the points kept so every point lies within `tolerance` of its segment of the kept polyline.

    A span between kept points is split at its farthest point until it deviates no more than
    `tolerance` and, if given, `segment_ok(first, last)` accepts it."""
    points = np.asarray(points, dtype=np.float64)
    keep = np.zeros(len(points), dtype=bool)
    keep[[0, -1]] = True
    spans = [(0, len(points) - 1)]
    while spans:
        first, last = spans.pop()
        if last - first < 2:
            continue
        deviation = point_segment_distance(points[first + 1:last], points[first], points[last])
        if deviation.max() <= tolerance and (segment_ok is None or segment_ok(first, last)):
            continue
        farthest = first + 1 + int(np.argmax(deviation))
        keep[farthest] = True
        spans += [(first, farthest), (farthest, last)]
    return np.flatnonzero(keep)


def segment_cells(start_rc: np.ndarray, end_rc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cells whose interior the segment crosses, in order, and the parameter t in [0, 1) where it enters each.

    An exact traversal: the segment is cut where it crosses grid lines; each piece lies in one cell.
    A segment through a cell corner touches the two side cells only at a point and does not cross
    them, which is what lets a diagonal A* step squeeze between two blocked cells."""
    a = np.asarray(start_rc, dtype=np.float64) + 0.5  # grid lines on integers from here on
    b = np.asarray(end_rc, dtype=np.float64) + 0.5
    direction = b - a
    cuts = [np.array([0.0, 1.0])]
    for axis in range(2):
        if direction[axis] != 0:
            low, high = sorted((a[axis], b[axis]))
            lines = np.arange(np.floor(low) + 1, np.ceil(high))
            cuts.append((lines - a[axis]) / direction[axis])
    t = np.unique(np.concatenate(cuts))
    pieces = np.flatnonzero(np.diff(t) > TOUCH_TOLERANCE)
    if pieces.size == 0:  # a point, not a segment
        return np.floor(a[None, :]).astype(np.int64), np.zeros(1)
    middle = (t[pieces] + t[pieces + 1]) / 2.0
    cells = np.floor(a + middle[:, None] * direction).astype(np.int64)
    return cells, t[pieces]


def segment_is_clear(blocked: np.ndarray, start_rc: np.ndarray, end_rc: np.ndarray) -> bool:
    """True if the segment crosses no blocked cell and stays on the grid."""
    cells, _ = segment_cells(start_rc, end_rc)
    inside = ((cells >= 0) & (cells < blocked.shape)).all(axis=1)
    return bool(inside.all() and not blocked[cells[:, 0], cells[:, 1]].any())


def simplify_path(cells: np.ndarray, blocked: np.ndarray, max_deviation_cells: float) -> np.ndarray:
    """Indices of the path cells kept as waypoints: straight segments within `max_deviation_cells` of
    the path that cross no blocked cell.

    Douglas-Peucker with one more reason to split a span: a segment that crosses a blocked cell.
    Two neighbouring path cells are always joined by a clear segment, so the splitting ends."""
    cells = np.asarray(cells).reshape(-1, 2)
    if len(cells) < 3:
        return np.arange(len(cells))
    blocked = np.asarray(blocked, dtype=bool)

    def segment_ok(first: int, last: int) -> bool:
        return segment_is_clear(blocked, cells[first], cells[last])

    return douglas_peucker(cells, max_deviation_cells, segment_ok)


def distance_to_border(known: np.ndarray, cell: float) -> np.ndarray:
    """Metres from each cell centre to the centre of the nearest unknown cell; 0 on unknown cells.

    The border is that of the known cells, and the map's own edge counts as one: the grid is padded
    with a ring of unknown cells before the distance transform."""
    padded = np.pad(np.asarray(known, dtype=bool), 1, constant_values=False)
    return distance_transform_edt(padded)[1:-1, 1:-1] * cell


@dataclass(frozen=True)
class DrivablePrefix:
    waypoints: np.ndarray  # (M, 2) world (x, y): the path's start up to the cut (or the whole path)
    complete: bool         # True if the whole path keeps the margin and nothing was cut


def drivable_prefix(waypoints_xy: np.ndarray, spec: GridSpec, border_distance: np.ndarray,
                    margin_m: float) -> DrivablePrefix:
    """The waypoints up to where the path first comes closer than `margin_m` to the local map's border.

    `border_distance` is `distance_to_border` of the local map over `spec`; off the map counts as
    distance 0. The cut point is where the path enters the first cell that is too close, so the
    last waypoint may lie inside a segment. If the start itself is too close, only the start is left."""
    waypoints_xy = np.asarray(waypoints_xy, dtype=np.float64).reshape(-1, 2)
    grid_points = world_to_grid(spec, waypoints_xy)
    for index in range(len(waypoints_xy) - 1):
        cells, entry = segment_cells(grid_points[index], grid_points[index + 1])
        too_close = _border_distance_at(border_distance, cells) < margin_m
        if too_close.any():
            t = entry[int(np.argmax(too_close))]
            head = waypoints_xy[:index + 1]
            if t == 0.0:
                return DrivablePrefix(head, False)
            cut = waypoints_xy[index] + t * (waypoints_xy[index + 1] - waypoints_xy[index])
            return DrivablePrefix(np.vstack([head, cut]), False)
    if len(waypoints_xy) == 1:
        cells, _ = segment_cells(grid_points[0], grid_points[0])
        if _border_distance_at(border_distance, cells)[0] < margin_m:
            return DrivablePrefix(waypoints_xy, False)
    return DrivablePrefix(waypoints_xy, True)


def _border_distance_at(border_distance: np.ndarray, cells: np.ndarray) -> np.ndarray:
    inside = ((cells >= 0) & (cells < border_distance.shape)).all(axis=1)
    distance = np.zeros(len(cells))
    distance[inside] = border_distance[cells[inside, 0], cells[inside, 1]]
    return distance


def mask_near_path(cells: np.ndarray, mask: np.ndarray, cell: float,
                   clearance_m: float) -> tuple[np.ndarray, np.ndarray]:
    """For a path of grid cells (N, 2 rows and columns): which pass within clearance_m of the mask,
    and the mask cell nearest each (N, 2). The mask must hold a cell."""
    cells = np.asarray(cells, dtype=np.int64).reshape(-1, 2)
    distance, (rows, cols) = distance_transform_edt(~mask, return_indices=True)
    near = distance[cells[:, 0], cells[:, 1]] <= clearance_m / cell + 1e-9
    return near, np.column_stack([rows[cells[:, 0], cells[:, 1]], cols[cells[:, 0], cells[:, 1]]])


def first_touch(cells: np.ndarray, mask: np.ndarray, cell: float, clearance_m: float) -> tuple[int, int] | None:
    """The cell of mask that a path of grid cells (N, 2 rows and columns) first passes within
    clearance_m of (the nearest one to the path there), or None if it never does."""
    if not mask.any() or len(cells) == 0:
        return None
    near, nearest = mask_near_path(cells, mask, cell, clearance_m)
    if not near.any():
        return None
    row, col = nearest[int(np.argmax(near))]
    return int(row), int(col)


def short_of_first_touch(drivable: DrivablePrefix, cells: np.ndarray, mask: np.ndarray, spec: GridSpec,
                         clearance_m: float, stop_m: float) -> tuple[DrivablePrefix, bool]:
    """The drivable part cut where it first comes within stop_m of the first cell of mask that the
    path (its grid cells) passes within clearance_m of; and whether it was cut. Ground the path
    only passes later, or never, does not shorten this drive."""
    touch = first_touch(cells, mask, spec.cell, clearance_m)
    if touch is None:
        return drivable, False
    x, y = cells_to_world(spec, np.array([touch]))[0]
    xs, ys = spec.centres()
    cut = drivable_prefix(drivable.waypoints, spec, np.hypot(xs[None, :] - x, ys[:, None] - y), stop_m)
    return (drivable, False) if cut.complete else (cut, True)
