"""Structure from motion and a CPU dense cloud for one hop's frames (hopping paper, "Scene reconstruction").

Not in toolbox/: COLMAP works through a database and image files in a working folder.

    sfm = reconstruct_hop(frames, timestamps, intrinsics, workdir)   # COLMAP via pycolmap, CPU
    points, colours = densify(frames, sfm, intrinsics)               # rectified pairs + SGBM
    result = hopping.process_hop(sfm.camera_centres[sfm.registered], timestamps[sfm.registered], points, ...)

`reconstruct_hop` is the paper's COLMAP pipeline with the camera's calibration held fixed: SIFT
features, sequential matching (the frames are a video: each frame against its next few, which is
what makes it fast), then the mapping. Its output is in COLMAP's own frame: arbitrary origin, axes
and scale, which the parabola fit (hopping_parabola) turns metric.

The mapping is global by default (GLOMAP, in pycolmap as `global_mapping`): every frame's rotation
from all pairwise rotations at once (rotation averaging), then every position and point at once,
then bundle adjustment. The paper's incremental mapping (PnP registration one frame at a time) is
kept as an option. Why: a hop's first frames see the near ground from 0.4 m, rushing past, with
short tracks; incremental mapping reaches them last, at the end of a chain of registrations, and
their scale drifts along it. It bent 8 of 38 stored campaign hops (18 of the chains, 20 single hops
with spin): the first third's scale 1.2 to 3.6 times the flight's, and the parabola fit refused
them. Which hops bent was chance: another RANSAC seed in the pair verification could bend or mend
the same hop. Global positioning has no chain to drift along; it bent none of the 38 and mended
all 8 (tests/bench/measure_hopping.py for the campaigns). No setting is immune, though: in the next
single-hop campaign global mapping bent 2 of 32 hops. The incremental mapper at SIFT octave -1
reconstructed one of them well; every setting bent the other (launched rolled 35 degrees off a rock,
half of each frame sky). hop-plan therefore checks every reconstruction's flight and tries the next
setting of hopping.toml's sfm_fallbacks while it is not clean (hopping/plan.py).

`densify` replaces COLMAP's PatchMatch MVS, which pycolmap runs only with CUDA ("Dense stereo
reconstruction requires CUDA or HIP"). Why two-view SGBM on chosen pairs:
  - the SfM poses are good to a fraction of a pixel, so a pair rectified from them is a calibrated
    stereo rig, and OpenCV's semi-global matching (stereo.py, already tuned and tested on our
    terrain, with its left-right check) does the work in about 0.1 s per 640x480 pair, where a CPU
    plane sweep would warp and compare every view at every trial depth;
  - the pair's baseline is chosen against the scene depth seen from its first frame (baseline /
    median depth about 0.1): long enough for depth to about a percent, short enough that the two
    views still look alike;
  - the baseline must stand well off both optical axes. Rectification turns both views to look
    across the baseline; in forward motion (the descent, when the camera flies toward what it sees)
    the epipole lies in the image and no rectification is sane. On a hop the ascent gives the good
    pairs (the camera moves mostly across its view), and it already sees the landing area, since the
    camera looks forward and down;
  - the rectification is our own rather than cv2.stereoRectify's: it always puts the baseline along
    the rectified x axis (a hop's baseline often runs up the image, which stereoRectify would make a
    vertical pair that SGBM cannot take) and bounds the rectified view to a field of view;
  - each pair's points are checked against the depth maps of neighbouring pairs and kept only where
    another pair sees the same depth (MVS's geometric consistency in its simplest form: it halves the
    90th percentile of the height error on the simulated hops), then merged by voxel averaging.
The cloud is in the SfM frame, like the cameras; lengths are in SfM units until the parabola fit.

Pixels: our intrinsics put pixel centres at integer (u, v), as OpenCV does; COLMAP puts them at
half-integers, hence the half-pixel shift of the principal point on the way in.
"""
from __future__ import annotations

import math
import shutil
import time
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, get_args

import cv2
import numpy as np
import pycolmap

from rvs_server.hopping.settings import Mapper
from toolbox.camera import Intrinsics
from toolbox.mapping.stereo import Rectification, SgbmConfig, stereo_points

__all__ = ["SfmConfig", "HopReconstruction", "reconstruct_hop", "colmap_camera",
           "Mapper", "MAPPERS", "DenseConfig", "StereoPair", "densify", "scene_depths", "choose_pairs",
           "pair_rectification", "consistent_points", "voxel_average", "similarity_umeyama"]

