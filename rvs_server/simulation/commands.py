"""Commands that act on the simulated world only (PROTOCOL.md "Simulated world"); with real devices
they are `409 wrong-mode`.

`sim-fault` breaks an emulated device the way hardware breaks: the switch (drivers/sim/faults.py)
sits inside the emulator, which then stops answering on its own line (no PTU reply, no SR4000
frame, no camera frame, no trigger pulse out of the box). The server learns of it only as it would
of a real fault, so what a job does about it is what it would do on the test bed.

`sun` moves the simulated sun (the image-based route paper's change of light); with real devices it
is `503 device`, since the sun is not ours to move.

`astronaut` and `sim-rock` put obstacles no map knew into the world (drivers/sim/obstacles.py): a
standing or walking person, dropped rocks. Both are immediate, so a rock can fall in front of a
driving rover; a world still being built is waited for off the event loop.
"""
from __future__ import annotations

import asyncio
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, Literal

from pydantic import Field

from rvs_server.config import CommandConfig, Point
from rvs_server.devices import FAULT_DEVICES, Sun
from rvs_server.dispatch import Call, Module
from rvs_server.protocol import BadRequest, DeviceError, WrongMode

if TYPE_CHECKING:
    from rvs_server.host import Host
    from rvs_server.jobs import JobContext

module = Module("simulation", summary="the simulated world: injected device faults, the sun, obstacles no map knew")

FaultDevice = Literal["ptu", "tof", "camera-left", "camera-right", "trigger", "worker"]
# one list of devices, drivers/sim/faults.py's, and the native worker (rvs_server/native.py)
assert set(FaultDevice.__args__) == set(FAULT_DEVICES) | {"worker"}
WORKER_KINDS = ("segv", "abrt", "kill", "memory")


class SimFaultConfig(CommandConfig):
    device: FaultDevice | None = Field(None, description="the emulated device to break (or, with --clear, to "
                                       "mend; --clear alone mends every one)")
    after: int | None = Field(None, ge=0, le=1_000_000, description="requests it still answers first (PTU "
                              "commands, SR4000 frames, camera frames, trigger pulses; the worker's steps); "
                              "default 0: fails from now")
    kind: Literal["silent", "segv", "abrt", "kill", "memory"] | None = Field(
        None, description="how it fails; a device: silent (default), it answers nothing until cleared; the worker: "
        "segv (default), abrt or kill, a real signal in the native worker at that step, or memory, that step "
        "allocates past server.toml worker_memory_mb")
    clear: bool = Field(False, description="remove the fault; the device answers again (reset, then continue)")


def _emulated(server: Host, device: str) -> str | None:
    """Why `device` cannot take a fault (it is a real one, or off), or None."""
    config = server.devices.config
    section, backend, wanted = {
        "ptu": ("ptu", config.ptu.backend, "sim"),
        "tof": ("tof", config.tof.backend, "sim"),
        "camera-left": ("cameras", config.cameras.backend, "sim"),
        "camera-right": ("cameras", config.cameras.backend, "sim"),
        "trigger": ("cameras", config.cameras.trigger_backend, "sim"),
    }[device]
    if backend != wanted:
        key = "trigger_backend" if device == "trigger" else "backend"
        return f"the {device} is a real device (devices.toml [{section}] {key} = {backend!r})"
    if not getattr(config, section).enabled:
        return f"the {device} is off (devices.toml [{section}] enabled = false)"
    return None


def validate_fault(server: Host, cfg: SimFaultConfig) -> None:
    if cfg.clear:
        if cfg.after is not None or cfg.kind is not None:
            raise BadRequest("sim-fault: --clear takes no --after or --kind (it removes the fault; "
                             "sim-fault --device D --after N arms one)")
    elif cfg.device is None:
        raise BadRequest(f"sim-fault: give --device ({', '.join(FAULT_DEVICES)}, worker) with --after N and --kind "
                         f"silent (worker: {', '.join(WORKER_KINDS)}), or --clear [--device D]")
    elif cfg.kind is not None and cfg.kind not in (WORKER_KINDS if cfg.device == "worker" else ("silent",)):
        allowed = ", ".join(WORKER_KINDS) if cfg.device == "worker" else "silent"
        raise BadRequest(f"sim-fault: --kind = {cfg.kind!r} does not apply to --device {cfg.device}: {allowed}")
    if cfg.device == "worker":      # a crash switch of our own process, with real devices as well
        return
    devices = [cfg.device] if cfg.device else list(FAULT_DEVICES)
    refusals = [why for why in (_emulated(server, d) for d in devices) if why]
    if refusals and len(refusals) == len(devices):  # --clear alone mends whichever devices are emulated
        raise WrongMode(f"sim-fault: {'; '.join(refusals)}; faults are injected into emulated devices only")


