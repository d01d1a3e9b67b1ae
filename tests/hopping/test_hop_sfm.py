"""Structure from motion and the CPU dense cloud of one simulated hop (rvs_server/toolbox/hop_sfm.py),
checked against the simulator's truth after a similarity alignment (SfM has no scale or axes of its
own), and through process_hop's parabola fit, which must find the metric scale from the SfM centres.

One small hop (320x240, ~46 frames, no motion blur) over a 10 m rocky world, reconstructed once per
module: the whole file runs in about 20 s on a free core.
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from drivers.sim.config import WorldConfig
from drivers.sim.hopper import Hopper, HopperConfig, HopRecord
from drivers.sim.world import World
from rvs_server.hopping import sfm as hop_sfm
from toolbox.camera import Intrinsics, project
from toolbox.geometry import rotation_x, rotation_y
from toolbox.hopping import process_hop

# A mild barrel distortion, so the known-intrinsics path carries k1 and k2 through COLMAP and rectification.
CAMERA = {"width": 320, "height": 240, "motion_blur": False, "k1": -0.05, "k2": 0.005}


@pytest.fixture(scope="module")
def world() -> World:
    return World.build(WorldConfig(seed=3, size_m=(10.0, 10.0), cell_m=0.02, craters={"count": 0}))


@pytest.fixture(scope="module")
def hop(world) -> HopRecord:
    config = HopperConfig(camera=CAMERA, bounce={"count": 0})
    return Hopper(world, config, x=-2.0, y=-2.0, heading=math.radians(45.0)).hop(1.37, 60.0, 45.0, seed=7)


@pytest.fixture(scope="module")
def sfm(hop, tmp_path_factory) -> hop_sfm.HopReconstruction:
    return hop_sfm.reconstruct_hop(hop.frames, hop.timestamps, hop.camera, tmp_path_factory.mktemp("colmap"))


@pytest.fixture(scope="module")
def dense(hop, sfm) -> tuple[np.ndarray, np.ndarray]:
    return hop_sfm.densify(hop.frames, sfm, hop.camera)


@pytest.fixture(scope="module")
def to_world(hop, sfm):
    """The similarity taking the SfM frame onto the truth, fitted to the registered camera centres."""
    registered = sfm.registered
    scale, rotation, translation = hop_sfm.similarity_umeyama(sfm.camera_centres[registered],
                                                              hop.camera_to_world[registered, :3, 3])
    return scale, rotation, lambda points: scale * points @ rotation.T + translation


def height_errors(world: World, points: np.ndarray) -> np.ndarray:
    """Signed height of world points above the true terrain (rocks included); NaN off the world."""
    return points[:, 2] - world.height_at(points[:, 0], points[:, 1])


# ------------------------------------------------------------------------------------ SfM
def test_sfm_registers_the_hop_and_finds_its_trajectory(hop, sfm, to_world):
    assert sfm.registration_rate >= 0.8
    assert sfm.camera_centres.shape == (len(hop.frames), 3)
    assert np.isnan(sfm.camera_centres[~sfm.registered]).all()
    # The calibration went in with COLMAP's half-pixel shift and came out untouched.
    _, params = hop_sfm.colmap_camera(hop.camera)
    assert np.allclose(sfm.camera_params, params)
    assert sfm.reprojection_error < 0.7 and len(sfm.points) > 500
    # Centres after the similarity: within 2 % of the hop's range (measured: about 0.05 %).
    _, rotation, align = to_world
    truth = hop.camera_to_world[sfm.registered, :3, 3]
    rmse = np.sqrt(np.mean(np.sum((align(sfm.camera_centres[sfm.registered]) - truth) ** 2, axis=1)))
    assert rmse < 0.02 * hop.hop_range
    # Rotations too: camera-to-SfM turned by the same similarity is the true camera-to-world.
    for index in sfm.registered_indices[::5]:
        turned = rotation @ sfm.camera_rotations[index]
        error = math.degrees(math.acos(np.clip((np.trace(turned.T @ hop.camera_to_world[index, :3, :3]) - 1) / 2,
                                               -1, 1)))
        assert error < 0.5
    assert {"features", "matching", "mapping", "total"} <= sfm.timings.keys()


def test_the_incremental_mapper_finds_the_same_trajectory(hop, sfm, tmp_path):
    """The paper's incremental mapping stays available (hopping.toml sfm_mapper) and agrees on this hop."""
    # One thread makes it deterministic. With every core, the thread schedule varies the run, and this hop
    # came out bent in 2 of 7 runs here and once in CI (RMS 0.2 of its extent): the chance the module docstring names.
    config = hop_sfm.SfmConfig(mapper="incremental", num_threads=1)
    incremental = hop_sfm.reconstruct_hop(hop.frames, hop.timestamps, hop.camera, tmp_path, config)
    both = sfm.registered & incremental.registered
    assert both.mean() >= 0.8
    scale, rotation, translation = hop_sfm.similarity_umeyama(incremental.camera_centres[both],
                                                              sfm.camera_centres[both])
    moved = scale * incremental.camera_centres[both] @ rotation.T + translation
    extent = np.ptp(sfm.camera_centres[both], axis=0).max()
    assert np.sqrt(np.mean(np.sum((moved - sfm.camera_centres[both]) ** 2, axis=1))) < 0.01 * extent


