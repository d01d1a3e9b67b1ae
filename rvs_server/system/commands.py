"""System commands: modes, jobs, help, status, logs, authentication (PROTOCOL.md's command list)."""
from __future__ import annotations

import hmac
import shutil
import time
from typing import TYPE_CHECKING, Any

from pydantic import Field

from rvs_server import __version__
from rvs_server.config import CommandConfig, describe_allowed, describe_default, option_name, type_label
from rvs_server.dispatch import Call, Mode, Module, Request
from rvs_server.files import atomic_path
from rvs_server.protocol import (
    EVENT_TOPICS,
    BadRequest,
    DeviceError,
    RvsError,
    Timeout,
    Unauthorized,
    WrongMode,
    parse_line,
)
from rvs_server.recovery import UnreadableRecoverySet

if TYPE_CHECKING:
    from rvs_server.host import Host

module = Module("system", summary="modes, jobs, help, status, logs, authentication")


@module.immediate("status")
def status(call: Call, cfg: Any) -> dict[str, Any]:
    """Mode, running job, stored recovery sets, PTU angles, device health, uptime, version."""
    server = call.server
    dispatcher = server.dispatcher
    job = dispatcher.job
    pan_tilt = server.devices.ptu.position()
    data: dict[str, Any] = {
        "mode": dispatcher.mode,
        "version": __version__,
        "uptime": f"{time.monotonic() - server.started:.1f}",
        "job": job.id if job else "none",
        "command": job.command if job else "none",
        "percent": f"{job.percent:.0f}" if job else "0",
        "recovery": server.recovery.count(),
        "pan": f"{pan_tilt[0]:.2f}" if pan_tilt else "none",
        "tilt": f"{pan_tilt[1]:.2f}" if pan_tilt else "none",
    }
    if dispatcher.sleep_until is not None:
        data["sleep_left"] = f"{max(0.0, dispatcher.sleep_until - server.clock.now()):.1f}"
    data.update(server.activities.status())
    data.update(server.devices.health())
    return data


@module.immediate("version", open_without_auth=True)
def version(call: Call, cfg: Any) -> dict[str, Any]:
    """The server's software and protocol versions."""
    from rvs_server.protocol import PROTOCOL_VERSION
    return {"version": __version__, "protocol": PROTOCOL_VERSION}


@module.immediate("help", raw=True, open_without_auth=True)
def help_(call: Call, tokens: tuple[str, ...]) -> dict[str, Any]:
    """The commands; or one command's options with types, defaults and allowed ranges."""
    registry = call.server.registry
    if not tokens:
        names = sorted(registry.commands)
        return {"commands": " ".join(names), "count": len(names),
                "usage": "help COMMAND lists a command's options"}
    if len(tokens) > 1:
        raise BadRequest(f"help takes one command name, got {len(tokens)} arguments")
    spec = registry.lookup(tokens[0].lower())
    data: dict[str, Any] = {"command": spec.name, "kind": spec.kind, "summary": spec.summary,
                            "usage": spec.usage}
    if spec.raw:
        return data
    defaults = call.server.command_defaults(spec)
    for name, info in spec.config.model_fields.items():
        default = defaults.get(name, None) if name in defaults else None
        shown_default = describe_default(info) if name not in defaults else str(default)
        parts = [type_label(info)]
        bounds = describe_allowed(info).removeprefix(type_label(info)).strip()
        if bounds:
            parts.append(bounds)
        parts.append(f"default {shown_default}")
        if info.description:
            parts.append(info.description)
        key = name if name in spec.positionals else option_name(name).lstrip("-")
        data[f"opt.{key}"] = "; ".join(parts)
    if spec.limits is not None:
        data.update(spec.limits(call.server))
    return data


@module.immediate("check", raw=True)
def check(call: Call, tokens: tuple[str, ...]) -> dict[str, Any]:
    """Validate a command line exactly as it would be run, without running it."""
    if not tokens:
        raise BadRequest("check needs a command line to check, e.g. check move-ptu --pan 30")
    parsed = parse_line(" ".join(_requote(t) for t in tokens))
    spec, _ = call.server.dispatcher.prepare(Request.from_line(parsed), call.session)
    return {"command": spec.name, "kind": spec.kind, "mode": call.server.dispatcher.mode}


