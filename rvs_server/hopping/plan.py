"""hop-plan's job: the last hop's frames to a corrected position and the next landing target.

The chain is a workflow (workflows/hop-plan.yaml, operations in steps.py), each step timed and
checkpointed like the maps' steps, so `continue` after a break or a crash resumes at the step that
was running:
    sfm        COLMAP through pycolmap on the CPU (global mapping), the camera's calibration held fixed (sfm)
    dense      two-view SGBM on pairs rectified from the SfM poses (sfm.densify)
    estimate   scale and gravity from the parabola, the cloud into the world at the launch estimate,
               ICP against the previous hop's cloud, the touchdown (estimate)
    plan       top-down maps, obstacle and safe-landing masks, the target and its launch (plan_landing)
then, here:
    write      the product's pictures, clouds and JSON; simulated, truth/ comparisons
The reconstruction goes into the product (sfm.npz) as soon as its step is done.
"""
from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from rvs_server.config import Point
from rvs_server.devices import HopperTruth
from rvs_server.files import atomic_file
from rvs_server.hopping.estimate import HopEstimate
from rvs_server.hopping.pictures import plan_pictures, trajectory_picture, truth_target_picture
from rvs_server.hopping.settings import HoppingSettings
from rvs_server.hopping.sfm import timed
from rvs_server.hopping.steps import LandingStepParams, Refused, operations
from rvs_server.hopping.store import HopObservation, load_observation, load_truth, save_reconstruction
from rvs_server.jobs import JobContext
from rvs_server.products.ply import write_ply
from rvs_server.products.rasters import write_geotiff, write_png
from rvs_server.protocol import BadRequest, RvsError
from rvs_server.workflow import Workflow, WorkflowError, load_workflow, resolve_params, run_workflow
from toolbox.geometry import apply
from toolbox.hopping import LandingPlan

if TYPE_CHECKING:
    from rvs_server.host import Host

WORKFLOW = "hop-plan"
FRAME_NOTE = ("world frame: x east, y north, z up, metres, heights relative to the start's ground; positions "
              "are the hopper's centre of mass; headings degrees counter-clockwise from east")
NO_TARGET = {"no_candidate": "no cell in reach has its whole landing error ellipse clear of obstacles and unseen "
                             "ground",
             "all_candidates_rejected": "every candidate examined was out of reach or its flight would hit the "
                                        "terrain"}


class HopPlanArgs(BaseModel):
    """What hop-plan's workflow sees as $args: the hop to plan from (the server's state, kept in the
    job's checkpoint so `continue` needs no state) and the command's options."""

    model_config = ConfigDict(extra="forbid")

    hop: str = Field(..., description="the hop product")
    launch: list[float] = Field(..., description="estimated centre of mass at launch, world")
    previous_cloud: str = Field("", description="the previous hop-plan's corrected cloud (PLY); empty: none")
    previous_plan: str = Field("", description="the hop-plan product it is from; empty: none")
    goal: Point | None = None
    goal_heading: float | None = None


@dataclass
class PlanOutcome:
    """What hop-plan found, for the server's state and the reply."""

    reply: dict[str, Any]
    estimate: HopEstimate
    plan: LandingPlan
    cloud_path: Path
    error: RvsError | None     # no landing target: raised after the state took the new position


def workflow_path(server: Host) -> Path:
    settings: HoppingSettings = server.settings_of("hopping")
    base = Path(settings.workflows_dir)
    if not base.is_absolute():
        base = server.config_dir.resolve() / base
    return base / f"{WORKFLOW}.yaml"


def check_workflow(server: Host) -> Workflow:
    """Load and check hop-plan's workflow: a broken file is refused before anything runs."""
    try:
        return load_workflow(workflow_path(server), operations, HopPlanArgs, HoppingSettings)
    except WorkflowError as exc:
        raise BadRequest(f"hop-plan: workflow refused: {exc}") from None


