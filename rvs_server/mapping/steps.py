"""The operations mapping workflows are made of (workflows/dem-*.yaml name them).

Each operation is a small adapter: it takes earlier steps' results and its parameters, calls the
toolbox (or, for acquisition, the devices), and returns plain dicts of arrays so its result can be
checkpointed. Acquisition checkpoints every view, so `break` loses at most the view being taken.
"""
from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
from pydantic import Field

from rvs_server.config import Range
from rvs_server.workflow import Operations, StepContext, StepParams
from toolbox.camera import Intrinsics
from toolbox.colour import grey
from toolbox.geometry import RoverPose, camera_to_world, footprint_polygon, relative_pose
from toolbox.mapping import dem as dem_tools
from toolbox.mapping import hazard as hazard_tools
from toolbox.mapping.fuse import FusionNoise, fuse_dems
from toolbox.mapping.localisation import AlignConfig, align_to_map, apply
from toolbox.mapping.ortho import merge_views, ortho_image
from toolbox.mapping.stereo import SgbmConfig, StereoCalibration, rectification, stereo_points
from toolbox.mapping.views import plan_views

if TYPE_CHECKING:
    from rvs_server.host import Host
    from rvs_server.jobs import JobContext

operations = Operations()

SR4000_FOV_DEG = (43.6, 34.6)
NO_DATA_DISTANCE = 0


# ---------------------------------------------------------------------------------------------
# Views and acquisition


class PlanViewsParams(StepParams):
    pan: Range = (-180.0, 180.0)
    tilt: Range = (-45.0, -15.0)
    overlap: float = Field(0.15, ge=0.0, lt=0.9)
    sensor: Literal["tof", "stereo"] = "tof"


@operations.register("views.plan", PlanViewsParams)
def plan(step: StepContext, params: PlanViewsParams) -> dict[str, Any]:
    """PTU positions covering the pan and tilt ranges with the sensor's field of view and overlap."""
    hfov, vfov = sensor_fov_deg(step.job, params.sensor)
    views = plan_views(tuple(np.radians(params.pan)), tuple(np.radians(params.tilt)), math.radians(hfov),
                       math.radians(vfov), params.overlap)
    wanted = np.degrees(np.asarray(views, dtype=np.float64)).reshape(-1, 2)
    wanted[:, 0] = (wanted[:, 0] + 180.0) % 360.0 - 180.0
    reachable = within_unit_limits(step.job, wanted)
    return {"pan_tilt_deg": reachable, "planned_deg": wanted, "fov_deg": np.array([hfov, vfov])}


def within_unit_limits(job: JobContext, views: np.ndarray) -> np.ndarray:
    """Views the PTU cannot reach are moved to its nearest limit: a D46 pans +-159 degrees, so the
    directions straight behind the rover are seen by the outermost views' field of view only."""
    limits = job.devices.ptu.require().limits
    clipped = views.copy()
    clipped[:, 0] = np.clip(clipped[:, 0], limits.pan_min_deg, limits.pan_max_deg)
    clipped[:, 1] = np.clip(clipped[:, 1], limits.tilt_min_deg, limits.tilt_max_deg)
    _, first = np.unique(np.round(clipped, 3), axis=0, return_index=True)
    return clipped[np.sort(first)]


def sensor_fov_deg(job: JobContext, sensor: str) -> tuple[float, float]:
    if sensor == "tof":
        k = job.server.calibration().tof_intrinsics
    else:
        k = stereo_intrinsics(job)[0]
    return (math.degrees(2 * math.atan((k.width / 2) / k.fx)), math.degrees(2 * math.atan((k.height / 2) / k.fy)))


def stereo_intrinsics(job: JobContext, acquired: dict | None = None) -> tuple[Intrinsics, Intrinsics]:
    """The pair's intrinsics: those an acquisition kept, else the cameras' own."""
    if acquired is not None and acquired.get("intrinsics"):
        kept = acquired["intrinsics"]
        return Intrinsics(**kept["left"]), Intrinsics(**kept["right"])
    pair = job.devices.cameras.require()
    mode = job.devices.cameras.config.resolution
    return pair.camera("left").intrinsics(mode), pair.camera("right").intrinsics(mode)