@module.immediate("sim-fault", SimFaultConfig, validate=validate_fault)
def sim_fault(call: Call, cfg: SimFaultConfig) -> dict[str, Any]:
    """Break an emulated device (it stops answering after N more requests) or mend it (--clear)."""
    native = call.server.native
    if cfg.device == "worker":
        if native.in_process and not cfg.clear:
            raise WrongMode("sim-fault: the native worker is off (server.toml native_worker = false): a fault "
                            "there would end the server itself")
        if cfg.clear:
            native.faults.clear()
            return {"cleared": "worker"}
        native.faults.arm(cfg.kind or "segv", cfg.after or 0)
        return {"device": "worker", "kind": cfg.kind or "segv", "after": cfg.after or 0, "state": "armed",
                "steps": native.steps}
    faults = call.server.devices.testbed.faults
    if cfg.clear:
        cleared = [cfg.device] if cfg.device else [d for d in FAULT_DEVICES if not _emulated(call.server, d)]
        for device in cleared:
            faults[device].clear()
        if cfg.device is None:
            native.faults.clear()
        return {"cleared": " ".join(cleared), "next": "reset, then continue"}
    switch = faults[cfg.device]
    switch.arm(after=cfg.after or 0, kind=cfg.kind or "silent")
    state = switch.state()
    return {"device": cfg.device, "kind": state.kind, "after": cfg.after or 0, "state": state.state,
            "answered": state.answered}


class SunConfig(CommandConfig):
    azimuth: float = Field(..., ge=0, lt=360, description="degrees clockwise from north")
    elevation: float = Field(..., gt=0, le=90, description="degrees above the horizon")


def _validate_sun(server: Host, cfg: SunConfig) -> None:
    if not server.devices.simulated:
        raise DeviceError("sun: the devices are real; the sun is not ours to move")


@module.job("sun", SunConfig, resumable=False, validate=_validate_sun)
def sun(ctx: JobContext, cfg: SunConfig) -> dict[str, Any]:
    """Simulated world: move the sun (shadows and brightness change; the ground does not)."""
    testbed = ctx.devices.testbed
    testbed.wait_for_build()
    world = testbed.world
    old = world.sun
    world.sun = Sun(azimuth_deg=cfg.azimuth, elevation_deg=cfg.elevation, irradiance=old.irradiance,
                    ambient=old.ambient)
    return {"azimuth": cfg.azimuth, "elevation": cfg.elevation,
            "was": f"{old.azimuth_deg:g},{old.elevation_deg:g}"}


# ---------------------------------------------------------------------------------------------
# Obstacles no map knew: astronaut, sim-rock


def _simulated(command: str):
    def check(server: Host, cfg: Any) -> None:
        if not server.devices.simulated:
            raise WrongMode(f"{command}: the devices are real; obstacles are put into the simulated world only")
    return check


async def _on_world(call: Call, work: Callable[[Any], Any]) -> Any:
    """Run `work(testbed)` once the world is built, in a worker thread: the event loop never waits."""
    testbed = call.server.devices.testbed
    loop = asyncio.get_running_loop()
    await loop.run_in_executor(None, testbed.wait_for_build)
    return await loop.run_in_executor(None, work, testbed)


def _f(value: float) -> str:
    return f"{value:.3f}"


class AstronautConfig(CommandConfig):
    at: Point | None = Field(None, description="where the person stands (or starts walking), X,Y in the world "
                             "frame, metres")
    to: Point | None = Field(None, description="walk from --at to X,Y and back, over and over")
    then: Point | None = Field(None, description="with --to: walk on from there to X,Y (a turn), then back the "
                               "same way")
    speed: float = Field(0.5, gt=0, le=3.0, description="walking speed, metres per second of simulation time")
    pause: float = Field(0.0, ge=0, le=600, description="with --to: seconds it stands still at each end of its "
                         "walk before it turns back")
    remove: bool = Field(False, description="take the person away")


