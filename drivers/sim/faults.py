"""Injected device faults: broken hardware the simulated test bed can switch on.

Each emulated device asks its FaultSwitch, for every request it gets (a PTU command, an SR4000
frame, a camera's triggered frame, a trigger pulse), whether to answer it. A fault is armed to trip
after N more requests; once tripped the device stays broken until the fault is cleared, as a unit
that has hung does. What broken means is the emulator's business (kind `silent`: no reply, no
frame, no pulse on the cable), so the drivers above see only what real hardware would show them.

The switches belong to the test bed, not to the emulators: `reset` replaces a device's emulator
with a new one, and a unit that is still broken must come back broken.
"""
from __future__ import annotations

import threading
from dataclasses import dataclass

FAULT_KINDS = ("silent",)
FAULT_DEVICES = ("ptu", "tof", "camera-left", "camera-right", "trigger")


@dataclass(frozen=True)
class FaultState:
    """A snapshot of one switch, for whoever reports it."""

    device: str
    kind: str | None      # None: no fault armed
    left: int             # requests still answered before it trips (0 once tripped)
    tripped: bool
    answered: int         # requests answered since the switch was made
    unanswered: int       # requests left unanswered since the fault tripped

    @property
    def state(self) -> str:
        return "tripped" if self.tripped else ("armed" if self.kind else "healthy")


class FaultSwitch:
    """One emulated device's injected fault; thread-safe (armed from the server's event loop,
    asked from the emulator's threads)."""

    def __init__(self, device: str):
        self.device = device
        self._lock = threading.Lock()
        self._kind: str | None = None
        self._left = 0
        self._tripped = False
        self._answered = 0
        self._unanswered = 0

    def arm(self, after: int, kind: str = "silent") -> None:
        """Answer `after` more requests, then none until clear()."""
        if kind not in FAULT_KINDS:
            raise ValueError(f"fault kind {kind!r}: allowed {', '.join(FAULT_KINDS)}")
        if after < 0:
            raise ValueError(f"after {after}: must be 0 or more requests")
        with self._lock:
            self._kind, self._left, self._tripped, self._unanswered = kind, after, after == 0, 0

    def clear(self) -> None:
        with self._lock:
            self._kind, self._left, self._tripped = None, 0, False

    def answers(self) -> bool:
        """Count one request; False when the device must leave it unanswered."""
        with self._lock:
            if not self._tripped and self._kind is not None:
                if self._left == 0:
                    self._tripped = True
                else:
                    self._left -= 1
            if self._tripped:
                self._unanswered += 1
                return False
            self._answered += 1
            return True

    @property
    def broken(self) -> bool:
        """Tripped now (asking does not count as a request)."""
        with self._lock:
            return self._tripped

    def state(self) -> FaultState:
        with self._lock:
            return FaultState(self.device, self._kind, self._left, self._tripped, self._answered,
                              self._unanswered)


class InjectedFaults:
    """The switch of every emulated device, by name (FAULT_DEVICES)."""

    def __init__(self) -> None:
        self._switches = {name: FaultSwitch(name) for name in FAULT_DEVICES}

    def __getitem__(self, device: str) -> FaultSwitch:
        return self._switches[device]

    def get(self, device: str, default: FaultSwitch | None = None) -> FaultSwitch | None:
        return self._switches.get(device, default)

    def states(self) -> list[FaultState]:
        return [switch.state() for switch in self._switches.values()]
