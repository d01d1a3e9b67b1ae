"""Maps from what the rover sees: dem-full-tof, dem-update-tof, dem-full, dem-update, dem-full-fused.

Each command runs its workflow (workflows/<command>.yaml) and writes a product: the DEM and the
slope, step, roughness and hazard maps as float32 GeoTIFF (NaN no-data, origin and cell size in the
tags), colour PNGs with legends, the ortho-image, the merged cloud as PLY, the views with their
poses, and the manifest with the workflow's provenance. With simulated devices the product's
truth/ holds the true heights and obstacles over the same cells.
"""
from __future__ import annotations

import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from pydantic import Field

from rvs_server.config import CommandConfig, Range, SafeName, Settings
from rvs_server.dispatch import Module
from rvs_server.jobs import JobContext
from rvs_server.mapping.steps import fusion_record, operations
from rvs_server.mapping.stored_views import keep_views
from rvs_server.products.canvas import side_by_side
from rvs_server.products.ply import write_ply
from rvs_server.products.rasters import write_geotiff, write_png
from rvs_server.protocol import BadRequest
from rvs_server.workflow import WorkflowError, load_workflow, resolve_params, run_workflow
from toolbox.colour import categorical, colourise, upscale, with_colour_bar, with_key, with_title
from toolbox.grid import GridSpec
from toolbox.mapping.hazard import HAZARD, ROUGHNESS, SLOPE, STEP, UNKNOWN

if TYPE_CHECKING:
    from rvs_server.host import Host


class MappingSettings(Settings):
    """configs/mapping.toml: the defaults every mapping workflow reads as $config.NAME."""

    workflows_dir: str = Field("../workflows", description="where the workflow files are, relative to "
                               "the config directory")
    cell: float = Field(0.05, ge=0.005, le=1.0)
    overlap: float = Field(0.15, ge=0.0, lt=0.9)
    tof_tilt: Range = (-62.0, -28.0)
    stereo_tilt: Range = (-40.0, -20.0)
    frames: int = Field(2, ge=1, le=50, description="SR4000 frames averaged per view")
    min_confidence: int = Field(16384, ge=0, le=65535, description="SR4000 pixels below are dropped")
    max_range_m: float = Field(4.8, gt=0, description="points beyond this range are dropped")
    max_reach_cells: float = Field(3.0, ge=0, le=50, description="TOF DEM holes are filled only this close to data")
    stereo_max_reach_cells: float = Field(3.0, ge=0, le=50, description="the same for stereo DEMs (whose small "
                                          "holes are often rocks the pair could not match)")
    tof_top_band_m: float = Field(0.02, ge=0, le=0.5, description="a TOF DEM cell's height is the mean of its "
                                  "points within this band of its highest (0: the highest point)")
    stereo_top_band_m: float = Field(0.02, ge=0, le=0.5, description="the same for stereo DEMs")
    slope_limit_deg: float = Field(20.0, gt=0, lt=90)
    step_limit: float = Field(0.10, gt=0)
    tof_step_min_cells: int = Field(2, ge=1, le=25, description="a TOF step counts when this many cells "
                                    "within 0.1 m exceed the limit (fewer scale it down: noise)")
    stereo_step_min_cells: int = Field(2, ge=1, le=25, description="the same for stereo maps")
    roughness_limit: float = Field(0.04, gt=0)
    truth_step: float = Field(0.10, gt=0, description="step height of the truth obstacle grid in products")
    keep_views: bool = Field(True, description="products keep their raw views and context (views/), so "
                             "that `rvs remap` can run a changed workflow on them later")


module = Module("mapping", settings=MappingSettings, summary="DEMs, ortho-images and hazard maps")


class DemConfig(CommandConfig):
    pan: Range = Field((-180.0, 180.0), description="pan range, degrees; the default is a full panorama")
    tilt: Range | None = Field(None, description="tilt range, degrees; default from mapping.toml")
    cell: float | None = Field(None, ge=0.005, le=1.0, description="cell size, metres; default mapping.toml")
    overlap: float | None = Field(None, ge=0.0, lt=0.9, description="overlap of neighbouring views, 0..0.9")
    output: SafeName | None = Field(None, description="product name; default COMMAND-TIME")


class DemUpdateConfig(DemConfig):
    pan: Range = Field((-30.0, 30.0), description="pan range of the new views, degrees")


class WorkflowArgs(CommandConfig):
    """What workflows see as $args: the command's options with the defaults filled in."""

    pan: Range
    tilt: Range
    cell: float
    overlap: float


