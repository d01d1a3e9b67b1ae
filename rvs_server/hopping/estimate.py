"""hop-plan's estimate: one hop's reconstruction made metric, gravity-aligned and placed in the world
(the hopping paper's Fig 3 through toolbox.hopping.process_hop), and where the flight touched down.

    fit_flight(camera centres)         a first fit for the scale, so eq 1 can move each camera centre
                                       to the centre of mass (the offset is metric, SfM is not)
    hop heading                        the sun sensor's body heading, less the body's yaw in the hop
                                       frame: SfM sees the launch's heading error, the sun sensor cannot
    process_hop(centres of mass, ...)  scale and gravity from the parabola (the accelerometer's gravity
                                       as the prior), the cloud into the world at the launch estimate
    correct_position                   the shift onto the previous hop's cloud around the launch estimate:
                                       height maps matched over every plausible shift, then ICP
                                       (hopping_icp's crop loop) from there; none where the ground is flat
    touchdown                          the fitted parabola followed down from the last frame to where
                                       the body's underside meets the ground the cloud shows there

The world frame is the map's: x east, y north, heights relative to the start's ground. Positions are
the centre of mass's.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from rvs_server.hopping.sfm import HopReconstruction
from rvs_server.hopping.store import HopObservation
from toolbox.geometry import apply, compose, rigid, rotation_z
from toolbox.hopping import HopResult, align_with_overlap_elimination, centre_of_mass_positions, fit_flight, process_hop
from toolbox.mapping.height_match import match_height_maps

TOUCHDOWN_SEARCH_RADIUS_M = 0.25  # cloud points this close to the last frame's position give the ground height


class EstimateError(ValueError):
    """The hop's reconstruction cannot be trusted; the message says what fell short."""


@dataclass(frozen=True)
class FitParams:
    """What the first parabola fit needs: hop-plan's SfM step checks each reconstruction with it."""

    gravity: float
    min_registered: float         # share of the frames SfM must register
    min_inliers: float            # share of the registered frames the parabola fit must keep


@dataclass(frozen=True)
class EstimateParams(FitParams):
    icp_voxel: float
    icp_initial_distance: float   # how far the launch estimate may be off: ICP's first correspondence distance
    icp_crop: float               # the alignment uses the ground within this of the launch estimate
    icp_max_yaw_deg: float        # a larger turn is a false match
    icp_min_contrast: float       # the height match's runner-up misfit / its best: less is ground too flat
    icp_distinct: float           # m: shifts farther than this from the best are its rivals


@dataclass(frozen=True)
class HopEstimate:
    result: HopResult              # process_hop's; its plan is None (planning is hop-plan's next step)
    heading: float                 # rad, world heading of the hop frame's x axis (the flight's direction)
    sun_heading: float             # rad, what the sun sensor said of the body
    registered: np.ndarray         # indices of the frames used
    com_hop: np.ndarray            # (R, 3) their centres of mass in the hop frame, metres
    launch_given: np.ndarray       # (3,) world position process_hop started from (first registered frame)
    touchdown: np.ndarray          # (3,) world, corrected: the centre of mass at the first touchdown
    touchdown_tau: float           # s after the first registered frame
    gravity: float                 # m/s^2, the g the fit assumed
    icp: dict = field(default_factory=dict)

    @property
    def to_world(self) -> np.ndarray:
        """Hop frame to world, the ICP correction included."""
        return compose(self.result.correction, self.result.hop_to_world)

    def trajectory(self, taus: np.ndarray) -> np.ndarray:
        """(M, 3) world positions of the fitted flight at times tau after the first registered frame."""
        return apply(self.to_world, flight_positions(self.result.flight.launch_velocity, taus, self.gravity))


def flight_positions(velocity: np.ndarray, taus, gravity: float) -> np.ndarray:
    """Hop-frame positions v tau - g tau^2 / 2 z (the hop frame's origin is the fit's first frame)."""
    taus = np.asarray(taus, dtype=np.float64)[:, None]
    return velocity * taus - 0.5 * gravity * taus ** 2 * np.array([0.0, 0.0, 1.0])


