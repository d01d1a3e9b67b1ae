"""configs/tracking.toml: how track3d-detect searches and track3d-start follows."""
from __future__ import annotations

from typing import Annotated, Literal

import numpy as np
from pydantic import Field

from rvs_server.config import PerSensor, Range, Settings
from rvs_server.devices.cameras import Resolution, mode_binning
from toolbox.tracking.kalman import TrackParams
from toolbox.tracking.person import PersonModel, Trapezoid
from toolbox.tracking.standing import StandingParams

Sensor = Literal["tof", "stereo"]
Tilt = Annotated[float, Field(ge=-60, le=30)]
Positive = Annotated[float, Field(gt=0)]


class TrackingSettings(Settings):
    sensor: Sensor = Field("tof", description="the sensor that searches and tracks unless --sensor says")
    rate_hz: float = Field(12.0, gt=0, le=30, description="track3d-start: frames per second")
    # -- the search ---------------------------------------------------------------------------
    pan_deg: Range = Field((-150.0, 150.0), description="track3d-detect sweeps the pan over this unless --pan "
                           "says (degrees, positive right)")
    search_tilt_deg: PerSensor[Tilt] = Field(PerSensor[Tilt](tof=-4.0, stereo=-6.0), description="per sensor, the "
                                             "tilt while searching: a person's head in view from about 2.3 m")
    ground_tilt_deg: PerSensor[Tilt] = Field(PerSensor[Tilt](tof=-22.0, stereo=-24.0), description="per sensor, the "
                                             "search's second tilt per pan: the ground at a near person's feet")
    search_step_deg: PerSensor[Positive] = Field(PerSensor[Positive](tof=30.0, stereo=45.0), description="per "
                                                 "sensor, pan between the search's views (the SR4000 sees 37 "
                                                 "degrees across, the cameras 61)")
    found_confidence: float = Field(0.6, gt=0, le=1, description="a candidate this person-like is a person")
    walk_speed_m_s: float = Field(1.5, gt=0, le=5, description="how fast a person may walk: the search takes "
                                  "two sightings no farther apart than this covers between their views as one")
    # -- the sensors --------------------------------------------------------------------------
    max_range_m: float = Field(9.5, gt=0, le=30, description="points farther from the sensor are dropped")
    tof_max_distance_m: float = Field(10.0, gt=0, le=10, description="the SR4000's modulation for tracking: "
                                      "10 m (15 MHz) where mapping uses 5 m (30 MHz); given back after each frame")
    tof_max_integration: int = Field(60, ge=1, le=255, description="the SR4000's auto exposure may reach this "
                                     "register while tracking (6.3 ms: four exposures make a frame, so 10 Hz needs "
                                     "short ones); the camera's own given back when a job takes it")
    tof_min_confidence: int = Field(4096, ge=0, le=65535, description="SR4000 pixels below this confidence are "
                                    "dropped (mapping's 16384 drops the ground a person stands on at 10 m range)")
    stereo_resolution: Resolution = Field(
        "low", description="the cameras' mode for tracking frames (low: 4 x 4 binning), given back after each")
    stereo_track_resolution: Resolution = Field(
        "low", description="the cameras' mode for the tracker's frames (narrow: the middle 25 x 28 degrees at 2 x "
        "2 binning, as few pixels as low, for a target the PTU keeps in the middle; the search keeps "
        "stereo_resolution's wide view); the stereo noise terms below are for 4 x 4 binning and scale with the "
        "mode's binning")
    stereo_disparities: int = Field(64, ge=16, le=256, multiple_of=16)
    tof_sigma_m: float = Field(0.04, gt=0, description="1 sigma of one TOF frame's centre, per axis")
    stereo_sigma_m: float = Field(0.04, gt=0, description="1 sigma of one stereo frame's centre along the line "
                                  "of sight at 1 m ...")
    stereo_sigma_per_m2: float = Field(0.003, ge=0, description="... plus this times the range squared (the "
                                       "range from disparity)")
    stereo_across_sigma_m: float = Field(0.03, gt=0, description="1 sigma of one stereo frame's centre across "
                                         "the line of sight (from the image position: 1.5-4.5 cm measured at "
                                         "5-8 m)")
    stereo_ground_noise_per_m2: float = Field(0.0025, ge=0, description="1 sigma of a stereo ground point's "
                                              "height per squared metre of range (4 x 4 binned: 0.14 m at 7.5 m; "
                                              "the ground is then found from medians and a point stands once "
                                              "clear of 4 sigma: toolbox/tracking/standing.py)")
    stereo_min_cell_points: int = Field(5, ge=1, description="stereo: a 10 cm cell with fewer standing points "
                                        "is the matcher's strays, not a body")
    stereo_legs_to_torso: Range = Field((0.92, 1.02), description="stereo: a person's legs band is at most the "
                                        "first share of its torso band's width wholly, none past the second (the "
                                        "pair widens thin legs and loses the arms beside the torso beyond 6 m; "
                                        "in 20 scenes' search views walkers read 0.55-1.05, most under 0.9, and "
                                        "boulders of person height 0.99-1.50, all but one over 1.02; the "
                                        "SR4000's model keeps 0.85-1.0)")
    # -- following ----------------------------------------------------------------------------
    centre_from_heading: PerSensor[bool] = Field(
        PerSensor[bool](tof=False, stereo=True), description="per sensor, while the target walks (see "
        "heading_min_speed_m_s) its centre lies behind the face the sensor sees by what the walk's heading says "
        "of how it is turned, not its measured width (the stereo matcher widens legs by 2-3 pixels a side: a "
        "side-on walker read as facing, 5-8 cm short; the SR4000 measures widths well)")
    shape_height_sigma_m: float = Field(0.05, gt=0, le=2, description="a frame whose person stands this much "
                                        "taller or shorter than the target's height counts as a measurement "
                                        "(1 + (difference / this)^2) times less sure")
    heading_min_speed_m_s: float = Field(0.3, ge=0, le=5, description="the track's speed above which its "
                                         "velocity is taken as the walker's heading")
    track_confidence: float = Field(0.3, ge=0, le=1, description="a cluster in the gate this person-like is the "
                                    "target (lower than found_confidence: a rock may hide its legs)")
    reacquire_confidence: float = Field(0.6, gt=0, le=1, description="once lost, a person this person-like "
                                        "anywhere in view is the target again")
    acceleration_density: PerSensor[Positive] = Field(
        PerSensor[Positive](tof=0.5, stereo=2.0), description="per sensor, the filter's white acceleration, "
        "(m/s^2)^2 s: how hard a walker may stop or turn between frames (TOF 0.5 at 10 Hz; the stereo pair's "
        "5 Hz frames, their range 0.1-0.15 m unsure at 6-7 m, lagged 0.4-1 m behind a 1.3 m/s walker's turns "
        "at 0.5: seed 407 RMSE 0.20 -> 0.135 m at 2.0, four other scenes 0.113 -> 0.111)")
    max_coast_s: float = Field(4.0, gt=0, le=60, description="unseen this long (simulated seconds): lost")
    acquire_s: float = Field(2.0, gt=0, le=60, description="track3d-start looks this long where the search saw "
                             "the target (state lost until it sees it) before it sweeps for it")
    min_gate_m: float = Field(0.4, ge=0, le=5, description="the gate is never narrower than this")
    aim_height_m: float = Field(0.9, ge=0, le=2.5, description="the PTU points at this height above the "
                                "target's feet")
    deadband_deg: float = Field(1.5, ge=0, le=10, description="the PTU moves only when the aim is off by more")
    max_ptu_speed_deg_s: float = Field(60.0, gt=0, le=300, description="the fastest the PTU is asked to turn")
    tilt_limits_deg: Range = Field((-40.0, 20.0), description="the tilt the tracker may ask for")
    lost_sweep_pan_deg: Range = Field((-90.0, 90.0), description="lost: the PTU sweeps the pan between these "
                                      "(at the search tilt) until a person is in view again")
    lost_sweep_speed_deg_s: float = Field(30.0, gt=0, le=300, description="the lost sweep's pan speed (a TOF "
                                          "frame at 10 Hz then spans 3 degrees, well inside its 37-degree view)")

    def stereo_detail(self, resolution: str | None) -> float:
        """The stereo range noise of a mode against 4 x 4 binning's (what the noise terms are given
        for): a disparity error of a fixed share of a pixel, so it scales with the binning."""
        return mode_binning(resolution or self.stereo_resolution) / 4

    def standing(self, sensor: str, resolution: str | None = None) -> StandingParams:
        """The ground and standing points' parameters of a sensor's frames (stereo: in the mode
        `resolution`, default the search's)."""
        if sensor == "tof":
            return StandingParams()
        return StandingParams(noise_per_m2=self.stereo_ground_noise_per_m2 * self.stereo_detail(resolution),
                              min_cell_points=self.stereo_min_cell_points)

    def person(self, sensor: str) -> PersonModel:
        if sensor == "tof":
            return PersonModel()
        high, zero = self.stereo_legs_to_torso
        return PersonModel(legs_to_torso=Trapezoid(0.0, 0.0, high, zero))

    def track(self, sensor: str) -> TrackParams:
        return TrackParams(q=self.acceleration_density.of(sensor), max_coast_s=self.max_coast_s,
                           min_gate_m=self.min_gate_m)

    def sigma_m(self, sensor: str, range_m: float, resolution: str | None = None) -> float:
        """1 sigma of one frame's centre along the line of sight at `range_m` (stereo: in the mode
        `resolution`, default the search's)."""
        if sensor == "tof":
            return self.tof_sigma_m
        return self.stereo_sigma_m + self.stereo_sigma_per_m2 * self.stereo_detail(resolution) * range_m ** 2

    def measurement_cov(self, sensor: str, offset: np.ndarray, resolution: str | None = None) -> np.ndarray:
        """The (2, 2) world covariance of one frame's centre at `offset` (world x, y) from the sensor:
        the stereo pair measures the range from disparity, far less surely than the bearing."""
        offset = np.asarray(offset, dtype=float)
        range_m = float(np.linalg.norm(offset))
        along = self.sigma_m(sensor, range_m, resolution)
        if sensor == "tof" or range_m < 1e-6:
            return np.eye(2) * along ** 2
        sight = offset / range_m
        across = np.array([-sight[1], sight[0]])
        return along ** 2 * np.outer(sight, sight) + self.stereo_across_sigma_m ** 2 * np.outer(across, across)
