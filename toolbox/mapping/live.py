"""A map that takes one sensor frame at a time, at frame rate.

`insert` drops a frame's world points into their cells (the highest point of a cell is its height
and counts add up, so the heights equal those of gridding every frame at once: a maximum does not
care about order), then recomputes the hazard maps only where they can have changed: the cells the
frame touched, grown by how far a hazard measure reaches (`hazard_reach`), computed on that window
grown once more by the same reach so that no output cell sees the window's edge. Every measure of
hazard_maps is local (box filters, erosions and dilations of bounded size), so the refreshed window
equals a recomputation of the whole grid: to the bit in the step map, within float rounding in
the plane fit's slope and roughness (they are taken relative to a window's own median height).

Points outside the grid are counted and dropped: a live map has a fixed extent (a `dem-update-*`
makes a new, larger grid when the rover leaves it).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from toolbox.grid import GridSpec

from .dem import Dem
from .hazard import HazardConfig, HazardMaps, half_width, hazard_maps


def hazard_reach(cell: float, config: HazardConfig) -> int:
    """How many cells away a height change can move a hazard measure: the step (local minimum, and
    the ground plate's opening, an erosion then a dilation), the step's agreement count over it,
    then the plane fit over the ground the step leaves."""
    k_edge = half_width(config.step_radius, cell)
    k_ground = half_width(config.ground_radius, cell) if config.ground_radius else 0
    k_agree = half_width(config.step_radius, cell)
    k_plane = half_width(config.plane_radius, cell)
    return max(k_edge, 2 * k_ground) + k_agree + k_plane


@dataclass(frozen=True)
class Inserted:
    """What one frame changed: the cells it touched and the refreshed window (row and column slices)."""

    points: int                   # points that fell into the grid
    outside: int                  # points beyond it, dropped
    touched: tuple[slice, slice]  # the bounding box of the cells the points fell in
    refreshed: tuple[slice, slice]


class LiveMap:
    """Heights, counts and hazard maps of a fixed grid, updated frame by frame (arrays owned, mutated)."""

    def __init__(self, dem: Dem, config: HazardConfig = HazardConfig()):
        self.spec: GridSpec = dem.spec
        self.config = config
        self.heights = np.array(dem.heights, dtype=np.float32)
        self.counts = np.array(dem.counts, dtype=np.int32)
        self.reach = hazard_reach(self.spec.cell, config)
        maps = hazard_maps(self.heights, self.spec.cell, config)
        self.slope, self.step, self.roughness, self.code = (np.array(m) for m in
                                                            (maps.slope_deg, maps.step, maps.roughness, maps.code))

    @classmethod
    def empty(cls, spec: GridSpec, config: HazardConfig = HazardConfig()) -> LiveMap:
        return cls(Dem(spec, np.full(spec.shape, np.nan, np.float32), np.zeros(spec.shape, np.int32)), config)

    def copy(self) -> LiveMap:
        """An independent map as this one stands (its arrays copied, no hazard map recomputed)."""
        twin = object.__new__(LiveMap)
        twin.__dict__.update({k: v.copy() if isinstance(v, np.ndarray) else v for k, v in self.__dict__.items()})
        return twin

    @property
    def maps(self) -> HazardMaps:
        return HazardMaps(self.slope, self.step, self.roughness, self.code)

    def insert(self, points: np.ndarray) -> Inserted | None:
        """One frame's world points (N, 3): heights, counts and the hazard window refreshed. None when
        no point fell into the grid (nothing changed)."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        spec = self.spec
        col = np.floor((points[:, 0] - spec.origin_x) / spec.cell)
        row = np.floor((points[:, 1] - spec.origin_y) / spec.cell)
        inside = (row >= 0) & (row < spec.rows) & (col >= 0) & (col < spec.cols) & np.isfinite(points[:, 2])
        if not inside.any():
            return None
        row, col, z = row[inside].astype(np.intp), col[inside].astype(np.intp), points[inside, 2]
        r0, r1, c0, c1 = int(row.min()), int(row.max()) + 1, int(col.min()), int(col.max()) + 1
        # The frame's own maxima and counts over its bounding box, then merged into the map's.
        box = (r1 - r0, c1 - c0)
        flat = (row - r0) * box[1] + (col - c0)
        highest = np.full(box[0] * box[1], -np.inf)
        np.maximum.at(highest, flat, z)
        added = np.bincount(flat, minlength=highest.size).astype(np.int32)
        heights = self.heights[r0:r1, c0:c1]
        seen = added.reshape(box) > 0
        new = highest.reshape(box).astype(np.float32)
        heights[seen] = np.fmax(heights[seen], new[seen])
        self.counts[r0:r1, c0:c1] += added.reshape(box)
        refreshed = self._refresh(r0, r1, c0, c1)
        return Inserted(int(inside.sum()), int((~inside).sum()), (slice(r0, r1), slice(c0, c1)), refreshed)

    def _refresh(self, r0: int, r1: int, c0: int, c1: int) -> tuple[slice, slice]:
        """Hazard maps recomputed over the touched box grown by the reach, from that grown once more."""
        k, rows, cols = self.reach, self.spec.rows, self.spec.cols
        out_r0, out_r1, out_c0, out_c1 = max(0, r0 - k), min(rows, r1 + k), max(0, c0 - k), min(cols, c1 + k)
        in_r0, in_r1 = max(0, out_r0 - k), min(rows, out_r1 + k)
        in_c0, in_c1 = max(0, out_c0 - k), min(cols, out_c1 + k)
        maps = hazard_maps(self.heights[in_r0:in_r1, in_c0:in_c1], self.spec.cell, self.config)
        inner = (slice(out_r0 - in_r0, out_r1 - in_r0), slice(out_c0 - in_c0, out_c1 - in_c0))
        target = (slice(out_r0, out_r1), slice(out_c0, out_c1))
        for mine, fresh in ((self.slope, maps.slope_deg), (self.step, maps.step), (self.roughness, maps.roughness),
                            (self.code, maps.code)):
            mine[target] = fresh[inner]
        return target
