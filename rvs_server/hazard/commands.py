"""hazard-start and hazard-stop: dynamic hazard detection beside the jobs (PROTOCOL.md "Background
activities"). The loop is rvs_server/hazard/activity.py, the guard it puts on every drive guard.py,
its product record.py; the algorithm toolbox/mapping/corridor.py."""
from __future__ import annotations

from typing import TYPE_CHECKING, Any, Literal

from pydantic import Field

from rvs_server.config import CommandConfig, SafeName, Settings
from rvs_server.dispatch import Call, Module
from rvs_server.protocol import Sleeping, WrongMode

from .activity import SENSOR_DEVICE, HazardActivity

if TYPE_CHECKING:
    from rvs_server.host import Host

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
    reach_m: float = Field(4.0, gt=0, le=10, description="look-ahead past the rover's leading edge")
    side_margin_m: float = Field(0.10, ge=0, le=1, description="added each side of the swept footprint")
    max_reach_cells: float = Field(2.0, ge=0, le=10, description="corridor DEM holes filled this close to data")
    latency_budget_s: float = Field(0.1, ge=0, le=5, description="a drive waits when the newest frame lies more "
                                    "than speed x (1/rate + this) behind the rover")
    max_blind_s: float = Field(10.0, gt=0, le=600, description="a drive without a fresh frame this long (wall "
                               "clock) stops")
    stereo_resolution: Literal["low", "medium", "high", "highest"] = Field(
        "low", description="the cameras' resolution mode for hazard frames (low: 4 x 4 binning, 480 x 270), given "
        "back after each frame")
    stereo_disparities: int = Field(64, ge=16, le=256, multiple_of=16)
    stereo_max_range_m: float = Field(4.0, gt=0, le=30, description="stereo points farther than this from the "
                                      "camera are dropped: at 480 x 270 their depth error reads as steps")
    picture_frames: int = Field(20, ge=1, le=500, description="corridor.png outlines this many last frames")


module = Module("hazard", settings=HazardSettings, summary="dynamic hazard detection beside the jobs")


class HazardStartConfig(CommandConfig):
    sensor: Sensor | None = Field(None, description="tof or stereo; default hazard.toml sensor")
    rate: float | None = Field(None, gt=0, le=30, description="frames per second; default hazard.toml rate_hz")
    stop_distance: float | None = Field(None, ge=0.05, le=3.0, description="metres; default hazard.toml "
                                        "stop_distance_m")
    output: SafeName | None = Field(None, description="product name; default hazard-TIME")


def _validate_start(server: Host, cfg: HazardStartConfig) -> None:
    if server.stopping:
        raise WrongMode("hazard-start: the server is shutting down")
    if server.dispatcher.sleep_until is not None:
        raise Sleeping("hazard-start: the server is sleeping (standby wakes it)")
    server.activities.require_free("hazard", "hazard-start")
    sensor = cfg.sensor or server.settings_of("hazard").sensor
    server.devices["ptu"].require_healthy()
    server.devices[SENSOR_DEVICE[sensor]].require_healthy()


@module.immediate("hazard-start", HazardStartConfig, validate=_validate_start)
def hazard_start(call: Call, cfg: HazardStartConfig) -> dict[str, Any]:
    """Start dynamic hazard detection: a look along the path per frame, and a guard on every drive."""
    server, settings = call.server, call.settings
    sensor = cfg.sensor or settings.sensor
    rate = cfg.rate or settings.rate_hz
    stop = cfg.stop_distance or settings.stop_distance_m
    product = server.products.create("hazard-start", cfg.output or None, cfg.model_dump(mode="json"),
                                      config=settings.model_dump(mode="json"))
    server.activities.start(HazardActivity(server, settings, sensor, rate, stop, product), "hazard-start")
    return {"activity": "hazard", "sensor": sensor, "rate": f"{rate:g}", "stop_distance": f"{stop:g}"}


@module.immediate("hazard-stop")
async def hazard_stop(call: Call, cfg: Any) -> dict[str, Any]:
    """Stop dynamic hazard detection: the summary, and the product with every frame's result."""
    return await call.server.activities.stop("hazard", "hazard-stop")
