"""Pictures made of pictures: a grid map as a north-up canvas to draw paths and markers on, panels
side by side, and tiles in a contact sheet. Every family's overview and contact sheet is built here."""
from __future__ import annotations

import math
from collections.abc import Sequence

import cv2
import numpy as np

from toolbox.colour import upscale
from toolbox.grid import GridSpec


class Canvas:
    """A grid's RGB picture, north up, enlarged by a whole factor to at least `size` pixels."""

    def __init__(self, rgb: np.ndarray, spec: GridSpec, size: int):
        self.spec = spec
        self.factor = max(1, int(math.ceil(size / max(rgb.shape[:2]))))
        self.image = np.ascontiguousarray(upscale(np.flipud(rgb), size))

    def pixel(self, xy: Sequence[float] | np.ndarray) -> tuple[int, int]:
        col = (xy[0] - self.spec.origin_x) / self.spec.cell * self.factor
        row = (self.spec.rows - (xy[1] - self.spec.origin_y) / self.spec.cell) * self.factor
        return int(round(col)), int(round(row))

    def pixels(self, points: Sequence[Sequence[float]] | np.ndarray) -> np.ndarray:
        return np.array([self.pixel(p) for p in points], np.int32)

    def line(self, points: Sequence[Sequence[float]] | np.ndarray, colour: tuple[int, ...], width: int = 2,
             antialiased: bool = True) -> None:
        if len(points) > 1:
            cv2.polylines(self.image, [self.pixels(points)], False, colour, width,
                          cv2.LINE_AA if antialiased else cv2.LINE_8)


BACKGROUND = 20  # the dark grey between and behind panels


def side_by_side(panels: list[np.ndarray], gap: int = 8) -> np.ndarray:
    """RGB panels left to right, `gap` pixels apart, bottoms padded to one height."""
    height = max(p.shape[0] for p in panels)
    padded = [np.concatenate([p, np.full((height - p.shape[0], p.shape[1], 3), BACKGROUND, np.uint8)], axis=0)
              for p in panels]
    spacer = np.full((height, gap, 3), BACKGROUND, np.uint8)
    out = [padded[0]]
    for panel in padded[1:]:
        out += [spacer, panel]
    return np.concatenate(out, axis=1)


def sheet(tiles: list[np.ndarray], columns: int, fill: int = BACKGROUND) -> np.ndarray:
    """Equal-sized tiles in rows of `columns`, the last row completed with blank tiles of `fill`."""
    blank = np.full_like(tiles[0], fill)
    tiles = tiles + [blank] * (-len(tiles) % columns)
    rows = [np.concatenate(tiles[k:k + columns], axis=1) for k in range(0, len(tiles), columns)]
    return np.concatenate(rows, axis=0)
