"""Albedo of the simulated world: regolith texture, grains and rock surfaces.

Stereo matching needs texture at every scale a camera may see: a multi-scale log-normal pattern
from 1 cm to several metres, scattered grains (the pebbles too small to be rocks), rocks with their
own darker or lighter albedo and a 3-D mottling, and sub-centimetre detail added at lookup time
(noise.DetailTexture).
"""
from __future__ import annotations

import math

import cv2
import numpy as np

from .config import AlbedoConfig
from .grid import GridSpec
from .noise import DetailTexture, fractal_noise


def regolith_albedo(grid: GridSpec, config: AlbedoConfig, rng: np.random.Generator) -> np.ndarray:
    """Per-grid-point albedo of the rock-free ground (float32)."""
    coarsest = 4.0 / grid.cell  # patches up to about 16 m across (four lattice spacings)
    # A flat spectrum (roughness near 1) keeps centimetre contrast, which close-up stereo needs.
    log_albedo = fractal_noise(rng, grid.shape, 1.0, coarsest, roughness=0.85)
    log_albedo *= np.float32(config.regolith_contrast)
    log_albedo += np.float32(config.grain_contrast) * grains(grid.shape, config.grain_fraction, rng)
    albedo = np.exp(log_albedo, out=log_albedo)
    albedo *= np.float32(config.regolith_mean)
    return np.clip(albedo, 0.02, 0.95, out=albedo)


def grains(shape: tuple[int, int], fraction: float, rng: np.random.Generator) -> np.ndarray:
    """Scattered light and dark grains a cell or two across: zero almost everywhere, up to +-1 on grains."""
    speckle = np.zeros(shape, dtype=np.float32)
    count = int(fraction * speckle.size)
    if count == 0:
        return speckle
    flat = rng.integers(0, speckle.size, count)
    sign = rng.choice(np.array([-1.0, 1.0], np.float32), count)
    speckle.flat[flat] = sign * rng.uniform(0.5, 1.0, count).astype(np.float32)
    # A slight blur turns single-cell spikes into grains with soft edges; renormalise the peaks.
    blurred = cv2.GaussianBlur(speckle, (0, 0), 0.7)
    peak = float(np.abs(blurred).max()) or 1.0
    return blurred / np.float32(peak)


class RockTexture:
    """Multiplicative mottling of rock surfaces (vesicles, spots) near 1, defined in 3-D.

    Rock faces are steep, so a texture looked up by (x, y) alone would streak down them. This one
    sums the same lattice noise on the three axis planes (triplanar), so every face is textured.
    Two scales, 1 cm and 4 cm; evaluated only at rock points, far cheaper than a full grid.
    """

    def __init__(self, rng: np.random.Generator, contrast: float):
        self.fine = DetailTexture(rng, spacing_m=0.01)
        self.coarse = DetailTexture(rng, spacing_m=0.04)
        self.contrast = np.float32(contrast)

    def __call__(self, points: np.ndarray) -> np.ndarray:
        x, y, z = points[:, 0], points[:, 1], points[:, 2]
        pattern = np.zeros(len(points), dtype=np.float32)
        for u, v in ((x, y), (y, z), (z, x)):
            pattern += 0.6 * self.fine(u, v) + 0.8 * self.coarse(u, v)
        return np.exp(self.contrast / np.float32(math.sqrt(3.0)) * pattern)
