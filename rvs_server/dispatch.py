"""The command registry and the mode state machine (standby / busy / break / sleep).

Every command, from any transport or a mission file, arrives here as a Request and leaves as one
final reply on its ReplySink (after any number of progress lines). The path is always the same:
authentication, lookup, option binding and validation against the command's Config class, the
mode check, the command's own validation (device limits and the like), then execution: immediate
and control commands on the event loop, jobs in the single worker thread.
"""
from __future__ import annotations

import asyncio
import difflib
import inspect
import logging
import os
import traceback
from collections.abc import Awaitable, Callable, Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path
from typing import Any, Literal, Protocol

from drivers.errors import DeviceFault, DeviceTimeout
from rvs_server.native import WorkerDied

from .config import CommandConfig, Settings, bind_tokens, build_config, option_name, type_label
from .host import Host, ModuleScope
from .jobs import Job, JobContext, JobCounter, JobInterrupted
from .products import retention
from .protocol import (
    Busy,
    CommandLine,
    DeviceError,
    InternalError,
    Interrupted,
    RvsError,
    Sleeping,
    StorageFull,
    Timeout,
    Unauthorized,
    UnknownCommand,
    WrongMode,
)
from .recovery import RecoverySet

log = logging.getLogger("rvs.dispatch")

Kind = Literal["immediate", "control", "job"]


class Mode(StrEnum):
    """The server's modes (PROTOCOL.md, "Modes"). A StrEnum, so a mode is its wire word."""

    STANDBY = "standby"
    BUSY = "busy"      # a job runs
    BREAK = "break"    # a job was interrupted; continue resumes it
    SLEEP = "sleep"    # until a time, or until `standby`


MODES = tuple(Mode)
# Jobs that ready the hardware for `continue` (PROTOCOL.md: after a device fault, reset, then
# continue): they run in break mode and leave the server in it.
BREAK_MODE_JOBS = ("reset",)


class NoOptions(CommandConfig):
    """For commands that take no options."""


@dataclass
class CommandSpec:
    """One command: its name, its Config class (its options), its handler and how it runs.

    kind: `immediate` commands are answered in any mode, even while a job runs; `control` commands
    change the mode or start a job from a recovery set and obey the mode; `job` commands run in the
    worker thread, one at a time.
    """

    name: str
    handler: Callable[..., Any]
    config: type[CommandConfig] = NoOptions
    kind: Kind = "control"
    summary: str = ""
    positionals: tuple[str, ...] = ()
    raw: bool = False  # the handler gets the tokens unparsed (check, help)
    devices: tuple[str, ...] = ()  # what `continue` checks before resuming
    validate: Callable[[Host, Any], None] | None = None  # (server, cfg) -> None, raises RvsError
    limits: Callable[[Host], dict[str, str]] | None = None  # (server) -> what help adds from devices
    resumable: bool = True
    open_without_auth: bool = False
    module: Module | None = None

    @property
    def usage(self) -> str:
        words = [self.name, *(p.upper() for p in self.positionals)]
        for name, info in self.config.model_fields.items():
            if name in self.positionals:
                continue
            option = option_name(name)
            label = type_label(info)
            text = option if label == "flag" else f"{option} {name.rstrip('_').upper()}"
            words.append(text if info.is_required() else f"[{text}]")
        if self.raw:
            words.append("...")
        return " ".join(words)


class Module:
    """A family of commands with its own settings file, `configs/<name>.toml`.

    In that file, top-level keys are the module's settings and a table named after a command holds
    defaults for that command's options, e.g. `[move-ptu] speed = 20.0`.
    """

    def __init__(self, name: str, settings: type[Settings] | None = None, summary: str = "",
                 state: Callable[[Host], Any] | None = None):
        self.name = name
        self.settings = settings
        self.summary = summary
        self.state = state  # makes the module's per-server state (stores, what a sequence remembers)
        self.commands: list[CommandSpec] = []

    def command(self, name: str, config: type[CommandConfig] = NoOptions, kind: Kind = "control",
                **options: Any) -> Callable[[Callable[..., Any]], Callable[..., Any]]:
        def register(handler: Callable[..., Any]) -> Callable[..., Any]:
            summary = options.pop("summary", None) or (inspect.getdoc(handler) or "").split("\n")[0]
            self.commands.append(CommandSpec(name=name, handler=handler, config=config, kind=kind,
                                             summary=summary, module=self, **options))
            return handler
        return register

    def job(self, name: str, config: type[CommandConfig] = NoOptions,
            **options: Any) -> Callable[[Callable[..., Any]], Callable[..., Any]]:
        return self.command(name, config, kind="job", **options)

    def immediate(self, name: str, config: type[CommandConfig] = NoOptions,
                  **options: Any) -> Callable[[Callable[..., Any]], Callable[..., Any]]:
        return self.command(name, config, kind="immediate", **options)


