"""The truth surface: triangles (ground and rocks) and the Open3D ray-casting scene built on them.

Sensors and ground truth share this one set of triangles. The renderer casts camera rays against
it; the truth queries (height, normal, slope) find the topmost triangle over a point with a vertical
ray and evaluate that triangle's plane in float64, so what a sensor hits and what the truth says
agree to the precision of the ray distance (micrometres), not to some resampling error.
"""
from __future__ import annotations

import numpy as np
import open3d as o3d

from .grid import GridSpec

RAY_CHUNK = 2_000_000  # rays per Embree call in truth queries: bounds the temporary ray buffers
PLANE_CHUNK = 500_000  # points per vectorised plane evaluation (each needs 72 bytes of corners)


class TriangleSurface:
    """Triangles in world coordinates, kept in float64 for exact planes; Embree is built on first use.

    A surface has a static part (the built world: one big Embree scene, built once) and may have a
    small dynamic part (obstacles added after the build) in a second scene of its own. A surface never
    changes: `with_dynamic` makes a new one that shares the static part, so a reader holding a
    surface sees one consistent set of triangles however the world changes meanwhile. Triangle ids
    are the static triangles first, then the dynamic ones, in `vertices`, `triangles`,
    `face_normals` and every id `cast` and `triangle_under` give.
    """

    def __init__(self, vertices: np.ndarray, triangles: np.ndarray):
        self.vertices = np.ascontiguousarray(vertices, dtype=np.float64)
        self.triangles = np.ascontiguousarray(triangles, dtype=np.uint32)
        self.face_normals = _face_normals(self.vertices, self.triangles)
        self.top = float(self.vertices[:, 2].max(initial=0.0)) + 1.0
        self.static = self                   # the surface without a dynamic part
        self.static_triangles = len(self.triangles)
        self._scene: o3d.t.geometry.RaycastingScene | None = None
        self._dynamic_scene: o3d.t.geometry.RaycastingScene | None = None

    def with_dynamic(self, vertices: np.ndarray, triangles: np.ndarray) -> TriangleSurface:
        """A new surface: this one's static part (arrays and Embree scene shared, not rebuilt) plus
        `vertices` (V, 3) and `triangles` (T, 3, indices into `vertices`) as its dynamic part, in a
        small scene of its own (milliseconds to build). No triangles: the static surface itself.
        The static arrays are not copied (a walking person makes a new surface every frame): vertices,
        triangles and face_normals are Stacked, static then dynamic."""
        static = self.static
        if len(triangles) == 0:
            return static
        _ = static.scene                         # built once, shared by every version
        vertices = np.ascontiguousarray(vertices, dtype=np.float64)
        triangles = np.ascontiguousarray(triangles, dtype=np.uint32)
        dynamic_scene = o3d.t.geometry.RaycastingScene()
        dynamic_scene.add_triangles(o3d.core.Tensor(vertices.astype(np.float32)), o3d.core.Tensor(triangles))
        surface = object.__new__(TriangleSurface)
        surface.vertices = Stacked(static.vertices, vertices)
        surface.triangles = Stacked(static.triangles, triangles + np.uint32(len(static.vertices)))
        surface.face_normals = Stacked(static.face_normals, _face_normals(vertices, triangles))
        surface.top = max(static.top, float(vertices[:, 2].max()) + 1.0)
        surface.static, surface.static_triangles = static, static.static_triangles
        surface._scene, surface._dynamic_scene = static._scene, dynamic_scene
        return surface

    @property
    def scene(self) -> o3d.t.geometry.RaycastingScene:
        """The static part's Embree scene."""
        if self._scene is None:
            scene = o3d.t.geometry.RaycastingScene()
            scene.add_triangles(o3d.core.Tensor(self.vertices.astype(np.float32)),
                                o3d.core.Tensor(self.triangles))
            self._scene = scene
        return self._scene

    def cast(self, rays: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """First hits of float32 rays (..., 6): distance in direction-length units and triangle id."""
        rays = o3d.core.Tensor.from_numpy(np.ascontiguousarray(rays, dtype=np.float32))
        result = self.scene.cast_rays(rays)
        t_hit, ids = result["t_hit"].numpy(), result["primitive_ids"].numpy().astype(np.int64)
        if self._dynamic_scene is not None:
            near = self._dynamic_scene.cast_rays(rays)
            near_t = near["t_hit"].numpy()
            nearer = near_t < t_hit
            t_hit = np.where(nearer, near_t, t_hit)
            ids = np.where(nearer, near["primitive_ids"].numpy().astype(np.int64) + self.static_triangles, ids)
        return t_hit, ids

    def occluded(self, rays: np.ndarray) -> np.ndarray:
        """True where a ray meets the surface at all (shadow rays)."""
        rays = o3d.core.Tensor.from_numpy(np.ascontiguousarray(rays, dtype=np.float32))
        hit = self.scene.test_occlusions(rays).numpy()
        if self._dynamic_scene is not None:
            hit = hit | self._dynamic_scene.test_occlusions(rays).numpy()
        return hit

    def triangle_under(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Index of the topmost triangle over each (x, y); -1 where there is none."""
        x, y = np.ravel(x), np.ravel(y)
        found = np.full(len(x), -1, dtype=np.int64)
        for start in range(0, len(x), RAY_CHUNK):
            part = slice(start, start + RAY_CHUNK)
            rays = np.zeros((len(x[part]), 6), dtype=np.float32)
            rays[:, 0], rays[:, 1], rays[:, 2], rays[:, 5] = x[part], y[part], self.top, -1.0
            t_hit, ids = self.cast(rays)
            found[part] = np.where(np.isfinite(t_hit), ids, -1)
        return found

    def height_on(self, triangle: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Height of each triangle's plane at (x, y), in float64; NaN where triangle is -1."""
        z = np.full(len(triangle), np.nan)
        for start in range(0, len(triangle), PLANE_CHUNK):
            part = slice(start, start + PLANE_CHUNK)
            ok = triangle[part] >= 0
            corners = self.vertices[self.triangles[triangle[part][ok]]]        # (n, 3, 3)
            gx, gy = _plane_gradient(corners)
            dx, dy = x[part][ok] - corners[:, 0, 0], y[part][ok] - corners[:, 0, 1]
            z[part][ok] = corners[:, 0, 2] + gx * dx + gy * dy
        return z

    def top_height(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Height of the topmost surface over each (x, y) and the triangle it lies on (-1: none)."""
        x, y = np.ravel(np.asarray(x, np.float64)), np.ravel(np.asarray(y, np.float64))
        triangle = self.triangle_under(x, y)
        return self.height_on(triangle, x, y), triangle

    def memory_bytes(self) -> int:
        """Bytes held in numpy by the surface (Embree's own copy and BVH come on top)."""
        return self.vertices.nbytes + self.triangles.nbytes + self.face_normals.nbytes


class Stacked:
    """Two arrays read as one, `static` then `dynamic`, along the first axis, without copying the
    big static one: integer-array indexing (what the renderer and the truth queries do) picks from
    each; anything else gets the concatenation, made once."""

    def __init__(self, static: np.ndarray, dynamic: np.ndarray):
        self.static, self.dynamic = static, dynamic
        self.shape = (len(static) + len(dynamic),) + static.shape[1:]
        self.dtype = static.dtype
        self._joined: np.ndarray | None = None

    def __len__(self) -> int:
        return self.shape[0]

    def __getitem__(self, index):
        if isinstance(index, np.ndarray) and index.dtype.kind in "iu":
            split = len(self.static)
            flat = index.ravel().astype(np.int64)
            out = np.empty((len(flat),) + self.shape[1:], dtype=self.dtype)
            first = flat < split
            out[first] = self.static[flat[first]]
            out[~first] = self.dynamic[flat[~first] - split]
            return out.reshape(index.shape + self.shape[1:])
        return self.joined()[index]

    def __array__(self, dtype=None, copy=None):
        joined = self.joined()
        return joined if dtype is None else joined.astype(dtype)

    def joined(self) -> np.ndarray:
        if self._joined is None:
            self._joined = np.concatenate([self.static, self.dynamic])
        return self._joined

    @property
    def nbytes(self) -> int:
        return self.static.nbytes + self.dynamic.nbytes


def grid_surface_parts(grid: GridSpec, heights: np.ndarray, triangle_points: np.ndarray):
    """Vertices (float64) and triangles of a mesh whose corners are grid points.

    `triangle_points` (M, 3) holds flat grid-point indices (row * (cols + 1) + col). Only the points
    used become vertices; a lookup table over the grid renumbers them far faster than np.unique.
    """
    used = np.zeros(heights.size, dtype=bool)
    used[triangle_points.ravel()] = True
    vertex_index = np.flatnonzero(used)
    number = np.zeros(heights.size, dtype=np.uint32)
    number[vertex_index] = np.arange(len(vertex_index), dtype=np.uint32)
    rows, cols = np.divmod(vertex_index, grid.cols + 1)
    z = heights.ravel()[vertex_index].astype(np.float64)
    vertices = np.stack([grid.x_of(cols), grid.y_of(rows), z], axis=1)
    return vertices, number[triangle_points]


def _plane_gradient(corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """dz/dx and dz/dy of the plane through each triangle's three corners."""
    e1 = corners[:, 1] - corners[:, 0]
    e2 = corners[:, 2] - corners[:, 0]
    det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    gx = (e1[:, 2] * e2[:, 1] - e2[:, 2] * e1[:, 1]) / det
    gy = (e2[:, 2] * e1[:, 0] - e1[:, 2] * e2[:, 0]) / det
    return gx, gy


def _face_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Unit normals (float32) by the right-hand rule; ours are counter-clockwise from above or outside."""
    normals = np.empty((len(triangles), 3), dtype=np.float32)
    for start in range(0, len(triangles), PLANE_CHUNK):
        tri = triangles[start:start + PLANE_CHUNK]
        p0, p1, p2 = vertices[tri[:, 0]], vertices[tri[:, 1]], vertices[tri[:, 2]]
        e1, e2 = p1 - p0, p2 - p0
        n = np.stack([e1[:, 1] * e2[:, 2] - e1[:, 2] * e2[:, 1],
                      e1[:, 2] * e2[:, 0] - e1[:, 0] * e2[:, 2],
                      e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]], axis=1)
        normals[start:start + len(tri)] = n / np.linalg.norm(n, axis=1, keepdims=True)
    return normals