def _validate_astronaut(server: Host, cfg: AstronautConfig) -> None:
    _simulated("astronaut")(server, cfg)
    if cfg.remove:
        if cfg.at is not None or cfg.to is not None:
            raise BadRequest("astronaut: --remove takes no --at or --to (astronaut --at X,Y puts one back)")
    elif cfg.at is None:
        raise BadRequest("astronaut: give --at X,Y (and --to X,Y [--speed M_PER_S] to walk), or --remove")
    elif cfg.to is None and (cfg.then is not None or cfg.pause):
        raise BadRequest(f"astronaut: --then and --pause shape a walk; give --to X,Y as well "
                         f"(given: {'--then' if cfg.then is not None else '--pause'})")


@module.immediate("astronaut", AstronautConfig, validate=_validate_astronaut)
def astronaut(call: Call, cfg: AstronautConfig):
    """Simulated world: a person standing at --at (or walking to --to and back), 1.8 m tall; --remove."""
    def work(testbed) -> dict[str, Any]:
        if cfg.remove:
            if testbed.astronaut_id is None:
                raise WrongMode("astronaut: there is no astronaut in the world to remove")
            gone = testbed.astronaut_id
            testbed.remove_obstacle(gone)
            return {"removed": gone}
        try:
            record = testbed.place_astronaut(*cfg.at, to=cfg.to, speed=cfg.speed, then=cfg.then, pause=cfg.pause)
        except ValueError as exc:
            raise BadRequest(f"astronaut: {exc}") from None
        reply = {"astronaut": record["id"], "x": _f(record["x"]), "y": _f(record["y"]),
                 "height": _f(record["height_m"])}
        if cfg.to is not None:
            reply.update(to=f"{_f(cfg.to[0])},{_f(cfg.to[1])}", speed=_f(cfg.speed))
            if cfg.then is not None:
                reply["then"] = f"{_f(cfg.then[0])},{_f(cfg.then[1])}"
            if cfg.pause:
                reply["pause"] = f"{cfg.pause:g}"
        return reply
    return _on_world(call, work)


class SimRockConfig(CommandConfig):
    at: Point | None = Field(None, description="where the rock falls, X,Y in the world frame, metres")
    height: float = Field(0.2, ge=0.02, le=2.5, description="how far it stands above the ground, metres "
                          "(up to 2.5: standing boulders of a person's height)")
    diameter: float | None = Field(None, ge=0.05, le=2.0, description="across its body, metres; default 1.5 x "
                                   "height (at least 0.05)")
    seed: int | None = Field(None, ge=0, le=2**31 - 1, description="its shape and albedo; default its id")
    remove: int | None = Field(None, ge=1, description="take away the dropped rock with this id")
    clear: bool = Field(False, description="take away every dropped rock")


def _validate_rock(server: Host, cfg: SimRockConfig) -> None:
    _simulated("sim-rock")(server, cfg)
    given = [name for name, on in (("--at", cfg.at is not None), ("--remove", cfg.remove is not None),
                                   ("--clear", cfg.clear)) if on]
    if len(given) != 1:
        what = "none of them" if not given else " and ".join(given)
        raise BadRequest(f"sim-rock: give one of --at X,Y [--height M] [--diameter M] [--seed N], --remove ID "
                         f"or --clear, not {what}")


@module.immediate("sim-rock", SimRockConfig, validate=_validate_rock)
def sim_rock(call: Call, cfg: SimRockConfig):
    """Simulated world: drop a rock no map knew at --at (--height, --diameter, --seed); --remove ID; --clear."""
    def work(testbed) -> dict[str, Any]:
        if cfg.clear:
            return {"removed": len(testbed.clear_rocks())}
        if cfg.remove is not None:
            rocks = [o["id"] for o in testbed.obstacles() if o["kind"] == "rock"]
            if cfg.remove not in rocks:
                there = ", ".join(map(str, rocks)) or "none"
                raise BadRequest(f"sim-rock: --remove = {cfg.remove}: no dropped rock has that id (dropped rocks: "
                                 f"{there})")
            testbed.remove_obstacle(cfg.remove)
            return {"removed": cfg.remove}
        diameter = cfg.diameter if cfg.diameter is not None else min(2.0, max(0.05, 1.5 * cfg.height))
        try:
            record = testbed.drop_rock(*cfg.at, cfg.height, diameter, cfg.seed)
        except ValueError as exc:
            raise BadRequest(f"sim-rock: --at = {cfg.at[0]:g},{cfg.at[1]:g}: {exc}") from None
        return {"rock": record["id"], "x": _f(record["x"]), "y": _f(record["y"]), "height": _f(record["height_m"]),
                "diameter": _f(record["diameter_m"])}
    return _on_world(call, work)