class Registry:
    def __init__(self, modules: list[Module]):
        self.modules = {m.name: m for m in modules}
        self.commands: dict[str, CommandSpec] = {}
        for module in modules:
            for spec in module.commands:
                if spec.name in self.commands:
                    raise ValueError(f"command {spec.name} registered twice")
                self.commands[spec.name] = spec

    def lookup(self, name: str) -> CommandSpec:
        spec = self.commands.get(name)
        if spec is None:
            close = difflib.get_close_matches(name, list(self.commands), n=1, cutoff=0.5)
            hint = f"; did you mean {close[0]}?" if close else "; help lists the commands"
            raise UnknownCommand(f"no command {name!r}{hint}")
        return spec


# ---------------------------------------------------------------------------------------------
# Requests, sessions, sinks


@dataclass
class Request:
    """A command as it arrived: from a text line (tokens) or from JSON (values already typed)."""

    command: str
    tokens: tuple[str, ...] | None = None
    values: Mapping[str, Any] | None = None
    tag: str | None = None
    line: str = ""

    @classmethod
    def from_line(cls, parsed: CommandLine) -> Request:
        return cls(command=parsed.command, tokens=parsed.tokens, tag=parsed.tag, line=parsed.text)


class ReplySink(Protocol):
    def progress(self, percent: float, message: str) -> None: ...
    def ok(self, data: Mapping[str, Any]) -> None: ...
    def error(self, error: RvsError) -> None: ...


@dataclass(eq=False)  # sessions are kept in a set, by identity
class Session:
    """One client connection (or one ZeroMQ peer), as the dispatcher sees it."""

    name: str
    authenticated: bool = False
    topics: set[str] = field(default_factory=set)
    send_event: Callable[[str, Mapping[str, Any]], None] | None = None
    close: Callable[[], None] | None = None


class DispatchHost(Host, Protocol):
    """The server as the dispatcher, the transports and the immediate and control commands see it: a
    Host with its whole dispatcher, its registry and the command defaults (app.Server)."""

    @property
    def dispatcher(self) -> Dispatcher: ...

    @property
    def registry(self) -> Registry: ...

    @property
    def job_counter(self) -> JobCounter: ...

    @property
    def sessions(self) -> set[Session]: ...

    def command_defaults(self, spec: CommandSpec) -> dict[str, Any]:
        """A command's option defaults from its module's TOML file."""


@dataclass
class Call(ModuleScope):
    """What an immediate or control handler gets besides its options."""

    server: DispatchHost
    session: Session
    request: Request
    sink: ReplySink
    module: str | None = None  # the command's module: its settings and state


# ---------------------------------------------------------------------------------------------
# The dispatcher


