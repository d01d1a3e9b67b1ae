"""The hopping rover (hopping paper): hop, hop-plan, hop-map.

    hop --speed V --elevation DEG --heading DEG    the hopper turns, launches and records its flight
                                                   (the hopper device, rvs_server/devices/hopper.py);
                                                   product hop-NNN (store.py)
    hop-plan [--goal X,Y | --goal-heading DEG]     the last hop reconstructed, made metric, corrected by
                                                   ICP, and the next landing target (plan.py: the
                                                   workflow workflows/hop-plan.yaml of steps.py)
    hop-map                                        every hop-plan cloud so far on one top-down map, true
                                                   colour and false colour by hop (paper Fig 18)

The server keeps the hopping state: the hops so far and the estimated position of the hopper's
centre of mass (the simulated hopper itself is the device's: made on first use at the configured
start, on the world every emulated device shares; a new world starts a new sequence). The estimate
starts at the start position (heights are the map's: the start's ground is z = 0). A hop moves it
by the commanded hop on flat ground (dead reckoning); hop-plan replaces that with the reconstructed
touchdown, and the next hop-plan starts from it, so the estimates chain. The state lives as long as
the server process: a restart begins a new sequence at the start (the hop products stay).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from pydantic import Field

from rvs_server.config import CommandConfig, Point
from rvs_server.devices import Hopper, HopperDevice, OffTerrain
from rvs_server.dispatch import Module
from rvs_server.hopping.pictures import contact_sheet, global_maps
from rvs_server.hopping.plan import check_workflow, run_hop_plan
from rvs_server.hopping.settings import HoppingSettings
from rvs_server.hopping.store import cloud_of, next_hop_number, write_hop
from rvs_server.host import Host
from rvs_server.jobs import JobContext
from rvs_server.products.ply import read_ply, write_ply
from rvs_server.products.rasters import write_geotiff, write_png
from rvs_server.protocol import BadRequest, WrongMode
from toolbox.colour import with_title
from toolbox.geometry import rotation_z
from toolbox.hopping import hop_range

module = Module("hopping", settings=HoppingSettings, summary="the hopping rover: hop, hop-plan, hop-map",
                state=lambda server: HoppingState())


class HopConfig(CommandConfig):
    speed: float = Field(..., gt=0, description="launch speed, m/s (at most hopping.toml max_speed_mps)")
    elevation: float = Field(..., ge=10, le=80, description="launch elevation above the horizontal, degrees")
    heading: float = Field(..., ge=-180, le=180, description="hop direction, degrees counter-clockwise from east")


class HopPlanConfig(CommandConfig):
    goal: Point | None = Field(None, description="hop toward this X,Y (world, metres)")
    goal_heading: float | None = Field(None, ge=-180, le=180, description="or in this direction, degrees "
                                       "counter-clockwise from east; neither: on along the last hop's direction")


class HopMapConfig(CommandConfig):
    cell: float | None = Field(None, gt=0.005, le=0.5, description="map cell, metres; default hopping.toml "
                               "map_cell_m")


# ------------------------------------------------------------------------------------ state
@dataclass
class HopEntry:
    """One hop of this server's sequence."""

    number: int
    product: str                       # hop-NNN
    launch: list[float]                # estimated centre of mass at launch (the estimate when it hopped)
    plan: str | None = None            # the latest hop-plan product of this hop
    cloud: str | None = None           # its corrected dense cloud (PLY)
    flight: list[list[float]] = field(default_factory=list)   # the estimated flight, launch to touchdown


