"""The operations hop-plan's workflow is made of (workflows/hop-plan.yaml names them), in the hopping
paper's order (Fig 3):

    hop.sfm        COLMAP through pycolmap on the CPU, the camera's calibration held fixed (sfm.py), with
                   hopping.toml's setting, then each of sfm_fallbacks while the reconstruction is not a
                   clean flight
    hop.dense      two-view SGBM on pairs rectified from the SfM poses (sfm.densify)
    hop.estimate   scale and gravity from the parabola, the cloud into the world at the launch estimate,
                   the correction against the previous hop's cloud, the touchdown (estimate.py)
    hop.landing    top-down maps, obstacle and safe-landing masks, the target and its launch (plan_landing)

Each step reads the hop's frames, calibration and sensors from its product (params.hop), and its
parameters are hopping.toml's settings under their own names ($config.NAME). The results are
checkpointed by the workflow engine, dataclasses and all (`result_types`), so `continue` resumes at
the step a break or a crash stopped. A step that finds the hop unusable raises Refused, which
hop-plan answers ERR 400 naming its product.
"""
from __future__ import annotations

import math
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import pycolmap
from pydantic import Field

from rvs_server.config import Point
from rvs_server.hopping.estimate import (
    EstimateError,
    EstimateParams,
    FitParams,
    HopEstimate,
    estimate_hop,
    flight_check,
)
from rvs_server.hopping.settings import Mapper, SfmSetting
from rvs_server.hopping.sfm import MIN_SFM_FRAMES, HopReconstruction, SfmConfig, densify, reconstruct_hop_quietly
from rvs_server.hopping.store import HopObservation, cloud_of, load_observation
from rvs_server.products.ply import read_ply
from rvs_server.workflow import Operations, StepContext, StepParams
from toolbox.hopping import (
    FlightFit,
    HopResult,
    IcpRound,
    LandingEllipse,
    LandingParams,
    LandingPlan,
    Launch,
    NoGroundError,
    OverlapAlignment,
    Plane,
    TopDown,
    plan_landing,
)

operations = Operations()
operations.result_types(HopReconstruction, HopEstimate, HopResult, FlightFit, OverlapAlignment, IcpRound,
                        LandingPlan, TopDown, Plane, LandingEllipse, Launch)


class Refused(Exception):
    """The hop cannot be planned from (its reconstruction falls short); the message says why."""


class HopParams(StepParams):
    hop: str = Field(..., description="the hop product to plan from ($args.hop)")


def observation_of(step: StepContext, hop: str) -> HopObservation:
    """The hop as the rover recorded it: frames, calibration, sensors (never the truth)."""
    return load_observation(step.job.server.products.root / hop)


# ---------------------------------------------------------------------------------------------
# Structure from motion


class SfmParams(HopParams):
    sfm_max_features: int = Field(..., ge=256, le=32768)
    sfm_first_octave: int = Field(..., ge=-1, le=2)
    sfm_mapper: Mapper
    sfm_fallbacks: list[SfmSetting] = Field(..., max_length=4)
    sfm_threads: int = Field(..., ge=-1, le=256)
    gravity_mps2: float = Field(..., gt=0)
    min_registered: float = Field(..., gt=0, le=1)
    min_fit_inliers: float = Field(..., gt=0, le=1)


@operations.register("hop.sfm", SfmParams)
def structure_from_motion(step: StepContext, params: SfmParams) -> dict[str, Any]:
    """COLMAP on the hop's frames: the first reconstruction that is a clean flight, and each attempt."""
    observation = observation_of(step, params.hop)
    if len(observation.frames) < MIN_SFM_FRAMES:   # a flight cut short: the season soak met one with 1 frame
        raise Refused(f"{params.hop} recorded {len(observation.frames)} frame(s) of its flight: structure from motion "
                      f"needs at least {MIN_SFM_FRAMES}; hop again with a longer flight")
    started = time.perf_counter()
    with colmap_quiet():
        sfm, attempts = reconstruct_cleanly(step, observation, params, step.scratch / "colmap")
    step.progress(1.0, f"structure from motion: {int(sfm.registered.sum())} of {len(sfm.registered)} frames "
                       f"registered, {len(sfm.points)} points, {time.perf_counter() - started:.1f} s")
    return {"reconstruction": sfm, "attempts": attempts}