def point_ptu(job: JobContext, pan: float, tilt: float) -> tuple[float, float]:
    """Move the PTU and wait until it stands; the angles it reports are what the maps use."""
    device = job.devices.ptu
    driver = device.require()
    driver.move_to(pan, tilt, speed_deg_s=job.settings_of("ptu").default_speed_deg_s)
    driver.wait_until_stopped(timeout_s=120.0)
    return device.read_position()


class AcquireTofParams(StepParams):
    frames: int = Field(1, ge=1, le=50)
    min_confidence: int = Field(0, ge=0, le=65535)
    settle_frames: int = Field(10, ge=0, le=100)


def each_view(step: StepContext, views: dict, take: Callable[[int, tuple[float, float]], dict]) -> list[dict]:
    """Point the PTU at every planned view and `take` it; a view taken before a break or a crash is
    loaded from its checkpoint instead of being taken again."""
    taken = []
    targets = views["pan_tilt_deg"]
    for index, (pan, tilt) in enumerate(targets):
        saved = step.load_partial(f"view{index:03d}")
        if saved is None:
            step.safe_point()
            step.progress(index / len(targets), f"view {index + 1}/{len(targets)} at pan {pan:.1f} tilt {tilt:.1f}")
            saved = take(index, point_ptu(step.job, float(pan), float(tilt)))
            step.save_partial(f"view{index:03d}", saved)
        taken.append(saved)
    return taken


@operations.register("acquire.tof", AcquireTofParams, inputs=("views",))
def acquire_tof(step: StepContext, params: AcquireTofParams, views: dict) -> dict[str, Any]:
    """For each view: point the PTU, grab (averaged) SR4000 frames, keep the points and their pose."""
    job = step.job
    camera = job.devices.tof.require()
    mount = job.server.calibration().mounts["tof"]
    pose = job.devices.rover.pose_estimate

    def take(index: int, measured: tuple[float, float]) -> dict:
        _repeatable(camera, index, step.load_partial(f"exposure{index - 1:03d}"))
        result = job.devices.tof.grab(frames=params.frames, min_confidence=params.min_confidence,
                                      settle_frames=params.settle_frames)
        step.save_partial(f"exposure{index:03d}", {"integration_time": int(camera.integration_time())})
        frame = result.frame
        return {"points_camera": frame.xyz().astype(np.float32), "valid": result.defined,
                "intensity": frame.amplitude.astype(np.float32), "pan_tilt_deg": np.array(measured),
                "camera_to_world": camera_to_world(pose, mount, math.radians(measured[0]), math.radians(measured[1])),
                "true_camera_to_world": _true_pose(camera)}

    taken = each_view(step, views, take)
    last = step.load_partial(f"exposure{len(taken) - 1:03d}") if taken else None
    return {"sensor": "tof", "views": taken, "integration_time": last["integration_time"] if last else -1}


def leave_camera_as_acquired(job: JobContext, acquired: dict) -> None:
    """The camera's exposure as the acquisition's last view left it, also when that acquisition was
    loaded from a checkpoint after a restart (which reopened the camera at its configured exposure):
    the next panorama's first view then starts from the same exposure as in an uninterrupted run."""
    exposure = int(acquired.get("integration_time", -1))
    if acquired.get("sensor") == "tof" and exposure >= 0:
        job.devices.tof.require().set_integration_time(exposure)


def _repeatable(camera: Any, index: int, exposure: dict | None) -> None:
    """An emulated camera draws view `index`'s noise, from the exposure the previous view left,
    so a resumed panorama equals an uninterrupted one."""
    if hasattr(camera, "set_frame_number"):
        camera.set_frame_number(100_000 * (index + 1))
    if exposure is not None:
        camera.set_integration_time(exposure["integration_time"])


def _true_pose(camera: Any) -> np.ndarray:
    pose = getattr(camera, "last_pose", None)
    return np.asarray(pose, dtype=np.float64) if pose is not None else np.full((4, 4), np.nan)


