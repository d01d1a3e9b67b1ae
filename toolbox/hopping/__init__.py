"""Monocular navigation of a hopping rover (the hopping paper): one hop's images, once reconstructed by
structure from motion, become a metric map, a corrected position and the next landing target.

`process_hop` is the paper's chain (Fig 3), step by step; the steps live in small modules:

    parabola            scale and gravity from the parabolic flight (eqs 1-13), the paper's fit and the
                        timed fit used by default
    icp                 position correction: ICP with iterative elimination of non-overlapping parts
    landing             landing target selection on the top-down image: obstacles, error ellipses,
                        clearance and goal maps, the collision check along the parabola
    ballistics          range equation, error ellipse (eqs 14-16), inverse ballistics, flight path
    plane               RANSAC planes (flight plane, ground plane)

Frames: SfM (arbitrary scale and axes) -> hop frame (metres, launch at the origin, z up, x along the
hop) -> world (x east, y north, z up) by the hop's heading from the sun sensor and the launch position.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from toolbox.geometry import apply, compose, rigid, rotation_z
from toolbox.hopping.ballistics import (
    CHI2_2D_95,
    LandingEllipse,
    Launch,
    ballistic_positions,
    elevation_for_target,
    hop_range,
    landing_error_ellipse,
    launch_to_target,
    speed_for_target,
)
from toolbox.hopping.icp import (
    IcpRound,
    OverlapAlignment,
    align_with_overlap_elimination,
    common_bounds,
    crop_mask,
    estimate_normals,
    horizontal_bounds,
    icp_point_to_plane,
    icp_point_to_point,
    icp_yaw_translation,
    transform_change,
)
from toolbox.hopping.landing import (
    LandingParams,
    LandingPlan,
    NoGroundError,
    TopDown,
    clearance_map,
    ellipse_safe_mask,
    goal_map,
    ground_plane,
    known_mask,
    obstacle_mask,
    plan_landing,
    protrusion_map,
    selection_score,
    swept_height,
    top_down_maps,
    trajectory_collides,
)
from toolbox.hopping.parabola import (
    MOON_GRAVITY,
    FlightFit,
    centre_of_mass_positions,
    conic_axis_angle,
    drop_beyond_mean_distance,
    fit_conic_through_origin,
    fit_flight,
    fit_flight_paper,
    fit_parabola,
    orient_parabola,
    parabola_closest_x,
    parabola_distance,
    scale_from_parabola,
)
from toolbox.hopping.plane import Plane, fit_plane_lsq, plane_basis, ransac_plane

__all__ = [
    "process_hop", "HopResult", "hop_to_world",
    "FlightFit", "fit_flight", "fit_flight_paper", "centre_of_mass_positions", "fit_conic_through_origin",
    "conic_axis_angle", "orient_parabola", "fit_parabola", "parabola_closest_x", "parabola_distance",
    "drop_beyond_mean_distance", "scale_from_parabola", "MOON_GRAVITY",
    "OverlapAlignment", "IcpRound", "align_with_overlap_elimination", "horizontal_bounds", "common_bounds",
    "crop_mask", "estimate_normals", "icp_point_to_plane", "icp_point_to_point", "icp_yaw_translation",
    "transform_change",
    "LandingParams", "LandingPlan", "NoGroundError", "TopDown", "plan_landing", "top_down_maps", "ground_plane",
    "protrusion_map",
    "known_mask", "obstacle_mask", "clearance_map", "goal_map", "ellipse_safe_mask", "selection_score",
    "swept_height", "trajectory_collides",
    "Launch", "LandingEllipse", "hop_range", "landing_error_ellipse", "launch_to_target", "speed_for_target",
    "elevation_for_target", "ballistic_positions", "CHI2_2D_95",
    "Plane", "fit_plane_lsq", "ransac_plane", "plane_basis",
]


@dataclass(frozen=True)
class HopResult:
    flight: FlightFit
    hop_to_world: np.ndarray             # (4, 4) hop frame -> world, before the correction
    correction: np.ndarray               # (4, 4) world -> world, from ICP (identity without a previous cloud)
    alignment: OverlapAlignment | None
    cloud: np.ndarray                    # (N, 3) this hop's dense cloud in the world, corrected
    launch_point: np.ndarray             # (3,) corrected world position of this hop's launch
    landing_point: np.ndarray            # (3,) corrected world position at the last frame: the next start
    plan: LandingPlan | None


def hop_to_world(launch_world: np.ndarray, heading: float) -> np.ndarray:
    """The hop frame into the world: turn x (the hop direction) to the heading, put the origin at launch."""
    return rigid(rotation_z(heading), launch_world)


def process_hop(centres_sfm: np.ndarray, timestamps: np.ndarray, cloud_sfm: np.ndarray, launch_world: np.ndarray,
                heading: float, previous_cloud: np.ndarray | None = None, goal_heading: float | None = None,
                goal_xy: np.ndarray | None = None, gravity: float = MOON_GRAVITY,
                gravity_prior: np.ndarray | None = None, landing: LandingParams = LandingParams(),
                icp_voxel: float = 0.05, icp_initial_distance: float = 0.6,
                icp_dof: Literal["6", "yaw"] = "6") -> HopResult:
    """One hop, from its SfM reconstruction to the next target (paper Fig 3).

    centres_sfm / timestamps: the hop's centre-of-mass positions (SfM frame) and frame times;
    cloud_sfm: its dense cloud (SfM frame); launch_world: where the hop started (the previous estimate);
    heading: the hop's direction in the world (sun sensor); previous_cloud: the previous hop's corrected
    cloud (world). The next target is planned when a goal heading or point is given. icp_dof "yaw" keeps
    gravity in the correction; only worth it when both hops' gravity is known better than the clouds
    align (an accelerometer prior), since the parabola fit's own gravity is good to a degree or two."""
    # Scale and gravity from the parabolic flight.
    flight = fit_flight(centres_sfm, timestamps, gravity, gravity_prior)
    # The metric, gravity-aligned hop into the world at the estimated launch point and heading.
    to_world = hop_to_world(launch_world, heading)
    cloud = apply(to_world, flight.to_hop_frame(cloud_sfm))
    # Position correction: this hop's cloud onto the previous hop's, non-overlapping parts eliminated.
    alignment = None
    correction = np.eye(4)
    if previous_cloud is not None:
        alignment = align_with_overlap_elimination(cloud, previous_cloud, voxel=icp_voxel,
                                                   initial_max_distance=icp_initial_distance, dof=icp_dof)
        correction = alignment.transform
        cloud = apply(correction, cloud)
    launch_point = apply(compose(correction, to_world), np.zeros((1, 3)))[0]
    landing_point = apply(compose(correction, to_world), flight.landing_point[None])[0]
    # The next landing target around the landing point.
    plan = None
    if goal_heading is not None or goal_xy is not None:
        plan = plan_landing(cloud, landing_point, goal_heading, goal_xy, landing)
    return HopResult(flight, to_world, correction, alignment, cloud, launch_point, landing_point, plan)