def reconstruct_cleanly(step: StepContext, observation: HopObservation, params: SfmParams, workdir: Path
                        ) -> tuple[HopReconstruction, list[dict]]:
    """SfM with hopping.toml's setting, then each of sfm_fallbacks in turn while the reconstruction is not a
    clean flight (estimate.flight_check). Every setting bends a few hops at random, seldom the same
    ones. Returns the first clean reconstruction, or the one whose parabola fit kept most frames, and what
    each attempt gave."""
    settings_tried = [(params.sfm_mapper, params.sfm_first_octave)] + \
        [(fallback.mapper, fallback.first_octave) for fallback in params.sfm_fallbacks]
    check = FitParams(gravity=params.gravity_mps2, min_registered=params.min_registered,
                      min_inliers=params.min_fit_inliers)
    best, best_share, attempts = None, -1.0, []
    for number, (mapper, octave) in enumerate(settings_tried, start=1):
        step.safe_point()
        step.progress((number - 1) / len(settings_tried),
                      f"structure from motion (COLMAP, {mapper} mapping, SIFT octave {octave}, CPU), attempt "
                      f"{number}: {len(observation.frames)} frames of {params.hop}")
        config = SfmConfig(max_features=params.sfm_max_features, first_octave=octave, mapper=mapper,
                           num_threads=params.sfm_threads)
        # COLMAP in the native worker: a crash there ends this job, not the server (rvs_server/native.py)
        sfm = step.native(reconstruct_hop_quietly, observation.frames, observation.timestamps, observation.camera,
                          workdir, config)
        share, problem = flight_check(observation, sfm, check)
        attempts.append({"mapper": mapper, "first_octave": octave, "registered": int(sfm.registered.sum()),
                         "fit_share": round(share, 4), "problem": problem,
                         "seconds": round(sfm.timings.get("total", math.nan), 2)})
        if share > best_share:
            best, best_share = sfm, share
        if not problem:
            break
        step.progress(number / len(settings_tried), f"structure from motion, attempt {number}: {problem}")
    return best, attempts


@contextmanager
def colmap_quiet() -> Iterator[None]:
    """COLMAP logs every image it registers at INFO: keep its warnings and errors only."""
    level = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = 1
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = level


# ---------------------------------------------------------------------------------------------
# Dense cloud, estimate, landing target


@operations.register("hop.dense", HopParams, inputs=("sfm",))
def dense(step: StepContext, params: HopParams, sfm: dict) -> dict[str, Any]:
    """Two-view SGBM on pairs rectified from the SfM poses: the hop's dense cloud in the SfM frame."""
    observation = observation_of(step, params.hop)
    reconstruction = sfm["reconstruction"]
    step.progress(0.0, f"dense cloud: pairs of {int(reconstruction.registered.sum())} registered frames, SGBM")
    points, colours = step.native(densify, observation.frames, reconstruction, observation.camera)
    return {"points": points, "colours": colours}


class EstimateStepParams(HopParams):
    launch: list[float] = Field(..., min_length=3, max_length=3, description="estimated centre of mass at "
                                "launch, world ($args.launch)")
    previous_cloud: str = Field("", description="the previous hop-plan's corrected cloud (PLY); empty: none")
    previous_plan: str = Field("", description="the hop-plan product it is from")
    gravity_mps2: float = Field(..., gt=0)
    icp_voxel_m: float = Field(..., gt=0)
    icp_initial_distance_m: float = Field(..., gt=0)
    icp_crop_m: float = Field(..., gt=0)
    icp_max_yaw_deg: float = Field(..., gt=0)
    icp_min_contrast: float = Field(..., ge=1)
    icp_distinct_m: float = Field(..., gt=0)
    min_registered: float = Field(..., gt=0, le=1)
    min_fit_inliers: float = Field(..., gt=0, le=1)