IMAGE_DIGITS = 4
MAPPERS = get_args(Mapper)

MIN_SFM_FRAMES = 3          # two views and one more to check them against


# ------------------------------------------------------------------------------------------- SfM
@dataclass(frozen=True)
class SfmConfig:
    """COLMAP's settings for one hop. Defaults: a few thousand SIFT features (plenty at 640x480), each
    frame matched to its next `overlap` frames plus frames 2^k ahead (quadratic overlap: a few long
    baselines tie the whole flight together and keep the scale from drifting along it)."""

    max_features: int = 4096
    # SIFT's first octave: 0 starts at full size; -1 doubles the image first (COLMAP's default: more
    # features on small images, but about 4x slower at 640x480, and the hops need no more).
    first_octave: int = 0
    overlap: int = 5
    quadratic_overlap: bool = True
    min_inliers: int = 15              # verified matches for a pair to count
    init_min_tri_angle_deg: float = 16.0  # incremental: COLMAP's default for the first pair
    mapper: Mapper = "global"          # "global" (GLOMAP) or "incremental" (COLMAP's): see the module docstring
    num_threads: int = -1
    seed: int = 0

    def __post_init__(self):
        if self.mapper not in MAPPERS:
            raise ValueError(f"mapper must be one of {', '.join(MAPPERS)}, got {self.mapper!r}")


@dataclass(frozen=True)
class HopReconstruction:
    """One hop in the SfM frame. Frame i is row i everywhere; frames that did not register are NaN."""

    camera_centres: np.ndarray       # (N, 3)
    camera_rotations: np.ndarray     # (N, 3, 3) camera (OpenCV axes) to SfM
    registered: np.ndarray           # (N,) bool
    timestamps: np.ndarray           # (N,) s, as given
    points: np.ndarray               # (P, 3) sparse points
    colours: np.ndarray              # (P, 3) uint8 RGB
    track_lengths: np.ndarray        # (P,) images seeing each point
    point_errors: np.ndarray         # (P,) mean reprojection error of each point, pixels
    reprojection_error: float        # mean over all observations, pixels
    camera_params: np.ndarray        # the model's camera after mapping (COLMAP's convention): unchanged
    num_models: int                  # models COLMAP made; the largest is the one kept
    timings: dict = field(default_factory=dict)   # seconds per step

    @property
    def registered_indices(self) -> np.ndarray:
        return np.flatnonzero(self.registered)

    @property
    def registration_rate(self) -> float:
        return float(self.registered.mean()) if len(self.registered) else 0.0

    @property
    def camera_to_sfm(self) -> np.ndarray:
        """(N, 4, 4) camera-to-SfM poses (NaN for frames not registered)."""
        poses = np.tile(np.eye(4), (len(self.registered), 1, 1))
        poses[:, :3, :3] = self.camera_rotations
        poses[:, :3, 3] = self.camera_centres
        return poses


def colmap_camera(intrinsics: Intrinsics) -> tuple[str, list[float]]:
    """The COLMAP camera model and parameters for our intrinsics: the simplest model that is exact."""
    i = intrinsics
    # COLMAP's pixel centres are at +0.5.
    cx, cy = i.cx + 0.5, i.cy + 0.5
    if i.k1 == 0.0 and i.k2 == 0.0:
        return "PINHOLE", [i.fx, i.fy, cx, cy]
    if i.fx == i.fy:
        return "RADIAL", [i.fx, cx, cy, i.k1, i.k2]
    return "OPENCV", [i.fx, i.fy, cx, cy, i.k1, i.k2, 0.0, 0.0]