class Dispatcher:
    def __init__(self, server: DispatchHost):
        self.server = server
        self._base_mode = Mode.STANDBY  # standby | break; busy and sleep are derived
        self.sleep_until: float | None = None
        self._sleep_timer: asyncio.TimerHandle | None = None
        self.job: Job | None = None
        self._job_future: asyncio.Future | None = None
        self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="rvs-job")
        self._last_mode = Mode.STANDBY

    # -- modes ----------------------------------------------------------------------------------

    @property
    def registry(self) -> Registry:
        return self.server.registry

    @property
    def mode(self) -> Mode:
        if self.job is not None:
            return Mode.BUSY
        if self.sleep_until is not None:
            return Mode.SLEEP
        return self._base_mode

    def set_mode(self, mode: Mode) -> None:
        assert mode in (Mode.STANDBY, Mode.BREAK)
        self._base_mode = Mode(mode)
        self._announce_mode()

    def _announce_mode(self) -> None:
        mode = self.mode
        if mode != self._last_mode:
            self._last_mode = mode
            log.info("mode %s", mode)
            self.server.publish("mode", {"mode": mode})

    def start_sleep(self, seconds: float) -> None:
        clock = self.server.clock
        self.sleep_until = clock.now() + seconds
        if self._sleep_timer:
            self._sleep_timer.cancel()
        self._sleep_timer = asyncio.get_running_loop().call_later(clock.to_wall(seconds), self.wake)
        self._announce_mode()

    def wake(self) -> None:
        if self._sleep_timer:
            self._sleep_timer.cancel()
            self._sleep_timer = None
        self.sleep_until = None
        self._base_mode = Mode.STANDBY
        self._announce_mode()

    def admit(self, spec: CommandSpec) -> None:
        """Raise the error the mode gives this command, if any."""
        if spec.kind == "immediate":
            return
        if self.server.stopping:
            raise WrongMode(f"the server is shutting down; {spec.name} is refused")
        if self.sleep_until is not None and spec.name != "standby":
            left = max(0.0, self.sleep_until - self.server.clock.now())
            raise Sleeping(f"sleeping for {left:.1f} s more; {spec.name} is refused until then (standby wakes "
                           f"the server)")
        if self.job is not None:
            raise Busy(f"job {self.job.id} ({self.job.command}) is running at {self.job.percent:.0f}%; only "
                       f"immediate commands are accepted (break interrupts it)")
        if spec.kind == "job" and self._base_mode == Mode.BREAK and spec.name not in BREAK_MODE_JOBS:
            latest = self.server.recovery.latest()
            which = f" (job {latest.job}, {latest.command})" if latest else ""
            raise WrongMode(f"mode is break{which}: continue, abort or standby before starting {spec.name}")

    # -- the one way in -------------------------------------------------------------------------

    def prepare(self, request: Request, session: Session) -> tuple[CommandSpec, Any]:
        """Everything short of running: auth, lookup, options, mode, the command's own checks."""
        if self.server.token is not None and not session.authenticated:
            spec = self.registry.commands.get(request.command)
            if spec is None or not spec.open_without_auth:
                raise Unauthorized("this server requires a token: auth TOKEN first")
        spec = self.registry.lookup(request.command)
        if spec.raw:
            cfg: Any = tuple(request.tokens or ()) if request.tokens is not None else _raw_from_values(request)
        else:
            values = (bind_tokens(spec.name, request.tokens, spec.config, spec.positionals)
                      if request.tokens is not None else dict(request.values or {}))
            defaults = self.server.command_defaults(spec)
            cfg = build_config(spec.name, spec.config, defaults, values)
        self.admit(spec)
        if spec.kind == "job":
            sharing = self.server.devices.sharing
            for name in spec.devices:  # fail before a job exists, not half-way through it
                if sharing.claimed_by(name):
                    raise Busy(f"{spec.name}: {sharing.claim_sentence(name)}")
                self.server.devices[name].require_healthy()
        if spec.validate is not None:
            spec.validate(self.server, cfg)
        return spec, cfg

    def submit(self, request: Request, session: Session, sink: ReplySink) -> None:
        """Run one command; its final reply reaches `sink` now or later. Never raises."""
        try:
            spec, cfg = self.prepare(request, session)
            if spec.kind == "job":
                outcome: Any = self.start_job(spec, cfg, request.line or request.command, sink)
            else:
                module = spec.module.name if spec.module else None
                outcome = spec.handler(Call(self.server, session, request, sink, module), cfg)
        except RvsError as exc:
            sink.error(exc)
            return
        except Exception as exc:  # keep the server up, tell the client what happened or where to look
            sink.error(self._unexpected(request.command, exc))
            return
        if inspect.isawaitable(outcome):
            asyncio.ensure_future(self._deliver(request.command, outcome, sink))
        else:
            sink.ok(outcome or {})

    async def _deliver(self, command: str, outcome: Awaitable[Any], sink: ReplySink) -> None:
        try:
            result = await outcome
        except RvsError as exc:
            sink.error(exc)
        except Exception as exc:
            sink.error(self._unexpected(command, exc))
        else:
            sink.ok(result or {})

    def _unexpected(self, where: str, exc: Exception) -> RvsError:
        """An exception no command turned into a reply. A file of the data directory that someone
        removed while the command used it is not a bug: say which; anything else is."""
        missing = _missing_data_file(exc, self.server.data_dir)
        if missing is None:
            return self._internal(where)
        log.warning("%s: %s was removed while in use (%s)", where, missing, exc)
        return WrongMode(f"{missing} was removed while {where} used it; nothing more was done (run the "
                         f"command that makes it again)")

    def _internal(self, where: str) -> InternalError:
        log.error("internal error in %s\n%s", where, traceback.format_exc())
        return InternalError(f"{where} failed; the traceback is in the log {self.server.log_path}")

    # -- jobs -----------------------------------------------------------------------------------

    def start_job(self, spec: CommandSpec, cfg: Any, line: str, sink: ReplySink,
                  recovery: RecoverySet | None = None) -> asyncio.Future:
        """Start a job in the worker thread; the future gives its OK data or raises its error."""
        server = self.server
        loop = asyncio.get_running_loop()
        job_id = recovery.job if recovery else server.job_counter.next()
        job = Job(job_id, spec.name, line)
        rset = None
        if spec.resumable:
            rset = recovery or RecoverySet(job=job_id, command=spec.name, options=cfg.model_dump(mode="json"),
                                           line=line, devices=list(spec.devices))
            rset.reason = "running"
            server.recovery.save(rset)
        resume = recovery.state if recovery else None

        def on_progress(percent: float, message: str) -> None:
            loop.call_soon_threadsafe(self._progress, job, sink, percent, message)

        ctx = JobContext(job=job, server=server, module=spec.module.name if spec.module else None,
                         recovery_set=rset, store=server.recovery if rset else None, resume=resume,
                         on_progress=on_progress)
        self.job = job
        self._announce_mode()
        log.info("job %s start: %s%s", job_id, line, " (continued)" if recovery else "")
        server.publish("progress", {"job": job_id, "command": spec.name, "percent": 0, "message": "started"})
        work = loop.run_in_executor(self._executor, _run_handler, spec, ctx, cfg)
        back_to_break = self._base_mode == Mode.BREAK and spec.name in BREAK_MODE_JOBS
        self._job_future = asyncio.ensure_future(self._finish(job, ctx, rset, work, back_to_break))
        return self._job_future

    def _progress(self, job: Job, sink: ReplySink, percent: float, message: str) -> None:
        sink.progress(percent, message)
        self.server.publish("progress", {"job": job.id, "command": job.command, "percent": round(percent),
                                         "message": message})

    async def _finish(self, job: Job, ctx: JobContext, rset: RecoverySet | None,
                      work: Awaitable[Any], back_to_break: bool = False) -> dict[str, Any]:
        store = self.server.recovery
        keep_reason: str | None = None  # why the recovery set is kept; None drops it
        outcome = "failed"
        try:
            result = await work
            outcome = "finished"
            return {"job": job.id, **(result or {})}
        except JobInterrupted as exc:
            keep_reason = exc.reason
            raise Interrupted(self._stopped_message(job, f"interrupted by {exc.reason}", rset),
                              data=self._recovery_data(rset)) from None
        except (DeviceFault, DeviceError, Timeout) as exc:
            err = exc if isinstance(exc, RvsError) else _device_error(exc)
            # Worth resuming only if the job got as far as its first checkpoint.
            kept = rset if rset is not None and rset.state is not None else None
            keep_reason = err.reason if kept is not None else None
            raise type(err)(f"{err.message}; {self._stopped_message(job, 'stopped', kept)}",
                            data=self._recovery_data(kept)) from None
        except WorkerDied as exc:
            # The server lives on; the step can be tried again with `continue` (native.py).
            keep_reason = "worker-died" if rset is not None else None
            stopped = f"recovery set kept; {self._stopped_message(job, 'stopped', rset)}" if rset is not None \
                else self._stopped_message(job, "stopped", None)
            raise InternalError(f"{exc}; {stopped}", data=self._recovery_data(rset)) from None
        except RvsError:
            raise
        except Exception as exc:
            full = retention.enospc_of(exc)  # a full disk (or the storage cap), wherever the job wrote
            if full is None:
                raise self._unexpected(f"job {job.id} ({job.command})", exc) from None
            keep_reason = "storage" if rset is not None else None
            raise StorageFull(f"{self._storage_sentence(full)}; {self._stopped_message(job, 'stopped', rset)}; "
                              f"free space (products --prune), then continue", data=self._recovery_data(rset)) from None
        finally:
            for product in ctx.products:  # a product the job did not finish says why in its manifest
                if not product.finished:
                    try:
                        product.finish("interrupted" if keep_reason else "failed")
                    except OSError as exc:  # a full disk: its files are whole, only the manifest is missing
                        log.warning("job %s: the manifest of %s is not written: %s", job.id, product.name, exc)
            if rset is not None:
                if keep_reason is None:
                    store.delete(rset.job)
                else:
                    rset.reason = keep_reason
                    rset.percent = job.percent
                    try:
                        store.save(rset)
                    except OSError as exc:  # the set saved at its last checkpoint stays, still usable
                        log.warning("job %s: recovery set not updated: %s", job.id, exc)
            self.job = None
            job.done.set()
            # A job that can be continued leaves the server in break mode, and so does a reset run in
            # it; anything else leaves it in standby.
            can_continue = keep_reason is not None and rset is not None
            self._base_mode = Mode.BREAK if can_continue or back_to_break else Mode.STANDBY
            log.info("job %s end (%s)", job.id, keep_reason or outcome)
            self._announce_mode()
            self._apply_retention(f"after job {job.id}")

    def _storage_sentence(self, exc: OSError) -> str:
        """`no space left writing PATH: N MiB free on DIR` (under the cap: what it leaves)."""
        root = self.server.products.root
        path = Path(os.fsdecode(exc.filename)) if exc.filename else root
        cap = retention.files.storage_cap(root)
        free = retention.free_space(path, root, cap)
        where = f"under the storage cap of {retention.human_bytes(cap)}" if cap else f"on {self.server.data_dir}"
        log.error("no space left writing %s (%s): %s free %s", path, exc.strerror, free, where)
        return f"no space left writing {path}: {retention.human_bytes(free)} free {where}"

    def _apply_retention(self, why: str) -> None:
        """The retention rule (server.toml [storage]) in a thread, after a job; it logs what it removed."""
        def run() -> None:
            try:
                retention.prune(self.server, why)
            except Exception:
                log.exception("retention (%s) failed", why)
        try:
            asyncio.get_running_loop().run_in_executor(None, run)
        except RuntimeError:  # no loop: the server is going away
            pass

    @staticmethod
    def _stopped_message(job: Job, how: str, rset: RecoverySet | None) -> str:
        text = f"job {job.id} ({job.command}) {how} at {job.percent:.0f}%"
        return f"{text}; recovery={rset.job}" if rset else f"{text}; not resumable"

    @staticmethod
    def _recovery_data(rset: RecoverySet | None) -> dict[str, Any]:
        return {"recovery": rset.job} if rset else {}

    async def wait_job(self, job: Job, timeout_s: float) -> bool:
        """Wait for a job to end (after an interrupt request); False on timeout."""
        future = self._job_future
        if future is None or job.done.is_set():
            return True
        done, _ = await asyncio.wait({future}, timeout=timeout_s)
        return bool(done)

    def shutdown(self) -> None:
        self._executor.shutdown(wait=False, cancel_futures=True)