def test_sparse_points_lie_on_the_terrain(world, sfm, to_world):
    _, _, align = to_world
    errors = height_errors(world, align(sfm.points))
    assert np.nanmedian(np.abs(errors)) < 0.01


# ------------------------------------------------------------------------------------ dense cloud
def test_dense_cloud_lies_on_the_terrain_and_covers_the_landing_area(world, hop, dense, to_world):
    points, colours = dense
    assert points.shape[1] == 3 and colours.shape == points.shape and colours.dtype == np.uint8
    _, _, align = to_world
    cloud = align(points)
    errors = np.abs(height_errors(world, cloud))
    assert np.nanmedian(errors) < 0.03                      # measured: about 4 mm
    assert np.nanpercentile(errors, 90) < 0.05
    # Area: occupied 5 cm cells.
    cells = np.unique(np.floor(cloud[:, :2] / 0.05).astype(int), axis=0)
    assert len(cells) * 0.05 ** 2 > 3.0                     # square metres
    # The landing area, which the next hop plans on, is mapped: most 5 cm cells within 30 cm of it.
    landing = hop.landing_centre[:2]
    near = np.linalg.norm((cells + 0.5) * 0.05 - landing, axis=1) < 0.3
    assert near.sum() > 0.6 * math.pi * 0.3 ** 2 / 0.05 ** 2


def test_process_hop_recovers_the_metric_scale_from_the_sfm_centres(world, hop, sfm, dense, to_world):
    # No spin: the camera keeps its offset from the centre of mass, so its centres fly the same parabola.
    true_scale, _, _ = to_world
    registered = sfm.registered
    result = process_hop(sfm.camera_centres[registered], hop.timestamps[registered], dense[0],
                         hop.camera_to_world[0, :3, 3], hop.launch_heading)
    scale_error = result.flight.scale / true_scale - 1
    print(f"\nscale through process_hop: {result.flight.scale:.5f} m/unit, truth {true_scale:.5f}, "
          f"error {100 * scale_error:+.3f} %")
    assert abs(scale_error) < 0.01
    # The metric cloud it makes, placed by the parabola's own gravity, is on the terrain too.
    assert np.nanmedian(np.abs(height_errors(world, result.cloud))) < 0.03


# ------------------------------------------------------------------------------------ pieces
def test_colmap_camera_picks_the_exact_model_and_shifts_the_principal_point():
    assert hop_sfm.colmap_camera(Intrinsics(64, 48, 50.0, 50.0, 31.5, 23.5)) == ("PINHOLE", [50.0, 50.0, 32.0, 24.0])
    assert hop_sfm.colmap_camera(Intrinsics(64, 48, 50.0, 50.0, 31.5, 23.5, -0.1, 0.01)) == \
        ("RADIAL", [50.0, 32.0, 24.0, -0.1, 0.01])
    assert hop_sfm.colmap_camera(Intrinsics(64, 48, 50.0, 52.0, 31.5, 23.5, -0.1))[0] == "OPENCV"


def test_pair_rectification_maps_a_point_to_one_row_at_its_disparity():
    # Two tilted cameras, the second mostly up the image from the first (a vertical pair, as on a hop).
    intrinsics = Intrinsics(320, 240, 200.0, 200.0, 159.5, 119.5, -0.05, 0.005)
    rotation = rotation_x(-0.4) @ rotation_y(0.2)
    centres = np.array([[0.0, 0.0, 0.0], [0.02, -0.1, 0.01]])
    pair = hop_sfm.pair_rectification(_two_cameras(rotation, centres), 0, 1, intrinsics, hop_sfm.DenseConfig())
    rect = pair.rectification
    baseline = float(np.linalg.norm(centres[1] - centres[0]))
    # A point seen at rectified pixel (u, v) with disparity 20 px: depth f B / 20.
    u, v, disparity = 150, 90, 20
    depth = rect.focal_px * baseline / disparity
    depth_map = np.full(rect.size[::-1], np.nan)
    depth_map[v, u] = depth
    points, _ = hop_sfm.rectified_points(pair, depth_map)
    point = points[0]
    # The rectification maps send (u, v) and (u - d, v) to where each real camera sees that point.
    for maps, centre, column in ((rect.left_maps, centres[0], u), (rect.right_maps, centres[1], u - disparity)):
        seen = project((point - centre) @ rotation, intrinsics)
        assert np.allclose([maps[0][v, column], maps[1][v, column]], seen, atol=1e-3)


