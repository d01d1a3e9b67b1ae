"""The server as a command module sees it: a typed Protocol, so the seam between the core and the
capabilities is written down once and checked by the type checker instead of passed as `Any`.

`app.Server` implements it. A capability reaches the rest of the server only through these names,
and through `JobContext` / `Call`, which add the command's own settings and state.

This module sits below the jobs, the dispatcher and the activities (they import it, it imports none of
them, not even for the type checker): what it shows of the dispatcher and the registry are the small
protocols below, and `dispatch.DispatchHost` is the whole server as the dispatcher, the transports and
the system commands see it. tests/core/test_import_directions.py keeps every circle out.
"""
from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

if TYPE_CHECKING:
    import logging

    from drivers.sim.clock import SimClock
    from rvs_server.activities import Activities
    from rvs_server.devices import Devices
    from rvs_server.devices.calibration import Calibration
    from rvs_server.native import NativeWorker
    from rvs_server.products.manifests import Products
    from rvs_server.recovery import RecoveryStore
    from rvs_server.server_config import ServerConfig


class RunningJob(Protocol):
    """The job that runs, as the server's parts see it (jobs.Job)."""

    @property
    def id(self) -> str: ...

    @property
    def products(self) -> list[str]: ...


class Dispatching(Protocol):
    """What every part may read of the server's dispatcher (dispatch.Dispatcher gives all of it)."""

    @property
    def job(self) -> RunningJob | None: ...

    @property
    def mode(self) -> str: ...

    @property
    def sleep_until(self) -> float | None: ...


class Commands(Protocol):
    """What every part may read of the command registry (dispatch.Registry): the modules by name."""

    @property
    def modules(self) -> Mapping[str, object]: ...


class Host(Protocol):
    """What a command module may use of the server that runs it."""

    version: str
    config_dir: Path
    data_dir: Path
    shared_dir: Path
    settings: ServerConfig         # server.toml
    token: str | None
    started: float                   # time.monotonic() at start
    log_handlers: list[logging.Handler]
    clock: SimClock
    devices: Devices
    recovery: RecoveryStore
    products: Products
    activities: Activities
    native: NativeWorker           # the heavy native steps of jobs, in a child process (native.py)
    stopping: bool                   # a shutdown was asked for

    @property
    def log_path(self) -> Path | None: ...

    @property
    def dispatcher(self) -> Dispatching: ...

    @property
    def registry(self) -> Commands: ...

    def settings_of(self, module: str) -> Any:
        """A module's settings (configs/<module>.toml), as last loaded or reloaded."""

    def state_of(self, module: str) -> Any:
        """A module's state on this server, made by its Module's `state` factory on first use."""

    def calibration(self) -> Calibration:
        """The calibration the maps use."""

    def publish(self, topic: str, data: dict[str, Any]) -> None:
        """An event to the subscribers (event loop thread)."""

    def publish_threadsafe(self, topic: str, data: dict[str, Any]) -> None:
        """An event to the subscribers, from a job's thread."""

    def reload_configuration(self) -> None: ...

    def reopen_devices(self) -> None: ...

    def shutdown(self) -> Any: ...


class ModuleScope:
    """What a handler's context (JobContext, Call) gives of its module: its settings and state, and
    other modules' settings. Needs `server` and `module` (the module's name, None for none)."""

    server: Host
    module: str | None

    @property
    def settings(self) -> Any:
        """The command's module's settings, from configs/<module>.toml."""
        return self.server.settings_of(self.module) if self.module else None

    def settings_of(self, module: str) -> Any:
        """Another module's settings (read them; the module that owns them says what they mean)."""
        return self.server.settings_of(module)

    @property
    def state(self) -> Any:
        """The command's module's state on this server (Module's `state` factory)."""
        return self.server.state_of(self.module) if self.module else None