def _requote(token: str) -> str:
    from rvs_server.protocol import quote_token
    return quote_token(token)


@module.command("standby")
def standby(call: Call, cfg: Any) -> dict[str, Any]:
    """Return to standby (wakes a sleeping server; refused while a job runs)."""
    dispatcher = call.server.dispatcher
    if dispatcher.sleep_until is not None:
        dispatcher.wake()
    dispatcher.set_mode(Mode.STANDBY)
    return {"mode": dispatcher.mode, "recovery": call.server.recovery.count()}


class SleepConfig(CommandConfig):
    seconds: float = Field(..., gt=0, le=7 * 24 * 3600, description="how long to sleep, seconds")


@module.command("sleep", SleepConfig, positionals=("seconds",))
def sleep(call: Call, cfg: SleepConfig) -> dict[str, Any]:
    """Sleep mode: no operations until the time has passed (standby wakes the server early)."""
    call.server.dispatcher.start_sleep(cfg.seconds)
    return {"mode": Mode.SLEEP, "seconds": cfg.seconds}


@module.immediate("break")
def break_(call: Call, cfg: Any):
    """Interrupt the running job at its next safe point and store its recovery set."""
    server = call.server
    job = server.dispatcher.job
    if job is None:
        raise WrongMode(f"no job is running (mode {server.dispatcher.mode}); break interrupts a running job")
    job.request_interrupt("break")

    async def stopped() -> dict[str, Any]:
        timeout = server.settings.break_timeout_s
        if not await server.dispatcher.wait_job(job, timeout):
            raise Timeout(f"job {job.id} ({job.command}) has not reached a safe point within {timeout:g} s; "
                          f"it stops at its next one")
        rset = server.recovery.load(job.id)
        return {"job": job.id, "recovery": rset.job if rset else "none", "mode": server.dispatcher.mode}
    return stopped()


class JobChoice(CommandConfig):
    job: str | None = Field(None, pattern=r"^[0-9]{1,12}$", description="job id; default the latest")


def _recovery_set(server: Host, job: str | None):
    """The named (or the latest) recovery set; a damaged one is named with what can be done."""
    chosen = job or server.recovery.latest_job()
    try:
        rset = server.recovery.read(chosen) if chosen else None
    except UnreadableRecoverySet as exc:
        others = [r.job for r in server.recovery.all()]
        hint = f"; continue --job ID resumes another ({', '.join(others)})" if others else ""
        raise WrongMode(f"{exc}; abort --job {chosen} drops it{hint}") from None
    if rset is None:
        raise _no_set(server, job)
    return rset


def _no_set(server: Host, job: str | None) -> WrongMode:
    stored = ", ".join(server.recovery.jobs()) or "none"
    what = f"no recovery set for job {job}" if job else "nothing to resume"
    return WrongMode(f"{what} (stored: {stored})")


@module.command("continue", JobChoice)
def continue_(call: Call, cfg: JobChoice):
    """Check the hardware the job used, then resume the latest (or the named) interrupted job."""
    server = call.server
    rset = _recovery_set(server, cfg.job)
    spec = server.registry.lookup(rset.command)
    try:
        job_cfg = spec.config.model_validate(rset.options)
    except Exception as exc:
        raise BadRequest(f"recovery set {rset.job} no longer fits {spec.name}'s options: {exc}") from None
    for name in rset.devices:
        device = server.devices[name]
        device.check()
        if device.health != "ok":
            raise DeviceError(f"{name} is {device.health}: {device.last_error or 'no detail'}; continue needs "
                              f"it for job {rset.job} ({rset.command}); reset, then continue")
    return server.dispatcher.start_job(spec, job_cfg, rset.line, call.sink, recovery=rset)