def reconstruct_hop(frames: np.ndarray, timestamps: np.ndarray, intrinsics: Intrinsics, workdir: str | Path,
                    config: SfmConfig = SfmConfig()) -> HopReconstruction:
    """COLMAP on one hop's frames (N, h, w) or (N, h, w, 3) uint8, in time order, with the camera's
    intrinsics known and held fixed. workdir receives the images, COLMAP's database and model."""
    frames, timestamps, intrinsics = _check_sfm_input(frames, timestamps, intrinsics)
    timings: dict[str, float] = {}
    # Frames to files named by index, so COLMAP's order (by name) is the flight's.
    with timed(timings, "write"):
        image_dir, database, sparse_dir = _fresh_workdir(Path(workdir))
        names = write_frames(frames, image_dir)
    pycolmap.set_random_seed(config.seed)
    # SIFT on the CPU; one camera, the known calibration.
    with timed(timings, "features"):
        extract_features(database, image_dir, names, intrinsics, config)
    # Sequential matching: the next few frames (and 2^k ahead), geometrically verified.
    with timed(timings, "matching"):
        match_sequential(database, config)
    # Global (rotation averaging, global positioning) or incremental mapping; intrinsics fixed.
    with timed(timings, "mapping"):
        mapping = global_mapping if config.mapper == "global" else incremental_mapping
        models = mapping(database, image_dir, sparse_dir, config)
    # The largest model, frame by frame.
    result = from_colmap(largest(models), len(frames), timestamps, len(models))
    timings["total"] = sum(timings.values())
    return replace(result, timings=timings)


def reconstruct_hop_quietly(*args: Any, **kwargs: Any) -> HopReconstruction:
    """reconstruct_hop with COLMAP's per-image INFO lines off (its warnings and errors kept), as the
    native worker runs it."""
    level = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = 1
    try:
        return reconstruct_hop(*args, **kwargs)
    finally:
        pycolmap.logging.minloglevel = level


@contextmanager
def timed(timings: dict, step: str):
    """Record the wall time of the block under timings[step]."""
    start = time.perf_counter()
    yield
    timings[step] = time.perf_counter() - start


def _check_sfm_input(frames, timestamps, intrinsics: Intrinsics):
    frames = np.asarray(frames)
    timestamps = np.asarray(timestamps, dtype=np.float64)
    if frames.dtype != np.uint8 or frames.ndim not in (3, 4) or (frames.ndim == 4 and frames.shape[3] != 3):
        raise ValueError(f"frames must be uint8 (N, h, w) or (N, h, w, 3), got {frames.dtype} {frames.shape}")
    if frames.shape[1:3] != (intrinsics.height, intrinsics.width):
        raise ValueError(f"frames are {frames.shape[2]}x{frames.shape[1]}, the intrinsics "
                         f"{intrinsics.width}x{intrinsics.height}")
    if timestamps.shape != (len(frames),):
        raise ValueError(f"{len(frames)} frames but timestamps of shape {timestamps.shape}")
    if len(frames) < MIN_SFM_FRAMES:
        raise ValueError(f"structure from motion needs at least {MIN_SFM_FRAMES} frames, got {len(frames)}")
    return frames, timestamps, intrinsics


def _fresh_workdir(workdir: Path) -> tuple[Path, Path, Path]:
    """images/, database.db and sparse/ under workdir, emptied of any earlier run (COLMAP would
    append to an old database)."""
    image_dir, database, sparse_dir = workdir / "images", workdir / "database.db", workdir / "sparse"
    for folder in (image_dir, sparse_dir):
        shutil.rmtree(folder, ignore_errors=True)
        folder.mkdir(parents=True)
    database.unlink(missing_ok=True)
    return image_dir, database, sparse_dir


def write_frames(frames: np.ndarray, image_dir: Path) -> list[str]:
    """PNG files 0000.png, 0001.png, ... (lossless, so COLMAP sees exactly our pixels)."""
    names = []
    for index, frame in enumerate(frames):
        name = f"{index:0{IMAGE_DIGITS}d}.png"
        image = cv2.cvtColor(frame, cv2.COLOR_RGB2BGR) if frame.ndim == 3 else frame
        if not cv2.imwrite(str(image_dir / name), image):
            raise OSError(f"could not write {image_dir / name}")
        names.append(name)
    return names


def extract_features(database: Path, image_dir: Path, names: list[str], intrinsics: Intrinsics,
                     config: SfmConfig) -> None:
    model, params = colmap_camera(intrinsics)
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = model
    reader.camera_params = ",".join(repr(float(p)) for p in params)
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.use_gpu = False
    extraction.num_threads = config.num_threads
    extraction.sift.max_num_features = config.max_features
    extraction.sift.first_octave = config.first_octave
    pycolmap.extract_features(database, image_dir, image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
                              reader_options=reader, extraction_options=extraction, device=pycolmap.Device.cpu)
    mark_calibrated(database)


def mark_calibrated(database: Path) -> None:
    """Flag the focal length as known: COLMAP then verifies pairs with the essential matrix (5 points,
    calibrated) instead of the fundamental matrix, and never estimates the focal length itself."""
    with pycolmap.Database.open(database) as db:
        for camera in db.read_all_cameras():
            camera.has_prior_focal_length = True
            db.update_camera(camera)


