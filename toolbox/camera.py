"""The one pinhole camera model of RVS: intrinsics with OpenCV's radial distortion, projection, and
the rays through every pixel. The maps, the stereo matcher, the SfM and the simulator's renderer
all use it, so a camera is described the same way everywhere (radians, pixels, OpenCV axes: x right,
y down, z forward; pixel centres at integer (u, v)).
"""
from __future__ import annotations

from dataclasses import dataclass, fields
from functools import lru_cache

import numpy as np

UNDISTORT_ITERATIONS = 30


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics with OpenCV's radial distortion x_d = x (1 + k1 r^2 + k2 r^4)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    k1: float = 0.0
    k2: float = 0.0

    def __post_init__(self) -> None:
        # Values as the files write them (integers as ints, the rest as floats), and a camera
        # with no pixels or no focal length is refused where it is made, not where it divides.
        for f in fields(self):
            value = getattr(self, f.name)
            object.__setattr__(self, f.name, int(value) if f.type == "int" else float(value))
        for name in ("width", "height", "fx", "fy"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} = {getattr(self, name)}: must be > 0")

    @classmethod
    def from_fov(cls, width: int, height: int, horizontal_fov: float) -> Intrinsics:
        """Square pixels, principal point at the image centre, horizontal field of view in radians."""
        f = (width / 2) / float(np.tan(horizontal_fov / 2))
        return cls(width, height, f, f, (width - 1) / 2, (height - 1) / 2)

    @property
    def matrix(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def distortion(self) -> np.ndarray:
        """OpenCV distortion vector (k1, k2, p1, p2, k3)."""
        return np.array([self.k1, self.k2, 0.0, 0.0, 0.0])

    def as_dict(self) -> dict[str, float | int]:
        return {f.name: getattr(self, f.name) for f in fields(self)}

    def project(self, points_camera: np.ndarray) -> np.ndarray:
        return project(points_camera, self)

    def ray_directions(self) -> np.ndarray:
        """Unit ray directions (height, width, 3), float32, in the camera frame (read-only, cached)."""
        return _ray_directions(self.width, self.height, self.fx, self.fy, self.cx, self.cy, self.k1, self.k2)


def project(points_camera: np.ndarray, intrinsics: Intrinsics) -> np.ndarray:
    """Pixel coordinates (..., 2) of camera-frame points (..., 3); NaN at or behind the camera."""
    points_camera = np.asarray(points_camera, dtype=np.float64)
    z = points_camera[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        x, y = points_camera[..., 0] / z, points_camera[..., 1] / z
    r2 = x * x + y * y
    radial = 1 + intrinsics.k1 * r2 + intrinsics.k2 * r2 * r2
    uv = np.stack([intrinsics.fx * x * radial + intrinsics.cx, intrinsics.fy * y * radial + intrinsics.cy], axis=-1)
    uv[~(z > 0)] = np.nan
    return uv


@lru_cache(maxsize=16)
def _ray_directions(width: int, height: int, fx: float, fy: float, cx: float, cy: float, k1: float,
                    k2: float) -> np.ndarray:
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    x, y = undistort_normalised((u - cx) / fx, (v - cy) / fy, k1, k2)
    directions = np.stack([x, y, np.ones_like(x)], axis=-1)
    directions /= np.linalg.norm(directions, axis=-1, keepdims=True)
    directions = directions.astype(np.float32)
    directions.flags.writeable = False
    return directions


def undistort_normalised(xd: np.ndarray, yd: np.ndarray, k1: float, k2: float) -> tuple[np.ndarray, np.ndarray]:
    """Invert x_d = x (1 + k1 r^2 + k2 r^4) by fixed-point iteration (as OpenCV's undistortPoints)."""
    x, y = xd.copy(), yd.copy()
    if k1 == 0 and k2 == 0:
        return x, y
    for _ in range(UNDISTORT_ITERATIONS):
        r2 = x * x + y * y
        radial = 1 + k1 * r2 + k2 * r2 * r2
        x, y = xd / radial, yd / radial
    r2 = x * x + y * y
    residual = np.max(np.hypot(x * (1 + k1 * r2 + k2 * r2 * r2) - xd, y * (1 + k1 * r2 + k2 * r2 * r2) - yd))
    if not residual < 1e-9:
        raise ValueError(f"radial distortion k1={k1}, k2={k2} cannot be inverted over this image")
    return x, y
