"""The server as a command module sees it: a typed Protocol, so the seam between the core and the
capabilities is written down once and checked by the type checker instead of passed as `Any`.

`app.Server` implements it. A capability reaches the rest of the server only through these names,
and through `JobContext` / `Call`, which add the command's own settings and state.
"""
from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

if TYPE_CHECKING:
    import logging

    from drivers.sim.clock import SimClock
    from rvs_server.activities import Activities
    from rvs_server.config import Settings
    from rvs_server.devices import Devices
    from rvs_server.devices.calibration import Calibration
    from rvs_server.dispatch import CommandSpec, Dispatcher, Registry
    from rvs_server.jobs import RecoveryStore
    from rvs_server.native import NativeWorker
    from rvs_server.products.manifests import Products


class Host(Protocol):
    """What a command module may use of the server that runs it."""

    version: str
    config_dir: Path
    data_dir: Path
    shared_dir: Path
    settings: Settings             # server.toml
    token: str | None
    started: float                   # time.monotonic() at start
    log_path: Path | None
    log_handlers: list[logging.Handler]
    clock: SimClock
    devices: Devices
    recovery: RecoveryStore
    products: Products
    dispatcher: Dispatcher
    activities: Activities
    native: NativeWorker           # the heavy native steps of jobs, in a child process (native.py)
    stopping: bool                   # a shutdown was asked for
    registry: Registry

    def settings_of(self, module: str) -> Any:
        """A module's settings (configs/<module>.toml), as last loaded or reloaded."""

    def state_of(self, module: str) -> Any:
        """A module's state on this server, made by its Module's `state` factory on first use."""

    def command_defaults(self, spec: CommandSpec) -> dict[str, Any]:
        """A command's option defaults from its module's TOML file."""

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