def match_sequential(database: Path, config: SfmConfig) -> None:
    matching = pycolmap.FeatureMatchingOptions()
    matching.use_gpu = False
    matching.num_threads = config.num_threads
    pairing = pycolmap.SequentialPairingOptions()
    pairing.overlap = config.overlap
    pairing.quadratic_overlap = config.quadratic_overlap
    verification = pycolmap.TwoViewGeometryOptions()
    verification.min_num_inliers = config.min_inliers
    verification.ransac.random_seed = config.seed
    pycolmap.match_sequential(database, matching_options=matching, pairing_options=pairing,
                              verification_options=verification, device=pycolmap.Device.cpu)


def mapping_options(config: SfmConfig) -> pycolmap.IncrementalPipelineOptions:
    """Incremental mapping with the calibration held: neither bundle adjustment nor PnP may touch the
    focal length, principal point or distortion (the paper's known camera; it also removes the
    focal-length / depth ambiguity that a narrow hop would otherwise leave to the data)."""
    options = pycolmap.IncrementalPipelineOptions()
    options.ba_refine_focal_length = False
    options.ba_refine_principal_point = False
    options.ba_refine_extra_params = False
    options.mapper.abs_pose_refine_focal_length = False
    options.mapper.abs_pose_refine_extra_params = False
    options.mapper.init_min_tri_angle = config.init_min_tri_angle_deg
    options.min_num_matches = config.min_inliers
    options.num_threads = config.num_threads
    options.random_seed = config.seed
    options.mapper.random_seed = config.seed
    options.triangulation.random_seed = config.seed
    return options


def incremental_mapping(database: Path, image_dir: Path, sparse_dir: Path, config: SfmConfig) -> dict:
    return pycolmap.incremental_mapping(database, image_dir, sparse_dir, options=mapping_options(config))


def global_mapping_options(config: SfmConfig) -> pycolmap.GlobalPipelineOptions:
    """GLOMAP with the calibration held (as in mapping_options) and every random choice seeded."""
    options = pycolmap.GlobalPipelineOptions()
    options.min_num_matches = config.min_inliers
    options.num_threads = config.num_threads
    options.random_seed = config.seed
    mapper = options.mapper
    mapper.num_threads = config.num_threads
    mapper.random_seed = config.seed
    mapper.rotation_averaging.random_seed = config.seed
    mapper.global_positioning.random_seed = config.seed
    mapper.global_positioning.use_gpu = False
    mapper.retriangulation.random_seed = config.seed
    adjustment = mapper.bundle_adjustment
    adjustment.refine_focal_length = False
    adjustment.refine_principal_point = False
    adjustment.refine_extra_params = False
    adjustment.ceres.use_gpu = False
    return options


def global_mapping(database: Path, image_dir: Path, sparse_dir: Path, config: SfmConfig) -> dict:
    return pycolmap.global_mapping(database, image_dir, sparse_dir, options=global_mapping_options(config))


def largest(models: dict) -> pycolmap.Reconstruction | None:
    """The model with the most registered images (a hop can break into pieces where the view blurs)."""
    if not models:
        return None
    return max(models.values(), key=lambda model: model.num_reg_images())


def from_colmap(model: pycolmap.Reconstruction | None, count: int, timestamps: np.ndarray,
                num_models: int) -> HopReconstruction:
    """Per-frame poses (frame index from the image name) and the sparse points of a COLMAP model."""
    centres = np.full((count, 3), np.nan)
    rotations = np.full((count, 3, 3), np.nan)
    registered = np.zeros(count, bool)
    if model is None:
        empty = np.zeros((0, 3))
        return HopReconstruction(centres, rotations, registered, timestamps, empty, empty.astype(np.uint8),
                                 np.zeros(0, int), np.zeros(0), math.nan, np.zeros(0), 0)
    for image in model.images.values():
        if not image.has_pose:
            continue
        index = int(Path(image.name).stem)
        cam_from_world = image.cam_from_world()
        rotation = cam_from_world.rotation.matrix()
        rotations[index] = rotation.T
        centres[index] = -rotation.T @ cam_from_world.translation
        registered[index] = True
    points3d = list(model.points3D.values())
    points = np.array([p.xyz for p in points3d]).reshape(-1, 3)
    colours = np.array([p.color for p in points3d], dtype=np.uint8).reshape(-1, 3)
    tracks = np.array([p.track.length() for p in points3d], dtype=int)
    errors = np.array([p.error for p in points3d], dtype=np.float64)
    camera_params = np.array(next(iter(model.cameras.values())).params, dtype=np.float64)
    return HopReconstruction(centres, rotations, registered, timestamps, points, colours, tracks, errors,
                             float(model.compute_mean_reprojection_error()), camera_params, num_models)


