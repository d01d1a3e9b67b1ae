"""Grid maps: the geometry shared by DEMs, hazard maps, cost maps and ortho-images.

A grid covers a rectangle of the world's x-y plane (x east, y north, metres). Cell [row, col]
covers x in [origin_x + col * cell, origin_x + (col + 1) * cell) and y in
[origin_y + row * cell, origin_y + (row + 1) * cell): rows count northwards, columns eastwards,
so array indices and world axes agree without flips. Pictures and GeoTIFFs show north up, which
is the array flipped on its first axis; the writers do that, never the algorithms.

MapLayers is the layered map on one grid that the families exchange: terrain cost, hazard and
unknown, as the maps produce them and the planners read them.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, overload

import numpy as np


@dataclass(frozen=True)
class GridSpec:
    origin_x: float  # world x of the west edge of column 0
    origin_y: float  # world y of the south edge of row 0
    cell: float      # cell size, metres
    rows: int
    cols: int

    @classmethod
    def covering(cls, x_range: tuple[float, float], y_range: tuple[float, float], cell: float) -> GridSpec:
        """The smallest grid of `cell`-sized cells, aligned to multiples of `cell`, covering the ranges.

        Aligning to the cell size makes grids built at different times from different views share
        cell boundaries, so they can be merged cell for cell."""
        if not cell > 0:
            raise ValueError(f"cell size must be > 0, got {cell!r}")
        x0 = np.floor(x_range[0] / cell) * cell
        y0 = np.floor(y_range[0] / cell) * cell
        cols = max(1, int(np.ceil((x_range[1] - x0) / cell - 1e-9)))
        rows = max(1, int(np.ceil((y_range[1] - y0) / cell - 1e-9)))
        return cls(float(x0), float(y0), float(cell), rows, cols)

    @property
    def shape(self) -> tuple[int, int]:
        return self.rows, self.cols

    @property
    def x_range(self) -> tuple[float, float]:
        return self.origin_x, self.origin_x + self.cols * self.cell

    @property
    def y_range(self) -> tuple[float, float]:
        return self.origin_y, self.origin_y + self.rows * self.cell

    def cell_of(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(row, col, inside) for world points; row/col are only meaningful where inside is True."""
        col = np.floor((np.asarray(x) - self.origin_x) / self.cell).astype(np.int64)
        row = np.floor((np.asarray(y) - self.origin_y) / self.cell).astype(np.int64)
        inside = (row >= 0) & (row < self.rows) & (col >= 0) & (col < self.cols)
        return row, col, inside

    def centres(self) -> tuple[np.ndarray, np.ndarray]:
        """World x (per column) and y (per row) of the cell centres."""
        xs = self.origin_x + (np.arange(self.cols) + 0.5) * self.cell
        ys = self.origin_y + (np.arange(self.rows) + 0.5) * self.cell
        return xs, ys

    @overload
    def centre_of(self, row: int, col: int) -> tuple[float, float]: ...

    @overload
    def centre_of(self, row: np.ndarray, col: np.ndarray) -> tuple[np.ndarray, np.ndarray]: ...

    def centre_of(self, row: np.ndarray | int, col: np.ndarray | int) -> tuple[Any, Any]:
        """World x, y of cell centres: floats for one cell, arrays for arrays of them."""
        return (self.origin_x + (np.asarray(col) + 0.5) * self.cell,
                self.origin_y + (np.asarray(row) + 0.5) * self.cell)

    def to_json(self) -> dict[str, float | int | str]:
        return {"origin_x": self.origin_x, "origin_y": self.origin_y, "cell": self.cell,
                "rows": self.rows, "cols": self.cols, "frame": "world (x east, y north, z up), rows northwards"}

    @classmethod
    def from_json(cls, data: dict) -> GridSpec:
        return cls(float(data["origin_x"]), float(data["origin_y"]), float(data["cell"]),
                   int(data["rows"]), int(data["cols"]))


@dataclass(frozen=True)
class MapLayers:
    """Cost, hazard and unknown layers over one grid. Hazard cells cost +inf and count as known;
    unknown cells cost NaN (their cost is the unknown policy's to give)."""

    spec: GridSpec
    cost: np.ndarray
    hazard: np.ndarray
    unknown: np.ndarray

    def __post_init__(self) -> None:
        cost = np.asarray(self.cost, dtype=np.float64)
        hazard = np.asarray(self.hazard, dtype=bool)
        unknown = np.asarray(self.unknown, dtype=bool) & ~hazard
        for name, layer in (("cost", cost), ("hazard", hazard), ("unknown", unknown)):
            if layer.shape != self.spec.shape:
                raise ValueError(f"{name} layer is {layer.shape}, the grid is {self.spec.shape}")
        known = ~unknown & ~hazard
        if np.isnan(cost[known]).any():
            raise ValueError("known cells hold NaN cost; mark them unknown")
        if (cost[known] < 0).any():
            raise ValueError("costs must be >= 0")
        object.__setattr__(self, "cost", np.where(hazard, np.inf, np.where(unknown, np.nan, cost)))
        object.__setattr__(self, "hazard", hazard)
        object.__setattr__(self, "unknown", unknown)

    @classmethod
    def from_cost(cls, spec: GridSpec, cost: np.ndarray, hazard: np.ndarray | None = None) -> MapLayers:
        """Layers from a cost grid whose NaN cells are unknown."""
        cost = np.asarray(cost, dtype=np.float64)
        hazard = np.zeros(cost.shape, dtype=bool) if hazard is None else hazard
        return cls(spec, cost, hazard, np.isnan(cost))
