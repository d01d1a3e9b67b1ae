"""A grid map as a north-up picture to draw on: world (x, y) to pixels, for paths and markers."""
from __future__ import annotations

import math

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

    def pixel(self, xy) -> tuple[int, int]:
        col = (xy[0] - self.spec.origin_x) / self.spec.cell * self.factor
        row = (self.spec.rows - (xy[1] - self.spec.origin_y) / self.spec.cell) * self.factor
        return int(round(col)), int(round(row))

    def pixels(self, points) -> np.ndarray:
        return np.array([self.pixel(p) for p in points], np.int32)

    def line(self, points, colour, width: int = 2, antialiased: bool = True) -> None:
        if len(points) > 1:
            cv2.polylines(self.image, [self.pixels(points)], False, colour, width,
                          cv2.LINE_AA if antialiased else cv2.LINE_8)
