"""Configuration of the simulated world: small pydantic models, one per part of the scene.

A `WorldConfig` and nothing else decides a world: the same config (seed included) builds the same
terrain, rocks, craters and texture on every machine. Lengths are metres, angles degrees (these are
human-facing settings); the code converts to radians where it computes.
"""
from __future__ import annotations

import math

from pydantic import BaseModel, ConfigDict, Field, model_validator


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


def _ordered(pair: tuple[float, float], name: str) -> None:
    if not pair[0] <= pair[1]:
        raise ValueError(f"{name} must be (low, high) with low <= high, got {pair}")


class Sun(_Model):
    """Where the sun stands and how bright the shadowed parts still are.

    Azimuth is clockwise from north (90 = east), elevation above the horizon. Intensity is
    albedo * (irradiance * cos(incidence) * lit + ambient), so `ambient` is the brightness of a
    white surface in full shadow.
    """

    azimuth_deg: float = 135.0
    elevation_deg: float = Field(35.0, gt=0.0, le=90.0)
    irradiance: float = Field(1.0, gt=0.0)
    ambient: float = Field(0.08, ge=0.0)

    def direction(self) -> tuple[float, float, float]:
        """Unit vector from the ground toward the sun in the world frame (x east, y north, z up)."""
        az, el = math.radians(self.azimuth_deg), math.radians(self.elevation_deg)
        return (math.sin(az) * math.cos(el), math.cos(az) * math.cos(el), math.sin(el))


class TerrainConfig(_Model):
    """The rock-free ground: a regional slope, gentle undulation and small-scale relief."""

    slope_deg: float = Field(2.0, ge=0.0, lt=45.0)
    # Direction the ground falls toward (GIS aspect), clockwise from north.
    slope_azimuth_deg: float = 200.0
    undulation_rms_m: float = Field(0.15, ge=0.0)
    undulation_wavelength_m: float = Field(8.0, gt=0.0)
    relief_rms_m: float = Field(0.006, ge=0.0)
    relief_wavelength_m: float = Field(0.6, gt=0.0)


class CraterConfig(_Model):
    """Bowl-shaped craters with raised rims; diameters drawn log-uniformly from the range."""

    count: int = Field(3, ge=0)
    diameter_range_m: tuple[float, float] = (2.0, 8.0)
    depth_ratio: float = Field(0.12, ge=0.0, le=0.5)
    rim_height_ratio: float = Field(0.03, ge=0.0, le=0.2)

    @model_validator(mode="after")
    def _check(self) -> CraterConfig:
        _ordered(self.diameter_range_m, "diameter_range_m")
        return self


class RockConfig(_Model):
    """Rocks: how much ground they cover, their size law, shape and burial.

    `cover` is the cumulative fractional area: the share of the ground, seen from above, on which a
    rock and not regolith is the surface. Diameters follow a truncated power law,
    N(>D) proportional to D**-size_exponent, so small rocks are many and boulders few.
    """

    cover: float = Field(0.07, ge=0.0, le=0.4)
    diameter_range_m: tuple[float, float] = (0.04, 1.0)
    size_exponent: float = Field(2.0, gt=0.0)
    # Full body height over diameter, and the fraction of that height below the ground at its centre.
    height_ratio_range: tuple[float, float] = (0.45, 0.85)
    buried_fraction_range: tuple[float, float] = (0.2, 0.5)
    # Horizontal minor over major axis.
    aspect_range: tuple[float, float] = (0.6, 1.0)
    albedo_range: tuple[float, float] = (0.08, 0.32)
    # No rock reaches into this circle around the world origin, where a rover usually starts.
    clear_radius_m: float = Field(1.0, ge=0.0)

    @model_validator(mode="after")
    def _check(self) -> RockConfig:
        for name in ("diameter_range_m", "height_ratio_range", "buried_fraction_range", "aspect_range",
                     "albedo_range"):
            _ordered(getattr(self, name), name)
        if self.diameter_range_m[0] <= 0:
            raise ValueError("diameter_range_m must be positive")
        if self.buried_fraction_range[0] < 0 or self.buried_fraction_range[1] > 0.9:
            raise ValueError("buried_fraction_range must stay within [0, 0.9]")
        return self