def run_hop_plan(ctx: JobContext, cfg: Any, inputs: dict, settings: HoppingSettings) -> PlanOutcome:
    """inputs: hop (product name), number, launch (estimated centre of mass at launch), previous_cloud
    (PLY path or None), previous_plan; they travel in the checkpoint so `continue` needs no state."""
    workflow = check_workflow(ctx.server)
    args = HopPlanArgs(hop=inputs["hop"], launch=inputs["launch"], previous_cloud=inputs.get("previous_cloud") or "",
                       previous_plan=inputs.get("previous_plan") or "", goal=cfg.goal, goal_heading=cfg.goal_heading)
    try:
        params = resolve_params(workflow, operations, args, settings)
    except WorkflowError as exc:
        raise BadRequest(f"hop-plan: {exc}") from None
    observation = load_observation(ctx.server.products.root / inputs["hop"])
    product = ctx.product(cfg, name=f"hop-plan-{inputs['number']:03d}")
    ctx.checkpoint({"product": product.name, "inputs": inputs})
    product.note("inputs", [{"hop": inputs["hop"]}, {"previous_plan": inputs.get("previous_plan")}])
    timings: dict[str, float] = {}

    def finished(step: str, result: Any, seconds: float | None) -> None:
        if seconds is not None:
            timings[step] = seconds
        if step == "sfm":   # in the product at once, also when a later step refuses the hop
            write_reconstruction(product, result)

    try:
        results, provenance = run_workflow(workflow, operations, params, ctx,
                                           ctx.server.recovery.folder(ctx.job.id) / "steps", on_step=finished)
    except Refused as exc:
        raise BadRequest(f"hop-plan: {exc}; product={product.name}", data={"product": product.name}) from None
    product.note("workflow", {"file": str(workflow.path), "name": workflow.name, "sha256_16": workflow.digest,
                              "steps": provenance, "args": args.model_dump(mode="json")})
    sfm, estimate, planned = results["sfm"]["reconstruction"], results["estimate"], results["plan"]
    plan = planned["plan"]
    ctx.progress(100.0, f"writing {product.name}")
    with timed(timings, "write"):
        cloud_path = write_plan_product(ctx, product, observation, sfm, estimate, results["dense"]["colours"], plan,
                                        inputs, timings, (planned["goal_heading"], planned["goal_xy"]))
    for step, seconds in timings.items():
        product.timing(step, seconds)
    reply = {**ctx.finish_product(product), **_reply_values(estimate, plan)}
    return PlanOutcome(reply, estimate, plan, cloud_path, _no_target(plan, product.name, params["plan"]))


def write_reconstruction(product: Any, sfm: dict) -> None:
    """The SfM step's result into the product: what each attempt gave, and the reconstruction."""
    product.note("sfm_attempts", sfm["attempts"])
    save_reconstruction(product.add("sfm.npz", "the reconstruction in COLMAP's frame (arbitrary scale and axes): "
                                    "camera centres and rotations per frame (NaN: not registered), sparse points, "
                                    "COLMAP's timings"), sfm["reconstruction"])


def _reply_values(estimate: HopEstimate, plan: LandingPlan) -> dict[str, Any]:
    position = f"{estimate.touchdown[0]:.3f},{estimate.touchdown[1]:.3f}"
    if not plan.found:
        return {"position": position}
    launch = plan.launch
    return {"target": f"{plan.target[0]:.3f},{plan.target[1]:.3f}", "speed": f"{launch.speed:.3f}",
            "elevation": f"{math.degrees(launch.elevation):.2f}", "heading": f"{math.degrees(launch.heading):.2f}",
            "position": position}


def _no_target(plan: LandingPlan, product: str, params: LandingStepParams) -> RvsError | None:
    if plan.found:
        return None
    return BadRequest(f"hop-plan: no landing target: {plan.reason}: {NO_TARGET.get(plan.reason, plan.reason)} "
                      f"({params.min_hop_m:g}-{params.max_hop_m:g} m from the touchdown, "
                      f"{len(plan.rejected)} candidates rejected); product={product}",
                      data={"product": product, "reason": plan.reason})


