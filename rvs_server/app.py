"""Builds an RVS server from a configuration directory and runs it: devices, modules, transports.

    rvs-server [--host H] [--port P] [--zmq-port Z] [--web-port W] [--data-dir D] [--config-dir C]
               [--sim-speed S] [--token-file F] [--world-seed N | --world FILE]

Exit status: 0 after `quit` or a signal, 2 when a configuration file or an option is invalid.
"""
from __future__ import annotations

import argparse
import asyncio
import functools
import ipaddress
import logging
import os
import signal
import stat
import sys
import time
from collections.abc import Awaitable, Mapping
from dataclasses import dataclass
from logging.handlers import RotatingFileHandler
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

import zmq
from pydantic import ValidationError

from drivers.sim.clock import SimClock
from drivers.sim.config import WorldConfig
from rvs_server.devices.calibration import Calibration, CalibrationConfig, build_calibration
from rvs_server.products.manifests import Products
from rvs_server.products.retention import prune

from . import __version__
from .activities import Activities
from .config import ConfigError, load_model, read_toml, validate_section
from .devices import Devices, DevicesConfig
from .dispatch import CommandSpec, Dispatcher, Module, Registry, Session
from .files import remove_stale_temporaries, set_storage_cap
from .jobs import JobCounter
from .native import NativeWorker
from .protocol import BadRequest
from .recovery import RecoveryStore
from .server_config import ServerConfig
from .transports.tcp import claim_tcp_port, start_tcp
from .transports.zmq import ZmqTransport
from .web import WebView

if TYPE_CHECKING:
    from pydantic_core import InitErrorDetails

log = logging.getLogger("rvs")


@dataclass(frozen=True)
class Configuration:
    """Everything read from the configuration directory, as one value: built whole, then swapped in."""

    settings: ServerConfig
    devices: DevicesConfig
    world: WorldConfig
    world_file: Path | None
    calibration: CalibrationConfig
    modules: dict[str, ModuleConfig]


def read_configuration(config_dir: Path, overrides: Mapping[str, Any], modules: list[Module]) -> Configuration:
    """Read and validate every file; raises ConfigError naming the file and the field."""
    server_keys = set(ServerConfig.model_fields)
    settings = load_model(config_dir / "server.toml", ServerConfig,
                          {k: v for k, v in overrides.items() if k in server_keys})
    devices = load_model(config_dir / "devices.toml", DevicesConfig)
    seed = overrides.get("world_seed")
    world = load_model(config_dir / "world.toml", WorldConfig, {"seed": seed} if seed is not None else None)
    world_file = Path(overrides["world"]) if overrides.get("world") else None
    if world_file is not None and not world_file.exists():
        raise ConfigError(f"--world {world_file}: no such file")
    calibration = load_model(config_dir / "calibration.toml", CalibrationConfig)
    module_configs = {m.name: load_module_config(config_dir, m) for m in modules}
    return Configuration(settings, devices, world, world_file, calibration, module_configs)


def all_modules() -> list[Module]:
    from rvs_server import (
        hazard,
        hopping,
        imaging,
        mapping,
        navigation,
        orientation,
        ptu,
        routes,
        simulation,
        system,
        tracking,
    )
    return [system.module, ptu.module, imaging.module, mapping.module, navigation.module, hopping.module,
            routes.module, hazard.module, orientation.module, simulation.module, tracking.module]


class ModuleConfig:
    """A module's settings and its commands' default options, from `configs/<module>.toml`."""

    def __init__(self, settings: Any, defaults: dict[str, dict[str, Any]]):
        self.settings = settings
        self.defaults = defaults


def load_module_config(config_dir: Path, module: Module) -> ModuleConfig:
    path = config_dir / f"{module.name}.toml"
    data = read_toml(path)
    commands = {spec.name: spec for spec in module.commands}
    defaults: dict[str, dict[str, Any]] = {}
    for key in [k for k in data if k in commands]:
        table = data.pop(key)
        if not isinstance(table, dict):
            raise ConfigError(f"{path}: [{key}] must be a table of default options")
        _validate_defaults(path, commands[key], table)
        defaults[key] = {k.replace("-", "_"): v for k, v in table.items()}
    if module.settings is None:
        if data:
            raise ConfigError(f"{path}: field {next(iter(data))}: unknown; this module has no settings, "
                              f"only tables named after its commands: {', '.join(commands)}")
        settings = None
    else:
        settings = validate_section(module.settings, data, str(path))
    return ModuleConfig(settings, defaults)


