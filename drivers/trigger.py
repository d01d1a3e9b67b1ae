"""Trigger box: one pulse makes every connected camera take a frame at the same instant.

The thesis' box sits on the PC's parallel port; setting data pin 2 (data bit 0) sends a trigger
pulse to both AVT cameras (an SR4000 trigger input could be added). This file holds
- `TriggerError`, `TriggerStatus` and `TriggerBox`, the interface: open(), close(), pulse(), status();
- `PpdevTrigger`, the real backend: Linux ppdev ioctls on /dev/parport0 (no third-party package;
  pyparallel wraps the same calls but is unmaintained);
- `EmulatedTrigger`, which calls every connected emulated camera at the simulated instant of the
  pulse, as the cable does.

pulse() returns the clock time of the pulse, so a grab can say when its frames were exposed.
"""
from __future__ import annotations

import errno
import fcntl
import logging
import os
import struct
import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass

from drivers.errors import DeviceFault
from drivers.sim.clock import SimClock
from drivers.sim.faults import FaultSwitch

log = logging.getLogger(__name__)

# ppdev ioctl request numbers on x86_64 (linux/ppdev.h: _IO('p', 0x8b) ... _IOW('p', 0x86, unsigned char)).
PPCLAIM = 0x708B
PPRELEASE = 0x708C
PPEXCL = 0x708F
PPWDATA = 0x40017086      # argument: one unsigned char, the new data register
PPDATADIR = 0x40047090    # argument: int, 0 = forward (the PC drives the data pins)

TRIGGER_BIT = 0x01        # data bit 0 is pin 2 of the DB-25 connector
IDLE_DATA = 0x00          # the other data pins are not wired in the box; hold them low
DEFAULT_PULSE_WIDTH_S = 0.001   # AVT trigger inputs need microseconds; 1 ms is safely seen


class TriggerError(DeviceFault):
    """The trigger box cannot be reached or refused an operation. The message names the device."""

    def __init__(self, detail: str, *, device: str):
        self.detail = detail
        super().__init__(f"{device}: {detail}", device=device)


@dataclass(frozen=True)
class TriggerStatus:
    """What a status reader sees: safe to read from any thread."""

    device: str
    is_open: bool
    pulses: int                      # pulses sent since the object was made
    last_pulse_s: float | None       # clock time of the last pulse
    last_error: str | None


class TriggerBox(ABC):
    """A box that sends one trigger pulse to every connected camera."""

    def __init__(self, device: str, clock: SimClock | None):
        self.device = device
        self._clock = clock if clock is not None else SimClock(1.0)
        self._lock = threading.Lock()
        self._is_open = False
        self._pulses = 0
        self._last_pulse_s: float | None = None
        self._last_error: str | None = None

    @abstractmethod
    def open(self) -> None: ...

    @abstractmethod
    def close(self) -> None: ...

    @abstractmethod
    def pulse(self) -> float:
        """Send one trigger pulse; return its clock time."""

    def status(self) -> TriggerStatus:
        with self._lock:
            return TriggerStatus(self.device, self._is_open, self._pulses, self._last_pulse_s, self._last_error)

    def __enter__(self) -> TriggerBox:
        self.open()
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    def unseen(self, at: float, detail: str) -> TriggerError:
        """The cameras report that the pulse sent at `at` reached none of them: the box (or its
        cable) failed, although the PC's side of it worked. Recorded for status() like any fault."""
        with self._lock:
            return self._fault(f"stopped answering: the trigger pulse at {at:.3f} s reached no camera ({detail}); "
                               "the trigger box or its cable is not working")

    def _fault(self, detail: str) -> TriggerError:
        """Record a fault for status() and build the error to raise (callers hold the lock)."""
        self._last_error = detail
        return TriggerError(detail, device=self.device)

    def _count_pulse(self, at: float) -> float:
        self._pulses += 1
        self._last_pulse_s = at
        self._last_error = None
        return at


# --------------------------------------------------------------------------------------------
# The real box on a parallel port
# --------------------------------------------------------------------------------------------