@module.command("abort", JobChoice)
def abort(call: Call, cfg: JobChoice) -> dict[str, Any]:
    """End an interrupted job for good: drop its recovery set, keep what it produced."""
    server = call.server
    job = cfg.job or server.recovery.latest_job()
    if job is None or job not in server.recovery.jobs():
        raise _no_set(server, cfg.job)
    rset = server.recovery.load(job)  # None when damaged: dropping it is how to be rid of it
    server.recovery.delete(job)
    server.dispatcher.set_mode(Mode.STANDBY)
    return {"job": job, "command": rset.command if rset else "unknown", "mode": server.dispatcher.mode,
            "recovery": server.recovery.count()}


@module.job("reset", resumable=False)
def reset(ctx, cfg: Any) -> dict[str, Any]:
    """Check every device's status, then re-initialise it."""
    ctx.devices.rover.new_epoch()   # the next orient takes a new keyframe
    devices = list(ctx.devices)
    result: dict[str, Any] = {}
    for i, device in enumerate(devices):
        ctx.progress(100 * i / len(devices), f"checking {device.name}")
        device.check()
        result[f"was.{device.name}"] = device.health
        ctx.progress(100 * (i + 0.5) / len(devices), f"re-initialising {device.name}")
        device.reset()
        result[f"dev.{device.name}"] = device.health
    return result


@module.job("reinit", resumable=False)
def reinit(ctx, cfg: Any) -> dict[str, Any]:
    """Reload the configuration files and re-initialise the devices with their defaults."""
    ctx.progress(10, "reloading configuration")
    ctx.server.reload_configuration()  # raises BadRequest naming file and field; then nothing changed
    ctx.progress(50, "re-initialising devices")
    ctx.server.reopen_devices()
    return ctx.server.devices.health()


@module.immediate("logbook")
def logbook(call: Call, cfg: Any) -> dict[str, Any]:
    """Copy the current log file to the configured shared directory."""
    server = call.server
    target_dir = server.shared_dir
    try:
        target_dir.mkdir(parents=True, exist_ok=True)
        for handler in server.log_handlers:
            handler.flush()
        target = target_dir / server.log_path.name
        with atomic_path(target) as partial:  # a reader of the shared folder never sees half a log
            shutil.copyfile(server.log_path, partial)
    except OSError as exc:
        raise RvsError(f"cannot copy the log to {target_dir}: {exc.strerror}", reason="internal") from None
    return {"path": str(target)}


@module.immediate("quit")
def quit_(call: Call, cfg: Any):
    """Stop gracefully: interrupt the job (storing its recovery set), park the devices, exit."""
    return call.server.shutdown()


@module.immediate("auth", raw=True, open_without_auth=True)
def auth(call: Call, tokens: tuple[str, ...]) -> dict[str, Any]:
    """Authenticate this connection with the server's token."""
    server = call.server
    if len(tokens) != 1:
        raise BadRequest("auth takes exactly one argument, the token")
    if server.token is None:
        call.session.authenticated = True
        return {"auth": "not-required"}
    if not hmac.compare_digest(tokens[0].encode(), server.token.encode()):
        call.session.authenticated = False
        raise Unauthorized("wrong token")
    call.session.authenticated = True
    return {"auth": "ok"}


@module.immediate("subscribe", raw=True)
def subscribe(call: Call, tokens: tuple[str, ...]) -> dict[str, Any]:
    """Receive `* EVENT TOPIC ...` lines: all topics, the ones named, or none with --off."""
    if tokens == ("--off",):
        call.session.topics = set()
        return {"topics": "none"}
    unknown = [t for t in tokens if t not in EVENT_TOPICS]
    if unknown:
        raise BadRequest(f"subscribe: unknown topic {unknown[0]!r}; topics: {' '.join(EVENT_TOPICS)} "
                         f"(or --off)")
    if call.session.send_event is None:
        raise BadRequest("this transport has no event stream; use the ZeroMQ PUB socket")
    call.session.topics = set(tokens or EVENT_TOPICS)
    return {"topics": " ".join(t for t in EVENT_TOPICS if t in call.session.topics)}

