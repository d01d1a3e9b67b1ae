"""What every device wrapper shares: its health (`ok`, `fault`, `off`) and last error."""
from __future__ import annotations

import logging
import threading
from typing import Any, Literal

from drivers.errors import DeviceFault

from ..protocol import DeviceError
from .sharing import DeviceSharing

log = logging.getLogger("rvs.devices")

Health = Literal["ok", "fault", "off"]


class Device:
    """Health bookkeeping shared by every device."""

    name = "device"

    def __init__(self) -> None:
        self.health: Health = "off"
        self.last_error = ""
        self.sharing: DeviceSharing | None = None  # set by Devices: who may use it (devices/sharing.py)

    def _fault(self, exc: BaseException) -> None:
        self.health = "fault"
        self.last_error = str(exc)
        log.error("%s: %s", self.name, exc)

    def live_fault(self) -> str | None:
        """What the driver reports wrong right now (a frame that failed in a job, a unit that stopped
        answering), before check() or reset() has looked; None: nothing. Status shows it; a new job
        still may try the device, and finds out itself."""
        return None

    def require_healthy(self) -> None:
        """ERR 503 naming the device and its last error, unless it is ok."""
        if self.health != "ok":
            detail = f": {self.last_error}" if self.last_error else ""
            raise DeviceError(f"{self.name} is {self.health}{detail}")

    def require(self) -> Any:
        """The driver, or ERR 503 naming the device and its last error. Called in a job's thread,
        the job holds the device from now on (devices/sharing.py)."""
        self.require_healthy()
        if self.sharing is not None:
            self.sharing.job_uses(self.name)
        return self.ready_driver()

    def ready_driver(self) -> Any:
        """The driver of a healthy device, without taking it for a job: what an activity uses inside
        a borrow (DeviceSharing.borrow)."""
        self.require_healthy()
        return self.driver  # type: ignore[attr-defined]

    def health_items(self) -> dict[str, str]:
        """What status shows for this device."""
        return {f"dev.{self.name}": "fault" if self.health == "ok" and self.live_fault() else self.health}

    def open(self) -> None: ...
    def close(self) -> None: ...
    def check(self) -> None: ...
    def reset(self) -> None: ...
    def park(self) -> None: ...


class SensorDevice(Device):
    """A sensor that runs on a real backend or on the simulated test bed. The emulator needs the
    simulated world, which takes seconds to build, so it is made on first use (in the job thread)
    while the world builds in the background from start-up; a real backend is opened at once."""

    def __init__(self, config: Any, clock: Any, testbed: Any = None):
        super().__init__()
        self.config = config
        self.clock = clock
        self.testbed = testbed
        self.driver: Any = None
        self._lock = threading.Lock()

    def _make(self) -> None:
        """Open the driver the config names and keep it in self.driver."""
        raise NotImplementedError

    def open(self) -> None:
        if not self.config.enabled:
            self.health = "off"
            return
        if self.config.backend == "sim":
            self.testbed.prebuild()
            self.health, self.last_error = "ok", ""
            return
        try:
            self._make()
        except (DeviceFault, OSError, ValueError) as exc:
            self._fault(exc)

    def ready_driver(self) -> Any:
        self.require_healthy()
        with self._lock:
            if self.driver is None:
                try:
                    self._make()
                except (DeviceFault, OSError, ValueError) as exc:
                    self._fault(exc)
                    raise
        return self.driver

    def close(self) -> None:
        if self.driver is not None:
            try:
                self.driver.close()
            except Exception as exc:  # closing must never stop a shutdown
                log.warning("%s close: %s", self.name, exc)
            self.driver = None
        self.health = "off"