def _validate_defaults(path: Path, spec: CommandSpec, table: dict[str, Any]) -> None:
    """Defaults must be valid values of the command's options; required options may stay missing."""
    from .config import describe_validation_error
    values = {k.replace("-", "_"): v for k, v in table.items()}
    try:
        spec.config.model_validate(values)
    except ValidationError as exc:
        real = [e for e in exc.errors() if e["type"] != "missing"]
        if real:
            raise ConfigError(describe_validation_error(
                ValidationError.from_exception_data(exc.title, cast("list[InitErrorDetails]", real)), spec.config,
                f"{path} [{spec.name}]",
                name_of=lambda loc: "field " + ".".join(str(p) for p in loc))) from None


def read_token(path: Path) -> str:
    """The token file must be readable by its owner only, or anyone on the machine could use it."""
    try:
        info = path.stat()
    except OSError as exc:
        raise ConfigError(f"token file {path}: {exc.strerror}") from None
    if info.st_mode & (stat.S_IRWXG | stat.S_IRWXO):
        raise ConfigError(f"token file {path}: mode {stat.filemode(info.st_mode)} lets others read it; "
                          f"chmod 600 {path}")
    if info.st_uid != os.getuid():
        raise ConfigError(f"token file {path}: owned by uid {info.st_uid}, not by this user ({os.getuid()})")
    token = path.read_text().strip()
    if len(token) < 8:
        raise ConfigError(f"token file {path}: the token must be at least 8 characters")
    return token


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


