"""toolbox.dem (direct reconstruction, hole filling, rover body, artifacts, mosaic) and toolbox.ortho."""
from __future__ import annotations

import math

import numpy as np
import open3d as o3d
import pytest

from toolbox import geometry as g
from toolbox.camera import Intrinsics
from toolbox.grid import GridSpec
from toolbox.mapping import dem as D
from toolbox.mapping import ortho as O

SR4000 = Intrinsics.from_fov(176, 144, math.radians(43.6))


def plane_heights(spec: GridSpec, gx: float = 0.1, gy: float = -0.05, z0: float = 1.0) -> np.ndarray:
    xs, ys = spec.centres()
    return z0 + gx * xs[None, :] + gy * ys[:, None]


# ---------------------------------------------------------------------------------- direct reconstruction
def test_the_highest_point_wins_and_counts_are_kept():
    spec = GridSpec(0.0, 0.0, 0.1, 3, 4)
    points = np.array([[0.05, 0.05, 1.0], [0.06, 0.04, 1.5], [0.01, 0.09, 0.2],   # cell (0, 0): three points
                       [0.35, 0.25, -2.0],                                      # cell (2, 3)
                       [0.20, 0.10, 7.0],                                       # on a boundary: cell (1, 2)
                       [0.45, 0.05, 9.0], [np.nan, 0.1, 1.0]])                  # outside, NaN
    dem = D.points_to_dem(points, spec)
    assert dem.heights.dtype == np.float32 and dem.counts.dtype == np.int32
    assert dem.heights[0, 0] == pytest.approx(1.5) and dem.counts[0, 0] == 3
    assert dem.heights[2, 3] == pytest.approx(-2.0) and dem.counts[2, 3] == 1
    assert dem.heights[1, 2] == pytest.approx(7.0)
    assert np.isnan(dem.heights).sum() == 12 - 3 and dem.counts.sum() == 5


def test_maximum_agrees_with_a_plain_loop():
    rng = np.random.default_rng(1)
    spec = GridSpec(-1.0, -2.0, 0.05, 40, 30)
    points = np.c_[rng.uniform(-1.2, 0.7, 5000), rng.uniform(-2.2, 0.2, 5000), rng.normal(size=5000)]
    expected = np.full(spec.shape, -np.inf)
    for x, y, z in points:
        col, row = math.floor((x + 1.0) / 0.05), math.floor((y + 2.0) / 0.05)
        if 0 <= row < 40 and 0 <= col < 30:
            expected[row, col] = max(expected[row, col], z)
    dem = D.points_to_dem(points, spec)
    assert np.array_equal(np.isnan(dem.heights), np.isinf(expected))
    assert np.allclose(dem.heights[np.isfinite(expected)], expected[np.isfinite(expected)], atol=1e-6)


