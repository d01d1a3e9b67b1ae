"""configs/hazard.toml: what hazard detection's loop (activity.py), its guard (guard.py) and its commands
(commands.py) read; its own module, so the loop and the guard need not import the commands."""
from __future__ import annotations

from typing import Literal

from pydantic import Field

from rvs_server.config import Settings
from rvs_server.devices.cameras import Resolution

Sensor = Literal["tof", "stereo"]


class HazardSettings(Settings):
    """configs/hazard.toml."""

    sensor: Sensor = Field("tof", description="the sensor that looks along the path")
    rate_hz: float = Field(5.0, gt=0, le=30, description="frames per second")
    stop_distance_m: float = Field(0.5, ge=0.05, le=3.0, description="a drive stops when its footprint would "
                                   "reach a detected hazard within this many metres")
    tof_tilt_deg: float = Field(-40.0, ge=-80, le=0, description="SR4000 tilt while detecting: the view spans "
                                "about 1 to 3.7 m ahead of the rover's centre")
    stereo_tilt_deg: float = Field(-35.0, ge=-80, le=0)
    stereo_step_min_cells: int = Field(5, ge=1, le=25, description="stereo: a step counts when this many cells "
                                       "within 0.1 m exceed the limit (the TOF takes mapping.toml's). One frame's "
                                       "stereo corridor is noisier than a panorama's map, which counts 2: 5 is what "
                                       "the guard was built with, kept until the stereo guard campaign measures less")
    reach_m: float = Field(4.0, gt=0, le=10, description="look-ahead past the rover's leading edge")
    side_margin_m: float = Field(0.10, ge=0, le=1, description="added each side of the swept footprint")
    max_reach_cells: float = Field(2.0, ge=0, le=10, description="corridor DEM holes filled this close to data")
    latency_budget_s: float = Field(0.1, ge=0, le=5, description="a drive waits when the newest frame lies more "
                                    "than speed x (1/rate + this) behind the rover")
    max_blind_s: float = Field(10.0, gt=0, le=600, description="a drive without a fresh frame this long (wall "
                               "clock) stops")
    stereo_resolution: Resolution = Field(
        "low", description="the cameras' resolution mode for hazard frames (low: 4 x 4 binning, 480 x 270), given "
        "back after each frame")
    stereo_disparities: int = Field(64, ge=16, le=256, multiple_of=16)
    stereo_min_disparity: int = Field(16, ge=0, le=256, description="the matcher searches stereo_disparities "
                                      "from this one (pixels): the ground a frame keeps lies nearer than "
                                      "stereo_max_range_m (25 px at 4 m in low), while the ground at the view's "
                                      "foot, uphill most, reaches 70; searched from 0, SGBM put that ground at a "
                                      "lower disparity, metres too far and 10 cm low, and its neighbours read as "
                                      "steps (false stops on a crater's 11-degree side)")
    stereo_max_range_m: float = Field(4.0, gt=0, le=30, description="stereo points farther than this from the "
                                      "camera are dropped: at 480 x 270 their depth error reads as steps")
    picture_frames: int = Field(20, ge=1, le=500, description="corridor.png outlines this many last frames")
    max_unseen_share: float = Field(0.25, ge=0, le=1, description="a turn on the spot or a backward drive is "
                                    "refused (unless drive --unguarded) when more of the ground it sweeps than "
                                    "this no frame saw: the sensor looks ahead, the rear and sides have none")