@operations.register("hop.estimate", EstimateStepParams, inputs=("sfm", "dense"))
def estimate(step: StepContext, params: EstimateStepParams, sfm: dict, dense: dict) -> HopEstimate:
    """Scale and gravity from the parabola, the cloud into the world, the position correction, the touchdown."""
    observation = observation_of(step, params.hop)
    previous = params.previous_cloud or None
    step.progress(0.0, "scale and gravity from the parabola" +
                  (f"; position correction by ICP against {params.previous_plan}" if previous else ""))
    cloud_sfm = dense["points"]
    if len(cloud_sfm) < 100:
        raise Refused(f"the dense cloud of {params.hop} has {len(cloud_sfm)} points: too few to map the landing "
                      f"area")
    previous_cloud = cloud_of(read_ply(Path(previous)))[0] if previous and Path(previous).exists() else None
    try:
        return estimate_hop(observation, sfm["reconstruction"], cloud_sfm, np.asarray(params.launch),
                            previous_cloud, estimate_params(params))
    except EstimateError as exc:
        raise Refused(f"{params.hop} not reconstructed well enough: {exc}") from None


def estimate_params(params: EstimateStepParams) -> EstimateParams:
    return EstimateParams(gravity=params.gravity_mps2, icp_voxel=params.icp_voxel_m,
                          icp_initial_distance=params.icp_initial_distance_m, icp_crop=params.icp_crop_m,
                          icp_max_yaw_deg=params.icp_max_yaw_deg, icp_min_contrast=params.icp_min_contrast,
                          icp_distinct=params.icp_distinct_m, min_registered=params.min_registered,
                          min_inliers=params.min_fit_inliers)


class LandingStepParams(HopParams):
    goal: Point | None = Field(..., description="hop toward this X,Y ($args.goal) ...")
    goal_heading: float | None = Field(..., description="... or in this direction, degrees ($args.goal_heading); "
                                       "neither: on along this hop's heading")
    cell_m: float = Field(..., gt=0)
    gravity_mps2: float = Field(..., gt=0)
    obstacle_m: float = Field(..., gt=0)
    min_hop_m: float = Field(..., gt=0)
    max_hop_m: float = Field(..., gt=0)
    elevation_deg: float = Field(..., gt=0, lt=90)
    sigma_speed_mps: float = Field(..., ge=0)
    sigma_elevation_deg: float = Field(..., ge=0)
    sigma_heading_deg: float = Field(..., ge=0)
    sigma_position_m: float = Field(..., ge=0)
    rover_radius_m: float = Field(..., gt=0)
    safety_weight: float = Field(..., ge=0, le=1)


@operations.register("hop.landing", LandingStepParams, inputs=("estimate", "dense"))
def landing(step: StepContext, params: LandingStepParams, estimate: HopEstimate, dense: dict) -> dict[str, Any]:
    """The next landing target on the top-down maps of the corrected cloud, and the launch that reaches it."""
    step.progress(0.0, "landing target: obstacles, error ellipses, selection, collision check")
    goal_heading, goal_xy = goal_of(params, estimate)
    try:
        plan = plan_landing(estimate.result.cloud, estimate.touchdown, goal_heading, goal_xy,
                            landing_params(params), dense["colours"])
    except NoGroundError as exc:    # a wrong scale or flight puts the touchdown off the cloud
        raise Refused(f"{params.hop} not reconstructed well enough: {exc}") from None
    return {"plan": plan, "goal_heading": goal_heading, "goal_xy": goal_xy}


def goal_of(params: LandingStepParams, estimate: HopEstimate) -> tuple[float | None, np.ndarray | None]:
    """The goal point, the goal heading, or on along this hop's heading."""
    if params.goal is not None:
        return None, np.asarray(params.goal, float)
    if params.goal_heading is not None:
        return math.radians(params.goal_heading), None
    return estimate.heading, None


def landing_params(params: LandingStepParams) -> LandingParams:
    return LandingParams(cell=params.cell_m, gravity=params.gravity_mps2, obstacle_threshold=params.obstacle_m,
                         min_distance=params.min_hop_m, max_distance=params.max_hop_m,
                         elevation=math.radians(params.elevation_deg), sigma_speed=params.sigma_speed_mps,
                         sigma_elevation=math.radians(params.sigma_elevation_deg),
                         sigma_heading=math.radians(params.sigma_heading_deg),
                         sigma_position=params.sigma_position_m, rover_radius=params.rover_radius_m,
                         safety_weight=params.safety_weight, goal_weight=1.0 - params.safety_weight)
