"""Ortho-images: a camera's picture draped over a DEM, one intensity per DEM cell (thesis 3.3.4, 4.3.4).

For one view, in order:

    points = cell_points(heights, spec)                       # each cell's centre at its height
    uv, depth = project_cells(points, intrinsics, pose)        # into the picture (pinhole + k1, k2)
    seen = visible_by_depth_image(...) or visible_by_ray_cast(...)   # hidden cells stay NaN
    values = sample_bilinear(image, uv)                        # intensity at the projection
    score = view_score(...)                                    # how well this view sees the cell

and `merge_views` keeps, per cell, the view with the best score. Visibility comes from the camera's
own depth image when there is one (TOF: a z-buffer test), otherwise from casting a ray from the
camera to each cell against the DEM surface itself (Open3D's Embree ray caster): a cell is hidden if
the ray meets the terrain more than `tolerance` before reaching it.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import open3d as o3d

from toolbox.camera import Intrinsics, project
from toolbox.geometry import apply, invert
from toolbox.grid import GridSpec

# Metres a cell may lie behind the surface that hides it and still count as seen (range noise, the
# DEM's own height error, rays grazing the cell's neighbouring facets).
DEFAULT_TOLERANCE = 0.05


@dataclass(frozen=True)
class OrthoView:
    """One view draped on the DEM: intensity per cell (float32, NaN: not seen) and the view's score
    per cell (float32, 0 where not seen), higher = seen with more pixels."""

    intensity: np.ndarray
    score: np.ndarray


def ortho_image(heights: np.ndarray, spec: GridSpec, image: np.ndarray, intrinsics: Intrinsics,
                camera_to_world: np.ndarray, depth_image: np.ndarray | None = None,
                tolerance: float = DEFAULT_TOLERANCE) -> OrthoView:
    """Drape one single-channel picture over a DEM. depth_image: the camera's z-depth per pixel
    (same intrinsics, inf/NaN where nothing), e.g. the TOF's own; None: ray-cast the DEM."""
    points = cell_points(heights, spec)
    uv, depth = project_cells(points, intrinsics, camera_to_world)
    in_frame = inside_frame(uv, intrinsics)
    if depth_image is not None:
        seen = in_frame & visible_by_depth_image(uv, depth, depth_image, tolerance)
    else:
        seen = in_frame & visible_by_ray_cast(heights, spec, camera_to_world[:3, 3], points, in_frame, tolerance)
    values = sample_bilinear(image, uv)
    seen &= np.isfinite(values)
    score = view_score(heights, spec, points, camera_to_world[:3, 3])
    return OrthoView(np.where(seen, values, np.nan).astype(np.float32), np.where(seen, score, 0.0).astype(np.float32))


def merge_views(views: Sequence[OrthoView]) -> np.ndarray:
    """Per cell, the intensity of the view with the highest score among those that see it."""
    if not views:
        raise ValueError("no views to merge")
    scores = np.stack([np.where(np.isfinite(v.intensity), v.score, -np.inf) for v in views])
    best = np.argmax(scores, axis=0)
    intensity = np.take_along_axis(np.stack([v.intensity for v in views]), best[None], axis=0)[0]
    return np.where(np.isfinite(scores.max(axis=0)), intensity, np.nan).astype(np.float32)


# ---------------------------------------------------------------------------------- steps
def cell_points(heights: np.ndarray, spec: GridSpec) -> np.ndarray:
    """World xyz (rows, cols, 3) of every cell centre at its DEM height (NaN where unknown)."""
    xs, ys = spec.centres()
    x, y = np.meshgrid(xs, ys)
    return np.stack([x, y, np.asarray(heights, dtype=np.float64)], axis=-1)