def _args(ctx: JobContext, cfg: DemConfig, sensor: str) -> WorkflowArgs:
    s: MappingSettings = ctx.settings
    return WorkflowArgs(pan=cfg.pan, tilt=cfg.tilt or (s.stereo_tilt if sensor == "stereo" else s.tof_tilt),
                        cell=cfg.cell or s.cell, overlap=cfg.overlap if cfg.overlap is not None else s.overlap)


def workflow_path(server: Host, command: str) -> Path:
    settings: MappingSettings = server.settings_of("mapping")
    base = Path(settings.workflows_dir)
    if not base.is_absolute():
        base = server.config_dir.resolve() / base
    return base / f"{command}.yaml"


def check_workflow(server: Host, command: str, args_model: type[CommandConfig] = WorkflowArgs) -> Any:
    """Load and check the command's workflow: a broken file is refused before anything moves."""
    try:
        return load_workflow(workflow_path(server, command), operations, args_model, MappingSettings)
    except WorkflowError as exc:
        raise BadRequest(f"{command}: workflow refused: {exc}") from None


def _validator(command: str):
    def validate(server: Host, cfg: DemConfig) -> None:
        check_workflow(server, command)
    return validate


def run_mapping(ctx: JobContext, cfg: DemConfig, sensor: str) -> dict[str, Any]:
    command = ctx.job.command
    workflow = check_workflow(ctx.server, command)
    args = _args(ctx, cfg, sensor)
    try:
        params = resolve_params(workflow, operations, args, ctx.settings)
    except WorkflowError as exc:
        raise BadRequest(f"{command}: {exc}") from None
    product = ctx.product(cfg)
    started = time.perf_counter()
    results, provenance = run_workflow(workflow, operations, params, ctx,
                                       ctx.server.recovery.folder(ctx.job.id) / "steps")
    for record in provenance:
        if "seconds" in record:
            product.timing(record["step"], record["seconds"])
    product.note("workflow", {"file": str(workflow.path), "name": workflow.name, "sha256_16": workflow.digest,
                              "steps": provenance, "args": args.model_dump(mode="json")})
    write_started = time.perf_counter()
    summary = write_maps(ctx, product, results)
    note_fusion(product, results, summary)
    if ctx.settings.keep_views:
        keep_views(product, workflow, results, ctx.devices.rover.pose_estimate, ctx.server.calibration(),
                   ctx.settings, args, command)
    product.timing("writing", time.perf_counter() - write_started)
    product.timing("total", time.perf_counter() - started)
    ctx.save_truth(product)
    return {**ctx.finish_product(product), **summary}


# ---------------------------------------------------------------------------------------------
# The product


HAZARD_PALETTE = {0: (70, 160, 70), UNKNOWN: (40, 40, 40)}
HAZARD_KEY = [("safe", (70, 160, 70)), ("step", (220, 60, 50)), ("slope", (240, 170, 40)),
              ("roughness", (170, 90, 200)), ("unknown", (40, 40, 40))]


def hazard_picture(code: np.ndarray) -> np.ndarray:
    """Safe green, unknown dark grey, hazards coloured by their main cause (step first)."""
    rgb = categorical(code, HAZARD_PALETTE)
    hazard = (code != UNKNOWN) & ((code & HAZARD) != 0)
    for bit, colour in ((ROUGHNESS, (170, 90, 200)), (SLOPE, (240, 170, 40)), (STEP, (220, 60, 50))):
        rgb[hazard & ((code & bit) != 0)] = colour
    rgb[hazard & ((code & (STEP | SLOPE | ROUGHNESS)) == 0)] = (220, 60, 50)
    return rgb


def _north_up(grid_rgb: np.ndarray) -> np.ndarray:
    """A grid as a picture: north up, small grids enlarged so a cell is a few pixels."""
    return upscale(np.ascontiguousarray(np.flipud(grid_rgb)), 480)


def _legend_title(spec: GridSpec) -> str:
    return (f"{spec.cols * spec.cell:.1f} x {spec.rows * spec.cell:.1f} m, cell {spec.cell * 100:.0f} cm, "
            f"origin ({spec.origin_x:.2f}, {spec.origin_y:.2f}), north up")


def note_fusion(product: Any, results: dict[str, Any], summary: dict[str, Any]) -> None:
    """A fused workflow's dem.fuse findings: into product.json `fusion` and the reply's summary."""
    fusion = fusion_record(results)
    if fusion is not None:
        summary.update(stereo_bias=f"{fusion['stereo_bias_m']:.4f}", shared_cells=fusion["shared_cells"])
        product.note("fusion", fusion)