class HoppingState:
    """What the server believes about the hopper; one per server."""

    def __init__(self) -> None:
        self.start_sequence(None)

    def start_sequence(self, sequence: object | None) -> None:
        self.sequence = sequence                      # the device's run of hops from the start these belong to
        self.estimate: list[float] | None = None     # centre of mass, world frame (map heights)
        self.hops: list[HopEntry] = []

    def hopper_on(self, device: HopperDevice, settings: HoppingSettings) -> Hopper:
        """The hopper to hop with (the device's rules: made at the start on first use, a new world
        starts a new sequence, a changed hopper configuration takes effect where it stands); the hops
        and the estimate start again with a new sequence."""
        hopper = device.require(settings.backend, settings.hopper, settings.start, settings.start_heading_deg)
        if device.sequence is not self.sequence:
            self.start_sequence(device.sequence)
        return hopper

    def position(self, settings: HoppingSettings) -> np.ndarray:
        if self.estimate is None:   # at rest on the start's ground (z = 0): the centre one body radius up
            self.estimate = [*map(float, settings.start), settings.rover_radius_m]
        return np.array(self.estimate)

    def record_hop(self, number: int, product: str, cfg: HopConfig, settings: HoppingSettings) -> None:
        """A new hop: launched from the current estimate, which moves by the commanded hop (dead
        reckoning on flat ground) until hop-plan measures it."""
        launch = self.position(settings)
        distance = float(hop_range(cfg.speed, math.radians(cfg.elevation), settings.gravity_mps2))
        self.hops.append(HopEntry(number, product, launch.tolist()))
        self.estimate = (launch + rotation_z(math.radians(cfg.heading)) @ [distance, 0.0, 0.0]).tolist()

    def plan_inputs(self) -> dict:
        """What hop-plan needs of the last hop; stored in its checkpoint."""
        last = self.hops[-1]
        previous = next((h for h in reversed(self.hops[:-1]) if h.cloud), None)
        return {"hop": last.product, "number": last.number, "launch": last.launch,
                "previous_cloud": previous.cloud if previous else None,
                "previous_plan": previous.plan if previous else None}

    def record_plan(self, hop: str, plan: str, cloud: str, flight: np.ndarray, touchdown: np.ndarray) -> None:
        """hop-plan's result: the hop's cloud for the next ICP and hop-map; its touchdown the new estimate."""
        entry = next((h for h in self.hops if h.product == hop), None)
        if entry is None:   # a continued job of a sequence this server did not fly
            return
        entry.plan, entry.cloud, entry.flight = plan, cloud, flight.tolist()
        if entry is self.hops[-1]:
            self.estimate = touchdown.tolist()


def state_of(server: Host) -> HoppingState:
    return server.state_of("hopping")


def _settings(server: Host) -> HoppingSettings:
    return server.settings_of("hopping")


# ------------------------------------------------------------------------------------ hop
def _validate_hop(server: Host, cfg: HopConfig) -> None:
    settings = _settings(server)
    server.devices.hopper.check_backend(settings.backend)
    if cfg.speed > settings.max_speed_mps:
        raise BadRequest(f"hop: --speed = {cfg.speed:g}: above the hopper's fastest launch; allowed: float > 0 and "
                         f"<= {settings.max_speed_mps:g} (hopping.toml max_speed_mps)")


@module.job("hop", HopConfig, resumable=False, validate=_validate_hop)
def hop(ctx: JobContext, cfg: HopConfig) -> dict[str, Any]:
    """Hop: turn to the heading, launch, record the flight's frames and the attitude sensors."""
    settings: HoppingSettings = ctx.settings
    state = ctx.state
    device: HopperDevice = ctx.devices.hopper
    if not device.ready:
        ctx.progress(1, "waiting for the simulated world to be built")
    hopper = state.hopper_on(device, settings)
    ctx.safe_point()   # the last moment to stop: a launched hop cannot be taken back
    ctx.progress(5, f"hop {hopper.hops + 1}: turning to {cfg.heading:g} deg, launching at {cfg.speed:g} m/s, "
                    f"{cfg.elevation:g} deg; the camera records the flight")
    try:
        record = hopper.hop(cfg.speed, cfg.elevation, cfg.heading)
    except OffTerrain as exc:
        raise BadRequest(f"hop: the flight would leave the simulated world ({exc}); the hopper stays at "
                         f"({hopper.x:.2f}, {hopper.y:.2f})") from None
    number = next_hop_number(ctx.server.products.root)
    product = ctx.product(cfg, name=f"hop-{number:03d}")
    ctx.progress(80, f"writing {product.name}: {len(record.frames)} frames")
    write_hop(product, record, number)
    write_png(product.add("frames.png", "contact sheet: frames spread over the flight, with their times"),
              with_title(contact_sheet(record.frames, record.timestamps, 8), f"{product.name}: the hop's frames"))
    state.record_hop(number, product.name, cfg, settings)
    result = ctx.finish_product(product)
    return {**result, "frames": len(record.frames), "flight_time": f"{record.timestamps[-1]:.3f}"}


