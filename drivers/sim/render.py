"""Camera renderer for the simulated world: per-pixel geometry and sun-lit intensity, no display.

Built on Open3D's RaycastingScene (Embree). Given a camera pose in the world and pinhole
intrinsics (with optional radial distortion), `render` returns per pixel: range along the ray,
z-depth, world hit point, surface normal, albedo, sun-lit intensity with cast shadows, and the cosine
of the incidence angle. Nothing here knows about a particular device: the SR4000 and stereo camera
emulators turn these physical quantities into their own images.

Camera frame as OpenCV: x right, y down, z forward; pixel centres at integer (u, v).
"""
from __future__ import annotations

from functools import cached_property

import numpy as np

from toolbox.camera import Intrinsics

from .config import Sun
from .lighting import shade
from .world import World


class RenderedView:
    """What one camera pose sees: per-pixel images, each computed on first access and kept.

    Images are (height, width) or (height, width, 3):
        hit            bool: the ray met the terrain
        range          float32 metres along the ray from the optical centre; inf: no hit
        depth          float32 z in the camera frame; inf: no hit
        points         float64 world xyz of the hit; NaN: no hit
        normals        float32 unit world normal of the surface hit; NaN: no hit
        albedo         float32; 0: no hit
        lit            bool: the sun reaches the point (faces it and, with shadows, no terrain between)
        intensity      float32 sun-lit radiance albedo * (E cos + ambient); sky_intensity: no hit
        incidence_cos  float32 cosine between the reversed ray and the normal; 0: no hit
        rock           int32 index into World.rocks of the rock hit; -1: ground or no hit
    Laziness matters: a stereo camera needs only `intensity`, the time-of-flight camera only range,
    incidence and albedo, and filling unused full-size images costs more than the ray casting.
    """

    def __init__(self, world: World, camera: Intrinsics, sun: Sun, shadows: bool, sky_intensity: float,
                 origin: np.ndarray, directions_camera: np.ndarray, directions: np.ndarray,
                 distance: np.ndarray, triangle: np.ndarray):
        self.camera, self.sun, self.shadows, self.sky_intensity = camera, sun, shadows, sky_intensity
        self._world, self._origin = world, origin
        self._directions_camera, self._directions = directions_camera, directions
        self._distance, self._triangle = distance, triangle
        self._index = np.flatnonzero(np.isfinite(distance))   # flat indices of the pixels that hit

    @property
    def shape(self) -> tuple[int, int]:
        return (self.camera.height, self.camera.width)

    # Per-hit values (compact, one entry per hit pixel) ------------------------------------------
    @cached_property
    def hit_points(self) -> np.ndarray:
        points = self._directions[self._index].astype(np.float64)
        points *= self._distance[self._index][:, None]
        points += self._origin
        return points

    @cached_property
    def hit_normals(self) -> np.ndarray:
        return self._world.surface.face_normals[self._triangle[self._index]]

    @cached_property
    def hit_rock(self) -> np.ndarray:
        return self._world.rock_of_triangle[self._triangle[self._index]]

    @cached_property
    def hit_albedo(self) -> np.ndarray:
        return self._world.albedo_of(self.hit_points, self.hit_rock)

    @cached_property
    def hit_lit(self) -> np.ndarray:
        if self.shadows:
            return self._world.in_sunlight(self.hit_points, self.hit_normals, self.sun)
        return (self.hit_normals @ np.asarray(self.sun.direction(), np.float32)) > 0

    # Images --------------------------------------------------------------------------------------
    @cached_property
    def hit(self) -> np.ndarray:
        return np.isfinite(self._distance).reshape(self.shape)

    @cached_property
    def range(self) -> np.ndarray:
        return self._distance.reshape(self.shape)

    @cached_property
    def depth(self) -> np.ndarray:
        return (self._distance * self._directions_camera[:, 2]).reshape(self.shape)

    @cached_property
    def points(self) -> np.ndarray:
        return self._image(self.hit_points, np.nan, np.float64)

    @cached_property
    def normals(self) -> np.ndarray:
        return self._image(self.hit_normals, np.nan, np.float32)

    @cached_property
    def albedo(self) -> np.ndarray:
        return self._image(self.hit_albedo, 0.0, np.float32)

    @cached_property
    def lit(self) -> np.ndarray:
        return self._image(self.hit_lit, False, bool)

    @cached_property
    def intensity(self) -> np.ndarray:
        radiance = shade(self.hit_albedo, self.hit_normals, self.hit_lit, self.sun)
        return self._image(radiance, self.sky_intensity, np.float32)

    @cached_property
    def incidence_cos(self) -> np.ndarray:
        cosine = -np.einsum("ij,ij->i", self._directions[self._index], self.hit_normals)
        return self._image(np.clip(cosine, 0.0, 1.0), 0.0, np.float32)

    @cached_property
    def rock(self) -> np.ndarray:
        return self._image(self.hit_rock, -1, np.int32)

    def _image(self, values: np.ndarray, fill, dtype) -> np.ndarray:
        """Full image from per-hit values, `fill` where the ray missed."""
        out = np.full((self.shape[0] * self.shape[1],) + values.shape[1:], fill, dtype=dtype)
        out[self._index] = values
        return out.reshape(self.shape + values.shape[1:])


def render(world: World, camera_to_world: np.ndarray, camera: Intrinsics, sun: Sun | None = None,
           shadows: bool = True, sky_intensity: float = 0.0) -> RenderedView:
    """Cast `camera`'s rays from pose `camera_to_world` (4x4, camera frame to world) into `world`.

    The rays are cast here; each image of the returned view is computed when first read.
    `sun` overrides world.sun for this view. With shadows=False no shadow rays are cast (faster;
    `lit` then only says whether a surface faces the sun). The view keeps the world as it was when
    the rays were cast: obstacles added or removed meanwhile (in another thread) change no image of it.
    """
    world = world.snapshot()   # the view's rays and every image of it see one state of the world
    pose = np.asarray(camera_to_world, dtype=np.float64)
    directions_camera = camera.ray_directions().reshape(-1, 3)
    origin = pose[:3, 3]
    directions = directions_camera @ pose[:3, :3].T.astype(np.float32)
    distance, triangle = world.surface.cast(camera_rays(origin, directions))
    return RenderedView(world, camera, sun or world.sun, shadows, sky_intensity, origin,
                        directions_camera, directions, distance, triangle)


def camera_rays(origin: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """Embree rays (N, 6) float32 from one origin along unit directions (N, 3)."""
    rays = np.empty((len(directions), 6), dtype=np.float32)
    rays[:, :3] = origin
    rays[:, 3:] = directions
    return rays
