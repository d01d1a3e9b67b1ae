"""Planning maps and their fusion: a global map with the rover's local maps laid over it.

A planning map is three layers on one GridSpec: the terrain cost of each cell (see planning_costs),
the hazard mask, and the mask of cells nobody has seen. Local maps come at their own cell sizes and
are resampled onto the global grid. The fusion is conservative, the worst of what any map says:

  - hazard: a global cell is a hazard if any map has a hazard anywhere in the area it covers;
  - cost: the largest cost any map gives to any part of the cell's area;
  - unknown: a cell stays unknown only while no map knows any part of it.

So a local map can add hazards and raise costs but never clear a global hazard; where the maps
disagree, the rover takes the safer reading. Without a global map, a blank one (all unknown) spans
the start, the goal and the local maps, with a margin, as in the thesis's `navigate`.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.ndimage import binary_fill_holes, label

from toolbox.grid import GridSpec, MapLayers
from toolbox.planning.paths import mask_near_path

# Overlaps thinner than this fraction of a cell are shared edges, not coverage.
EDGE_TOLERANCE = 1e-9


@dataclass(frozen=True)
class FusedLayers(MapLayers):
    """Fused layers, and per cell how far from it the look that decided it stood (inf: no look)."""

    seen_from: np.ndarray | None = field(default=None, repr=False)


def blank_map(spec: GridSpec) -> MapLayers:
    """A map of nothing known: every cell unknown, no hazards."""
    return MapLayers(spec, np.full(spec.shape, np.nan), np.zeros(spec.shape, bool), np.ones(spec.shape, bool))


def blank_map_spanning(start_xy: Sequence[float], goal_xy: Sequence[float], cell: float, margin_m: float,
                       local_maps: Sequence[MapLayers] = ()) -> MapLayers:
    """A blank global map covering start, goal and the local maps, `margin_m` wider on every side."""
    xs = [start_xy[0], goal_xy[0]] + [x for m in local_maps for x in m.spec.x_range]
    ys = [start_xy[1], goal_xy[1]] + [y for m in local_maps for y in m.spec.y_range]
    spec = GridSpec.covering((min(xs) - margin_m, max(xs) + margin_m),
                             (min(ys) - margin_m, max(ys) + margin_m), cell)
    return blank_map(spec)


def overlap_ranges(src_origin: float, src_cell: float, src_count: int,
                   dst_origin: float, dst_cell: float) -> tuple[np.ndarray, np.ndarray]:
    """Along one axis: for each source cell, the first and last destination cell its extent overlaps."""
    low = (src_origin + np.arange(src_count) * src_cell - dst_origin) / dst_cell
    high = low + src_cell / dst_cell
    first = np.floor(low + EDGE_TOLERANCE).astype(np.int64)
    last = np.ceil(high - EDGE_TOLERANCE).astype(np.int64) - 1
    return first, last


def resample_onto(local: MapLayers, target: GridSpec) -> MapLayers:
    """A local map on another grid: per target cell, any hazard, the max known cost, unknown if none known.

    Each local cell is spread over every target cell its square overlaps, whichever grid is finer."""
    row_first, row_last = overlap_ranges(local.spec.origin_y, local.spec.cell, local.spec.rows,
                                         target.origin_y, target.cell)
    col_first, col_last = overlap_ranges(local.spec.origin_x, local.spec.cell, local.spec.cols,
                                         target.origin_x, target.cell)
    cost = np.full(target.shape, -np.inf)
    hazard = np.zeros(target.shape, dtype=bool)
    known = np.zeros(target.shape, dtype=bool)
    local_known = ~local.unknown & ~local.hazard
    for row_step in range(int((row_last - row_first).max()) + 1):
        rows = row_first + row_step
        row_ok = (rows <= row_last) & (rows >= 0) & (rows < target.rows)
        for col_step in range(int((col_last - col_first).max()) + 1):
            cols = col_first + col_step
            col_ok = (cols <= col_last) & (cols >= 0) & (cols < target.cols)
            inside = row_ok[:, None] & col_ok[None, :]
            target_rows = np.broadcast_to(rows[:, None], inside.shape)
            target_cols = np.broadcast_to(cols[None, :], inside.shape)
            spread = inside & local.hazard
            hazard[target_rows[spread], target_cols[spread]] = True
            spread = inside & local_known
            np.maximum.at(cost, (target_rows[spread], target_cols[spread]), local.cost[spread])
            known[target_rows[spread], target_cols[spread]] = True
    return MapLayers(target, np.where(known, cost, np.nan), hazard, ~known)


def fuse_maps(global_map: MapLayers, local_maps: Sequence[MapLayers]) -> MapLayers:
    """The global map with every local map resampled onto it, by the conservative rule above."""
    spec = global_map.spec
    cost = np.where(global_map.unknown, -np.inf, global_map.cost)
    hazard = global_map.hazard.copy()
    unknown = global_map.unknown.copy()
    for local in local_maps:
        part = resample_onto(local, spec)
        hazard |= part.hazard
        cost = np.maximum(cost, np.where(part.unknown, -np.inf, part.cost))
        unknown &= part.unknown
    return MapLayers(spec, np.where(unknown, np.nan, cost), hazard, unknown)


def fuse_nearest(global_map: MapLayers, local_maps: Sequence[MapLayers],
                 observers_xy: Sequence[Sequence[float]], sticky_range_m: float = 0.0) -> FusedLayers:
    """The global map with each cell taken from the local map whose observer stood nearest to it.

    For a rover that maps as it goes: a rock seen at the edge of one map (far, noisy, a few pixels)
    is seen again from close by later, and the close look should decide. Unlike `fuse_maps`, a later,
    nearer map can clear a hazard, and unknown in one map never hides what another knows. A hazard
    any map saw from within `sticky_range_m` stays, whoever saw the cell nearest: a close look is
    trusted whichever came first. Cells no local map knows keep the global map's layers. seen_from
    is the distance from each cell to the observer that decided it."""
    if len(local_maps) != len(observers_xy):
        raise ValueError(f"{len(local_maps)} maps but {len(observers_xy)} observer positions")
    spec = global_map.spec
    xs, ys = spec.centres()
    cost, hazard, unknown = global_map.cost.copy(), global_map.hazard.copy(), global_map.unknown.copy()
    best = np.full(spec.shape, np.inf)
    close_hazard = np.zeros(spec.shape, bool)
    for local, (ox, oy) in zip(local_maps, observers_xy, strict=True):
        part = resample_onto(local, spec)
        distance = np.hypot(xs[None, :] - ox, ys[:, None] - oy)
        take = ~part.unknown & (distance < best)
        best = np.where(take, distance, best)
        cost = np.where(take, part.cost, cost)
        hazard = np.where(take, part.hazard, hazard)
        unknown = np.where(take, False, unknown)
        close_hazard |= part.hazard & (distance <= sticky_range_m)
    hazard |= close_hazard
    unknown &= ~close_hazard
    return FusedLayers(spec, np.where(hazard | unknown, np.nan, cost), hazard, unknown, seen_from=best)


def enclosed_unknown(layers: MapLayers, min_cells: int = 1, exempt: np.ndarray | None = None) -> np.ndarray:
    """Unknown cells walled in by known ground: the holes of a map, as opposed to its unexplored
    outside. Cells in `exempt` (the blind ring round where the rover started, which no look of its
    own could see) are never holes, and components smaller than min_cells (a dropped pixel or two)
    are left out.

    A hole in ground the sensor looked at is where it got nothing back: a rock's shadow, or a rock
    the stereo pair could not match (a dark, shadowed face). Seen from all sides and still empty,
    such a hole is a rock far more often than free ground, so the caller can treat it as one."""
    known = ~layers.unknown
    holes = binary_fill_holes(known) & layers.unknown
    if exempt is not None:
        holes &= ~exempt
    labels, count = label(holes, structure=np.ones((3, 3), bool))
    if count == 0:
        return holes
    drop = np.bincount(labels.ravel(), minlength=count + 1) < min_cells
    drop[0] = True
    return ~drop[labels]


def holes_on_path(cells: np.ndarray, holes: np.ndarray, cell: float, clearance_m: float) -> np.ndarray:
    """The holes (8-connected parts of the mask) that a path of grid cells (N, 2 rows and columns)
    passes within clearance_m of: those that would have closed its way as grown hazards."""
    labels, count = label(holes, structure=np.ones((3, 3), bool))
    if count == 0 or len(cells) == 0:
        return np.zeros(holes.shape, bool)
    near, nearest = mask_near_path(cells, holes, cell, clearance_m)
    crossed = labels[nearest[near, 0], nearest[near, 1]]
    return np.isin(labels, crossed[crossed > 0])


def inside_box(x: float | np.ndarray, y: float | np.ndarray, box: tuple[float, float, float, float]) -> np.ndarray:
    """Whether world points (arrays broadcast) lie in the box (x_min, x_max, y_min, y_max), metres."""
    x_min, x_max, y_min, y_max = box
    return (np.asarray(x) >= x_min) & (np.asarray(x) <= x_max) & (np.asarray(y) >= y_min) & (np.asarray(y) <= y_max)


def outside_box(spec: GridSpec, box: tuple[float, float, float, float]) -> np.ndarray:
    """Cells whose centre lies outside the box (x_min, x_max, y_min, y_max), world metres."""
    xs, ys = spec.centres()
    return ~inside_box(xs[None, :], ys[:, None], box)


def hazards_onto(spec: GridSpec, source: GridSpec, hazard: np.ndarray) -> np.ndarray:
    """Another grid's hazard cells on `spec`: a cell of `spec` that holds a hazard cell's centre is a
    hazard (any of them: a rock one fine cell wide stays a rock on a coarser grid)."""
    rows, cols = np.nonzero(hazard)
    mask = np.zeros(spec.shape, dtype=bool)
    if len(rows):
        row, col, inside = spec.cell_of(source.origin_x + (cols + 0.5) * source.cell,
                                        source.origin_y + (rows + 0.5) * source.cell)
        mask[row[inside], col[inside]] = True
    return mask


def with_hazards(layers: MapLayers, mask: np.ndarray) -> MapLayers:
    """The map with the cells of mask made hazards."""
    return MapLayers(layers.spec, np.where(mask, np.inf, layers.cost), layers.hazard | mask, layers.unknown & ~mask)


def with_unknown(layers: MapLayers, mask: np.ndarray) -> MapLayers:
    """The map with the cells of mask made unknown again, hazards or not."""
    return MapLayers(layers.spec, np.where(mask, np.nan, layers.cost), layers.hazard & ~mask, layers.unknown | mask)
