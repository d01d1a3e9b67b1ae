"""Pan-tilt unit commands: move-ptu.

A move is a job: it starts the unit, reports PROGRESS from the position read back while it turns,
and on `break` halts the unit where it is and keeps the absolute target in the recovery set, so
`continue` completes the same move (even after a relative move, which is resolved once, at start).
"""
from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

from pydantic import Field

from rvs_server.config import CommandConfig, Settings
from rvs_server.dispatch import Module
from rvs_server.jobs import JobContext, JobInterrupted
from rvs_server.protocol import BadRequest, Timeout

if TYPE_CHECKING:
    from rvs_server.host import Host


class PtuSettings(Settings):
    default_speed_deg_s: float = Field(20.0, gt=0, le=300, description="speed of a move without --speed")
    move_timeout_s: float = Field(120.0, gt=0, description="simulated seconds a move may take")
    tolerance_deg: float = Field(0.06, gt=0, le=5, description="how close counts as arrived")
    poll_wall_s: float = Field(0.05, gt=0, le=1, description="wall seconds between position reads")


module = Module("ptu", settings=PtuSettings, summary="the pan-tilt unit")


class MovePtuConfig(CommandConfig):
    pan: float | None = Field(None, ge=-360, le=360, description="pan angle, degrees (an offset with "
                              "--relative); default: keep")
    tilt: float | None = Field(None, ge=-360, le=360, description="tilt angle, degrees (an offset with "
                               "--relative); default: keep")
    speed: float | None = Field(None, gt=0, le=300, description="degrees per second; default from ptu.toml")
    relative: bool = Field(False, description="pan and tilt are offsets from the current position")


def _target(server: Host, cfg: MovePtuConfig) -> tuple[float, float]:
    """The absolute target; refuses angles outside the unit's limits, naming the range."""
    if cfg.pan is None and cfg.tilt is None:
        raise BadRequest("move-ptu: give --pan, --tilt or both")
    device = server.devices.ptu
    driver = device.require()
    current = device.position() or driver.position()
    pan = cfg.pan if cfg.pan is not None else (0.0 if cfg.relative else current[0])
    tilt = cfg.tilt if cfg.tilt is not None else (0.0 if cfg.relative else current[1])
    if cfg.relative:
        pan, tilt = current[0] + pan, current[1] + tilt
    limits = driver.limits
    for name, value, lo, hi in (("pan", pan, limits.pan_min_deg, limits.pan_max_deg),
                                ("tilt", tilt, limits.tilt_min_deg, limits.tilt_max_deg)):
        if not lo - 1e-9 <= value <= hi + 1e-9:
            raise BadRequest(f"move-ptu: --{name} {value:.2f} is outside the unit's range "
                             f"{lo:.2f}..{hi:.2f} degrees")
    if cfg.speed is not None:
        low = max(limits.pan_min_speed_deg_s, limits.tilt_min_speed_deg_s)
        high = min(limits.pan_max_speed_deg_s, limits.tilt_max_speed_deg_s)
        if not low <= cfg.speed <= high:
            raise BadRequest(f"move-ptu: --speed {cfg.speed:g} is outside the unit's speed range "
                             f"{low:.2f}..{high:.2f} degrees/s")
    return pan, tilt


def validate_move(server: Host, cfg: MovePtuConfig) -> None:
    _target(server, cfg)


def unit_limits(server: Host) -> dict[str, str]:
    """What the unit itself allows, for help: the Config's bounds are only the outer envelope."""
    device = server.devices.ptu
    driver = device.driver  # once: a reset or reinit in the job thread may drop it meanwhile
    if device.health != "ok" or driver is None:
        return {"unit": f"{device.name} is {device.health if driver is not None else 're-initialising'}"}
    limits = driver.limits
    low = max(limits.pan_min_speed_deg_s, limits.tilt_min_speed_deg_s)
    high = min(limits.pan_max_speed_deg_s, limits.tilt_max_speed_deg_s)
    return {"unit.pan": f"{limits.pan_min_deg:.2f}..{limits.pan_max_deg:.2f}",
            "unit.tilt": f"{limits.tilt_min_deg:.2f}..{limits.tilt_max_deg:.2f}",
            "unit.speed": f"{low:.2f}..{high:.2f}",
            "unit.step": f"{limits.pan_resolution_deg:.4f}"}


@module.job("move-ptu", MovePtuConfig, devices=("ptu",), validate=validate_move, limits=unit_limits)
def move_ptu(ctx: JobContext, cfg: MovePtuConfig) -> dict[str, Any]:
    """Turn the pan-tilt unit to an angle; PROGRESS while it moves."""
    settings: PtuSettings = ctx.settings
    device = ctx.devices.ptu
    driver = device.require()
    if ctx.resume:
        pan, tilt, speed = ctx.resume["pan"], ctx.resume["tilt"], ctx.resume["speed"]
    else:
        pan, tilt = _target(ctx.server, cfg)
        speed = cfg.speed or settings.default_speed_deg_s
        ctx.checkpoint({"pan": pan, "tilt": tilt, "speed": speed})
    start = device.read_position()
    distance = max(abs(pan - start[0]), abs(tilt - start[1]), 1e-9)
    ctx.progress(0, f"moving to pan {pan:.2f} tilt {tilt:.2f} at {speed:g} deg/s")
    driver.move_to(pan, tilt, speed_deg_s=speed)
    deadline = ctx.clock.now() + settings.move_timeout_s
    last_percent = 0
    try:
        while True:
            now_pan, now_tilt = device.read_position()
            left = max(abs(pan - now_pan), abs(tilt - now_tilt))
            arrived = left <= settings.tolerance_deg and not driver.is_moving()
            percent = 100.0 if arrived else min(99.0, 100.0 * (1.0 - left / distance))
            if math.floor(percent) != last_percent:
                last_percent = math.floor(percent)
                ctx.progress(percent, f"pan {now_pan:.2f} tilt {now_tilt:.2f}")
            if arrived:
                break
            if ctx.clock.now() > deadline:
                driver.halt()
                raise Timeout(f"ptu: move to pan {pan:.2f} tilt {tilt:.2f} not finished after "
                              f"{settings.move_timeout_s:g} s (at pan {now_pan:.2f} tilt {now_tilt:.2f})")
            ctx.sleep(settings.poll_wall_s * ctx.clock.speed)
    except JobInterrupted:
        # Stop where it is and wait until it stands, so break answers with the unit at rest; the
        # target stays in the recovery set for continue.
        driver.halt()
        driver.wait_until_stopped(timeout_s=settings.move_timeout_s)
        device.read_position()
        raise
    final = device.read_position()
    return {"pan": f"{final[0]:.2f}", "tilt": f"{final[1]:.2f}"}