def write_maps(ctx: JobContext, product: Any, results: dict[str, Any],
               settings: MappingSettings | None = None) -> dict[str, Any]:
    """Every layer as GeoTIFF and PNG, the overview, cloud, views and (simulated) truth grids.
    `settings`: the mapping settings when the job is not a mapping command's (navigate)."""
    settings = settings or ctx.settings
    dem = results["dem"]
    hazard = results["hazard"]
    spec: GridSpec = dem["spec"]
    heights = dem["heights"].astype(np.float32)
    layers = {"dem": (heights, "height above the world's z = 0, metres"),
              "slope": (hazard["slope_deg"], "slope from a local plane fit, degrees"),
              "step": (hazard["step"], "step: height above the local minimum, metres"),
              "roughness": (hazard["roughness"], "roughness: residual of the plane fit, metres"),
              "hazard": (hazard["code"].astype(np.float32), "hazard code: 0 safe, 255 unknown, odd = hazard "
                         "(+2 slope, +4 step, +8 roughness)"),
              "counts": (dem["counts"].astype(np.float32), "points per cell (0: filled or unknown)")}
    for name, (values, what) in layers.items():
        write_geotiff(product.add(f"{name}.tif", f"{what} (float32 GeoTIFF, NaN no-data)"), values, spec, what)
    title = _legend_title(spec)
    known = np.isfinite(heights)
    low, high = (float(np.nanpercentile(heights, 1)), float(np.nanpercentile(heights, 99))) if known.any() else (0, 1)
    pictures = {
        "dem.png": with_colour_bar(_north_up(colourise(heights, low, high)), low, high, "height, m"),
        "slope.png": with_colour_bar(_north_up(colourise(hazard["slope_deg"], 0, 40)), 0, 40, "slope, degrees"),
        "step.png": with_colour_bar(_north_up(colourise(hazard["step"], 0, 0.3)), 0, 0.3, "step, m"),
        "roughness.png": with_colour_bar(_north_up(colourise(hazard["roughness"], 0, 0.08)), 0, 0.08, "roughness, m"),
        "hazard.png": with_key(_north_up(hazard_picture(hazard["code"])), HAZARD_KEY, "hazard map"),
    }
    if "ortho" in results:
        intensity = results["ortho"]["intensity"]
        top = float(np.nanpercentile(intensity, 99)) if np.isfinite(intensity).any() else 1.0
        pictures["ortho.png"] = with_colour_bar(_north_up(colourise(intensity, 0, top, "gray")), 0, top,
                                                "ortho-image intensity", cmap="gray")
        write_geotiff(product.add("ortho.tif", "ortho-image intensity (float32 GeoTIFF, NaN unseen)"),
                      intensity.astype(np.float32), spec, "ortho-image")
    for name, rgb in pictures.items():
        write_png(product.add(name, f"{name[:-4]} picture with legend"), with_title(rgb, f"{product.name}: {title}"))
    truth_picture = truth_obstacle_picture(ctx, spec, settings.truth_step)
    panels = [pictures["dem.png"], pictures.get("ortho.png"), pictures["hazard.png"], truth_picture]
    write_png(product.add("overview.png", "DEM, ortho-image, hazard map and (simulated) true obstacles side by side"),
              with_title(side_by_side([p for p in panels if p is not None]), f"{product.name}: {title}"))
    # The last cloud the chain made: localised if a step aligned it, the rover's body removed if one did.
    cloud = next((results[key]["points"] for key in ("aligned", "body", "points") if key in results), None)
    if cloud is not None:
        write_ply(product.add("cloud.ply", "merged point cloud, world frame (x east, y north, z up), metres"), cloud)
    acquired = results.get("acquired")
    if acquired is not None:
        product.write_json("views.json", [
            {"index": i, "pan_deg": float(v["pan_tilt_deg"][0]), "tilt_deg": float(v["pan_tilt_deg"][1]),
             "camera_to_world": np.asarray(v.get("camera_to_world", v.get("left_to_world"))).tolist()}
            for i, v in enumerate(acquired["views"])], "each view's PTU angles and estimated camera pose")
    product.write_json("grid.json", spec.to_json(), "the grid's origin, cell size and frame")
    write_truth_grids(ctx, product, spec, acquired, settings.truth_step)
    observed = float(np.mean(known))
    hazardous = float(np.mean((hazard["code"] != UNKNOWN) & ((hazard["code"] & HAZARD) != 0)))
    return {"cells": f"{spec.rows}x{spec.cols}", "cell": spec.cell, "known": f"{observed:.3f}",
            "hazardous": f"{hazardous:.3f}", "views": len(acquired["views"]) if acquired else 0}