class Server:
    def __init__(self, config_dir: Path, overrides: Mapping[str, Any] | None = None):
        self.version = __version__
        self.config_dir = config_dir
        self.overrides = dict(overrides or {})
        self.modules = all_modules()
        self.registry = Registry(self.modules)
        self._module_states: dict[str, Any] = {}
        self._load_configuration()  # raises ConfigError; nothing is started before it passed
        self.data_dir = Path(self.settings.data_dir).resolve()
        self.data_dir.mkdir(parents=True, exist_ok=True)
        self.shared_dir = Path(self.settings.shared_dir).resolve() if self.settings.shared_dir else \
            self.data_dir / "shared"
        self.token = read_token(Path(self.settings.token_file)) if self.settings.token_file else None
        s = self.settings
        own_ports = {s.port} | ({s.zmq_port, s.zmq_port + 1} if s.zmq_port else set())
        if s.web_port and s.web_port in own_ports:
            raise ConfigError(f"web_port {s.web_port} is one of the server's other ports (the text port, "
                              f"the ZeroMQ ROUTER or the PUB port on zmq_port + 1): choose another")
        if not is_loopback(self.settings.host) and self.token is None:
            raise ConfigError(f"host {self.settings.host} is not loopback: listening there requires "
                              f"--token-file (a file only its owner can read)")
        self.clock = SimClock(self.settings.sim_speed)
        self.recovery = RecoveryStore(self.data_dir / "recovery")
        self.products = Products(self.data_dir)
        self.job_counter = JobCounter(self.data_dir / "jobs.counter")
        self.sessions: set[Session] = set()
        self.dispatcher = Dispatcher(self)
        self.activities = Activities()  # background loops beside the job (activities.py)
        self.devices = Devices(self.devices_config, self.clock, self.world_config, self.world_file)
        self.zmq: ZmqTransport | None = None
        self.web: WebView | None = None  # the web view, when web_port is not 0
        self.native = NativeWorker(self.settings.worker_memory_mb or None,   # started with the devices
                                   in_process=not self.settings.native_worker)
        self.started = time.monotonic()
        self.log_handlers: list[logging.Handler] = []
        self.log_path = self._start_log()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stopped: asyncio.Event | None = None
        self._tcp: asyncio.Server | None = None
        self._zmq_task: asyncio.Future | None = None
        self._start_task: asyncio.Future | None = None
        self._opening: asyncio.Future | None = None  # devices being opened, in a worker thread
        self._shutdown: asyncio.Future | None = None
        self.stopping = False  # a shutdown was asked for: start-up goes no further, jobs are refused
        self.ready = False  # the ports are open and every device started
        remove_stale_temporaries(self.data_dir)  # writes a kill cut short (rvs_server/files.py)
        self._use_storage_settings()
        prune(self, "start-up")  # the retention rule (products/retention.py); logs what it removed

    # -- configuration --------------------------------------------------------------------------

    def _load_configuration(self) -> None:
        self._use(read_configuration(self.config_dir, self.overrides, self.modules))

    def reload_configuration(self) -> None:
        """`reinit`: read every file again. The whole new configuration is built before any of it is
        used, so a refused reload changes nothing."""
        try:
            configuration = read_configuration(self.config_dir, self.overrides, self.modules)
        except ConfigError as exc:
            raise BadRequest(f"configuration not reloaded: {exc}") from None
        self._use(configuration)
        self._use_storage_settings()

    def _use_storage_settings(self) -> None:
        set_storage_cap(self.data_dir / "products", int(self.settings.storage.cap_gib * 1024 ** 3))

    def _use(self, c: Configuration) -> None:
        self.settings, self.devices_config, self.world_config = c.settings, c.devices, c.world
        self.world_file, self.calibration_config, self.module_configs = c.world_file, c.calibration, c.modules

    def settings_of(self, module: str) -> Any:
        return self.module_configs[module].settings

    def state_of(self, module: str) -> Any:
        """A module's state lives as long as the server (reinit keeps it), made on first use."""
        if module not in self._module_states:
            factory = self.registry.modules[module].state
            if factory is None:
                raise KeyError(f"module {module} keeps no state")
            self._module_states[module] = factory(self)
        return self._module_states[module]

    def calibration(self) -> Calibration:
        """The calibration the maps use: from the file, or the simulated rover's calibrated mounts."""
        testbed = self.devices.testbed if self.devices.simulated else None
        return build_calibration(self.calibration_config, testbed)

    def command_defaults(self, spec: CommandSpec) -> dict[str, Any]:
        if spec.module is None:
            return {}
        return self.module_configs[spec.module.name].defaults.get(spec.name, {})

    def reopen_devices(self) -> None:
        """reinit: devices from the reloaded configuration; the world is rebuilt only if it changed."""
        old = self.devices
        old.close_all()
        same_world = old.testbed.world_config == self.world_config and old.testbed.world_file == self.world_file
        self.devices = Devices(self.devices_config, self.clock, self.world_config, self.world_file,
                               testbed=old.testbed if same_world else None, sharing=old.sharing)
        self.devices.rover.take_over(old.rover)   # the rover has not moved: its estimate stays
        self.devices.hopper.take_over(old.hopper)   # on the same world the hopper stays where it landed
        self.devices.open_all()

    # -- logging and events ---------------------------------------------------------------------

    def _start_log(self) -> Path:
        logs = self.data_dir / "logs"
        logs.mkdir(parents=True, exist_ok=True)
        path = logs / f"rvs-{time.strftime('%Y%m%d-%H%M%S')}-{os.getpid()}.log"
        root = logging.getLogger("rvs")
        root.setLevel(self.settings.log_level)
        fmt = logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s")
        to_file = BoundedLogFile(path, int(self.settings.log_file_max_mb * 1e6), self.settings.log_files_kept)
        to_file.setFormatter(fmt)
        to_stderr = logging.StreamHandler(sys.stderr)
        to_stderr.setFormatter(fmt)
        to_events = _EventHandler(self)
        to_events.setLevel(logging.INFO)
        for handler in (to_file, to_stderr, to_events):
            root.addHandler(handler)
        self.log_handlers = [to_file, to_stderr, to_events]
        return path

    def publish(self, topic: str, data: Mapping[str, Any]) -> None:
        """Send an event to subscribed connections and the PUB socket (event-loop thread only)."""
        for session in list(self.sessions):
            if topic in session.topics and session.send_event is not None:
                session.send_event(topic, data)
        if self.zmq is not None:
            self.zmq.publish(topic, data)
        if self.web is not None:  # the third consumer: browsers' event streams (rvs_server/web/events.py)
            self.web.publish(topic, data)

    def publish_threadsafe(self, topic: str, data: Mapping[str, Any]) -> None:
        loop = self._loop
        if loop is None or loop.is_closed():
            return
        try:
            if threading_is_loop(loop):
                self.publish(topic, data)
            else:
                loop.call_soon_threadsafe(self.publish, topic, dict(data))
        except RuntimeError:  # the loop closed between the check and the call
            pass

    # -- running --------------------------------------------------------------------------------

    async def start(self) -> None:
        """Claim the ports, start every device, then open the ports (see docs/PROTOCOL.md, start-up).

        Until the server is ready the text port is bound but not listening (connections are
        refused) and ZeroMQ requests wait in their queue: nothing is answered before every device
        is started and every command can run. A shutdown requested meanwhile ends start-up at the
        next step instead."""
        s = self.settings
        # Claim first: a taken port must stop start-up before any device moves or a world is built.
        listener = claim_tcp_port(s.host, s.port)
        try:
            if s.web_port:
                self.web = WebView(self)
                self.web.claim(s.host, self._web_port())
            self.zmq = ZmqTransport(self)
            self.zmq.bind(s.host, s.zmq_port)
            if not self.stopping:
                self._opening = asyncio.get_running_loop().run_in_executor(None, self._open_devices)
                await asyncio.shield(self._opening)
            if self.stopping:
                return
            self._tcp = await start_tcp(self, listener)
        finally:
            if self._tcp is None:
                listener.close()
                if self.web is not None:
                    self.web.release()
        if self.stopping:  # asked to stop while the listener was being set up
            return
        self._zmq_task = asyncio.ensure_future(self.zmq.serve())
        self.ready = True
        web = "off"
        if self.web is not None:  # listens only now: a browser never sees a half-started server
            web_host, web_port = await self.web.start()
            web = f"{web_host}:{web_port}"
        tcp_port = self._tcp.sockets[0].getsockname()[1]
        self.address = (s.host, tcp_port)
        log.info("RVS %s listening tcp=%s:%d zmq=%s pub=%s web=%s data=%s log=%s", self.version, s.host,
                 tcp_port, self.zmq.router_endpoint, self.zmq.pub_endpoint, web, self.data_dir, self.log_path)
        # One machine-readable line on stdout, for scripts and tests that start the server on port 0.
        print(f"rvs-server ready tcp={s.host}:{tcp_port} zmq={self.zmq.router_endpoint} "  # noqa: T201  an interface
              f"pub={self.zmq.pub_endpoint} web={web} pid={os.getpid()}", flush=True)

    def _web_port(self) -> int:
        """The web port to bind. A server started with `--port 0` (scripts and tests, often several side
        by side) picks a free web port too unless one was given, instead of all fighting over 7403."""
        s = self.settings
        if s.port == 0 and "web_port" not in s.model_fields_set:
            return 0
        return s.web_port

    def _open_devices(self) -> None:
        """Every device, and the simulated world they share: jobs never wait for it once ready."""
        self.native.start()          # the child imports its libraries while the devices open
        self.devices.open_all()
        for device in self.devices:
            if device.health == "fault":
                log.error("%s failed to open: %s (the server runs on; reset retries)", device.name,
                          device.last_error)
        if self.devices.simulated:
            self.devices.testbed.wait_for_build()

    async def run(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._stopped = asyncio.Event()
        self._start_task = asyncio.ensure_future(self.start())
        try:
            await self._start_task  # a taken port raises here
            await self._stopped.wait()
        finally:
            if self.web is not None:
                await self.web.close()

    def shutdown(self, reason: str = "quit") -> Awaitable[dict[str, Any]]:
        """Interrupt the job (keeping its recovery set), park and close devices, then stop. Safe to
        call in any state and any number of times: every call waits for the same one shutdown."""
        return asyncio.shield(self.begin_shutdown(reason))

    def begin_shutdown(self, reason: str) -> asyncio.Future:
        if self._shutdown is None:
            self.stopping = True
            self._shutdown = asyncio.ensure_future(self._stop(reason))
        return self._shutdown

    async def _stop(self, reason: str) -> dict[str, Any]:
        job = self.dispatcher.job
        try:
            await self.activities.stop_all()   # they borrow devices that are about to close
            if job is not None:
                job.request_interrupt(reason)
                await self.dispatcher.wait_job(job, self.settings.quit_timeout_s)
            if self._opening is not None:  # devices still opening: close them once they are open
                await asyncio.wait({self._opening})
            await asyncio.to_thread(self._park_and_close)
        except Exception:  # a bug; the process must end all the same
            log.exception("shutdown: closing the devices failed")
        finally:
            log.info("RVS stopping (%s)", reason)
            for handler in self.log_handlers:
                handler.flush()
            asyncio.get_running_loop().call_later(0.05, self._finish)
        return {"job": job.id if job else "none", "recovery": self.recovery.count(), "log": str(self.log_path)}

    def _park_and_close(self) -> None:
        for device in self.devices:
            if getattr(getattr(device, "config", None), "park_on_quit", False):
                device.park()
        self.devices.close_all()

    def _finish(self) -> None:
        for session in list(self.sessions):
            if session.close is not None:
                session.close()
        if self._tcp is not None:
            self._tcp.close()
        if self._zmq_task is not None:
            self._zmq_task.cancel()
        if self.zmq is not None:
            self.zmq.close()
            self.zmq = None
        self.dispatcher.shutdown()
        self.native.stop()
        log.info("RVS stopped")
        if self._stopped is not None:
            self._stopped.set()


def threading_is_loop(loop: asyncio.AbstractEventLoop) -> bool:
    try:
        return asyncio.get_running_loop() is loop
    except RuntimeError:
        return False


class _EventHandler(logging.Handler):
    """Log records become `log` events for subscribers (the `log` topic)."""

    def __init__(self, server: Server):
        super().__init__()
        self.server = server

    def emit(self, record: logging.LogRecord) -> None:
        if record.name.startswith("rvs.tcp") or record.name.startswith("rvs.zmq"):
            return  # connection chatter would echo every subscriber's own traffic back to it
        try:
            self.server.publish_threadsafe("log", {"level": record.levelname, "source": record.name,
                                                   "message": record.getMessage()})
        except Exception:
            self.handleError(record)


# ---------------------------------------------------------------------------------------------
# Command line


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="rvs-server", description="The Rover Vision System server.")
    parser.add_argument("--host", help="address to listen on (default 127.0.0.1)")
    parser.add_argument("--port", type=int, help="text (telnet) port (default 7400; 0 picks a free one)")
    parser.add_argument("--zmq-port", type=int, help="ZeroMQ ROUTER port; PUB on the next (default 7401)")
    parser.add_argument("--web-port", type=int, help="web view (HTTP) port, same host as --port (default 7403; "
                                                       "0 turns it off)")
    parser.add_argument("--data-dir", help="where products, logs and recovery sets go (default ./data)")
    parser.add_argument("--config-dir", default="./configs", help="configuration files (default ./configs)")
    parser.add_argument("--sim-speed", type=float, help="simulated seconds per wall second (default 1.0)")
    parser.add_argument("--token-file", help="file holding the token clients must send with auth")
    parser.add_argument("--world-seed", type=int, help="seed of the simulated world (default: configs/world.toml)")
    parser.add_argument("--world", help="a saved simulated world (.npz) to load instead of building one")
    return parser.parse_args(argv)