def reference_points_to_dem(points: np.ndarray, spec: GridSpec) -> tuple[np.ndarray, np.ndarray]:
    """points_to_dem as it was before the compiled kernel: cell index, np.maximum.at, bincount."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    col = (points[:, 0] - spec.origin_x) / spec.cell
    row = (points[:, 1] - spec.origin_y) / spec.cell
    inside = (col >= 0) & (col < spec.cols) & (row >= 0) & (row < spec.rows) & np.isfinite(points[:, 2])
    flat = row[inside].astype(np.int64) * spec.cols + col[inside].astype(np.int64)
    heights = np.full(spec.rows * spec.cols, -np.inf)
    np.maximum.at(heights, flat, points[inside, 2])
    counts = np.bincount(flat, minlength=spec.rows * spec.cols).astype(np.int32)
    heights[counts == 0] = np.nan
    return heights.astype(np.float32).reshape(spec.shape), counts.reshape(spec.shape)


@pytest.mark.parametrize("count", [1000, D.COMPILED_MIN_POINTS + 1, 400_000])
def test_gridding_is_the_same_as_before_to_the_bit(count):
    """Both paths (numpy below COMPILED_MIN_POINTS, the compiled kernel above) against the old code,
    on points inside and outside the grid, exactly on cell boundaries, NaN, infinite and tied."""
    rng = np.random.default_rng(count)
    spec = GridSpec(-3.0, 1.5, 0.02, 210, 330)
    points = np.c_[rng.uniform(-3.5, 4.0, count), rng.uniform(1.0, 6.0, count), rng.normal(0.0, 1.0, count)]
    edges = rng.random(count) < 0.1                   # on cell boundaries: the floor must match
    points[edges, 0] = -3.0 + rng.integers(-2, 333, edges.sum()) * 0.02
    points[edges, 1] = 1.5 + rng.integers(-2, 213, edges.sum()) * 0.02
    bad = rng.integers(0, count, (4, count // 50))
    points[bad[0], 0], points[bad[1], 1], points[bad[2], 2] = np.nan, np.inf, np.nan
    points[bad[3], 2] = -np.inf
    points[rng.integers(0, count, count // 20), 2] = 0.25   # ties and -0.0 against 0.0
    points[rng.integers(0, count, count // 50), 2] = -0.0
    heights, counts = reference_points_to_dem(points, spec)
    dem = D.points_to_dem(points, spec)
    assert dem.heights.dtype == np.float32 and dem.counts.dtype == np.int32
    assert np.array_equal(dem.counts, counts)
    assert np.array_equal(dem.heights, heights, equal_nan=True)
    # The kernel directly, on the same small cloud the numpy path took above.
    from toolbox.mapping import _dem_kernel
    kernel_heights, kernel_counts = _dem_kernel.points_to_dem_arrays(points, spec.origin_x, spec.origin_y,
                                                                     spec.cell, spec.rows, spec.cols)
    assert np.array_equal(kernel_counts.reshape(spec.shape), counts)
    assert np.array_equal(kernel_heights.reshape(spec.shape), heights, equal_nan=True)


def test_the_top_band_mean_is_unbiased_on_flat_ground_and_keeps_a_rock_edge():
    """Flat cells of 20 noisy points: the highest reads about +1.9 sigma high, the mean of the top
    3.5 sigma within 0.3 sigma. A cell holding a rock's top (10 cm) and the ground beside it reads the top."""
    rng = np.random.default_rng(7)
    sigma, spec = 0.01, GridSpec(origin_x=0.0, origin_y=0.0, cell=0.05, rows=40, cols=40)
    xy = rng.uniform(0, 2.0, (32_000, 2))
    flat = np.column_stack([xy, rng.normal(0.0, sigma, len(xy))])
    highest = D.points_to_dem(flat, spec).heights
    banded = D.points_to_dem(flat, spec, top_band=3.5 * sigma).heights
    assert 1.6 * sigma < np.mean(highest) < 2.2 * sigma
    assert abs(np.mean(banded)) < 0.3 * sigma
    edge = np.array([[0.01, 0.01, 0.0], [0.02, 0.01, 0.001], [0.03, 0.02, 0.1], [0.04, 0.03, 0.098]])
    assert D.points_to_dem(edge, spec, top_band=0.02).heights[0, 0] == pytest.approx(0.099, abs=1e-6)
    with pytest.raises(ValueError, match="top_band"):
        D.points_to_dem(flat, spec, top_band=-0.01)


def test_the_top_band_is_the_same_in_numpy_and_in_the_kernel():
    rng = np.random.default_rng(8)
    spec = GridSpec(origin_x=-1.0, origin_y=-1.0, cell=0.02, rows=100, cols=100)
    points = np.column_stack([rng.uniform(-1.1, 1.1, (D.COMPILED_MIN_POINTS + 5, 2)),
                              rng.normal(0, 0.02, D.COMPILED_MIN_POINTS + 5)])
    compiled = D.points_to_dem(points, spec, top_band=0.015)
    numpy_path = D._points_to_dem_numpy(points, spec, top_band=0.015)
    assert np.array_equal(compiled.heights, numpy_path.heights, equal_nan=True)
    assert np.array_equal(compiled.counts, numpy_path.counts)


def test_grid_covering_holds_every_point_and_is_aligned():
    rng = np.random.default_rng(2)
    points = np.c_[rng.uniform(-3.3, 2.1, 500), rng.uniform(4.0, 6.5, 500), rng.normal(size=500)]
    points[0, :2] = (2.2, 6.6)                  # exactly on a cell boundary
    spec = D.grid_covering(points, 0.2)
    _, _, inside = spec.cell_of(points[:, 0], points[:, 1])
    assert inside.all()
    assert spec.origin_x / 0.2 == pytest.approx(round(spec.origin_x / 0.2))
    assert spec.origin_y / 0.2 == pytest.approx(round(spec.origin_y / 0.2))
    margin = D.grid_covering(points, 0.2, margin=0.5)
    assert margin.x_range[0] <= points[:, 0].min() - 0.5 and margin.y_range[1] >= points[:, 1].max() + 0.5
    with pytest.raises(ValueError):
        D.grid_covering(np.full((3, 3), np.nan), 0.1)


