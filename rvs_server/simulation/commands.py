"""Commands that act on the simulated world only (PROTOCOL.md "Simulated world"); with real devices
they are `409 wrong-mode`.

`sim-fault` breaks an emulated device the way hardware breaks: the switch (drivers/sim/faults.py)
sits inside the emulator, which then stops answering on its own line (no PTU reply, no SR4000
frame, no camera frame, no trigger pulse out of the box). The server learns of it only as it would
of a real fault, so what a job does about it is what it would do on the test bed.

`sun` moves the simulated sun (the image-based route paper's change of light); with real devices it
is `503 device`, since the sun is not ours to move.
"""
from __future__ import annotations

from typing import TYPE_CHECKING, Any, Literal

from pydantic import Field

from rvs_server.config import CommandConfig
from rvs_server.devices import FAULT_DEVICES, Sun
from rvs_server.dispatch import Call, Module
from rvs_server.protocol import BadRequest, DeviceError, WrongMode

if TYPE_CHECKING:
    from rvs_server.host import Host
    from rvs_server.jobs import JobContext

module = Module("simulation", summary="the simulated world: injected device faults")

FaultDevice = Literal["ptu", "tof", "camera-left", "camera-right", "trigger"]
assert set(FaultDevice.__args__) == set(FAULT_DEVICES)  # one list of devices, drivers/sim/faults.py's


class SimFaultConfig(CommandConfig):
    device: FaultDevice | None = Field(None, description="the emulated device to break (or, with --clear, to "
                                       "mend; --clear alone mends every one)")
    after: int | None = Field(None, ge=0, le=1_000_000, description="requests it still answers first (PTU "
                              "commands, SR4000 frames, camera frames, trigger pulses); default 0: fails from now")
    kind: Literal["silent"] | None = Field(None, description="how it fails; silent (default): it answers nothing "
                                           "until cleared")
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
        raise BadRequest(f"sim-fault: give --device ({', '.join(FAULT_DEVICES)}) with --after N and --kind "
                         f"silent, or --clear [--device D]")
    devices = [cfg.device] if cfg.device else list(FAULT_DEVICES)
    refusals = [why for why in (_emulated(server, d) for d in devices) if why]
    if refusals and len(refusals) == len(devices):  # --clear alone mends whichever devices are emulated
        raise WrongMode(f"sim-fault: {'; '.join(refusals)}; faults are injected into emulated devices only")


@module.immediate("sim-fault", SimFaultConfig, validate=validate_fault)
def sim_fault(call: Call, cfg: SimFaultConfig) -> dict[str, Any]:
    """Break an emulated device (it stops answering after N more requests) or mend it (--clear)."""
    faults = call.server.devices.testbed.faults
    if cfg.clear:
        cleared = [cfg.device] if cfg.device else [d for d in FAULT_DEVICES if not _emulated(call.server, d)]
        for device in cleared:
            faults[device].clear()
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
