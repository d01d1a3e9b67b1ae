"""Seeded random fields for relief and texture, cheap enough for 4000 x 4000 grids.

Fields are built as a pyramid of blurred white noise, each octave upsampled with bicubic
interpolation onto the next finer one: a few resizes instead of an FFT of the full grid. Textures
finer than the grid come from small periodic lattices looked up at any point (DetailTexture).
"""
from __future__ import annotations

import math

import cv2
import numpy as np
from scipy import ndimage

from .grid import remap_bilinear


def fractal_noise(rng: np.random.Generator, shape: tuple[int, int], finest_cells: float,
                  coarsest_cells: float, roughness: float = 0.5) -> np.ndarray:
    """Unit-variance sum of octaves from `finest_cells` to `coarsest_cells` lattice spacing.

    Octave k (spacing finest * 2**k) has weight 2**(k * (1 - roughness)): roughness 1 weighs all
    scales alike, roughness 0 lets the coarse scales dominate like natural relief. Built as a
    pyramid: the sum so far is doubled in resolution and the next finer octave added, so each octave
    costs in proportion to its own resolution.
    """
    base = max(1.0, float(finest_cells))
    octaves = max(1, int(math.floor(math.log2(max(coarsest_cells, base) / base + 1e-9))) + 1)
    top = octaves - 1
    top_shape = (int(math.ceil(shape[0] / base / 2**top)) + 1, int(math.ceil(shape[1] / base / 2**top)) + 1)
    field = None
    for k in range(top, -1, -1):
        level_shape = (top_shape[0] * 2 ** (top - k), top_shape[1] * 2 ** (top - k))
        octave = cv2.GaussianBlur(rng.standard_normal(level_shape, dtype=np.float32), (0, 0), 0.8,
                                  borderType=cv2.BORDER_REFLECT)
        octave *= np.float32(2.0 ** (k * (1.0 - roughness)))
        if field is not None:
            octave += cv2.resize(field, level_shape[::-1], interpolation=cv2.INTER_CUBIC)
        field = octave
    if base > 1.0:
        field = _magnify(field, base, shape)
    else:
        field = np.ascontiguousarray(field[:shape[0], :shape[1]])
    return _unit(field)


def _magnify(field: np.ndarray, factor: float, shape: tuple[int, int]) -> np.ndarray:
    """Bicubic upsampling by `factor` straight into an array of `shape` (no oversized copy)."""
    inverse = np.array([[1.0 / factor, 0.0, 0.0], [0.0, 1.0 / factor, 0.0]])
    return cv2.warpAffine(field, inverse, (shape[1], shape[0]),
                          flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_REFLECT)


def _unit(field: np.ndarray) -> np.ndarray:
    """Shift and scale in place to zero mean and unit variance (OpenCV's float64 accumulation)."""
    field = field.astype(np.float32, copy=False)
    mean, std = (float(v[0, 0]) for v in cv2.meanStdDev(field))
    field -= np.float32(mean)
    if std > 0:
        field /= np.float32(std)
    return field


class DetailTexture:
    """Zero-mean, unit-variance texture evaluated at any (x, y): a periodic lattice of random values.

    The world's albedo grid has one value per height cell (1 cm); a camera a metre away sees
    millimetres per pixel. Lattices like this add finer texture, exact and repeatable, at lookup
    time, and give rocks their mottling without a full-resolution grid.
    """

    SIZE = 1024  # lattice points per period; with 2.5 mm spacing the period is 2.56 m

    def __init__(self, rng: np.random.Generator, spacing_m: float = 0.0025):
        lattice = rng.standard_normal((self.SIZE, self.SIZE), dtype=np.float32)
        # Wrapped blur keeps the lattice seamless across its period.
        self.lattice = _unit(ndimage.gaussian_filter(lattice, 0.7, mode="wrap"))
        self.spacing_m = spacing_m

    def __call__(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        # OpenCV wraps coordinates into the period itself; float32 lattice coordinates of a 40 m
        # world are good to a micrometre.
        scale = np.float32(1.0 / self.spacing_m)
        col = np.multiply(x, scale, dtype=np.float32)
        row = np.multiply(y, scale, dtype=np.float32)
        return remap_bilinear(self.lattice, col, row, wrap=True)