# ------------------------------------------------------------------------------------------- dense
@dataclass(frozen=True)
class DenseConfig:
    """How pairs are chosen, matched, checked and merged. Lengths relative to the scene depth, since
    the SfM frame has no unit."""

    target_baseline_ratio: float = 0.10   # baseline / median depth seen from the pair's first frame
    min_baseline_ratio: float = 0.04
    max_baseline_ratio: float = 0.25
    max_frame_gap: int = 10               # frames between a pair's two views
    min_baseline_angle_deg: float = 60.0  # between the baseline and each optical axis ...
    fallback_baseline_angle_deg: float = 30.0  # ... or this, when no pair of the hop reaches it (a steep hop
                                          # flies along the camera's 45 degree view: its pairs stand 40-50 off)
    max_view_angle_deg: float = 55.0      # half field of view kept in the rectified images
    max_pairs: int = 12                   # spread over the usable frames; the cost is per pair
    min_disparity_px: float = 4.0         # depth error grows as 1 / disparity: drop the far tail
    block_size: int = 5
    agreement: float = 0.015              # relative depth difference for two pairs to agree
    min_agreeing_pairs: int = 1
    neighbour_pairs: int = 3              # pairs each side (in time) a point is checked against
    voxel_fraction: float = 0.004         # voxel edge / median scene depth


@dataclass(frozen=True)
class StereoPair:
    """Two registered frames rectified into a horizontal stereo rig (left = `first`)."""

    first: int
    second: int
    rect_to_sfm: np.ndarray       # (3, 3) rotation of the rectified frame (x along the baseline)
    centre: np.ndarray            # (3,) the first camera's centre, SfM frame
    rectification: Rectification  # stereo.py's: maps, projections, reprojection


def densify(frames: np.ndarray, reconstruction: HopReconstruction, intrinsics: Intrinsics,
            config: DenseConfig = DenseConfig()) -> tuple[np.ndarray, np.ndarray]:
    """Dense points (M, 3) in the SfM frame and their colours (M, 3) uint8 from rectified pairs of
    registered frames (see the module docstring)."""
    frames = np.asarray(frames)
    # Scene depth per frame from the sparse points: it sets the baselines and disparity ranges.
    depths = scene_depths(reconstruction, intrinsics)
    # Pairs with a useful baseline standing well off the optical axes.
    pairs = [pair_rectification(reconstruction, first, second, intrinsics, config)
             for first, second in choose_pairs(reconstruction, depths, config)]
    if not pairs:
        return np.zeros((0, 3)), np.zeros((0, 3), np.uint8)
    # SGBM with a left-right check on each pair, as depth maps on the rectified grids.
    maps = [pair_depth(frames, pair, depths[pair.first], config) for pair in pairs]
    # Keep what neighbouring pairs confirm.
    points, colours = consistent_points(pairs, maps, config)
    # Merge the overlapping pairs.
    finite = [d for d in depths.values() if np.isfinite(d[0])]
    voxel = config.voxel_fraction * float(np.median([d[0] for d in finite]))
    return voxel_average(points, colours, voxel)