# ---------------------------------------------------------------------------------- hole filling
def test_small_holes_are_filled_and_big_ones_stay_unknown():
    spec = GridSpec(0.0, 0.0, 0.05, 60, 60)
    truth = plane_heights(spec)
    heights = truth.astype(np.float32).copy()
    heights[10:12, 10:15] = np.nan               # a 2-cell-wide gap: filled
    heights[30, 30] = np.nan                     # a single cell: filled
    heights[35:50, 35:50] = np.nan               # 15 x 15 cells: stays unknown
    heights[0:4, 20:30] = np.nan                 # small, but open to the edge: no data beyond, stays unknown
    counts = np.where(np.isfinite(heights), 1, 0).astype(np.int32)
    filled = D.fill_small_holes(D.Dem(spec, heights, counts), max_reach_cells=3)
    small = np.zeros(spec.shape, bool)
    small[10:12, 10:15] = small[30, 30] = True
    assert np.isfinite(filled.heights[small]).all()
    # On a plane the rim-inwards averaging is off by at most the rise over a cell or two.
    assert np.abs(filled.heights[small] - truth[small]).max() < 2 * 0.05 * 0.15
    assert np.isnan(filled.heights[35:50, 35:50]).all()
    assert np.isnan(filled.heights[0:4, 20:30]).all()
    assert (filled.counts[small] == 0).all()                     # filled cells are not measured cells
    assert np.array_equal(filled.heights[np.isfinite(heights)], heights[np.isfinite(heights)])


def test_a_long_thin_gap_is_filled_a_wide_one_is_not():
    spec = GridSpec(0.0, 0.0, 0.05, 40, 80)
    heights = plane_heights(spec).astype(np.float32)
    heights[10:13, 5:75] = np.nan       # 3 cells wide, 70 long: every cell within 2 cells of data
    heights[25:35, 5:75] = np.nan       # 10 cells wide
    dem = D.fill_small_holes(D.Dem(spec, heights, np.isfinite(heights).astype(np.int32)), 3)
    assert np.isfinite(dem.heights[10:13, 5:75]).all()
    assert np.isnan(dem.heights[25:35, 5:75]).all()


# ---------------------------------------------------------------------------------- rover body
def test_points_on_the_rover_are_removed():
    footprint = g.footprint_polygon(g.RoverPose(1.0, 2.0, heading=0.6), 0.55, 0.50)
    rng = np.random.default_rng(3)
    points = np.c_[rng.uniform(0, 2, 4000), rng.uniform(1, 3, 4000), rng.uniform(0, 1.6, 4000)]
    kept = D.remove_rover_body(points, footprint)
    local = g.apply(g.invert(g.RoverPose(1.0, 2.0, heading=0.6).to_world()), points)
    on_rover = (np.abs(local[:, 0]) < 0.275) & (np.abs(local[:, 1]) < 0.25)
    assert len(kept) == (~on_rover).sum()
    grown = D.remove_rover_body(points, footprint, margin=0.1)
    near = (np.abs(local[:, 0]) < 0.375) & (np.abs(local[:, 1]) < 0.35)
    assert len(grown) == (~near).sum()


def test_inside_polygon_on_a_concave_shape():
    l_shape = np.array([[0, 0], [2, 0], [2, 1], [1, 1], [1, 2], [0, 2]], dtype=float)
    xy = np.array([[0.5, 0.5], [1.5, 0.5], [0.5, 1.5], [1.5, 1.5], [3.0, 0.5], [-0.1, 1.0]])
    assert D.inside_polygon(xy, l_shape).tolist() == [True, True, True, False, False, False]
    assert D.inside_polygon(xy, l_shape[::-1]).tolist() == [True, True, True, False, False, False]


# ---------------------------------------------------------------------------------- artifacts
def ray_cast_view(meshes, camera_to_world, intrinsics=SR4000):
    """Organized camera-frame points and the index of the mesh each pixel hit (-1: none)."""
    scene = o3d.t.geometry.RaycastingScene()
    ids = [scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(m)) for m in meshes]
    u, v = np.meshgrid(np.arange(intrinsics.width), np.arange(intrinsics.height))
    directions = np.stack([(u - intrinsics.cx) / intrinsics.fx, (v - intrinsics.cy) / intrinsics.fy,
                           np.ones(u.shape)], axis=-1)
    directions /= np.linalg.norm(directions, axis=-1, keepdims=True)
    rays = np.concatenate([np.broadcast_to(camera_to_world[:3, 3], directions.shape),
                           directions @ camera_to_world[:3, :3].T], axis=-1).astype(np.float32)
    result = scene.cast_rays(o3d.core.Tensor(rays))
    t_hit = result["t_hit"].numpy().astype(np.float64)
    geometry = result["geometry_ids"].numpy().astype(np.int64)
    hit = np.isfinite(t_hit)
    which = np.where(hit, np.searchsorted(ids, geometry), -1)
    points = directions * np.where(hit, t_hit, np.nan)[..., None]
    return points, which


