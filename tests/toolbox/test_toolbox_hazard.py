"""toolbox.hazard against known answers, and the whole TOF chain on a small simulated scene."""
from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from scipy import ndimage

from drivers.sim.config import WorldConfig
from drivers.sim.render import render
from drivers.sim.rover import Rover
from drivers.sim.world import World
from toolbox import geometry as g
from toolbox.camera import Intrinsics
from toolbox.grid import GridSpec
from toolbox.mapping import dem as D
from toolbox.mapping import hazard as H
from toolbox.mapping import views as V

CELL = 0.02


def inclined_plane(slope_deg: float, azimuth: float, shape=(120, 150), z0: float = 250.0) -> np.ndarray:
    """A plane rising at slope_deg toward azimuth (radians from x), far from z = 0 on purpose."""
    rows, cols = np.mgrid[0:shape[0], 0:shape[1]]
    along = cols * CELL * math.cos(azimuth) + rows * CELL * math.sin(azimuth)
    return z0 + math.tan(math.radians(slope_deg)) * along


def interior(array: np.ndarray, margin: int = 15) -> np.ndarray:
    return array[margin:-margin, margin:-margin]


@pytest.fixture(params=["numpy", "compiled"])
def plane_fit_path(request, monkeypatch):
    """plane_fit in numpy (small grids) or through the compiled kernel (large ones), on any grid."""
    monkeypatch.setattr(H, "COMPILED_MIN_CELLS", 10 ** 12 if request.param == "numpy" else 0)
    return request.param


# ---------------------------------------------------------------------------------- slope, roughness
@pytest.mark.parametrize("slope_deg, azimuth", [(0.0, 0.0), (10.0, 0.3), (25.0, 2.0), (40.0, -1.2)])
def test_slope_of_a_plane(slope_deg, azimuth, plane_fit_path):
    slope, roughness = H.plane_fit(inclined_plane(slope_deg, azimuth), CELL, 0.1)
    assert np.abs(interior(slope) - slope_deg).max() < 1e-6
    assert interior(roughness).max() < 1e-6


def test_slope_ignores_unknown_cells(plane_fit_path):
    heights = inclined_plane(15.0, 0.7)
    rng = np.random.default_rng(0)
    heights[rng.random(heights.shape) < 0.3] = np.nan
    slope, roughness = H.plane_fit(heights, CELL, 0.1)
    known = np.isfinite(heights)
    assert np.isnan(slope[~known]).all() and np.isnan(roughness[~known]).all()
    assert np.nanmax(np.abs(interior(slope) - 15.0)) < 1e-6


def test_roughness_of_noise_is_its_sigma(plane_fit_path):
    rng = np.random.default_rng(1)
    sigma = 0.01
    heights = inclined_plane(12.0, 1.0, shape=(200, 200)) + rng.normal(0.0, sigma, (200, 200))
    slope, roughness = H.plane_fit(heights, CELL, 0.1)
    assert np.median(interior(roughness)) == pytest.approx(sigma, rel=0.03)
    assert np.median(interior(slope)) == pytest.approx(12.0, abs=0.3)