# ------------------------------------------------------------------------------------ the product
def write_plan_product(ctx: JobContext, product: Any, observation: HopObservation, sfm, estimate: HopEstimate,
                       colours: np.ndarray, plan: LandingPlan, inputs: dict, timings: dict, goal) -> Path:
    title = f"{product.name} ({observation.name})"
    cloud_path = write_ply(product.add("cloud.ply", "this hop's dense cloud, world frame after the ICP correction, "
                                       "grey levels as RGB"), estimate.result.cloud, colours)
    sparse = apply(estimate.to_world, estimate.result.flight.to_hop_frame(sfm.points))
    write_ply(product.add("sparse.ply", "COLMAP's sparse points, world frame"), sparse, sfm.colours)
    write_png(product.add("trajectory.png", "side view: SfM centres of mass, the fitted parabola, the ground"),
              trajectory_picture(estimate, title))
    write_trajectory_csv(product, observation, estimate)
    pictures = plan_pictures(plan, estimate.touchdown, title)
    for name, picture in pictures.items():
        write_png(product.add(name, PICTURES[name]), picture)
    write_geotiff(product.add("height.tif", "highest point per cell, metres (float32 GeoTIFF, NaN no data)"),
                  plan.top_down.height.astype(np.float32), plan.spec, "hop-plan top-down height")
    product.write_json("estimate.json", estimate_document(observation, sfm, estimate, plan, inputs, timings, goal),
                       "the estimate: launch, touchdown, heading, the parabola fit, ICP, the plan, timings per step")
    write_truth(ctx, product, observation, estimate, plan, title)
    return cloud_path


PICTURES = {"topdown.png": "top-down map of the dense cloud: mean grey level per cell",
            "height.png": "top-down height map",
            "obstacles.png": "obstacle mask: protrusion above the RANSAC ground plane",
            "safe.png": "safe-landing mask: reachable cells whose whole error ellipse is clear",
            "selection.png": "selection map with the chosen target, its error ellipse and the planned flight"}