def project_cells(points: np.ndarray, intrinsics: Intrinsics,
                  camera_to_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates (rows, cols, 2) and camera z-depth (rows, cols) of world points."""
    in_camera = apply(invert(camera_to_world), points)
    return project(in_camera, intrinsics), in_camera[..., 2]


def inside_frame(uv: np.ndarray, intrinsics: Intrinsics) -> np.ndarray:
    """True where a projection lies between the outermost pixel centres (bilinear needs both sides)."""
    u, v = uv[..., 0], uv[..., 1]
    return (u >= 0) & (u <= intrinsics.width - 1) & (v >= 0) & (v <= intrinsics.height - 1)


def visible_by_depth_image(uv: np.ndarray, depth: np.ndarray, depth_image: np.ndarray, tolerance: float) -> np.ndarray:
    """z-buffer test: a cell is seen if it is no more than `tolerance` behind what its pixel saw."""
    height, width = depth_image.shape
    u = np.clip(np.rint(np.nan_to_num(uv[..., 0], nan=-1)), 0, width - 1).astype(np.int64)
    v = np.clip(np.rint(np.nan_to_num(uv[..., 1], nan=-1)), 0, height - 1).astype(np.int64)
    seen_depth = np.asarray(depth_image, dtype=np.float64)[v, u]
    return np.isfinite(depth) & (depth <= np.where(np.isfinite(seen_depth), seen_depth, np.inf) + tolerance)


def visible_by_ray_cast(heights: np.ndarray, spec: GridSpec, camera_position: np.ndarray, points: np.ndarray,
                        candidates: np.ndarray, tolerance: float) -> np.ndarray:
    """True for candidate cells the straight line from the camera reaches without meeting the DEM
    surface more than `tolerance` before the cell."""
    visible = np.zeros(candidates.shape, dtype=bool)
    targets = points[candidates]
    if len(targets) == 0:
        return visible
    scene = o3d.t.geometry.RaycastingScene()
    # Only terrain inside the box spanned by the camera and the targets can lie between them:
    # meshing just that box keeps Embree's tree build (most of the cost) to the part in view.
    box = _box_between(spec, camera_position, targets)
    vertices, triangles = dem_mesh(heights[box], _sub_spec(spec, box))
    if len(triangles) == 0:
        visible[candidates] = True
        return visible
    scene.add_triangles(o3d.core.Tensor(vertices.astype(np.float32)), o3d.core.Tensor(triangles.astype(np.uint32)))
    offsets = targets - camera_position
    distance = np.linalg.norm(offsets, axis=1)
    rays = np.empty((len(targets), 6), dtype=np.float32)
    rays[:, :3] = camera_position
    rays[:, 3:] = offsets / distance[:, None]
    hit = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
    visible[candidates] = hit >= distance - tolerance    # inf (no hit) is visible too
    return visible


def _box_between(spec: GridSpec, camera_position: np.ndarray, targets: np.ndarray) -> tuple[slice, slice]:
    """Row and column slices of the cells within the x-y bounding box of the camera and the targets."""
    xy = np.vstack([targets[:, :2], camera_position[None, :2]])
    col = np.floor((xy[:, 0] - spec.origin_x) / spec.cell)
    row = np.floor((xy[:, 1] - spec.origin_y) / spec.cell)
    rows = slice(int(np.clip(row.min() - 1, 0, spec.rows)), int(np.clip(row.max() + 2, 0, spec.rows)))
    cols = slice(int(np.clip(col.min() - 1, 0, spec.cols)), int(np.clip(col.max() + 2, 0, spec.cols)))
    return rows, cols


def _sub_spec(spec: GridSpec, box: tuple[slice, slice]) -> GridSpec:
    rows, cols = box
    return GridSpec(spec.origin_x + cols.start * spec.cell, spec.origin_y + rows.start * spec.cell, spec.cell,
                    rows.stop - rows.start, cols.stop - cols.start)


def dem_mesh(heights: np.ndarray, spec: GridSpec) -> tuple[np.ndarray, np.ndarray]:
    """The DEM as triangles between cell centres: two per 2 x 2 block of known cells."""
    rows, cols = spec.shape
    points = cell_points(heights, spec).reshape(-1, 3)
    index = np.arange(rows * cols).reshape(rows, cols)
    known = np.isfinite(np.asarray(heights))
    full = known[:-1, :-1] & known[1:, :-1] & known[:-1, 1:] & known[1:, 1:]
    a, b = index[:-1, :-1][full], index[:-1, 1:][full]
    c, d = index[1:, :-1][full], index[1:, 1:][full]
    triangles = np.concatenate([np.stack([a, b, d], axis=1), np.stack([a, d, c], axis=1)])
    return np.nan_to_num(points), triangles


def sample_bilinear(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear samples of a single-channel image at pixel coordinates (..., 2) (pixel centres at
    integers); NaN outside the outermost pixel centres or at NaN pixels. Plain numpy rather than
    cv2.remap, whose linear interpolation rounds positions to 1/32 pixel."""
    image = np.asarray(image, dtype=np.float64)
    height, width = image.shape
    u, v = uv[..., 0], uv[..., 1]
    inside = (u >= 0) & (u <= width - 1) & (v >= 0) & (v <= height - 1)
    u, v = np.where(inside, u, 0.0), np.where(inside, v, 0.0)
    u0 = np.minimum(u.astype(np.int64), max(width - 2, 0))
    v0 = np.minimum(v.astype(np.int64), max(height - 2, 0))
    u1, v1 = np.minimum(u0 + 1, width - 1), np.minimum(v0 + 1, height - 1)
    fu, fv = u - u0, v - v0
    top = image[v0, u0] * (1 - fu) + image[v0, u1] * fu
    bottom = image[v1, u0] * (1 - fu) + image[v1, u1] * fu
    return np.where(inside, top * (1 - fv) + bottom * fv, np.nan)


def view_score(heights: np.ndarray, spec: GridSpec, points: np.ndarray, camera_position: np.ndarray) -> np.ndarray:
    """cos(incidence) / distance^2: proportional to the pixels per square metre the view puts on the
    cell, so the closest, most squarely seen view wins. Normals from the DEM's gradient (vertical
    where it is unknown)."""
    z = np.asarray(heights, dtype=np.float64)
    dz_drow, dz_dcol = np.gradient(z, spec.cell) if min(z.shape) > 1 else (np.zeros_like(z), np.zeros_like(z))
    normal = np.stack([-dz_dcol, -dz_drow, np.ones_like(z)], axis=-1)
    normal[~np.isfinite(normal).all(axis=-1)] = (0.0, 0.0, 1.0)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    to_camera = camera_position - points
    distance = np.linalg.norm(to_camera, axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        cosine = np.einsum("ijk,ijk->ij", normal, to_camera) / distance
        # A seen cell whose gradient normal faces away (a wall's edge) still counts, a little.
        score = np.clip(cosine, 0.01, 1.0) / distance ** 2
    return np.nan_to_num(score, nan=0.0)
