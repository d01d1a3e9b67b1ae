"""The rock-free ground of the simulated world: regional slope, undulation, relief and craters.

Rocks are added on top later (rocks.py); this surface is kept as the reference that rock
protrusion, and so the obstacle truth, is measured from.
"""
from __future__ import annotations

import math

import numpy as np

from .config import CraterConfig, TerrainConfig
from .grid import GridSpec
from .noise import fractal_noise


def ground_heights(grid: GridSpec, terrain: TerrainConfig, craters: CraterConfig,
                   rng: np.random.Generator) -> np.ndarray:
    """Heights (float32, one per grid point) of the ground before rocks are placed."""
    heights = regional_slope(grid, terrain)
    heights += undulation(grid, terrain, rng)
    for crater in sample_craters(grid, craters, rng):
        add_crater(heights, grid, *crater)
    return heights


def regional_slope(grid: GridSpec, terrain: TerrainConfig) -> np.ndarray:
    """A plane through the origin falling at slope_deg toward slope_azimuth_deg."""
    az = math.radians(terrain.slope_azimuth_deg)
    gradient = math.tan(math.radians(terrain.slope_deg))
    xs, ys = grid.point_coordinates()
    # Height drops along the downhill unit vector (sin az, cos az).
    east = (-gradient * math.sin(az) * xs).astype(np.float32)
    north = (-gradient * math.cos(az) * ys).astype(np.float32)
    return north[:, None] + east[None, :]


def undulation(grid: GridSpec, terrain: TerrainConfig, rng: np.random.Generator) -> np.ndarray:
    """Gentle hills (undulation) plus small-scale relief, both zero-mean with the configured RMS.

    Noise spacing is a quarter of the nominal wavelength: blurred, upsampled lattice noise has
    crests about four lattice spacings apart.
    """
    cells = lambda metres: metres / 4 / grid.cell  # noqa: E731
    hills = fractal_noise(rng, grid.shape, cells(terrain.undulation_wavelength_m / 2),
                          cells(terrain.undulation_wavelength_m * 2), roughness=0.2)
    hills *= np.float32(terrain.undulation_rms_m)
    relief = fractal_noise(rng, grid.shape, cells(terrain.relief_wavelength_m / 2),
                           cells(terrain.relief_wavelength_m), roughness=0.5)
    hills += np.float32(terrain.relief_rms_m) * relief
    return hills


def sample_craters(grid: GridSpec, craters: CraterConfig, rng: np.random.Generator):
    """(x, y, diameter, depth, rim height) of each crater, centres anywhere on the grid."""
    low, high = craters.diameter_range_m
    for _ in range(craters.count):
        diameter = float(math.exp(rng.uniform(math.log(low), math.log(high))))
        x = float(rng.uniform(grid.x_min, grid.x_max))
        y = float(rng.uniform(grid.y_min, grid.y_max))
        yield x, y, diameter, craters.depth_ratio * diameter, craters.rim_height_ratio * diameter


CRATER_REACH = 3.0  # the rim's outer flank fades to nothing at this many radii


def crater_profile(rho: np.ndarray, depth: float, rim: float) -> np.ndarray:
    """Height change at rho crater radii from the centre: a parabolic bowl inside the rim crest,
    an outer flank falling as rho**-3 (the classic ejecta profile) tapered to zero at CRATER_REACH,
    and a rounded crest where the two meet (a soft minimum of bowl and flank)."""
    bowl = -depth + (depth + rim) * rho**2
    tail = CRATER_REACH**-3
    flank = rim * (np.maximum(rho, 0.2) ** -3 - tail) / (1 - tail)
    softness = 0.25 * rim + 1e-6
    low = np.minimum(bowl, flank)
    rounded = low - softness * np.log1p(np.exp(-np.abs(bowl - flank) / softness))
    return np.where(rho < CRATER_REACH, rounded, 0.0)


def add_crater(heights: np.ndarray, grid: GridSpec, x: float, y: float, diameter: float,
               depth: float, rim: float) -> None:
    """Add one crater to `heights` in place, touching only its bounding box."""
    radius = diameter / 2
    reach = CRATER_REACH * radius
    i0, i1 = _index_span(y - reach, y + reach, grid.y_min, grid.cell, grid.rows)
    j0, j1 = _index_span(x - reach, x + reach, grid.x_min, grid.cell, grid.cols)
    if i0 >= i1 or j0 >= j1:
        return
    dy = grid.y_of(np.arange(i0, i1)) - y
    dx = grid.x_of(np.arange(j0, j1)) - x
    rho = np.hypot(dy[:, None], dx[None, :]) / radius
    heights[i0:i1, j0:j1] += crater_profile(rho, depth, rim).astype(np.float32)


def _index_span(low: float, high: float, origin: float, cell: float, cells: int) -> tuple[int, int]:
    start = max(0, int(math.floor((low - origin) / cell)))
    stop = min(cells + 1, int(math.ceil((high - origin) / cell)) + 1)
    return start, stop
