"""hazard-start and hazard-stop: dynamic hazard detection beside the jobs (PROTOCOL.md "Background
activities"). The loop is rvs_server/hazard/activity.py, the guard it puts on every drive guard.py,
its product record.py; the algorithm toolbox/mapping/corridor.py."""
from __future__ import annotations

from typing import TYPE_CHECKING, Any

from pydantic import Field

from rvs_server.config import CommandConfig, SafeName
from rvs_server.dispatch import Call, Module
from rvs_server.protocol import Sleeping, WrongMode

from .activity import SENSOR_DEVICE, HazardActivity
from .settings import HazardSettings, Sensor

if TYPE_CHECKING:
    from rvs_server.host import Host

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
