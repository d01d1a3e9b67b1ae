"""The world's heights with rocks, kept as the rock-free ground plus the grid points a rock tops.

A dense copy of the heights is one more full grid (64 MiB on the default 40 m world at 1 cm) that
differs from the ground only where rocks stand (7 % of the points on the default world). Kept
sparse (sorted flat indices and the heights there), it costs a tenth of that; every truth query
asks for a window (the ground under the rover, the cells of a scored map), which is built from the
ground and the points inside it, equal to the dense grid's window to the bit.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class TopHeights:
    """`ground` (rows, cols) float32 and, at the sorted unique flat indices `points`, the height
    `tops` (float32) of the rock that is the topmost surface there."""

    ground: np.ndarray
    points: np.ndarray
    tops: np.ndarray

    @classmethod
    def of(cls, ground: np.ndarray, points: np.ndarray, tops: np.ndarray) -> TopHeights:
        """From flat indices in any order; where one repeats, the last wins, as an assignment
        `heights.ravel()[points] = tops` would have it."""
        points = np.asarray(points, np.int64)
        order = np.argsort(points, kind="stable")
        points, tops = points[order], np.asarray(tops, np.float32)[order]
        last = np.r_[points[1:] != points[:-1], True] if len(points) else np.zeros(0, bool)
        return cls(ground, points[last], tops[last])

    def dense(self) -> np.ndarray:
        """The whole grid (a new array of the ground's size)."""
        heights = self.ground.copy()
        heights.ravel()[self.points] = self.tops
        return heights

    def window(self, rows: slice, cols: slice) -> np.ndarray:
        """`dense()[rows, cols]` (a new array), made from the ground and the points inside."""
        heights = self.ground[rows, cols].copy()
        r0, c0, flat, tops = self.inside(rows, cols)
        row, col = np.divmod(flat, self.ground.shape[1])
        heights[row - r0, col - c0] = tops
        return heights

    def inside(self, rows: slice, cols: slice) -> tuple[int, int, np.ndarray, np.ndarray]:
        """The first row and column of the window, and the flat indices and tops of the points in it."""
        r0, r1, step_r = rows.indices(self.ground.shape[0])
        c0, c1, step_c = cols.indices(self.ground.shape[1])
        if step_r != 1 or step_c != 1:
            raise ValueError(f"a window of unit steps, not rows {rows} and cols {cols}")
        width = self.ground.shape[1]
        row_starts = np.arange(r0, max(r0, r1), dtype=np.int64) * width
        first = np.searchsorted(self.points, row_starts + c0)
        counts = np.searchsorted(self.points, row_starts + c1) - first
        total = int(counts.sum())
        if total == 0:
            return r0, c0, np.zeros(0, np.int64), np.zeros(0, np.float32)
        index = np.repeat(first - np.cumsum(counts) + counts, counts) + np.arange(total)
        return r0, c0, self.points[index], self.tops[index]

    def topped(self) -> int:
        """How many grid points a rock tops above the ground."""
        return int(np.count_nonzero(self.tops > self.ground.ravel()[self.points]))

    @property
    def nbytes(self) -> int:
        return self.points.nbytes + self.tops.nbytes