def _run_handler(spec: CommandSpec, ctx: JobContext, cfg: Any) -> Any:
    """The job's handler, in the worker thread; with emulated devices, after the simulated world
    being built in the background is ready (see SimulatedTestbed.wait_for_build)."""
    devices = ctx.devices
    if spec.devices and devices.simulated:
        if not devices.testbed.ready:
            ctx.progress(0.0, "waiting for the simulated world to be built")
        devices.testbed.wait_for_build()
    with devices.sharing.job_running():   # what the job takes it holds until it ends (devices/sharing.py)
        return spec.handler(ctx, cfg)


def _missing_data_file(exc: Exception, data_dir: Path) -> str | None:
    """The data-directory path (relative) that `exc` found missing, or None."""
    filename = getattr(exc, "filename", None)
    if not isinstance(exc, (FileNotFoundError, NotADirectoryError)) or not filename:
        return None
    path = Path(os.fsdecode(filename)).absolute()
    return str(path.relative_to(data_dir)) if path.is_relative_to(data_dir) else None


def _device_error(exc: Exception) -> RvsError:
    name = getattr(exc, "device", None) or "device"
    text = str(exc)
    if not text.startswith(name):  # drivers' messages mostly begin with the device's name already
        text = f"{name}: {text}"
    if isinstance(exc, DeviceTimeout):
        return Timeout(text)
    return DeviceError(text)


def map_device_errors(exc: Exception) -> RvsError:
    """Driver exceptions become ERR 503 / 504 naming the device and what it said."""
    return _device_error(exc)


def _raw_from_values(request: Request) -> tuple[str, ...]:
    """Raw commands (check, help) called over JSON: their `line` or `command` argument, split."""
    import shlex
    values = dict(request.values or {})
    text = values.get("line") or values.get("command") or ""
    return tuple(shlex.split(str(text)))


__all__ = ["Module", "CommandSpec", "Registry", "Dispatcher", "Request", "Session", "Call", "NoOptions",
           "ReplySink", "Mode", "MODES", "map_device_errors"]