class PpdevTrigger(TriggerBox):
    """The trigger box on a parallel port through the Linux ppdev driver.

    open(): open the node, claim the port exclusively (PPEXCL must come before PPCLAIM), set the
    data pins to output and low. pulse(): data bit 0 high, wait `pulse_width_s`, low.
    close(): data low, PPRELEASE, close the node.

    `open_node`, `ioctl`, `close_node` and `sleep` default to os.open, fcntl.ioctl, os.close and
    time.sleep; tests pass fakes to check the exact calls without a parallel port.
    """

    def __init__(self, path: str = "/dev/parport0", *, clock: SimClock | None = None,
                 pulse_width_s: float = DEFAULT_PULSE_WIDTH_S, exclusive: bool = True,
                 open_node: Callable[[str, int], int] = os.open,
                 ioctl: Callable[..., object] = fcntl.ioctl,
                 close_node: Callable[[int], None] = os.close,
                 sleep: Callable[[float], None] = time.sleep):
        super().__init__(f"trigger ({path})", clock)
        self.path = path
        self.pulse_width_s = pulse_width_s
        self.exclusive = exclusive
        self._open_node, self._ioctl, self._close_node, self._sleep = open_node, ioctl, close_node, sleep
        self._fd: int | None = None

    def __repr__(self) -> str:
        return f"PpdevTrigger({self.path!r}, {'open' if self._fd is not None else 'closed'})"

    def open(self) -> None:
        with self._lock:
            if self._fd is not None:
                return
            fd = self._open_port_node()
            try:
                if self.exclusive:
                    self._call(fd, PPEXCL, None, "claim the port exclusively (PPEXCL)")
                self._call(fd, PPCLAIM, None, "claim the port (PPCLAIM)")
                self._call(fd, PPDATADIR, struct.pack("i", 0), "set the data pins to output (PPDATADIR)")
                self._call(fd, PPWDATA, bytes([IDLE_DATA]), "set the data pins low (PPWDATA)")
            except BaseException:
                self._close_node(fd)
                raise
            self._fd = fd
            self._is_open = True
            log.debug("%s: claimed", self.device)

    def close(self) -> None:
        with self._lock:
            fd, self._fd = self._fd, None
            self._is_open = False
            if fd is None:
                return
            try:
                self._call(fd, PPWDATA, bytes([IDLE_DATA]), "set the data pins low (PPWDATA)")
            finally:
                try:
                    self._call(fd, PPRELEASE, None, "release the port (PPRELEASE)")
                finally:
                    self._close_node(fd)

    def pulse(self) -> float:
        with self._lock:
            if self._fd is None:
                raise self._fault("not open: call open() first")
            at = self._clock.now()
            self._call(self._fd, PPWDATA, bytes([IDLE_DATA | TRIGGER_BIT]), "raise pin 2 (PPWDATA)")
            try:
                self._sleep(self.pulse_width_s)
            finally:
                # Pin 2 must come down even if the wait is interrupted, or no later pulse has an edge.
                self._call(self._fd, PPWDATA, bytes([IDLE_DATA]), "lower pin 2 (PPWDATA)")
            return self._count_pulse(at)

    def _open_port_node(self) -> int:
        try:
            return self._open_node(self.path, os.O_RDWR)
        except FileNotFoundError as exc:
            raise self._fault(f"no such device node ({exc.strerror}): load the ppdev kernel module "
                              "(modprobe ppdev) and check that the machine has a parallel port") from exc
        except PermissionError as exc:
            raise self._fault(f"permission denied ({exc.strerror}): the node is usually root:lp mode 0660; "
                              "add the user to group lp (usermod -aG lp USER) and log in again") from exc
        except OSError as exc:
            raise self._fault(f"cannot open the device node: {exc}") from exc

    def _call(self, fd: int, request: int, argument: bytes | None, what: str) -> None:
        try:
            if argument is None:
                self._ioctl(fd, request)
            else:
                self._ioctl(fd, request, argument)
        except OSError as exc:
            raise self._fault(f"cannot {what}: {exc}{_ppdev_hint(exc)}") from exc


def _ppdev_hint(exc: OSError) -> str:
    if exc.errno == errno.ENOTTY:
        return " (the node is not a ppdev parallel port)"
    if exc.errno == errno.EBUSY:
        return " (another program or the lp driver holds the port)"
    return ""


# --------------------------------------------------------------------------------------------
# The emulated box
# --------------------------------------------------------------------------------------------

TriggerInput = Callable[[float], None]


class EmulatedTrigger(TriggerBox):
    """A trigger box whose cable runs to emulated cameras.

    Cameras `connect()` a trigger input, a callable taking the simulated time of the pulse. pulse()
    calls every input with the same instant, so frames triggered together are exposed together;
    inputs must return quickly (the emulated camera only notes the instant and renders elsewhere).
    `fault` (drivers/sim/faults.py) counts pulses; once tripped, pulses reach no camera.
    """

    def __init__(self, clock: SimClock | None = None, name: str = "trigger (emulated)",
                 fault: FaultSwitch | None = None):
        super().__init__(name, clock)
        self._inputs: list[TriggerInput] = []
        self._fault_switch = fault or FaultSwitch("trigger")   # each pulse is one request

    def connect(self, trigger_input: TriggerInput) -> None:
        with self._lock:
            self._inputs.append(trigger_input)

    def disconnect(self, trigger_input: TriggerInput) -> None:
        with self._lock:
            if trigger_input in self._inputs:
                self._inputs.remove(trigger_input)

    def open(self) -> None:
        with self._lock:
            self._is_open = True

    def close(self) -> None:
        with self._lock:
            self._is_open = False

    def pulse(self) -> float:
        with self._lock:
            if not self._is_open:
                raise self._fault("not open: call open() first")
            at = self._clock.now()
            # A broken box (injected fault): the PC raises the pin, no pulse comes out of the box.
            inputs = list(self._inputs) if self._fault_switch.answers() else []
            self._count_pulse(at)
        for trigger_input in inputs:
            trigger_input(at)
        return at
