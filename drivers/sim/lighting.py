"""Sun lighting of the simulated world: Lambert shading, cast shadows and an ambient term.

Intensity = albedo * (irradiance * max(0, n . s) * lit + ambient), where s points to the sun and
`lit` is False where a shadow ray from the surface toward the sun meets the terrain.
"""
from __future__ import annotations

import numpy as np

from .config import Sun
from .mesh import TriangleSurface

# Shadow rays start this far off the surface along its normal, so a surface never shadows itself.
SHADOW_RAY_OFFSET_M = 2e-4


def sun_direction(sun: Sun) -> np.ndarray:
    return np.asarray(sun.direction(), dtype=np.float64)


def in_sunlight(surface: TriangleSurface, points: np.ndarray, normals: np.ndarray, sun: Sun) -> np.ndarray:
    """True where the sun is above a surface point's tangent plane and no terrain blocks it.

    Every point casts a shadow ray, even one facing away from the sun (unlit anyway): selecting
    the facing ones first costs more in copying than the few extra rays cost Embree.
    """
    toward_sun = sun_direction(sun).astype(np.float32)
    rays = np.empty((len(points), 6), dtype=np.float32)
    rays[:, :3] = points
    rays[:, :3] += np.float32(SHADOW_RAY_OFFSET_M) * normals
    rays[:, 3:] = toward_sun
    facing = (normals @ toward_sun) > 0
    return facing & ~surface.occluded(rays)


def shade(albedo: np.ndarray, normals: np.ndarray, lit: np.ndarray, sun: Sun) -> np.ndarray:
    """Sun-lit intensity (float32): Lambert term where lit, plus ambient everywhere."""
    cos_sun = np.clip(normals @ sun_direction(sun).astype(np.float32), 0.0, None)
    direct = np.float32(sun.irradiance) * cos_sun * lit
    return (albedo * (direct + np.float32(sun.ambient))).astype(np.float32)