# ---------------------------------------------------------------------------------- step
def box_on_ground(height: float, side_cells: int, base: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    heights = np.zeros((100, 100)) if base is None else base.copy()
    box = np.zeros(heights.shape, bool)
    start = 50 - side_cells // 2
    box[start:start + side_cells, start:start + side_cells] = True
    heights[box] += height
    return heights, box


@pytest.mark.parametrize("side_cells", [8, 40])     # 0.16 m: narrower than the plate; 0.8 m: wider than the edge window
def test_step_of_a_box_is_its_height(side_cells):
    heights, box = box_on_ground(0.15, side_cells)
    step = H.step_height(heights, CELL, 0.1, 0.5)
    assert np.allclose(step[box], 0.15)             # the whole top, not just the rim
    far = ~ndimage.binary_dilation(box, iterations=3)
    assert np.abs(step[far]).max() < 1e-12


def test_a_slope_is_not_a_step():
    heights = inclined_plane(18.0, 0.4)
    step = H.step_height(heights, CELL, 0.1, 0.5)
    assert step.max() < 0.06                         # edge window only: 0.1 m * tan 18 * (|cos| + |sin|)
    assert np.abs(H.ground_surface(heights, 25) - heights).max() < 1e-9   # the plate alone: zero on a plane


def test_the_box_on_a_slope_keeps_its_height():
    heights, box = box_on_ground(0.15, 20, base=inclined_plane(10.0, 1.0, shape=(100, 100)))
    step = H.step_height(heights, CELL, 0.1, 0.5)
    assert np.abs(step[box] - 0.15).max() < 0.03       # the plate rests a little off the rock's own ground


def test_a_lone_spike_is_not_a_step_but_a_patch_is():
    heights = np.zeros((100, 100))
    heights[30, 30] = 0.15                           # one noisy cell
    heights[60:63, 60:63] = 0.15                     # nine cells: a small rock
    maps = H.hazard_maps(heights, CELL)
    step_bit = (maps.code & H.STEP) > 0
    assert not step_bit[25:36, 25:36].any()
    assert step_bit[60:63, 60:63].all()
    assert maps.step[30, 30] == pytest.approx(0.15 / 5)     # one agreeing cell of five needed


# ---------------------------------------------------------------------------------- hazard codes
def test_hazard_codes_keep_unknown_apart_from_safe():
    heights = inclined_plane(5.0, 0.0, shape=(100, 200))
    heights[:, 100:] = inclined_plane(30.0, 0.0, shape=(100, 100)) - inclined_plane(30.0, 0.0, (100, 100))[0, 0] \
        + heights[0, 99]
    heights[40:60, 20:40] = np.nan                   # a hole nobody saw
    heights[5, 5] = np.nan
    maps = H.hazard_maps(heights, CELL)
    code = maps.code
    assert code.dtype == np.uint8
    assert (code[40:60, 20:40] == H.UNKNOWN).all() and code[5, 5] == H.UNKNOWN
    assert (code[20:80, 45:85] == H.SAFE).all()                    # gentle 5 degrees
    assert (code[20:80, 125:180] == H.HAZARD | H.SLOPE).all()      # 30 degrees: hazard by slope only
    assert H.is_hazard(code[20:80, 125:180]).all()
    assert not H.is_hazard(code[40:60, 20:40]).any()               # unknown is not a hazard either
    assert np.isnan(maps.slope_deg[40:60, 20:40]).all()


def test_an_isolated_known_cell_is_unknown_not_safe():
    heights = np.full((50, 50), np.nan)
    heights[25, 25] = 1.0
    assert H.hazard_maps(heights, CELL).code[25, 25] == H.UNKNOWN


def test_a_rock_spreads_no_slope_or_roughness_around_itself():
    heights, box = box_on_ground(0.30, 12)           # a 0.6 m rock, 0.3 m tall
    maps = H.hazard_maps(heights, CELL)
    hazard = H.is_hazard(maps.code)
    assert hazard[box].all()                          # the rock is a step hazard
    beside = ndimage.binary_dilation(box, iterations=2) & ~box
    assert not hazard[~box & ~beside].any()           # nothing beyond 2 cells of its edge
    assert (maps.code[box] & H.STEP).all()


def test_roughness_limit_flags_a_rubble_field():
    rng = np.random.default_rng(3)
    heights = np.zeros((120, 120))
    heights[30:90, 30:90] = (rng.random((60, 60)) < 0.5) * 0.09   # stones just below the step limit
    maps = H.hazard_maps(heights, CELL)
    rough = (maps.code & H.ROUGHNESS) > 0
    assert rough[40:80, 40:80].all()
    assert not rough[:10].any()


# ---------------------------------------------------------------------------------- the reference
# hazard_maps as it was before issue 26 (ten float64 sepFilter2D correlations for the plane fit,
# float64 cv2.erode / cv2.dilate for the step, whole-grid numpy for the rest): slow (about 0.7 s on
# 1000 x 1000) but the definition the fast one is held to, on random DEMs with holes and a real one.
# tests/bench/bench_hazard.py times it as "before".
def reference_hazard_maps(heights: np.ndarray, cell: float,
                          config: H.HazardConfig = H.HazardConfig()) -> H.HazardMaps:
    heights = np.asarray(heights, dtype=np.float64)
    step = reference_step_height(heights, cell, config.step_radius, config.ground_radius)
    step = reference_agreed_step(step, cell, config.step_radius, config.step_limit, config.step_min_cells)
    # Slope and roughness are the ground's: cells that are already a step hazard (rocks) take no
    # part in the plane fit. Otherwise every rock spreads a ring of false slope and roughness
    # hazards a plane window wide around itself, which the planner's clearance then grows again:
    # on 15-20 % rock cover that ring held half the mapped hazards and closed open passages.
    ground = np.where(np.nan_to_num(step, nan=0.0) > config.step_limit, np.nan, heights)
    slope, roughness = reference_plane_fit(ground, cell, config.plane_radius)
    code = reference_hazard_code(heights, slope, step, roughness, config)
    return H.HazardMaps(slope.astype(np.float32), step.astype(np.float32), roughness.astype(np.float32), code)


def reference_plane_fit(heights: np.ndarray, cell: float, radius: float) -> tuple[np.ndarray, np.ndarray]:
    z = np.asarray(heights, dtype=np.float64)
    known = np.isfinite(z)
    if not known.any():
        nan = np.full(z.shape, np.nan)
        return nan, nan.copy()
    k = H.half_width(radius, cell)
    ones = np.ones(2 * k + 1)
    offsets = np.arange(-k, k + 1) * cell
    weight = known.astype(np.float64)
    zc = np.where(known, z - np.median(z[known]), 0.0)

    def window_sum(image, along_x, along_y):
        # kernelX runs along columns (x, east), kernelY along rows (y, north); correlation, zeros outside.
        return cv2.sepFilter2D(image, cv2.CV_64F, along_x, along_y, borderType=cv2.BORDER_CONSTANT)

    n = window_sum(weight, ones, ones)
    sx, sy = window_sum(weight, offsets, ones), window_sum(weight, ones, offsets)
    sxx, syy = window_sum(weight, offsets ** 2, ones), window_sum(weight, ones, offsets ** 2)
    sxy = window_sum(weight, offsets, offsets)
    sz, szz = window_sum(zc, ones, ones), window_sum(zc * zc, ones, ones)
    sxz, syz = window_sum(zc, offsets, ones), window_sum(zc, ones, offsets)
    with np.errstate(divide="ignore", invalid="ignore"):
        # Centre the sums on the window's mean (eliminates the plane's offset c).
        cxx, cyy, cxy = sxx - sx * sx / n, syy - sy * sy / n, sxy - sx * sy / n
        cxz, cyz, czz = sxz - sx * sz / n, syz - sy * sz / n, szz - sz * sz / n
        det = cxx * cyy - cxy * cxy
        a = (cyy * cxz - cxy * cyz) / det
        b = (cxx * cyz - cxy * cxz) / det
        residual = np.maximum(czz - a * cxz - b * cyz, 0.0)
        roughness = np.sqrt(residual / (n - 3))
    fit = known & (n >= H.MIN_FIT_CELLS - 0.5) & (det > 1e-12 * (cell ** 4) * n * n)
    slope = np.where(fit, np.degrees(np.arctan(np.hypot(a, b))), np.nan)
    return slope, np.where(fit, roughness, np.nan)


def reference_step_height(heights: np.ndarray, cell: float, edge_radius: float,
                          ground_radius: float | None = None) -> np.ndarray:
    z = np.asarray(heights, dtype=np.float64)
    known = np.isfinite(z)
    step = z - reference_local_minimum(z, H.half_width(edge_radius, cell))
    if ground_radius:
        step = np.maximum(step, z - reference_ground_surface(z, H.half_width(ground_radius, cell)))
    return np.where(known, step, np.nan)


def reference_local_minimum(z: np.ndarray, k: int) -> np.ndarray:
    kernel = np.ones((2 * k + 1, 2 * k + 1), np.uint8)
    return cv2.erode(np.where(np.isfinite(z), z, np.inf), kernel, borderType=cv2.BORDER_CONSTANT,
                     borderValue=np.inf)


def reference_ground_surface(z: np.ndarray, k: int) -> np.ndarray:
    kernel = np.ones((2 * k + 1, 2 * k + 1), np.uint8)
    # Beyond the grid is unknown like any unseen cell: the plate may hang over it, resting on known
    # cells only (else a plane would read as a step along the grid's uphill edges).
    padded = np.pad(z, k, constant_values=np.nan)
    eroded = reference_local_minimum(padded, k)
    eroded = np.where(np.isfinite(eroded), eroded, -np.inf)
    opened = cv2.dilate(eroded, kernel, borderType=cv2.BORDER_CONSTANT, borderValue=-np.inf)
    return opened[k:-k, k:-k]


def reference_agreed_step(step: np.ndarray, cell: float, radius: float, limit: float,
                          min_cells: int) -> np.ndarray:
    k = H.half_width(radius, cell)
    over = (np.nan_to_num(step, nan=0.0) > limit).astype(np.float64)
    agreeing = cv2.boxFilter(over, -1, (2 * k + 1, 2 * k + 1), normalize=False, borderType=cv2.BORDER_CONSTANT)
    return step * np.minimum(1.0, agreeing / min_cells)


def reference_hazard_code(heights: np.ndarray, slope_deg: np.ndarray, step: np.ndarray, roughness: np.ndarray,
                          config: H.HazardConfig) -> np.ndarray:
    causes = ((slope_deg > config.slope_limit_deg) * H.SLOPE | (step > config.step_limit) * H.STEP
              | (roughness > config.roughness_limit) * H.ROUGHNESS).astype(np.uint8)
    code = np.where(causes > 0, causes | H.HAZARD, H.SAFE).astype(np.uint8)
    measured = np.isfinite(slope_deg) & np.isfinite(step) & np.isfinite(roughness)
    code[(code == H.SAFE) & ~measured] = H.UNKNOWN
    code[~np.isfinite(heights)] = H.UNKNOWN
    return code


def random_dem(rng: np.random.Generator, shape, z0: float = 0.0, single: bool = True) -> np.ndarray:
    """Rolling ground with rocks, 1 cm noise, 10 % unknown cells and a few unseen patches; float32
    values (as a Dem holds) or float64 ones float32 cannot hold."""
    rows, cols = np.mgrid[0:shape[0], 0:shape[1]] * CELL
    heights = z0 + 0.4 * np.sin(cols / 1.3) * np.cos(rows / 1.7) + 0.08 * cols
    for _ in range(shape[0] * shape[1] // 2500):
        r0, c0 = rng.uniform(0, shape[0] * CELL), rng.uniform(0, shape[1] * CELL)
        radius, height = rng.uniform(0.05, 0.3), rng.uniform(0.03, 0.3)
        heights += height * np.sqrt(np.clip(1 - ((rows - r0) ** 2 + (cols - c0) ** 2) / radius ** 2, 0, None))
    heights += rng.normal(0, 0.01, heights.shape)
    heights[rng.random(heights.shape) < 0.10] = np.nan
    for _ in range(5):
        r, c = rng.integers(0, shape[0]), rng.integers(0, shape[1])
        heights[r:r + rng.integers(3, 40), c:c + rng.integers(3, 40)] = np.nan
    return heights.astype(np.float32) if single else heights


def assert_same_maps(maps: H.HazardMaps, reference: H.HazardMaps) -> None:
    """The same maps within float32 rounding (the slope's arctan and the window sums' order aside)."""
    for name, atol in (("slope_deg", 1e-4), ("step", 1e-7), ("roughness", 1e-6)):
        ours, theirs = getattr(maps, name), getattr(reference, name)
        assert ours.dtype == np.float32 and ours.shape == theirs.shape
        assert np.array_equal(np.isnan(ours), np.isnan(theirs)), name
        np.testing.assert_allclose(ours, theirs, rtol=1e-6, atol=atol, equal_nan=True, err_msg=name)
    assert np.array_equal(maps.code, reference.code)


@pytest.mark.parametrize("seed, shape, z0, single", [(0, (160, 190), 0.0, True), (1, (217, 143), 250.0, True),
                                                     (2, (150, 150), 250.0, False), (3, (60, 400), -3.0, False)])
def test_hazard_maps_are_the_reference_on_random_dems(plane_fit_path, seed, shape, z0, single):
    heights = random_dem(np.random.default_rng(seed), shape, z0, single)
    assert_same_maps(H.hazard_maps(heights, CELL), reference_hazard_maps(heights, CELL))
    config = H.HazardConfig(plane_radius=0.1, step_radius=0.06, ground_radius=0.3, step_min_cells=3)
    assert_same_maps(H.hazard_maps(heights, 0.03, config), reference_hazard_maps(heights, 0.03, config))


def test_hazard_maps_are_the_reference_on_a_large_dem():
    """Past COMPILED_MIN_CELLS without any patching: the server's path for a full map."""
    heights = random_dem(np.random.default_rng(4), (400, 300))
    assert heights.size >= H.COMPILED_MIN_CELLS
    assert_same_maps(H.hazard_maps(heights, CELL), reference_hazard_maps(heights, CELL))


@pytest.mark.parametrize("k", [0, 1, 2, 5, 12, 25])
def test_grey_morphology_is_cv2s_to_the_bit(k):
    rng = np.random.default_rng(k)
    image = rng.normal(0.0, 1.0, (70, 90)) + 100.0            # float64 values float32 cannot hold
    image[rng.random(image.shape) < 0.2] = np.inf
    square = np.ones((2 * k + 1, 2 * k + 1), np.uint8)
    for minimum, morph, border in ((True, cv2.erode, np.inf), (False, cv2.dilate, -np.inf)):
        expected = morph(image, square, borderType=cv2.BORDER_CONSTANT, borderValue=border)
        assert np.array_equal(H.box_extreme(image, k, minimum), expected)
        assert np.array_equal(H.box_extreme(image.astype(np.float32).astype(np.float64), k, minimum),
                              morph(image.astype(np.float32), square, borderType=cv2.BORDER_CONSTANT,
                                    borderValue=border))


# ---------------------------------------------------------------------------------- the simulated scene
@pytest.fixture(scope="module")
def scene():
    """A rocky 8 x 8 m world without craters, and a TOF-like panorama from a rover near its centre:
    rendered ranges along the true rays plus 5 mm noise, taken to the world with the calibrated
    mounts (as RVS would), through the DEM chain at 3 cm."""
    world = World.build(WorldConfig(seed=3, size_m=(8.0, 8.0), craters={"count": 0}))
    rover = Rover(world, x=0.0, y=0.0, heading=0.3)
    camera = Intrinsics.from_fov(176, 144, math.radians(43.6))
    rays = camera.ray_directions().astype(np.float64)
    fov = (math.radians(43.6), 2 * math.atan(72 / camera.fy))
    views = V.plan_views((-math.pi, math.pi), (math.radians(-65), math.radians(-20)), *fov, overlap=0.1)
    rng = np.random.default_rng(0)
    pose = g.RoverPose.from_matrix(rover.body_to_world)
    mounts = rover.calibrated_mounts["tof"]
    mount = g.SensorMount.from_offsets(rover.config.ptu_position_m, mounts.position_m, mounts.rotation_deg)
    clouds = []
    for pan, tilt in views:
        view = render(world, rover.sensor_to_world("tof", math.degrees(pan), math.degrees(tilt)), camera, shadows=False)
        ranges = view.range.astype(np.float64) + rng.normal(0.0, 0.005, view.range.shape)
        clouds.append(D.view_points(rays * ranges[..., None], None, g.camera_to_world(pose, mount, pan, tilt)))
    spec = GridSpec.covering((-4.0, 4.0), (-4.0, 4.0), 0.03)
    footprint = g.footprint_polygon(pose, rover.config.body_length_m, rover.config.body_width_m)
    dem = D.dem_from_points(np.concatenate(clouds), spec, footprint)
    return world, rover, dem


def test_simulated_dem_matches_the_truth_at_the_noise_level(scene):
    world, rover, dem = scene
    spec = dem.spec
    truth = world.height_map(spec.cell, spec.x_range, spec.y_range)
    rocky = world.obstacle_mask(0.005, spec.cell, spec.x_range, spec.y_range)
    measured = dem.counts > 0
    assert measured.mean() > 0.6
    # Bare ground away from rocks: the error is the 5 mm noise (a little up: the highest point wins).
    bare = measured & ~ndimage.binary_dilation(rocky)
    error = (dem.heights - truth)[bare]
    assert np.sqrt(np.mean(error ** 2)) < 0.008
    assert 0.0 < np.mean(error) < 0.008
    # Everywhere, rocks' sharp edges included (the cell's top against its centre): within 2 cm RMS.
    assert np.sqrt(np.nanmean((dem.heights - truth) ** 2)) < 0.02
    # No point of the rover's own body made it in, and its footprint is unknown.
    xs, ys = spec.centres()
    under = D.inside_polygon(np.c_[np.repeat(xs[None], len(ys), 0).ravel(), np.repeat(ys, len(xs))],
                             rover.footprint())
    assert (dem.counts.ravel()[under] == 0).all()


def test_simulated_hazards_find_the_obstacles(scene):
    world, _, dem = scene
    spec = dem.spec
    maps = H.hazard_maps(dem.heights, spec.cell)
    known = maps.code != H.UNKNOWN
    obstacles = world.obstacle_mask(0.10, spec.cell, spec.x_range, spec.y_range) & known
    hazard = H.is_hazard(maps.code)
    step = (maps.code & H.STEP) > 0
    assert obstacles.sum() > 500
    assert (step & obstacles).sum() / obstacles.sum() > 0.95          # step alone finds them
    assert (hazard & obstacles).sum() / obstacles.sum() > 0.97
    # Rock-free ground more than 0.3 m from any rock taller than 5 cm is almost all safe.
    rocks = world.obstacle_mask(0.05, spec.cell, spec.x_range, spec.y_range)
    clear = known & ~ndimage.binary_dilation(rocks, iterations=10)
    assert clear.sum() > 20000
    assert hazard[clear].mean() < 0.02


def test_hazard_maps_are_the_reference_on_the_simulated_dem(scene, plane_fit_path):
    dem = scene[2]
    assert dem.heights.dtype == np.float32 and np.isnan(dem.heights).any()
    assert_same_maps(H.hazard_maps(dem.heights, dem.spec.cell), reference_hazard_maps(dem.heights, dem.spec.cell))
