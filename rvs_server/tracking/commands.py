"""track3d-detect, track3d-start, track3d-stop: finding a person around the rover and following it
(PROTOCOL.md "Background activities"). The search is search.py, the tracker activity.py, where the
sensor looks sight.py, the products record.py; the methods toolbox/tracking."""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from pydantic import Field

from rvs_server.config import CommandConfig, Range, SafeName
from rvs_server.devices.frame_points import SENSOR_DEVICE
from rvs_server.dispatch import Call, Module
from rvs_server.protocol import BadRequest, Sleeping, WrongMode

from .activity import Target, TrackActivity
from .record import write_candidates, write_search_picture, write_views
from .search import sweep
from .settings import Sensor, TrackingSettings
from .sight import Sight

if TYPE_CHECKING:
    from rvs_server.host import Host
    from rvs_server.jobs import JobContext


@dataclass
class TrackingState:
    """What this server's tracking remembers: the target the last search found (None: none yet, or
    the last search found nobody)."""

    target: Target | None = None


module = Module("tracking", settings=TrackingSettings, summary="finding and following a person in 3-D",
                state=lambda server: TrackingState())


class DetectConfig(CommandConfig):
    sensor: Sensor | None = Field(None, description="tof or stereo; default tracking.toml sensor")
    pan: Range | None = Field(None, description="the pan range to sweep, A:B degrees (positive right); default "
                              "tracking.toml pan_deg")
    output: SafeName | None = Field(None, description="product name; default track3d-detect-TIME")


def _validate_detect(server: Host, cfg: DetectConfig) -> None:
    sensor = cfg.sensor or server.settings_of("tracking").sensor
    server.devices[SENSOR_DEVICE[sensor]].require_healthy()
    if cfg.pan is not None:
        low, high = cfg.pan
        if low < -159.0 or high > 159.0:
            raise BadRequest(f"track3d-detect: --pan = {low:g}:{high:g}: the PTU-D46 pans -159..159 degrees")


@module.job("track3d-detect", DetectConfig, devices=("ptu",), validate=_validate_detect)
def track3d_detect(ctx: JobContext, cfg: DetectConfig) -> dict[str, Any]:
    """Search for a target (possibly an astronaut): sweep the PTU, find what stands on the ground, judge its shape."""
    settings: TrackingSettings = ctx.settings
    sensor = cfg.sensor or settings.sensor
    product = ctx.product(cfg, name=cfg.output)
    ctx.checkpoint({"product": product.name})
    ctx.devices.rover.wait_for_world()
    sight = Sight(ctx.server, settings, sensor)
    search = sweep(ctx, sight, settings, cfg.pan or settings.pan_deg)
    truth = search.views[-1].truth if search.views else None
    ctx.save_truth(product)
    write_candidates(product, search.judged)
    write_views(product, search.views)
    write_search_picture(product, search.points, search.sensor_xy, search.judged, settings.max_range_m + 0.5, truth)
    people = search.people
    product.note("summary", {"sensor": sensor, "views": len(search.views), "points": int(len(search.points)),
                             "candidates": len(search.judged), "found": len(people)})
    state: TrackingState = ctx.state
    ctx.progress(100, f"{len(people)} found")
    if not people:
        state.target = None
        return {"found": 0, **ctx.finish_product(product)}
    nearest = people[0]
    shape = nearest.candidate.shape
    done = ctx.finish_product(product)
    state.target = Target(shape.x, shape.y, shape.ground_z, shape.height, nearest.candidate.confidence, sensor,
                          nearest.seen_s, done["product"], nearest.range_m)
    return {"found": len(people), "x": f"{shape.x:.3f}", "y": f"{shape.y:.3f}", "z": f"{shape.ground_z:.3f}",
            "range": f"{nearest.range_m:.2f}", "bearing": f"{nearest.bearing_deg:.1f}", "height": f"{shape.height:.2f}",
            "confidence": f"{nearest.candidate.confidence:.2f}", **done}


class StartConfig(CommandConfig):
    sensor: Sensor | None = Field(None, description="tof or stereo; default tracking.toml sensor")
    rate: float | None = Field(None, gt=0, le=30, description="frames per second; default tracking.toml rate_hz")
    output: SafeName | None = Field(None, description="product name; default track3d-start-TIME")


def _validate_start(server: Host, cfg: StartConfig) -> None:
    if server.stopping:
        raise WrongMode("track3d-start: the server is shutting down")
    if server.dispatcher.sleep_until is not None:
        raise Sleeping("track3d-start: the server is sleeping (standby wakes it)")
    server.activities.require_free("track", "track3d-start")
    if server.state_of("tracking").target is None:
        raise WrongMode("track3d-start: no target: track3d-detect first (none was run, or the last found nobody)")
    sensor = cfg.sensor or server.settings_of("tracking").sensor
    server.devices["ptu"].require_healthy()
    server.devices[SENSOR_DEVICE[sensor]].require_healthy()


@module.immediate("track3d-start", StartConfig, validate=_validate_start)
def track3d_start(call: Call, cfg: StartConfig) -> dict[str, Any]:
    """Start tracking the target found last, the PTU kept pointed at it."""
    server, settings = call.server, call.settings
    sensor = cfg.sensor or settings.sensor
    rate = cfg.rate or settings.rate_hz
    target = server.state_of("tracking").target
    product = server.products.create("track3d-start", cfg.output or None, cfg.model_dump(mode="json"),
                                     config=settings.model_dump(mode="json"))
    product.note("target", {"x": target.x, "y": target.y, "z": target.z, "height_m": target.height,
                            "confidence": target.confidence, "found_by": target.product})
    server.activities.start(TrackActivity(server, settings, sensor, rate, target, product), "track3d-start")
    return {"activity": "track", "sensor": sensor, "rate": f"{rate:g}"}


@module.immediate("track3d-stop")
async def track3d_stop(call: Call, cfg: Any) -> dict[str, Any]:
    """Stop tracking: the summary, and the product with the track."""
    return await call.server.activities.stop("track", "track3d-stop")