def truth_obstacle_picture(ctx: JobContext, spec: GridSpec, step: float) -> np.ndarray | None:
    truth = ctx.devices.truth
    if truth is None:
        return None
    obstacles = truth.obstacle_mask(step, spec.cell, spec.x_range, spec.y_range)
    rgb = categorical(obstacles[:spec.rows, :spec.cols].astype(np.uint8), {0: (70, 160, 70), 1: (220, 60, 50)})
    return with_key(_north_up(rgb), [("clear", (70, 160, 70)), (f"rock > {step} m", (220, 60, 50))],
                    "truth: obstacles")


def write_truth_grids(ctx: JobContext, product: Any, spec: GridSpec, acquired: dict | None,
                      truth_step: float) -> None:
    truth = ctx.devices.truth
    if truth is None:
        return
    x_range, y_range = spec.x_range, spec.y_range
    truth_height = truth.height_map(spec.cell, x_range, y_range).astype(np.float32)
    write_geotiff(product.add("truth/height.tif", "true height at each cell centre, metres"),
                  truth_height[:spec.rows, :spec.cols], spec, "truth height")
    cell = max(spec.cell, truth.cell)
    if abs(cell - spec.cell) < 1e-12:
        obstacles = truth.obstacle_mask(truth_step, spec.cell, x_range, y_range)
        write_geotiff(product.add("truth/obstacles.tif", f"1 where a rock stands more than {truth_step} m "
                                  "above the rock-free ground (drivers/sim/world.py obstacle_mask)"),
                      obstacles[:spec.rows, :spec.cols].astype(np.float32), spec, "truth obstacles")
        write_png(product.add("truth/obstacles.png", "true obstacles, north up"),
                  with_title(with_key(_north_up(categorical(obstacles.astype(np.uint8), {0: (70, 160, 70),
                                                                                          1: (220, 60, 50)})),
                                      [("clear", (70, 160, 70)), (f"rock > {truth_step} m", (220, 60, 50))],
                                      "true obstacles"), f"{product.name}: truth"))
    if acquired is not None:
        product.write_json("truth/views.json",
                           [np.asarray(v.get("true_camera_to_world", np.full((4, 4), np.nan))).tolist()
                            for v in acquired["views"]], "true camera-to-world pose of each view")


# ---------------------------------------------------------------------------------------------
# Commands


@module.job("dem-full-tof", DemConfig, devices=("ptu", "tof"), validate=_validator("dem-full-tof"))
def dem_full_tof(ctx: JobContext, cfg: DemConfig) -> dict[str, Any]:
    """A new DEM, ortho-image and hazard maps from SR4000 views across the pan/tilt range."""
    return run_mapping(ctx, cfg, "tof")


@module.job("dem-update-tof", DemUpdateConfig, devices=("ptu", "tof"), validate=_validator("dem-update-tof"))
def dem_update_tof(ctx: JobContext, cfg: DemUpdateConfig) -> dict[str, Any]:
    """New SR4000 views merged into the last DEM."""
    return run_mapping(ctx, cfg, "tof")


@module.job("dem-full", DemConfig, devices=("ptu", "cameras"), validate=_validator("dem-full"))
def dem_full(ctx: JobContext, cfg: DemConfig) -> dict[str, Any]:
    """A new DEM, ortho-image and hazard maps from the stereo pair across the pan/tilt range."""
    return run_mapping(ctx, cfg, "stereo")


@module.job("dem-update", DemUpdateConfig, devices=("ptu", "cameras"), validate=_validator("dem-update"))
def dem_update(ctx: JobContext, cfg: DemUpdateConfig) -> dict[str, Any]:
    """New stereo views merged into the last DEM."""
    return run_mapping(ctx, cfg, "stereo")


@module.job("dem-full-fused", DemConfig, devices=("ptu", "tof", "cameras"), validate=_validator("dem-full-fused"))
def dem_full_fused(ctx: JobContext, cfg: DemConfig) -> dict[str, Any]:
    """One DEM, ortho-image and hazard maps from the SR4000 and the stereo pair at the same views."""
    return run_mapping(ctx, cfg, "fused")
