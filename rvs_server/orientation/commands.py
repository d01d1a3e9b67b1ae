"""orient: acquire along the rover's heading and say how it moved since the last look (PROTOCOL.md
"Vehicle orientation"). The look is look.py, the odometer (keyframes, fusion) odometer.py, the
product record.py; the methods are toolbox/odometry."""
from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

from pydantic import Field

from rvs_server.config import CommandConfig, SafeName
from rvs_server.dispatch import Module
from rvs_server.protocol import BadRequest
from toolbox.odometry.chain import wrap

from .odometer import Odometer, OrientFailed, look_and_match
from .record import write_failure, write_outcome
from .settings import OrientSettings, Sensor

if TYPE_CHECKING:
    from rvs_server.host import Host
    from rvs_server.jobs import JobContext

module = Module("orientation", settings=OrientSettings, summary="vehicle orientation by visual odometry",
                state=lambda server: Odometer())


class OrientConfig(CommandConfig):
    sensor: Sensor | None = Field(None, description="stereo or tof; default orient.toml sensor")
    apply: bool = Field(True, description="--apply (default): the result becomes the pose estimate; --no-apply "
                        "leaves the estimate alone")
    output: SafeName | None = Field(None, description="product name; default orient-TIME")


SENSOR_DEVICE = {"stereo": "cameras", "tof": "tof"}


def _validate(server: Host, cfg: OrientConfig) -> None:
    sensor = cfg.sensor or server.settings_of("orientation").sensor
    server.devices[SENSOR_DEVICE[sensor]].require_healthy()


@module.job("orient", OrientConfig, devices=("ptu",), validate=_validate)
def orient(ctx: JobContext, cfg: OrientConfig) -> dict[str, Any]:
    """Acquire in the moving direction and compute the rover's motion and heading since the last look."""
    settings: OrientSettings = ctx.settings
    sensor = cfg.sensor or settings.sensor
    product = ctx.product(cfg, name=cfg.output)
    ctx.checkpoint({"product": product.name})   # continue after a break looks again into the same product
    rover = ctx.devices.rover
    rover.wait_for_world()
    ctx.progress(10, f"pointing the {sensor} at the keyframe's ground")
    try:
        sighting = look_and_match(ctx, sensor, settings, apply=cfg.apply)
    except OrientFailed as failed:
        ctx.save_truth(product)
        product.timing("acquisition", failed.look.acquire_s)
        write_failure(product, failed.look, failed)
        done = ctx.finish_product(product)
        raise BadRequest(f"orient failed: {failed.failure.reason}: {failed.failure.sentence}"
                         f"{_advice(failed.aim, settings, sensor)}; product={done['product']}") from None
    ctx.save_truth(product)
    outcome = sighting.outcome
    product.timing("acquisition", sighting.look.acquire_s + (sighting.home.acquire_s if sighting.home else 0.0))
    product.timing("odometry", outcome.odometry_s)
    if cfg.apply:
        rover.pose_estimate = outcome.belief.pose
    write_outcome(product, sighting, applied=cfg.apply)
    ctx.progress(100, "written")
    return {**_reply(outcome), **ctx.finish_product(product)}


def _advice(aim, settings: OrientSettings, sensor: str) -> str:
    """What the rover should do when no pointing of the head could bring the keyframe back."""
    if aim is None or aim.share >= settings.aim_share.of(sensor):
        return ""
    return (f" (no view the pan-tilt unit can take would see more than {100 * aim.share:.0f} % of the keyframe's "
            f"ground after this manoeuvre: orient after each turn of at most {settings.reach_turn_deg:g} deg and "
            f"each {settings.reach_m:g} m driven, and before driving on after a turn of more than "
            f"{settings.reach_drive_turn_deg:g} deg)")


def _reply(outcome) -> dict[str, Any]:
    pose = outcome.belief.pose
    previous = outcome.previous.pose if outcome.previous is not None else pose
    sigma_xy, sigma_heading = outcome.belief.sigmas()
    reply: dict[str, Any] = {"x": f"{pose.x:.3f}", "y": f"{pose.y:.3f}", "heading": f"{math.degrees(pose.heading):.2f}",
                             "dx": f"{pose.x - previous.x:.3f}", "dy": f"{pose.y - previous.y:.3f}",
                             "dheading": f"{math.degrees(wrap(pose.heading - previous.heading)):.2f}",
                             "matches": outcome.motion.inliers if outcome.motion is not None else 0}
    if outcome.keyframe:
        reply["keyframe"] = 1
    reply.update({"sigma_xy": f"{sigma_xy:.3f}", "sigma_heading": f"{math.degrees(sigma_heading):.2f}",
                  "sources": ",".join(outcome.sources) or "none"})
    return reply