class BoundedLogFile(RotatingFileHandler):
    """A log file that rotates at `max_bytes` and keeps at most `kept` log files in its directory,
    this run's and earlier runs' together: a week of running cannot fill the disk."""

    def __init__(self, path: Path, max_bytes: int, kept: int):
        super().__init__(path, maxBytes=max_bytes, backupCount=kept - 1)
        self.kept = kept
        self.prune()

    def doRollover(self) -> None:
        super().doRollover()
        self.prune()

    def prune(self) -> None:
        folder = Path(self.baseFilename).parent
        logs = []
        for path in folder.glob("rvs-*.log*"):
            try:
                logs.append((path.stat().st_mtime, path))
            except FileNotFoundError:  # another server on this data directory pruned it
                pass
        for _, path in sorted(logs)[:-self.kept]:
            path.unlink(missing_ok=True)


def main(argv: list[str] | None = None) -> int:
    """Run the server. rvs_server/__main__.py blocks SIGINT and SIGTERM from the first instant; they
    are unblocked once the loop handles them, so one sent during start-up is delivered then."""
    args = parse_args(argv)
    overrides = {"host": args.host, "port": args.port, "zmq_port": args.zmq_port, "web_port": args.web_port,
                 "data_dir": args.data_dir,
                 "sim_speed": args.sim_speed, "token_file": args.token_file, "world_seed": args.world_seed,
                 "world": args.world}
    try:
        server = Server(Path(args.config_dir), overrides)
    except ConfigError as exc:
        print(f"rvs-server: {exc}", file=sys.stderr)  # noqa: T201  command-line error before logging exists
        return 2

    async def run() -> None:
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, functools.partial(_on_signal, server, sig))
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT, signal.SIGTERM})
        await server.run()

    try:
        asyncio.run(run())
    except (OSError, zmq.ZMQError) as exc:  # the port is taken, the address is not ours
        print(f"rvs-server: cannot listen: {exc}", file=sys.stderr)  # noqa: T201  command-line error on stderr
        server.devices.close_all()
        return 2
    finally:
        # The loop's handlers are gone; a signal while the interpreter winds down is no news.
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, signal.SIG_IGN)
    return 0


def _on_signal(server: Server, signum: int) -> None:
    log.info("%s received: stopping", signal.Signals(signum).name)
    server.begin_shutdown("quit")


if __name__ == "__main__":
    sys.exit(main())