# ------------------------------------------------------------------------------------ hop-plan
def _validate_plan(server: Host, cfg: HopPlanConfig) -> None:
    if cfg.goal is not None and cfg.goal_heading is not None:
        raise BadRequest("hop-plan: --goal and --goal-heading given together; give one of them (or neither: on "
                         "along the last hop's direction)")
    if cfg.goal is not None and not all(math.isfinite(v) for v in cfg.goal):
        raise BadRequest(f"hop-plan: --goal = {cfg.goal[0]},{cfg.goal[1]}: must be finite numbers")
    if not state_of(server).hops:
        raise WrongMode("hop-plan: no hop yet: hop --speed V --elevation DEG --heading DEG first")
    check_workflow(server)


@module.job("hop-plan", HopPlanConfig, validate=_validate_plan)
def hop_plan(ctx: JobContext, cfg: HopPlanConfig) -> dict[str, Any]:
    """Reconstruct the last hop, correct the position by ICP, choose the next landing target."""
    state = ctx.state
    inputs = (ctx.resume or {}).get("inputs")
    if inputs is None:
        if not state.hops:   # continued after a restart, from before its inputs were checkpointed
            raise WrongMode("hop-plan: no hop in this server's sequence to plan from (the server restarted)")
        inputs = state.plan_inputs()
    outcome = run_hop_plan(ctx, cfg, inputs, ctx.settings)
    taus = np.linspace(0.0, outcome.estimate.touchdown_tau, 40)
    state.record_plan(inputs["hop"], outcome.reply["product"], str(outcome.cloud_path),
                      outcome.estimate.trajectory(taus), outcome.estimate.touchdown)
    if outcome.error is not None:
        raise outcome.error
    return outcome.reply


# ------------------------------------------------------------------------------------ hop-map
def _validate_map(server: Host, cfg: HopMapConfig) -> None:
    if not any(h.cloud for h in state_of(server).hops):
        raise WrongMode("hop-map: no hop reconstructed yet: hop, then hop-plan, first")


@module.job("hop-map", HopMapConfig, resumable=False, validate=_validate_map)
def hop_map(ctx: JobContext, cfg: HopMapConfig) -> dict[str, Any]:
    """The global map of every reconstructed hop: true colour and false colour by hop, and the merged cloud."""
    settings: HoppingSettings = ctx.settings
    entries = [h for h in ctx.state.hops if h.cloud]
    ctx.progress(10, f"merging the clouds of {len(entries)} hops")
    clouds = []
    for entry in entries:
        points, colours = cloud_of(read_ply(entry.cloud))
        clouds.append((entry.number, points, colours))
    product = ctx.product(cfg, name=f"hop-map-{entries[-1].number:03d}")
    product.note("inputs", [{"hop": h.product, "plan": h.plan} for h in entries])
    ctx.progress(50, "top-down maps")
    tracks = [(h.number, np.array(h.flight)) for h in entries]
    true_picture, false_picture, spec, seen = global_maps(clouds, tracks, cfg.cell or settings.map_cell_m,
                                                          product.name)
    write_png(product.add("map.png", "global map, true colour (mean grey level), estimated flights drawn"),
              true_picture)
    write_png(product.add("map-hops.png", "global map, false colour by hop: which hop saw each cell"), false_picture)
    write_geotiff(product.add("hops-per-cell.tif", "how many hops saw each cell (float32 GeoTIFF)"),
                  seen.astype(np.float32), spec, "hops per cell")
    points = np.vstack([p for _, p, _ in clouds])
    colours = np.vstack([c if c is not None else np.full((len(p), 3), 128, np.uint8) for _, p, c in clouds])
    hops = np.concatenate([np.full(len(p), n) for n, p, _ in clouds])
    write_ply(product.add("map.ply", "all hops' clouds, world frame, grey levels as RGB, property hop: the hop "
                          "number"), points, colours, hops)
    product.write_json("map.json", {"grid": spec.to_json(), "hops": [
        {"hop": h.product, "plan": h.plan, "points": int(len(p)), "launch_m": h.launch,
         "touchdown_m": h.flight[-1] if h.flight else None} for h, (_, p, _) in zip(entries, clouds, strict=True)]},
        "the hops in the map, their clouds' sizes and estimated launch and touchdown")
    result = ctx.finish_product(product)
    return {**result, "hops": len(entries), "points": len(points), "cells": f"{spec.rows}x{spec.cols}",
            "seen": f"{float(np.mean(seen > 0)):.3f}"}