def scene_depths(reconstruction: HopReconstruction, intrinsics: Intrinsics) -> dict[int, tuple[float, float]]:
    """Per registered frame: (median, 5th percentile) depth of the sparse points in its view."""
    depths = {}
    for index in reconstruction.registered_indices:
        camera = (reconstruction.points - reconstruction.camera_centres[index]) @ reconstruction.camera_rotations[index]
        z = camera[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = intrinsics.fx * camera[:, 0] / z + intrinsics.cx
            v = intrinsics.fy * camera[:, 1] / z + intrinsics.cy
        seen = (z > 0) & (u >= 0) & (u < intrinsics.width) & (v >= 0) & (v < intrinsics.height)
        depths[int(index)] = ((float(np.median(z[seen])), float(np.percentile(z[seen], 5)))
                              if seen.sum() >= 10 else (math.nan, math.nan))
    return depths


def choose_pairs(reconstruction: HopReconstruction, depths: dict, config: DenseConfig) -> list[tuple[int, int]]:
    """For each registered frame, the later frame whose baseline / depth ratio is nearest the target,
    among those in range whose baseline stands off both optical axes (min_baseline_angle_deg, or the
    fallback angle if no pair does); then at most max_pairs of them, spread evenly in time."""
    for angle in (config.min_baseline_angle_deg, config.fallback_baseline_angle_deg):
        chosen = _pairs_off_axis(reconstruction, depths, config, angle)
        if chosen:
            break
    if len(chosen) > config.max_pairs:
        keep = np.unique(np.round(np.linspace(0, len(chosen) - 1, config.max_pairs)).astype(int))
        chosen = [chosen[k] for k in keep]
    return chosen


def _pairs_off_axis(reconstruction: HopReconstruction, depths: dict, config: DenseConfig,
                    min_angle_deg: float) -> list[tuple[int, int]]:
    chosen = []
    registered = set(reconstruction.registered_indices.tolist())
    for first in sorted(registered):
        depth = depths[first][0]
        if not np.isfinite(depth):
            continue
        best, best_error = None, math.inf
        for second in range(first + 1, first + config.max_frame_gap + 1):
            if second not in registered:
                continue
            baseline = reconstruction.camera_centres[second] - reconstruction.camera_centres[first]
            ratio = float(np.linalg.norm(baseline)) / depth
            if not config.min_baseline_ratio <= ratio <= config.max_baseline_ratio:
                continue
            if min(_off_axis_deg(baseline, reconstruction.camera_rotations[k]) for k in (first, second)) \
                    < min_angle_deg:
                continue
            error = abs(math.log(ratio / config.target_baseline_ratio))
            if error < best_error:
                best, best_error = second, error
        if best is not None:
            chosen.append((first, best))
    return chosen


def _off_axis_deg(baseline: np.ndarray, camera_to_sfm: np.ndarray) -> float:
    """Angle between the baseline's line and the optical axis, 0-90 degrees."""
    cosine = abs(float(baseline @ camera_to_sfm[:, 2])) / float(np.linalg.norm(baseline))
    return math.degrees(math.acos(min(cosine, 1.0)))


def pair_rectification(reconstruction: HopReconstruction, first: int, second: int, intrinsics: Intrinsics,
                       config: DenseConfig) -> StereoPair:
    """Rectify two registered frames: both rotated to one frame whose x runs along the baseline (so the
    second view is the right camera of a horizontal rig) and whose z is the mean optical axis made
    perpendicular to it; the rectified image keeps the part of both views within max_view_angle."""
    centres, rotations = reconstruction.camera_centres, reconstruction.camera_rotations
    baseline_vector = centres[second] - centres[first]
    baseline = float(np.linalg.norm(baseline_vector))
    x = baseline_vector / baseline
    z = rotations[first][:, 2] + rotations[second][:, 2]
    z -= (z @ x) * x
    z /= np.linalg.norm(z)
    rect_to_sfm = np.column_stack([x, np.cross(z, x), z])
    # Each camera into the rectified frame (OpenCV's R: p_rect = R p_camera).
    left_rotation = rect_to_sfm.T @ rotations[first]
    right_rotation = rect_to_sfm.T @ rotations[second]
    focal = 0.5 * (intrinsics.fx + intrinsics.fy)
    size, cx, cy = _rectified_window(intrinsics, (left_rotation, right_rotation), focal, config.max_view_angle_deg)
    matrix = np.array([[focal, 0.0, cx], [0.0, focal, cy], [0.0, 0.0, 1.0]])
    left_projection = np.column_stack([matrix, np.zeros(3)])
    right_projection = np.column_stack([matrix, [-focal * baseline, 0.0, 0.0]])
    # (u, v, d, 1) -> rectified 3D: Z = f B / d.
    reprojection = np.array([[1.0, 0, 0, -cx], [0, 1.0, 0, -cy], [0, 0, 0, focal], [0, 0, 1.0 / baseline, 0]])
    left_maps = cv2.initUndistortRectifyMap(intrinsics.matrix, intrinsics.distortion, left_rotation, matrix, size,
                                            cv2.CV_32FC1)
    right_maps = cv2.initUndistortRectifyMap(intrinsics.matrix, intrinsics.distortion, right_rotation, matrix,
                                             size, cv2.CV_32FC1)
    rectification = Rectification(size, left_rotation, right_rotation, left_projection, right_projection,
                                  reprojection, tuple(left_maps), tuple(right_maps))
    return StereoPair(first, second, rect_to_sfm, centres[first].copy(), rectification)


def _rectified_window(intrinsics: Intrinsics, rotations, focal: float, max_angle_deg: float):
    """Size and principal point of the rectified image: the rows both views cover, the columns the
    left view covers, all within max_angle of the rectified axis (a view turned far from its own
    axis would otherwise stretch toward infinity)."""
    border = _border_rays(intrinsics)
    limit = math.tan(math.radians(max_angle_deg))
    boxes = []
    for rotation in rotations:
        rays = border @ rotation.T
        rays = rays[rays[:, 2] > 1e-6]
        xy = np.clip(rays[:, :2] / rays[:, 2:], -limit, limit)
        boxes.append((xy.min(axis=0), xy.max(axis=0)))
    (left_low, left_high), (right_low, right_high) = boxes
    x_low, x_high = left_low[0], left_high[0]
    y_low, y_high = max(left_low[1], right_low[1]), min(left_high[1], right_high[1])
    width = max(int(math.ceil(focal * (x_high - x_low))), 16)
    height = max(int(math.ceil(focal * (y_high - y_low))), 16)
    return (width, height), -focal * x_low, -focal * y_low


def _border_rays(intrinsics: Intrinsics, samples: int = 64) -> np.ndarray:
    """Camera-frame rays through points along the image border (distortion removed)."""
    w, h = intrinsics.width - 1, intrinsics.height - 1
    t = np.linspace(0.0, 1.0, samples)
    u = np.concatenate([t * w, np.full_like(t, w), t * w, np.zeros_like(t)])
    v = np.concatenate([np.zeros_like(t), t * h, np.full_like(t, h), t * h])
    pixels = np.stack([u, v], axis=-1).reshape(-1, 1, 2)
    normalised = cv2.undistortPoints(pixels, intrinsics.matrix, intrinsics.distortion).reshape(-1, 2)
    return np.column_stack([normalised, np.ones(len(normalised))])


@dataclass(frozen=True)
class PairDepth:
    depth: np.ndarray     # (H, W) rectified depth (z of the rectified frame), NaN where none
    colour: np.ndarray    # (H, W, 3) uint8, the rectified left image


def pair_depth(frames: np.ndarray, pair: StereoPair, scene_depth: tuple[float, float],
               config: DenseConfig) -> PairDepth:
    """SGBM depth of one pair on its rectified left grid: disparity range from the nearest sparse
    depth, left-right checked (stereo.py), far tail dropped."""
    rect = pair.rectification
    baseline = float(-rect.right_projection[0, 3] / rect.right_projection[0, 0])
    focal = rect.focal_px
    # Enough disparities for the nearest sparse points, with a margin.
    nearest = scene_depth[1] if np.isfinite(scene_depth[1]) else math.nan
    needed = 1.3 * focal * baseline / nearest if nearest > 0 else 128.0
    sgbm = SgbmConfig(num_disparities=int(min(256, max(32, 16 * math.ceil(needed / 16)))),
                      block_size=config.block_size)
    left, right = (_grey(frames[k]) for k in (pair.first, pair.second))
    points, valid = stereo_points(left, right, rect, sgbm)
    depth = np.where(valid, points @ rect.left_rotation[2], np.nan)   # z in the rectified frame
    with np.errstate(invalid="ignore"):
        depth[depth > focal * baseline / config.min_disparity_px] = np.nan
    colour = cv2.remap(_rgb(frames[pair.first]), *rect.left_maps, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    return PairDepth(depth.astype(np.float32), colour)


def _grey(frame: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(frame, cv2.COLOR_RGB2GRAY) if frame.ndim == 3 else frame


def _rgb(frame: np.ndarray) -> np.ndarray:
    return frame if frame.ndim == 3 else cv2.cvtColor(frame, cv2.COLOR_GRAY2RGB)


def rectified_points(pair: StereoPair, depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """SfM-frame points of a rectified depth map and their flat pixel indices."""
    rect = pair.rectification
    focal, cx, cy = rect.focal_px, rect.left_projection[0, 2], rect.left_projection[1, 2]
    rows, cols = np.nonzero(np.isfinite(depth))
    z = depth[rows, cols].astype(np.float64)
    in_rect = np.column_stack([(cols - cx) * z / focal, (rows - cy) * z / focal, z])
    return pair.centre + in_rect @ pair.rect_to_sfm.T, rows * depth.shape[1] + cols


def agrees(points: np.ndarray, pair: StereoPair, depth: np.ndarray, tolerance: float) -> np.ndarray:
    """True where another pair's depth map holds the same depth (relative `tolerance`) as the points."""
    rect = pair.rectification
    focal, cx, cy = rect.focal_px, rect.left_projection[0, 2], rect.left_projection[1, 2]
    local = (points - pair.centre) @ pair.rect_to_sfm
    z = local[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.rint(focal * local[:, 0] / z + cx)
        v = np.rint(focal * local[:, 1] / z + cy)
    height, width = depth.shape
    inside = (z > 0) & (u >= 0) & (u < width) & (v >= 0) & (v < height)
    seen = np.full(len(points), np.nan)
    seen[inside] = depth[v[inside].astype(int), u[inside].astype(int)]
    with np.errstate(invalid="ignore"):
        return np.abs(seen - z) <= tolerance * z


def consistent_points(pairs: list[StereoPair], maps: list[PairDepth],
                      config: DenseConfig) -> tuple[np.ndarray, np.ndarray]:
    """Each pair's points that at least min_agreeing_pairs of its neighbours (in time) confirm. The
    nearest neighbours are asked first and only about points still short of votes: most points are
    settled by the first one, which keeps this linear in the points rather than in points x pairs."""
    all_points, all_colours = [], []
    for k, (pair, result) in enumerate(zip(pairs, maps, strict=True)):
        points, flat = rectified_points(pair, result.depth)
        votes = np.zeros(len(points), int)
        for m in _neighbours(k, len(pairs), config.neighbour_pairs):
            open_ = np.flatnonzero(votes < config.min_agreeing_pairs)
            if len(open_) == 0:
                break
            votes[open_] += agrees(points[open_], pairs[m], maps[m].depth, config.agreement)
        keep = votes >= config.min_agreeing_pairs
        all_points.append(points[keep])
        all_colours.append(result.colour.reshape(-1, 3)[flat[keep]])
    return np.concatenate(all_points), np.concatenate(all_colours)


def _neighbours(k: int, count: int, reach: int) -> list[int]:
    """Pair indices within `reach` of k, nearest first."""
    order = [k + sign * step for step in range(1, reach + 1) for sign in (-1, 1)]
    return [m for m in order if 0 <= m < count]


def voxel_average(points: np.ndarray, colours: np.ndarray, voxel: float) -> tuple[np.ndarray, np.ndarray]:
    """One point per occupied voxel: the mean position and colour of the points in it."""
    if len(points) == 0:
        return points.reshape(0, 3), colours.reshape(0, 3).astype(np.uint8)
    cells = np.floor(points / voxel).astype(np.int64)
    cells -= cells.min(axis=0)
    # One integer per voxel: a 1-D unique is many times faster than np.unique(axis=0).
    extent = cells.max(axis=0) + 1
    keys = (cells[:, 0] * extent[1] + cells[:, 1]) * extent[2] + cells[:, 2]
    _, inverse, counts = np.unique(keys, return_inverse=True, return_counts=True)

    def mean(values: np.ndarray) -> np.ndarray:
        columns = [np.bincount(inverse, weights=values[:, k], minlength=len(counts)) for k in range(values.shape[1])]
        return np.column_stack(columns) / counts[:, None]

    return mean(points), np.rint(mean(colours.astype(np.float64))).astype(np.uint8)


# ------------------------------------------------------------------------------------------- checks
def similarity_umeyama(source: np.ndarray, target: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """(scale, rotation, translation) minimising |target - (s R source + t)|^2 (Umeyama 1991): how an
    SfM result is compared with the truth."""
    source, target = np.asarray(source, np.float64), np.asarray(target, np.float64)
    mu_s, mu_t = source.mean(axis=0), target.mean(axis=0)
    a, b = source - mu_s, target - mu_t
    u, sigma, vt = np.linalg.svd(b.T @ a / len(source))
    sign = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
    rotation = u @ sign @ vt
    scale = float(np.trace(np.diag(sigma) @ sign) / (a * a).sum(axis=1).mean())
    return scale, rotation, mu_t - scale * rotation @ mu_s