@operations.register("acquire.stereo", inputs=("views",))
def acquire_stereo(step: StepContext, params: StepParams, views: dict) -> dict[str, Any]:
    """For each view: point the PTU, grab both cameras on one trigger, keep the images and poses."""
    job = step.job
    pair = job.devices.cameras.require()
    mounts = job.server.calibration().mounts
    pose = job.devices.rover.pose_estimate
    timeout = job.devices.cameras.grab_timeout_s

    def take(index: int, measured: tuple[float, float]) -> dict:
        for role in ("left", "right"):
            _repeatable(pair.camera(role), index, None)
        frames = pair.grab("both", timeout_s=timeout)
        pan, tilt = math.radians(measured[0]), math.radians(measured[1])
        return {"left": grey(frames["left"].image), "right": grey(frames["right"].image),
                "pan_tilt_deg": np.array(measured),
                "left_to_world": camera_to_world(pose, mounts["left"], pan, tilt),
                "right_to_world": camera_to_world(pose, mounts["right"], pan, tilt)}

    left_k, right_k = stereo_intrinsics(job)
    # The intrinsics go with the images, so that the stored views can be matched again without the
    # cameras (`rvs remap`).
    return {"sensor": "stereo", "views": each_view(step, views, take), "intrinsics": {
        "left": dataclasses.asdict(left_k), "right": dataclasses.asdict(right_k)}}




class StereoParams(StepParams):
    num_disparities: int = Field(128, ge=16, le=512, multiple_of=16)
    block_size: int = Field(5, ge=3, le=21)
    max_range_m: float = Field(8.0, gt=0, description="points farther than this are dropped (depth error grows as z^2)")


@operations.register("stereo.points", StereoParams, inputs=("acquired",))
def stereo_to_points(step: StepContext, params: StereoParams, acquired: dict) -> dict[str, Any]:
    """Rectify each pair, match with SGBM, and turn disparity into points in the left camera frame."""
    left_k, right_k = stereo_intrinsics(step.job, acquired)
    config = SgbmConfig(num_disparities=params.num_disparities, block_size=params.block_size)
    out = []
    for index, view in enumerate(acquired["views"]):
        step.safe_point()
        step.progress(index / len(acquired["views"]), f"matching view {index + 1}")
        calib = StereoCalibration(left_k, right_k, relative_pose(view["left_to_world"], view["right_to_world"]))
        rect = rectification(calib)
        points, valid = stereo_points(view["left"], view["right"], rect, config)
        valid &= points[..., 2] < params.max_range_m
        out.append({"points_camera": points.astype(np.float32), "valid": valid,
                    "intensity": view["left"].astype(np.float32), "pan_tilt_deg": view["pan_tilt_deg"],
                    "camera_to_world": view["left_to_world"], "true_camera_to_world": np.full((4, 4), np.nan)})
    return {"sensor": "stereo", "views": out, "intrinsics": acquired.get("intrinsics")}


# ---------------------------------------------------------------------------------------------
# Points, DEM, hazards, ortho-image


class ViewPointsParams(StepParams):
    max_blob_pixels: int = Field(256, ge=0, description="isolated groups up to this size are artifacts")
    max_relative_jump: float = Field(0.05, gt=0, le=1, description="range jump that separates surfaces")
    max_range_m: float = Field(4.8, gt=0, description="drop points farther than this from the camera")


@operations.register("dem.view_points", ViewPointsParams, inputs=("acquired",))
def view_points(step: StepContext, params: ViewPointsParams, acquired: dict) -> dict[str, Any]:
    """Each view's trusted points, isolated blobs removed, in the world frame; all views stacked."""
    config = dem_tools.DemConfig(max_blob_pixels=params.max_blob_pixels, max_relative_jump=params.max_relative_jump)
    clouds, per_view = [], []
    for view in acquired["views"]:
        points = view["points_camera"]
        valid = view["valid"] & (np.linalg.norm(np.nan_to_num(points, nan=np.inf), axis=-1) <= params.max_range_m)
        world = dem_tools.view_points(points, valid, view["camera_to_world"], config)
        clouds.append(world)
        per_view.append(len(world))
    return {"points": np.vstack(clouds) if clouds else np.empty((0, 3)), "per_view": np.array(per_view)}