def estimate_hop(observation: HopObservation, sfm: HopReconstruction, cloud_sfm: np.ndarray,
                 launch: np.ndarray, previous_cloud: np.ndarray | None, params: EstimateParams) -> HopEstimate:
    """The hop in the world: see the module docstring. launch: the estimated centre of mass at launch."""
    index, gravity_sfm, first = first_fit(observation, sfm, params)
    centres, rotations = sfm.camera_centres[index], sfm.camera_rotations[index]
    times = observation.timestamps[index]
    # Eq 1 with the scale known: camera centres to the centre of mass.
    com_sfm = centre_of_mass_positions(centres, rotations, observation.com_in_camera, first.scale)
    heading = observation.sun_heading_launch - body_yaw_in_hop(first.rotation, rotations[0], observation.camera_to_body)
    # process_hop's hop frame starts at the first registered frame: move the launch estimate there.
    start = np.asarray(launch, float) + rotation_z(heading) @ flight_positions(first.launch_velocity, [times[0]],
                                                                              params.gravity)[0]
    result, icp = corrected_hop(com_sfm, times, cloud_sfm, start, heading, previous_cloud, gravity_sfm, params)
    problem = too_few_inliers(result.flight.inliers, params.min_inliers)
    if problem:
        raise EstimateError(problem)
    estimate = HopEstimate(result, heading, observation.sun_heading_launch, index,
                           result.flight.to_hop_frame(com_sfm), start, np.full(3, np.nan), math.nan,
                           params.gravity, icp)
    point, tau = touchdown(estimate, times[-1] - times[0], observation.frame_interval, observation.body_radius)
    return replace(estimate, touchdown=point, touchdown_tau=tau)


def first_fit(observation: HopObservation, sfm: HopReconstruction, params: FitParams):
    """(registered frame indices, gravity in the SfM frame, the parabola fit to their camera centres)."""
    index = registered_frames(sfm, params.min_registered)
    times = observation.timestamps[index]
    # The accelerometer's gravity at rest, into the SfM frame through the first registered view (no spin).
    gravity_sfm = sfm.camera_rotations[index[0]] @ observation.gravity_launch
    fit = _fit(lambda: fit_flight(sfm.camera_centres[index], times, params.gravity, gravity_sfm, launch_time=0.0))
    return index, gravity_sfm, fit


def flight_check(observation: HopObservation, sfm: HopReconstruction, params: FitParams) -> tuple[float, str]:
    """How cleanly the reconstruction flies a parabola: (share of the frames the fit keeps, of all the hop's
    frames; what falls short of min_registered / min_inliers, or "" when nothing does). hop-plan tries its
    next SfM setting when something does."""
    try:
        _, _, fit = first_fit(observation, sfm, params)
    except EstimateError as exc:
        return 0.0, str(exc)
    return float(fit.inliers.sum()) / len(sfm.registered), too_few_inliers(fit.inliers, params.min_inliers)


def too_few_inliers(inliers: np.ndarray, min_share: float) -> str:
    kept = float(inliers.mean())
    if kept >= min_share:
        return ""
    return (f"the parabola fit kept {int(inliers.sum())} of {len(inliers)} registered frames ({100 * kept:.0f} %, "
            f"at least {100 * min_share:.0f} % needed: hopping.toml min_fit_inliers): the reconstruction is not a "
            f"clean flight")


def registered_frames(sfm: HopReconstruction, min_share: float) -> np.ndarray:
    index = sfm.registered_indices
    needed = max(6, int(math.ceil(min_share * len(sfm.registered))))
    if len(index) < needed:
        raise EstimateError(f"structure from motion registered {len(index)} of {len(sfm.registered)} frames "
                            f"(at least {needed} needed: hopping.toml min_registered)")
    return index


def _fit(run):
    try:
        return run()
    except ValueError as exc:
        raise EstimateError(f"the parabola fit failed: {exc}") from None


def body_yaw_in_hop(sfm_to_hop: np.ndarray, camera_to_sfm: np.ndarray, camera_to_body: np.ndarray) -> float:
    """Yaw of the body's x axis in the hop frame (x along the flight): the launch's heading error."""
    forward_in_camera = camera_to_body[:3, :3][0]   # body x in camera coordinates (a row of camera-to-body)
    forward = sfm_to_hop @ camera_to_sfm @ forward_in_camera
    return float(math.atan2(forward[1], forward[0]))


def corrected_hop(com_sfm, times, cloud_sfm, start, heading, previous_cloud, gravity_sfm,
                  params: EstimateParams) -> tuple[HopResult, dict]:
    """process_hop (scale, gravity, the cloud into the world), then the position correction against the
    previous hop's cloud; the hop uncorrected, and why, when there is none or it is not trusted."""
    result = _fit(lambda: process_hop(com_sfm, times, cloud_sfm, start, heading, gravity=params.gravity,
                                      gravity_prior=gravity_sfm))
    if previous_cloud is None or len(previous_cloud) < 10:
        return result, {"used": False, "reason": "no earlier hop-plan cloud to align with"}
    return correct_position(result, previous_cloud, start, params)


