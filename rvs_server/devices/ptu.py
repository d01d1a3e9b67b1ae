"""The pan-tilt unit device: the PTU-D46 driver over a serial port or over the emulator's pty."""
from __future__ import annotations

import threading
from typing import Any, Literal

from pydantic import Field

from drivers.errors import DeviceFault
from drivers.sim.clock import SimClock

from ..config import Settings
from .base import Device, log

SIM_REPLY_TIMEOUT_S = 10.0
POLL_MISSES_FOR_FAULT = 3


class PtuDeviceConfig(Settings):
    enabled: bool = True
    backend: Literal["sim", "serial"] = Field("sim", description="sim: the emulator on a pseudo-terminal")
    port: str = Field("/dev/ttyS0", description="serial device or pyserial URL, for backend serial")
    baudrate: int = Field(9600, gt=0)
    timeout_s: float = Field(2.0, gt=0, le=60, description="read timeout of one command, wall seconds")
    poll_interval_s: float = Field(0.1, gt=0, le=10, description="how often the position is read, wall s")
    park_pan_deg: float = 0.0
    park_tilt_deg: float = 0.0
    park_on_quit: bool = True


class PtuDevice(Device):
    """The pan-tilt unit: the PTU-D46 driver over a serial port or over the emulator's pty."""

    name = "ptu"

    def __init__(self, config: PtuDeviceConfig, clock: SimClock, testbed: Any = None):
        super().__init__()
        self.config = config
        self.clock = clock
        self.testbed = testbed  # the simulated test bed takes the unit's true angles from here
        self.driver: Any = None
        self.emulator: Any = None
        self._line: Any = None  # the emulator's pseudo-terminal
        self._position: tuple[float, float] | None = None
        self._stop = threading.Event()
        self._poller: threading.Thread | None = None

    def open(self) -> None:
        if not self.config.enabled:
            self.health = "off"
            return
        from drivers.ptu import PtuD46
        from drivers.ptu_emulator import PtuEmulator
        try:
            if self.config.backend == "sim":
                if self.emulator is None:
                    fault = self.testbed.faults["ptu"] if self.testbed is not None else None
                    self.emulator = PtuEmulator(self.clock, fault=fault)
                    self._line = self.emulator.serve_pty()
                    if self.testbed is not None:
                        self.testbed.ptu_angles = self.emulator.true_angles_deg
                self.url = self._line.path
            else:
                self.url = self.config.port
            timeout = self.config.timeout_s
            if self.config.backend == "sim":
                # The emulator shares the interpreter with the server: while a long C call holds it
                # (Open3D building a world, aligning clouds) it answers late, through no fault of a unit.
                timeout = max(timeout, SIM_REPLY_TIMEOUT_S)
            self.driver = PtuD46(self.url, clock=self.clock, baudrate=self.config.baudrate, reply_timeout_s=timeout)
            self.driver.open()
            self._position = self.driver.position()
            self.health, self.last_error = "ok", ""
        except (DeviceFault, OSError) as exc:
            self._fault(exc)
            return
        self._stop.clear()
        self._poller = threading.Thread(target=self._poll, name="rvs-ptu-poll", daemon=True)
        self._poller.start()

    def _poll(self) -> None:
        """Keep the position fresh so `status` answers at once, even while a job holds the unit. A
        unit that stopped answering is left alone until a command talks to it (a job, continue's
        check, reset): each poll would hold the line for a whole read timeout."""
        missed = 0
        while not self._stop.wait(self.config.poll_interval_s):
            if self.driver.not_answering:
                continue
            try:
                self._position = self.driver.position()
                missed = 0
                if self.health == "fault" and self.last_error.startswith("not answering"):
                    self.health, self.last_error = "ok", ""
            except DeviceFault as exc:
                missed += 1  # one late answer on a busy host is not a dead unit; three in a row are
                if self.health == "ok" and missed >= POLL_MISSES_FOR_FAULT:
                    self._fault(DeviceFault(f"not answering: {exc}", "ptu"))
            except Exception as exc:  # a closed port during shutdown
                if self._stop.is_set():
                    return
                self._fault(exc)

    def live_fault(self) -> str | None:
        """Set from the first exchange the unit left unanswered (a job's or the poller's) until it
        answers again, so status shows a silent unit at once."""
        return self.driver.not_answering if self.driver is not None else None

    def position(self) -> tuple[float, float] | None:
        return self._position if self.health == "ok" and not self.live_fault() else None

    def read_position(self) -> tuple[float, float]:
        self._position = self.driver.position()
        return self._position

    def check(self) -> None:
        if not self.config.enabled:
            self.health = "off"
            return
        if self.driver is None:
            self.open()
            return
        try:
            self.driver.check()
            self.health, self.last_error = "ok", ""
        except (DeviceFault, OSError) as exc:
            self._fault(exc)

    def reset(self) -> None:
        """Re-initialise: recalibrate the axes and run the start-up sequence again."""
        self.close()
        self.open()
        if self.health == "ok":
            try:
                self.driver.reset()
                self.driver.open()
            except (DeviceFault, OSError) as exc:
                self._fault(exc)

    def park(self) -> None:
        if self.health != "ok":
            return
        try:
            self.driver.move_to(self.config.park_pan_deg, self.config.park_tilt_deg)
            self.driver.wait_until_stopped(timeout_s=60.0)
        except (DeviceFault, OSError) as exc:
            self._fault(exc)

    def close(self) -> None:
        self.health = "off"  # first: commands on the event loop read health, then the driver
        self._stop.set()
        if self._poller is not None:
            self._poller.join(timeout=2)
            self._poller = None
        if self.driver is not None:
            try:
                self.driver.close()
            except Exception as exc:  # closing must never stop a shutdown
                log.warning("ptu close: %s", exc)
            self.driver = None
        if self._line is not None:
            self._line.stop()
            self._line = None
            self.emulator = None
        self.health = "off"