class RemoveBodyParams(StepParams):
    margin_m: float = Field(0.05, ge=0, le=1)


@operations.register("dem.remove_body", RemoveBodyParams, inputs=("points",))
def remove_body(step: StepContext, params: RemoveBodyParams, points: dict) -> dict[str, Any]:
    """Points on the rover's own body (its footprint, grown by a margin) are not terrain."""
    calibration = step.job.server.calibration()
    footprint = footprint_polygon(step.job.devices.rover.pose_estimate, calibration.rover_length_m,
                                  calibration.rover_width_m)
    kept = dem_tools.remove_rover_body(points["points"], footprint, params.margin_m)
    return {"points": kept, "removed": int(len(points["points"]) - len(kept)), "footprint": footprint}


class AlignParams(StepParams):
    reference: str = Field("", description="the map's cloud (.npy, world frame) to align to; empty: none yet")
    max_translation_m: float = Field(1.0, gt=0, description="largest position correction believed")
    max_rotation_deg: float = Field(10.0, gt=0, le=90, description="largest heading correction believed")
    min_fitness: float = Field(0.3, ge=0, le=1, description="share of new points that must meet the map")


@operations.register("localise.align", AlignParams, inputs=("points",))
def localise(step: StepContext, params: AlignParams, points: dict) -> dict[str, Any]:
    """Align the new points to the map's cloud (4-DOF ICP about the rover) and correct them; the
    correction is the odometry pose's error, which the caller applies to the rover's pose."""
    pose = step.job.devices.rover.pose_estimate
    if not params.reference:
        alignment = None
        reason = "no map to align to yet"
    else:
        reference = np.load(Path(params.reference))
        config = AlignConfig(max_translation_m=params.max_translation_m, max_rotation_deg=params.max_rotation_deg,
                             min_fitness=params.min_fitness)
        alignment = step.native(align_to_map, points["points"], reference, np.array([pose.x, pose.y, pose.z]), config)
        reason = alignment.reason
    correction = alignment.correction if alignment is not None else np.eye(4)
    summary = {key: float(getattr(alignment, key)) if alignment is not None else 0.0
               for key in ("dx", "dy", "dz", "dyaw", "fitness", "rmse", "constraint")}
    return {"points": apply(correction, points["points"]), "correction": correction,
            "accepted": bool(alignment is not None and alignment.accepted), "reason": reason, **summary}


@operations.register("localise.apply", inputs=("points", "alignment"))
def localise_apply(step: StepContext, params: StepParams, points: dict, alignment: dict) -> dict[str, Any]:
    """Another sensor's points of the same views moved by the correction a localise.align step found
    (navigate-fused: the SR4000's cloud is aligned to the map, the stereo pair's follows it)."""
    correction = np.asarray(alignment["correction"])
    return {"points": apply(correction, points["points"]), "correction": correction,
            "accepted": bool(alignment["accepted"])}


class GridParams(StepParams):
    cell: float = Field(0.05, ge=0.005, le=1.0, description="cell size, metres")
    max_extent_m: float = Field(12.0, gt=0, description="the grid spans at most this far from the rover")
    top_band_m: float = Field(0.0, ge=0, le=0.5, description="0: a cell's highest point is its height; more: the "
                              "mean of its points within this band of the highest (unbiased under noise, see "
                              "toolbox/mapping/dem.py points_to_dem)")


