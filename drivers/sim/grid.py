"""The regular grid the world is generated on: where grid point (row, col) lies in the world.

Rows run north (y), columns east (x). A grid of `rows` x `cols` cells has (rows + 1) x (cols + 1)
points; point (i, j) is at x = x_min + j * cell, y = y_min + i * cell.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class GridSpec:
    x_min: float
    y_min: float
    cell: float
    rows: int
    cols: int

    @classmethod
    def centred(cls, size_x: float, size_y: float, cell: float, block: int) -> GridSpec:
        """A grid centred on the world origin, at least size_x by size_y, in whole blocks of cells."""
        cols = block * max(1, int(np.ceil(size_x / cell / block - 1e-9)))
        rows = block * max(1, int(np.ceil(size_y / cell / block - 1e-9)))
        return cls(x_min=-cols * cell / 2, y_min=-rows * cell / 2, cell=cell, rows=rows, cols=cols)

    @property
    def shape(self) -> tuple[int, int]:
        """Shape of arrays holding one value per grid point."""
        return (self.rows + 1, self.cols + 1)

    @property
    def x_max(self) -> float:
        return self.x_min + self.cols * self.cell

    @property
    def y_max(self) -> float:
        return self.y_min + self.rows * self.cell

    def x_of(self, col) -> np.ndarray:
        return self.x_min + np.asarray(col, dtype=np.float64) * self.cell

    def y_of(self, row) -> np.ndarray:
        return self.y_min + np.asarray(row, dtype=np.float64) * self.cell

    def fractional_index(self, x, y) -> tuple[np.ndarray, np.ndarray]:
        """(row, col) as floats: where (x, y) falls between grid points."""
        return ((np.asarray(y, dtype=np.float64) - self.y_min) / self.cell,
                (np.asarray(x, dtype=np.float64) - self.x_min) / self.cell)

    def contains(self, x, y) -> np.ndarray:
        x, y = np.asarray(x), np.asarray(y)
        return (x >= self.x_min) & (x <= self.x_max) & (y >= self.y_min) & (y <= self.y_max)

    def point_coordinates(self) -> tuple[np.ndarray, np.ndarray]:
        """1-D x of every column and y of every row of grid points."""
        return self.x_of(np.arange(self.cols + 1)), self.y_of(np.arange(self.rows + 1))


def bilinear(values: np.ndarray, grid: GridSpec, x, y) -> np.ndarray:
    """Bilinear interpolation of a per-grid-point array at world (x, y); NaN outside the grid."""
    row, col = grid.fractional_index(x, y)
    inside = (row >= 0) & (row <= grid.rows) & (col >= 0) & (col <= grid.cols)
    row = np.clip(row, 0, grid.rows)
    col = np.clip(col, 0, grid.cols)
    i0 = np.minimum(row.astype(np.int64), grid.rows - 1)
    j0 = np.minimum(col.astype(np.int64), grid.cols - 1)
    fr, fc = row - i0, col - j0
    v00, v01 = values[i0, j0], values[i0, j0 + 1]
    v10, v11 = values[i0 + 1, j0], values[i0 + 1, j0 + 1]
    out = (v00 * (1 - fc) + v01 * fc) * (1 - fr) + (v10 * (1 - fc) + v11 * fc) * fr
    return np.where(inside, out, np.nan)


REMAP_ROW = 4096  # OpenCV remaps 2-D maps: point lists are folded into rows of this length


def remap_bilinear(image: np.ndarray, col: np.ndarray, row: np.ndarray, wrap: bool = False) -> np.ndarray:
    """Bilinear samples of a float32 image at fractional (col, row), by OpenCV (multi-threaded).

    OpenCV quantises the interpolation weights to 1/32 of a cell, which is fine for textures
    (not for heights: use `bilinear`). Outside the image: edge values, or periodic with `wrap`.
    """
    count = col.size
    rows = max(1, -(-count // REMAP_ROW))
    map_x = np.zeros(rows * REMAP_ROW, dtype=np.float32)
    map_y = np.zeros(rows * REMAP_ROW, dtype=np.float32)
    map_x[:count], map_y[:count] = col.ravel(), row.ravel()
    border = cv2.BORDER_WRAP if wrap else cv2.BORDER_REPLICATE
    sampled = cv2.remap(image, map_x.reshape(rows, REMAP_ROW), map_y.reshape(rows, REMAP_ROW),
                        cv2.INTER_LINEAR, borderMode=border)
    return sampled.ravel()[:count].reshape(col.shape)