def write_trajectory_csv(product: Any, observation: HopObservation, estimate: HopEstimate) -> None:
    flight = estimate.result.flight
    positions = apply(estimate.to_world, estimate.com_hop)
    with atomic_file(product.add("trajectory.csv", "per registered frame: time, estimated centre of mass (world), "
                                 "inlier of the parabola fit, residual"), "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["frame", "t_s", "x", "y", "z", "inlier", "residual_m"])
        for k, index in enumerate(estimate.registered):
            writer.writerow([int(index), f"{observation.timestamps[index]:.4f}", *(f"{v:.4f}" for v in positions[k]),
                             int(flight.inliers[k]), f"{flight.residuals_m[k]:.4f}"])


def estimate_document(observation, sfm, estimate: HopEstimate, plan: LandingPlan, inputs: dict, timings: dict,
                      goal) -> dict:
    result, first = estimate.result, float(observation.timestamps[estimate.registered[0]])
    launch = plan.launch
    return {
        "hop": observation.name, "frame": FRAME_NOTE,
        "frames": int(len(observation.frames)), "registered": int(len(estimate.registered)),
        "launch": {"given_m": list(inputs["launch"]), "first_frame_m": estimate.launch_given.tolist(),
                   "corrected_m": result.launch_point.tolist(), "first_frame_s": first},
        "touchdown_m": estimate.touchdown.tolist(), "touchdown_s": first + estimate.touchdown_tau,
        "last_frame_m": result.landing_point.tolist(),
        "heading_deg": math.degrees(estimate.heading), "sun_heading_deg": math.degrees(estimate.sun_heading),
        "flight": result.flight.report(),
        "sfm": {"registered": int(sfm.registered.sum()), "points": int(len(sfm.points)),
                "reprojection_error_px": sfm.reprojection_error, "models": sfm.num_models, "timings_s": sfm.timings},
        "dense_points": int(len(result.cloud)),
        "icp": {**estimate.icp, "against": inputs.get("previous_plan")},
        "goal": {"heading_deg": None if goal[0] is None else math.degrees(goal[0]),
                 "point_m": None if goal[1] is None else list(goal[1])},
        "plan": {"found": plan.found, "reason": plan.reason, "target_m": plan.target.tolist(),
                 "launch": None if launch is None else {
                     "speed_mps": launch.speed, "elevation_deg": math.degrees(launch.elevation),
                     "heading_deg": math.degrees(launch.heading), "flight_time_s": launch.flight_time},
                 "ellipse_semi_axes_m": None if plan.ellipse_axes is None else list(plan.ellipse_axes),
                 "ground_plane": {"normal": plan.ground.normal.tolist(), "offset": plan.ground.offset},
                 "grid": plan.spec.to_json(), "rejected": plan.rejected},
        "timings_s": timings,
    }


# ------------------------------------------------------------------------------------ truth
def write_truth(ctx: JobContext, product: Any, observation: HopObservation, estimate: HopEstimate,
                plan: LandingPlan, title: str) -> None:
    """Simulated hops: the estimate against the simulator's truth, and the target on the true obstacles."""
    hop_dir = ctx.server.products.root / observation.name
    truth = load_truth(hop_dir)
    world = ctx.devices.hopper.truth()
    if truth is None or world is None:
        return
    settings = ctx.settings
    offset = world.height_at(*settings.start)   # the map's heights start from the start's ground
    with np.load(hop_dir / "truth" / "poses.npz") as poses:
        first_pose = poses["camera_to_world"][estimate.registered[0]]
    comparison = truth_comparison(truth, estimate, plan, first_pose, observation.com_in_camera, offset)
    comparison["target"] = target_truth(world, plan, settings)
    product.write_json("truth/comparison.json", comparison, "estimated against true positions (world frame; "
                       "estimates shifted by map_z_offset_m to the world's heights), the target on the true obstacles")
    obstacles = world.obstacle_mask(settings.obstacle_m, plan.spec.cell, plan.spec.x_range, plan.spec.y_range)
    write_png(product.add("truth/obstacles.png", "true obstacles on the plan's grid with the target and its ellipse"),
              truth_target_picture(obstacles[:plan.spec.rows, :plan.spec.cols], plan, estimate.touchdown, title))


def truth_comparison(truth: dict, estimate: HopEstimate, plan: LandingPlan, first_pose: np.ndarray,
                     com_in_camera: np.ndarray, offset: float) -> dict:
    lift = np.array([0.0, 0.0, offset])
    landing_true = np.array(truth["landing"]["centre_m"])
    landing_estimated = estimate.touchdown + lift
    hop_range = float(truth["flight"]["range_m"])
    first_true = first_pose[:3, :3] @ com_in_camera + first_pose[:3, 3]
    flight = estimate.result.flight
    return {
        "map_z_offset_m": offset, "hop_range_m": hop_range,
        "landing": _error(landing_estimated, landing_true, hop_range),
        "launch_before_icp": _error(estimate.launch_given + lift, first_true, hop_range),
        "launch_after_icp": _error(estimate.result.launch_point + lift, first_true, hop_range),
        "heading_deg": {"estimated": math.degrees(estimate.heading), "true": truth["launch"]["heading_deg"],
                        "sun_sensor_body": math.degrees(estimate.sun_heading)},
        "launch_speed_mps": {"estimated": flight.launch_speed, "true": truth["launch"]["speed_mps"]},
        "launch_elevation_deg": {"estimated": math.degrees(flight.launch_elevation),
                                 "true": truth["launch"]["elevation_deg"]},
        "next_launch": {"estimated_m": landing_estimated.tolist(), "true_settled_m": truth["settled"]["centre_m"],
                        "bounce_horizontal_m": float(np.hypot(*truth["bounces"]["displacement_m"][:2]))},
    }


def _error(estimated: np.ndarray, true: np.ndarray, hop_range: float) -> dict:
    horizontal = float(np.hypot(*(estimated - true)[:2]))
    return {"estimated_m": estimated.tolist(), "true_m": true.tolist(), "horizontal_error_m": horizontal,
            "horizontal_error_of_hop": horizontal / hop_range if hop_range > 0 else None,
            "vertical_error_m": float(estimated[2] - true[2])}


def target_truth(world: HopperTruth, plan: LandingPlan, settings: HoppingSettings) -> dict | None:
    """Is the target's footprint (rover radius) clear of the world's obstacles, and how far is the nearest?"""
    if not plan.found:
        return None
    x, y = plan.target[:2]
    reach = 1.0
    cell = world.cell
    mask = world.obstacle_mask(settings.obstacle_m, cell, (x - reach, x + reach), (y - reach, y + reach))
    rows, cols = np.nonzero(mask)
    distances = np.hypot((cols + 0.5) * cell - reach, (rows + 0.5) * cell - reach)
    nearest = float(distances.min()) if len(distances) else None
    return {"target_m": plan.target.tolist(), "obstacle_step_m": settings.obstacle_m,
            "nearest_true_obstacle_m": nearest, "footprint_clear": nearest is None or nearest > settings.rover_radius_m}