@operations.register("dem.grid", GridParams, inputs=("points",))
def grid(step: StepContext, params: GridParams, points: dict) -> dict[str, Any]:
    """Direct reconstruction: every point to its cell, the highest wins (or the mean of the top band);
    no data stays NaN."""
    cloud = points["points"]
    pose = step.job.devices.rover.pose_estimate
    near = np.all(np.abs(cloud[:, :2] - [pose.x, pose.y]) <= params.max_extent_m, axis=1)
    cloud = cloud[near]
    if len(cloud) == 0:
        raise ValueError("no points to make a DEM from (every view was empty or filtered out)")
    spec = dem_tools.grid_covering(cloud, params.cell, margin=params.cell)
    dem = step.native(dem_tools.points_to_dem, cloud, spec, params.top_band_m)
    return {"spec": dem.spec, "heights": dem.heights, "counts": dem.counts}


class FuseParams(StepParams):
    """toolbox/mapping/fuse.py's FusionNoise, its defaults, editable in a workflow."""

    tof_sigma_m: float = Field(FusionNoise.tof_sigma_m, gt=0, description="SR4000 cell height noise at "
                               "tof_reference_m, growing in proportion to range")
    tof_reference_m: float = Field(FusionNoise.tof_reference_m, gt=0)
    stereo_sigma_per_m2: float = Field(FusionNoise.stereo_sigma_per_m2, gt=0, description="stereo cell height "
                                       "noise per range squared")
    stereo_sigma_min_m: float = Field(FusionNoise.stereo_sigma_min_m, gt=0)
    bias_range_m: float = Field(FusionNoise.bias_range_m, gt=0, description="the stereo bias is measured on cells "
                                "both saw within this")
    bias_band_m: float = Field(FusionNoise.bias_band_m, gt=0, description="the bias is a line in range through "
                               "the medians of bands this wide")
    min_band_cells: int = Field(FusionNoise.min_band_cells, ge=1, description="a band with fewer shared cells is "
                                "left out of the bias line")
    bias_hold_m: float = Field(FusionNoise.bias_hold_m, ge=0, description="the bias line is held level from this "
                               "far past its last band")
    slope_sigmas: float = Field(FusionNoise.slope_sigmas, ge=0, description="a bias slope within this many "
                                "standard errors of 0 is taken for noise: one median instead")
    min_shared_cells: int = Field(FusionNoise.min_shared_cells, ge=1, description="fewer shared cells: no bias "
                                  "correction")
    disagree_sigmas: float = Field(FusionNoise.disagree_sigmas, gt=0, description="heights further apart than this "
                                   "many combined sigmas: the TOF's stands (the stereo's errors are heavy-tailed)")


@operations.register("dem.fuse", FuseParams, inputs=("tof", "stereo"))
def fuse(step: StepContext, params: FuseParams, tof: dict, stereo: dict) -> dict[str, Any]:
    """The TOF and stereo DEMs of the same views as one: the stereo bias measured against the TOF and
    taken off, shared cells weighted by each sensor's noise at their range (toolbox/mapping/fuse.py)."""
    pose = step.job.devices.rover.pose_estimate
    fused = fuse_dems(dem_tools.Dem(tof["spec"], tof["heights"], tof["counts"]),
                      dem_tools.Dem(stereo["spec"], stereo["heights"], stereo["counts"]),
                      (pose.x, pose.y), FusionNoise(**params.model_dump()))
    return {"spec": fused.dem.spec, "heights": fused.dem.heights, "counts": fused.dem.counts, **fused.summary()}


FUSION_KEYS = ("stereo_bias_m", "stereo_bias_per_m", "stereo_bias_at_m", "bias_measured", "shared_cells", "tof_only",
               "stereo_only", "weighted", "tof_kept")


def fusion_record(results: dict[str, Any]) -> dict[str, Any] | None:
    """What a workflow's dem.fuse step (named `fused`) found, as plain JSON values; None without one."""
    if "fused" not in results:
        return None
    return {key: np.asarray(results["fused"][key]).item() for key in FUSION_KEYS}


class FillParams(StepParams):
    max_reach_cells: float = Field(3.0, ge=0, le=50, description="holes are filled only this close to data")


