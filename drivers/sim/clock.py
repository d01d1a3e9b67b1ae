"""The simulation clock: simulated seconds that run `speed` times faster than the wall clock.

Every emulated device takes its time from one SimClock, so a test can run a 30 s PTU move in
0.3 s (speed 100) and still see the same trapezoidal profile, timeouts and settling as at speed 1.
Real backends use a SimClock with speed 1.0, which is the wall clock.
"""
from __future__ import annotations

import threading
import time


class SimClock:
    """Monotonic simulated time, `speed` simulated seconds per wall-clock second."""

    def __init__(self, speed: float = 1.0):
        if not speed > 0:
            raise ValueError(f"clock speed must be > 0, got {speed!r}")
        self._lock = threading.Lock()
        self._speed = float(speed)
        self._wall0 = time.monotonic()
        self._sim0 = 0.0

    @property
    def speed(self) -> float:
        return self._speed

    @speed.setter
    def speed(self, speed: float) -> None:
        if not speed > 0:
            raise ValueError(f"clock speed must be > 0, got {speed!r}")
        with self._lock:
            # Re-anchor so simulated time stays continuous across a change of speed.
            now_wall = time.monotonic()
            self._sim0 += (now_wall - self._wall0) * self._speed
            self._wall0 = now_wall
            self._speed = float(speed)

    def now(self) -> float:
        """Simulated seconds since the clock was made."""
        with self._lock:
            return self._sim0 + (time.monotonic() - self._wall0) * self._speed

    def to_wall(self, sim_seconds: float) -> float:
        """Wall-clock seconds that `sim_seconds` of simulated time take."""
        return max(0.0, sim_seconds) / self._speed

    def sleep(self, sim_seconds: float) -> None:
        """Block for `sim_seconds` of simulated time."""
        if sim_seconds > 0:
            time.sleep(self.to_wall(sim_seconds))

    def wait(self, event: threading.Event, sim_seconds: float) -> bool:
        """Wait for `event` at most `sim_seconds` of simulated time; True if it was set."""
        return event.wait(self.to_wall(sim_seconds))