def correct_position(result: HopResult, previous_cloud: np.ndarray, start: np.ndarray,
                     params: EstimateParams) -> tuple[HopResult, dict]:
    """The shift of this hop's cloud onto the previous hop's, on the ground within icp_crop_m of the launch
    estimate: found by matching height maps over every shift within icp_initial_distance_m, refined by
    ICP with the paper's crop loop (hopping_icp, gravity held: yaw and translation) started there.

    Why not ICP alone: on the chain test's flat landing spot ICP started at the launch estimate stopped
    1 cm from it for a true 19 cm, every check passed; the height match found 18-25 cm at every crop.
    ICP is pulled off that by ground it cannot tell apart, so its answer is taken only within one cell
    of the match. Why not a turn: on local crops ICP's turn was off by several degrees where the sun
    sensor knows each hop's heading to about a degree, so the heading stays the sun sensor's.
    Refused, and said why: ground too flat to show the shift (contrast under icp_min_contrast), or a
    shift beyond icp_initial_distance_m."""
    def near(cloud: np.ndarray) -> np.ndarray:
        return cloud[np.hypot(*(cloud[:, :2] - start[:2]).T) < params.icp_crop]

    source, target = near(result.cloud), near(previous_cloud)
    if min(len(source), len(target)) < 100:
        return result, {"used": False, "reason": f"too little ground within {params.icp_crop:g} m of the launch "
                        f"estimate in both clouds ({len(source)} and {len(target)} points)"}
    try:
        match = match_height_maps(source, target, start[:2], params.icp_crop, params.icp_initial_distance,
                                  params.icp_voxel, params.icp_distinct)
    except ValueError as exc:   # too little shared ground
        return result, {"used": False, "reason": f"height match failed: {exc}"}
    summary = {"crop_m": params.icp_crop, "source_points": len(source), "target_points": len(target),
               "match": {"shift_m": [*match.shift.tolist(), match.vertical], "misfit_m": match.misfit,
                         "runner_up_m": match.runner_up, "contrast": match.contrast, "cells": match.overlap}}
    if match.contrast < params.icp_min_contrast:
        return result, {"used": False, "reason": f"the ground within {params.icp_crop:g} m does not show the shift: "
                        f"the best shift fits to {100 * match.misfit:.1f} cm, the best one more than "
                        f"{params.icp_distinct:g} m from it to {100 * match.runner_up:.1f} cm (contrast "
                        f"{match.contrast:.2f} < {params.icp_min_contrast:g}: hopping.toml icp_min_contrast)",
                        **summary}
    matched = np.array([*match.shift, match.vertical])
    shift, how = matched, "the height match's shift (ICP left it)"
    try:
        alignment = align_with_overlap_elimination(source, target, init=rigid(None, matched), voxel=params.icp_voxel,
                                                   dof="yaw", initial_max_distance=params.icp_distinct)
        refined = apply(alignment.transform, start[None])[0] - start
        yaw = math.degrees(math.atan2(alignment.transform[1, 0], alignment.transform[0, 0]))
        summary["icp"] = {"shift_m": refined.tolist(), "yaw_deg": yaw, "fitness": alignment.fitness,
                          "inlier_rmse_m": alignment.inlier_rmse, "rounds": len(alignment.rounds),
                          "checks": alignment.checks}
        if alignment.good and abs(yaw) <= params.icp_max_yaw_deg and \
                np.hypot(*(refined - matched)[:2]) <= params.icp_voxel:
            shift, how = refined, "ICP's shift, started at the height match's"
    except ValueError as exc:   # too few points in the crop loop's bounds
        summary["icp"] = {"failed": str(exc)}
    if np.linalg.norm(shift) > params.icp_initial_distance:
        return result, {"used": False, "reason": f"shift {np.linalg.norm(shift):.2f} m > "
                        f"{params.icp_initial_distance:g} m (hopping.toml icp_initial_distance_m)", **summary}
    summary.update({"shift_m": shift.tolist(), "shift_horizontal_m": float(np.hypot(*shift[:2])),
                    "applied": f"{how} at the launch estimate; heading kept"})
    correction = rigid(None, shift)
    corrected = replace(result, correction=correction, cloud=result.cloud + shift,
                        launch_point=result.launch_point + shift, landing_point=result.landing_point + shift)
    return corrected, {"used": True, **summary}


def touchdown(estimate: HopEstimate, tau_last: float, interval: float, radius: float) -> tuple[np.ndarray, float]:
    """The last frame comes up to one frame interval before the touchdown: follow the fitted parabola
    on over that interval to where the centre of mass is one body radius above the ground the cloud
    shows there (the interval's middle when the cloud has too little there)."""
    taus = tau_last + np.linspace(0.0, interval, 21)
    path = estimate.trajectory(taus)
    cloud = estimate.result.cloud
    near = cloud[np.hypot(*(cloud[:, :2] - path[0, :2]).T) < TOUCHDOWN_SEARCH_RADIUS_M]
    if len(near) < 20:
        index = len(taus) // 2
    else:
        below = np.flatnonzero(path[:, 2] <= float(np.median(near[:, 2])) + radius)
        index = int(below[0]) if len(below) else len(taus) - 1
    return path[index], float(taus[index])