def rock_and_blob_scene():
    """Flat ground, a half-buried rock (a dome of radius 0.15 m) and a blob of the same size
    floating 0.4 m above the ground, seen from a mast 1.5 m high looking 30 degrees down."""
    ground = o3d.geometry.TriangleMesh.create_box(20, 20, 0.1).translate((-10, -10, -0.1))
    rock = o3d.geometry.TriangleMesh.create_sphere(0.15, 40).translate((2.5, -0.4, 0.0))
    blob = o3d.geometry.TriangleMesh.create_sphere(0.15, 40).translate((2.5, 0.4, 0.4))
    mount = g.SensorMount.from_offsets((0.0, 0.0, 1.5), (0.0, 0.0, 0.0))
    pose = g.camera_to_world(g.RoverPose(0.0, 0.0), mount, 0.0, math.radians(-30))
    points, which = ray_cast_view([ground, rock, blob], pose)
    return points, which, pose


def test_a_floating_blob_goes_and_a_rock_of_its_size_stays():
    points, which, _ = rock_and_blob_scene()
    ground, rock, blob = which == 0, which == 1, which == 2
    assert rock.sum() > 300 and blob.sum() > 300          # same size in the image, well over 64 pixels
    # A patch of ground pushed 15 % farther away (multipath): a blob below the ground.
    below = np.zeros_like(ground)
    below[20:30, 20:32] = True
    assert ground[below].all()
    points = points.copy()
    points[below] *= 1.15
    removed = D.isolated_blobs(points, 1000, 0.05)
    assert removed[blob].mean() > 0.99
    assert removed[below].mean() > 0.99
    assert removed[rock].mean() < 0.01
    assert removed[ground & ~below].mean() < 0.001


def test_view_points_drops_invalid_pixels_and_blobs():
    points, which, pose = rock_and_blob_scene()
    valid = np.ones(which.shape, bool)
    valid[:, :10] = False
    world = D.view_points(points, valid, pose, D.DemConfig(max_blob_pixels=1000))
    expected = (which >= 0) & (which != 2) & valid
    assert len(world) == expected.sum()
    assert np.allclose(world, g.apply(pose, points[expected]))
    assert world[:, 2].max() < 0.16                        # the rock's top, not the blob's


# ---------------------------------------------------------------------------------- mosaic
def test_mosaic_prefers_the_cell_seen_with_more_points():
    a_spec, b_spec = GridSpec(0.0, 0.0, 0.1, 4, 4), GridSpec(0.2, 0.1, 0.1, 4, 4)
    a = D.Dem(a_spec, np.full((4, 4), 1.0, np.float32), np.full((4, 4), 5, np.int32))
    b_heights, b_counts = np.full((4, 4), 2.0, np.float32), np.full((4, 4), 3, np.int32)
    b_counts[0, 0] = 9                        # world cell (row 1, col 2): b saw it better
    b_counts[0, 1] = 5                        # a tie on (1, 3): the higher wins
    b_heights[1, 0], b_counts[1, 0] = np.nan, 0     # b never saw (2, 2): a's value stays
    a.counts[3, 3] = 0                        # a only filled (3, 3); b measured it
    b = D.Dem(b_spec, b_heights, b_counts)
    merged = D.mosaic([a, b])
    assert merged.spec == GridSpec(0.0, 0.0, 0.1, 5, 6)
    h = merged.heights
    assert h[1, 2] == 2.0 and h[1, 3] == 2.0 and h[2, 2] == 1.0 and h[3, 3] == 2.0
    assert h[2, 3] == 1.0                     # a's 5 points beat b's 3
    assert np.isnan(h[0, 4])                  # nobody saw it
    assert h[4, 5] == 2.0 and h[0, 0] == 1.0
    assert merged.counts[1, 2] == 9
    # Order does not matter.
    assert np.array_equal(D.mosaic([b, a]).heights, h, equal_nan=True)


def test_mosaic_refuses_grids_that_do_not_line_up():
    a = D.Dem(GridSpec(0.0, 0.0, 0.1, 2, 2), np.zeros((2, 2), np.float32), np.ones((2, 2), np.int32))
    shifted = D.Dem(GridSpec(0.05, 0.0, 0.1, 2, 2), np.zeros((2, 2), np.float32), np.ones((2, 2), np.int32))
    coarser = D.Dem(GridSpec(0.0, 0.0, 0.2, 2, 2), np.zeros((2, 2), np.float32), np.ones((2, 2), np.int32))
    for other in (shifted, coarser):
        with pytest.raises(ValueError):
            D.mosaic([a, other])