class AlbedoConfig(_Model):
    """Regolith texture: a multi-scale pattern plus grains, strong enough for stereo matching."""

    regolith_mean: float = Field(0.24, gt=0.0, lt=1.0)
    # Standard deviation of log-albedo across all scales from 1 cm to several metres.
    regolith_contrast: float = Field(0.22, ge=0.0)
    grain_fraction: float = Field(0.04, ge=0.0, le=1.0)
    grain_contrast: float = Field(0.5, ge=0.0)
    rock_contrast: float = Field(0.18, ge=0.0)
    # Sub-centimetre detail added at lookup time, so close-up views still have texture.
    detail_contrast: float = Field(0.12, ge=0.0)


class RoverSpeed(BaseModel):
    """How fast the simulated rover drives and turns (world.toml [rover_speed]): a property of the
    rover, the same whichever command drives it; it moves in steps at this speed (motion.py)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    drive_m_s: float = Field(0.3, gt=0.0, le=5.0)
    turn_deg_s: float = Field(20.0, gt=0.0, le=180.0)


class SunSensor(BaseModel):
    """The simulated rover's sun sensor (world.toml [sun_sensor]): a fine sun sensor on the body,
    looking up, that reads the direction toward the sun with this angular error (1 sigma; fine sun
    sensors are specified at 0.1-0.5 degrees) while the sun is within its field of view. Averaging
    readings takes the white noise down, never the alignment bias."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    noise_deg: float = Field(0.2, ge=0.0, le=10.0, description="white noise of one reading, per axis")
    bias_deg: float = Field(0.05, ge=0.0, le=10.0, description="what calibration left of the sensor's alignment "
                            "to the body, per axis: drawn once per world, the same in every reading")
    half_fov_deg: float = Field(85.0, gt=0.0, le=90.0, description="the sun farther than this from the body's "
                                "up axis is not seen")


class DriveError(BaseModel):
    """Standard deviations of a rover's open-loop motion errors: the simulated rover draws them
    (world.toml, drivers/sim/motion.py), navigate's drive-error cut assumes them (navigation.toml)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    turn_scale: float = Field(0.02, ge=0, description="relative error of a turn's angle")
    turn_noise_deg: float = Field(0.5, ge=0, description="absolute error of every turn, degrees")
    distance_scale: float = Field(0.02, ge=0, description="relative error of a distance")
    heading_drift_deg_per_m: float = Field(0.3, ge=0, description="heading creep while driving, degrees per metre")
    lateral_slip_per_m: float = Field(0.01, ge=0, description="sideways slip, metres per metre driven")

    @classmethod
    def none(cls) -> DriveError:
        return cls(turn_scale=0, turn_noise_deg=0, distance_scale=0, heading_drift_deg_per_m=0, lateral_slip_per_m=0)


class WorldConfig(_Model):
    """Everything that decides a simulated world. The same config builds the same world."""

    seed: int = 1
    # East-west and north-south extent; rounded up to whole mesh blocks (see World.grid).
    size_m: tuple[float, float] = (40.0, 40.0)
    # Spacing of the grid the ground is generated on.
    cell_m: float = Field(0.01, gt=0.0, le=0.05)
    # Largest vertical distance, at any grid point, between the ground mesh and the ground grid.
    mesh_tolerance_m: float = Field(0.001, gt=0.0)
    terrain: TerrainConfig = TerrainConfig()
    craters: CraterConfig = CraterConfig()
    rocks: RockConfig = RockConfig()
    albedo: AlbedoConfig = AlbedoConfig()
    sun: Sun = Sun()
    # Where the simulated rover stands when a server starts: x, y (metres), heading (degrees CCW
    # from east). Not part of the ground: the same seed builds the same world wherever it starts.
    rover_start: tuple[float, float, float] = (0.0, 0.0, 0.0)
    # How the simulated rover misses the motions it is told to make (drivers/sim/motion.py).
    drive_error: DriveError = DriveError()
    # How fast it drives and turns.
    rover_speed: RoverSpeed = RoverSpeed()
    # What its sun sensor reads (toolbox/odometry/sun.py turns that into a heading).
    sun_sensor: SunSensor = SunSensor()

    @model_validator(mode="after")
    def _check(self) -> WorldConfig:
        if min(self.size_m) <= 0:
            raise ValueError(f"size_m must be positive, got {self.size_m}")
        if self.rocks.diameter_range_m[0] < 2 * self.cell_m:
            raise ValueError("the smallest rock must span at least two height cells")
        return self