def test_pairs_fall_back_to_a_smaller_angle_off_the_optical_axis_when_no_pair_reaches_the_preferred_one():
    # A steep hop flies along the camera's view: every baseline stands 45 degrees off the optical axis.
    direction = np.array([0.0, math.sin(math.radians(45)), math.cos(math.radians(45))])
    centres = 0.25 * np.arange(12)[:, None] * direction
    reconstruction = _two_cameras(np.eye(3), centres)
    depths = {k: (10.0, 5.0) for k in range(12)}
    pairs = hop_sfm.choose_pairs(reconstruction, depths, hop_sfm.DenseConfig())
    assert pairs[:4] == [(0, 4), (1, 5), (2, 6), (3, 7)]                  # baseline 1 m = 0.1 x depth
    assert hop_sfm.choose_pairs(reconstruction, depths, hop_sfm.DenseConfig(fallback_baseline_angle_deg=50.0)) == []
    # Where pairs reach the preferred angle, the fallback is not used: a sideways pass.
    sideways = _two_cameras(np.eye(3), 0.25 * np.arange(12)[:, None] * np.array([1.0, 0.0, 0.1]))
    assert hop_sfm.choose_pairs(sideways, depths, hop_sfm.DenseConfig()) == \
        hop_sfm.choose_pairs(sideways, depths, hop_sfm.DenseConfig(fallback_baseline_angle_deg=60.0))


def _two_cameras(rotation: np.ndarray, centres: np.ndarray) -> hop_sfm.HopReconstruction:
    n = len(centres)
    return hop_sfm.HopReconstruction(centres, np.repeat(rotation[None], n, axis=0), np.ones(n, bool),
                                     np.arange(n, dtype=float), np.zeros((0, 3)), np.zeros((0, 3), np.uint8),
                                     np.zeros(0, int), np.zeros(0), 0.0, np.zeros(0), 1)


def test_similarity_and_voxel_average():
    rng = np.random.default_rng(0)
    source = rng.normal(size=(20, 3))
    angle = 0.7
    rotation = np.array([[math.cos(angle), -math.sin(angle), 0], [math.sin(angle), math.cos(angle), 0], [0, 0, 1]])
    scale, found, translation = hop_sfm.similarity_umeyama(source, 2.5 * source @ rotation.T + [1.0, -2.0, 3.0])
    assert scale == pytest.approx(2.5) and np.allclose(found, rotation) and np.allclose(translation, [1, -2, 3])
    points = np.array([[0.01, 0.01, 0.01], [0.03, 0.03, 0.03], [0.51, 0.0, 0.0]])
    colours = np.array([[0, 0, 0], [100, 100, 100], [7, 7, 7]], np.uint8)
    merged, mean_colours = hop_sfm.voxel_average(points, colours, 0.1)
    order = np.argsort(merged[:, 0])
    assert np.allclose(merged[order], [[0.02] * 3, [0.51, 0.0, 0.0]])
    assert mean_colours[order].tolist() == [[50, 50, 50], [7, 7, 7]]


def test_bad_input_is_refused(tmp_path):
    intrinsics = Intrinsics(64, 48, 50.0, 50.0, 31.5, 23.5)
    frames = np.zeros((5, 48, 64), np.uint8)
    with pytest.raises(ValueError, match="intrinsics"):
        hop_sfm.reconstruct_hop(frames[:, :40], np.arange(5.0), intrinsics, tmp_path)
    with pytest.raises(ValueError, match="timestamps"):
        hop_sfm.reconstruct_hop(frames, np.arange(4.0), intrinsics, tmp_path)
    with pytest.raises(ValueError, match="uint8"):
        hop_sfm.reconstruct_hop(frames.astype(np.float32), np.arange(5.0), intrinsics, tmp_path)
    with pytest.raises(ValueError, match="mapper must be one of global, incremental, got 'sequential'"):
        hop_sfm.SfmConfig(mapper="sequential")