# ---------------------------------------------------------------------------------- ortho-images
def wall_scene():
    """Flat ground at z = 0 with a wall 0.5 m high along x = 2 (columns 40-41 of 5 cm cells), and a
    camera at the origin 1 m up looking east and down at 20 degrees."""
    spec = GridSpec(0.0, -1.0, 0.05, 40, 80)
    heights = np.zeros(spec.shape, np.float32)
    heights[:, 40:42] = 0.5
    mount = g.SensorMount.from_offsets((0.0, 0.0, 1.0), (0.0, 0.0, 0.0))
    pose = g.camera_to_world(g.RoverPose(0.0, 0.0), mount, 0.0, math.radians(-20))
    intrinsics = Intrinsics.from_fov(320, 240, math.radians(70))
    return spec, heights, pose, intrinsics


def ramp_image(intrinsics):
    v, u = np.mgrid[0:intrinsics.height, 0:intrinsics.width]
    return (u + 1000.0 * v).astype(np.float32)


@pytest.mark.parametrize("use_depth_image", [False, True])
def test_ortho_samples_the_picture_and_hides_what_the_wall_hides(use_depth_image):
    spec, heights, pose, intrinsics = wall_scene()
    depth = None
    if use_depth_image:
        ground = o3d.geometry.TriangleMesh.create_box(10, 10, 0.1).translate((-5, -5, -0.1))
        wall = o3d.geometry.TriangleMesh.create_box(0.1, 10, 0.5).translate((2.0, -5, 0.0))
        points, _ = ray_cast_view([ground, wall], pose, intrinsics)
        depth = np.where(np.isfinite(points[..., 2]), points[..., 2], np.inf)
    view = O.ortho_image(heights, spec, ramp_image(intrinsics), intrinsics, pose, depth_image=depth)
    uv, _ = O.project_cells(O.cell_points(heights, spec), intrinsics, pose)
    in_frame = O.inside_frame(uv, intrinsics)
    seen = np.isfinite(view.intensity)
    # Bilinear on a linear ramp is exact: the value tells where the cell landed in the picture.
    assert np.allclose(view.intensity[seen], (uv[..., 0] + 1000 * uv[..., 1])[seen], atol=1e-3)
    # In front of the wall every cell in the frame is seen; right behind it (shadow 0.5 m / 0.5 of
    # the camera's height over the wall's distance) nothing is; far behind, the ground shows again.
    front = np.zeros(spec.shape, bool)
    front[:, 10:39] = True
    shadow = np.zeros(spec.shape, bool)
    shadow[:, 43:75] = True                      # x from 2.15 m to 3.75 m: shadow reaches 4 m
    assert seen[front & in_frame].mean() > 0.99
    assert not seen[shadow].any()
    assert seen[:, 40:42][in_frame[:, 40:42]].mean() > 0.99      # the wall's top is seen
    assert (view.score[seen] > 0).all() and (view.score[~seen] == 0).all()


def test_merging_prefers_the_closer_view():
    spec = GridSpec(0.0, -1.0, 0.05, 40, 80)
    heights = np.zeros(spec.shape, np.float32)
    intrinsics = Intrinsics.from_fov(320, 240, math.radians(90))
    mount = g.SensorMount.from_offsets((0.0, 0.0, 1.5), (0.0, 0.0, 0.0))
    near = g.camera_to_world(g.RoverPose(3.0, 0.0, heading=math.pi), mount, 0.0, math.radians(-45))
    far = g.camera_to_world(g.RoverPose(-1.0, 0.0), mount, 0.0, math.radians(-30))
    views = [O.ortho_image(heights, spec, np.full((240, 320), value, np.float32), intrinsics, pose)
             for value, pose in ((1.0, near), (2.0, far))]
    merged = O.merge_views(views)
    xs, _ = spec.centres()
    both = np.isfinite(views[0].intensity) & np.isfinite(views[1].intensity)
    nearer_to_near = np.broadcast_to(np.abs(xs - 3.0) < np.abs(xs + 1.0), spec.shape)
    assert both.sum() > 200
    assert (merged[both & nearer_to_near] == 1.0).all()
    only_far = np.isfinite(views[1].intensity) & ~np.isfinite(views[0].intensity)
    assert (merged[only_far] == 2.0).all()
    assert np.isnan(merged[~np.isfinite(views[0].intensity) & ~np.isfinite(views[1].intensity)]).all()