@operations.register("dem.fill_holes", FillParams, inputs=("dem",))
def fill_holes(step: StepContext, params: FillParams, dem: dict) -> dict[str, Any]:
    """Interpolate across small enclosed gaps only: the unseen stays unknown."""
    filled = dem_tools.fill_small_holes(dem_tools.Dem(dem["spec"], dem["heights"], dem["counts"]),
                                        params.max_reach_cells)
    return {"spec": filled.spec, "heights": filled.heights, "counts": filled.counts}


class MergeParams(StepParams):
    sensor: Literal["tof", "stereo", "any"] = "any"


@operations.register("dem.merge_last", MergeParams, inputs=("dem",))
def merge_last(step: StepContext, params: MergeParams, dem: dict) -> dict[str, Any]:
    """Mosaic the new DEM with the last DEM product (more points per cell wins where they overlap)."""
    from rvs_server.products.rasters import read_geotiff
    pattern = {"tof": "dem-(full|update)-tof", "stereo": "dem-(full|update)", "any": "dem-.*"}[params.sensor]
    last = step.job.server.products.latest(pattern)
    if last is None:
        return {**dem, "merged_with": ""}
    heights, spec = read_geotiff(last.path / "dem.tif")
    counts_path = last.path / "counts.tif"
    from rvs_server.products.rasters import read_geotiff as read
    counts = read(counts_path)[0].astype(np.int32) if counts_path.exists() else np.isfinite(heights).astype(np.int32)
    merged = dem_tools.mosaic([dem_tools.Dem(spec, heights.astype(np.float32), counts),
                               dem_tools.Dem(dem["spec"], dem["heights"], dem["counts"])])
    return {"spec": merged.spec, "heights": merged.heights, "counts": merged.counts, "merged_with": last.name}


class HazardParams(StepParams):
    slope_limit_deg: float = Field(20.0, gt=0, lt=90)
    plane_radius: float = Field(0.25, gt=0)
    roughness_limit: float = Field(0.04, gt=0)
    step_limit: float = Field(0.10, gt=0)
    step_radius: float = Field(0.10, gt=0)
    ground_radius: float = Field(0.5, gt=0)
    step_min_cells: int = Field(5, ge=1)


@operations.register("hazard.maps", HazardParams, inputs=("dem",))
def hazards(step: StepContext, params: HazardParams, dem: dict) -> dict[str, Any]:
    """Slope, step and roughness from local plane fits, and the hazard map; unknown stays unknown."""
    config = hazard_tools.HazardConfig(**params.model_dump())
    maps = step.native(hazard_tools.hazard_maps, dem["heights"], dem["spec"].cell, config)
    return {"slope_deg": maps.slope_deg, "step": maps.step, "roughness": maps.roughness, "code": maps.code}


@operations.register("ortho.views", inputs=("dem", "acquired"), optional_inputs=("aligned",))
def ortho(step: StepContext, params: StepParams, dem: dict, acquired: dict,
          aligned: dict | None = None) -> dict[str, Any]:
    """Each view's intensity image draped on the DEM through the calibration; the best view per cell.
    With `aligned`, the views' poses get the localisation's correction first."""
    job = step.job
    correction = aligned["correction"] if aligned is not None else np.eye(4)
    if acquired["sensor"] == "tof":
        intrinsics = job.server.calibration().tof_intrinsics
        views = [(v["intensity"], correction @ v["camera_to_world"], _depth_of(v)) for v in acquired["views"]]
    else:
        intrinsics = stereo_intrinsics(job, acquired)[0]
        views = [(v["intensity"], correction @ v["camera_to_world"], None) for v in acquired["views"]]
    draped = []
    for index, (image, pose, depth) in enumerate(views):
        step.safe_point()
        step.progress(index / len(views), f"draping view {index + 1}")
        draped.append(ortho_image(dem["heights"], dem["spec"], image, intrinsics, pose, depth_image=depth))
    return {"intensity": merge_views(draped).astype(np.float32)}


def _depth_of(view: dict) -> np.ndarray:
    z = view["points_camera"][..., 2].astype(np.float64)
    return np.where(view["valid"] & np.isfinite(z), z, np.nan)


def current_pose(server: Host) -> RoverPose:
    return server.devices.rover.pose_estimate
