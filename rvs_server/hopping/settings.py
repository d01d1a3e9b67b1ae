"""configs/hopping.toml: the hopping rover's settings (HoppingSettings) and the choices they name.

At the bottom of the hopping package: commands.py, plan.py and the steps read these, and this file
imports none of them.
"""
from __future__ import annotations

import math
from typing import Literal

from pydantic import Field, model_validator

from rvs_server.config import Point, Settings
from rvs_server.devices import HopperBackend, HopperConfig
from toolbox.hopping import MOON_GRAVITY, hop_range

Mapper = Literal["global", "incremental"]   # how COLMAP maps a hop (sfm.py's module docstring says why)


class SfmSetting(Settings):
    """One way to run structure from motion (sfm.SfmConfig's choices)."""

    mapper: Mapper = Field(..., description="global: GLOMAP; incremental: COLMAP's")
    first_octave: int = Field(..., ge=-1, le=2, description="SIFT's first octave: 0 the frames as they are, -1 "
                              "doubled first")


class HoppingSettings(Settings):
    """configs/hopping.toml."""

    backend: HopperBackend = Field("sim", description="sim: the simulated hopper on the test bed's world")
    start: Point = Field((0.0, 0.0), description="where the hopper starts, X,Y world metres; the estimate starts "
                         "there too")
    start_heading_deg: float = Field(0.0, ge=-180, le=180, description="the hopper's heading at the start")
    max_speed_mps: float = Field(3.0, gt=0, le=20, description="the spring's fastest launch; hop refuses more")
    gravity_mps2: float = Field(MOON_GRAVITY, gt=0, description="the g the estimator assumes (the simulated "
                                "hopper's is hopper.gravity_mps2)")
    hopper: HopperConfig = Field(HopperConfig(), description="the simulated hopper: camera, launch errors, bounces, "
                                 "sensor noise (drivers/sim/hopper_config.py)")
    # Reconstruction and the estimate.
    sfm_max_features: int = Field(4096, ge=256, le=32768, description="SIFT features per frame")
    sfm_first_octave: int = Field(0, ge=-1, le=2, description="SIFT's first octave: 0 the frames as they are, "
                                  "-1 doubled first (more features on small frames, about 4x slower at 640x480)")
    sfm_mapper: Mapper = Field("global", description="global: GLOMAP, every frame's "
                                                          "pose at once; incremental: the paper's COLMAP mapping, "
                                                          "which bent 8 of 38 campaign hops (sfm.py)")
    sfm_fallbacks: list[SfmSetting] = Field(
        [SfmSetting(mapper="incremental", first_octave=-1), SfmSetting(mapper="global", first_octave=-1)],
        max_length=4, description="tried in turn when a reconstruction is not a clean flight (the parabola fit's "
        "min_registered / min_fit_inliers); each setting bends a few hops in twenty, at random, and seldom the same")
    sfm_threads: int = Field(-1, ge=-1, le=256, description="COLMAP's threads: -1 every core; 1 makes a "
                             "reconstruction repeatable (threads finish in varying order)")
    min_registered: float = Field(0.6, gt=0, le=1, description="share of the frames SfM must register")
    min_fit_inliers: float = Field(0.6, gt=0, le=1, description="share of the registered frames the parabola fit "
                                   "must keep")
    icp_voxel_m: float = Field(0.05, gt=0, le=1)
    icp_initial_distance_m: float = Field(0.6, gt=0, le=5, description="how far the launch estimate may be off "
                                          "(the last hop's bounces): ICP's first correspondence distance")
    icp_crop_m: float = Field(1.5, gt=0.2, le=20, description="ICP aligns the ground within this of the launch "
                              "estimate (the clouds' far parts are too noisy to align)")
    icp_max_yaw_deg: float = Field(10.0, gt=0, le=45, description="ICP turning the cloud more is a false "
                                   "match (its turn is never applied: the sun sensor keeps the heading)")
    icp_min_contrast: float = Field(1.1, ge=1, le=10, description="the position correction needs ground that "
                                    "shows the shift: the height match's best rival (farther than "
                                    "icp_distinct_m) must fit this many times worse than its best")
    icp_distinct_m: float = Field(0.15, gt=0, le=2, description="shifts farther than this from the height "
                                  "match's best are its rivals; ICP refines within this")
    # Landing target selection (toolbox/hopping_landing.py LandingParams).
    cell_m: float = Field(0.025, gt=0.005, le=0.5, description="cell of the top-down maps")
    obstacle_m: float = Field(0.08, gt=0, description="protrusion above the ground plane that is an obstacle")
    min_hop_m: float = Field(0.8, gt=0, description="shortest hop the planner proposes")
    max_hop_m: float = Field(2.0, gt=0, description="longest hop the planner proposes")
    elevation_deg: float = Field(60.0, ge=10, le=80, description="launch elevation of the planned hops")
    sigma_speed_mps: float = Field(0.05, ge=0, description="launch errors, 1 sigma, for the error ellipse")
    sigma_elevation_deg: float = Field(3.0, ge=0)
    sigma_heading_deg: float = Field(3.0, ge=0)
    sigma_position_m: float = Field(0.05, ge=0)
    rover_radius_m: float = Field(0.15, gt=0, le=2, description="the body's largest protrusion from its centre")
    safety_weight: float = Field(0.5, ge=0, le=1, description="selection: clearance weight (the goal gets the rest)")
    # hop-map and pictures.
    map_cell_m: float = Field(0.02, gt=0.005, le=0.5, description="cell of hop-map's global map")
    # hop-plan's steps: workflows/hop-plan.yaml names them and the settings above they read.
    workflows_dir: str = Field("../workflows", description="where hop-plan.yaml is, relative to the config "
                               "directory")

    @model_validator(mode="after")
    def _reachable(self) -> HoppingSettings:
        if not self.min_hop_m < self.max_hop_m:
            raise ValueError(f"min_hop_m {self.min_hop_m:g} must be less than max_hop_m {self.max_hop_m:g}")
        reach = float(hop_range(self.max_speed_mps, math.radians(self.elevation_deg), self.gravity_mps2))
        if self.max_hop_m > 0.9 * reach:
            raise ValueError(f"max_hop_m {self.max_hop_m:g} is beyond 90 % of the flat-ground reach at max_speed_mps "
                             f"{self.max_speed_mps:g} and elevation_deg {self.elevation_deg:g} ({reach:.2f} m)")
        return self
