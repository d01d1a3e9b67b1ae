"""Background activities: work that runs beside the one job, frame after frame (PROTOCOL.md
"Background activities"): dynamic hazard detection now, target tracking next.

An activity is a loop in its own thread that takes one frame every 1/rate simulated seconds and
publishes one event per frame. The core gives it what every kind needs, so a new kind writes only
its frame and its summary:

    class Tracking(Activity):
        kind = "track"
        def frame(self, seq) -> dict: ...          # the event's fields after seq (state=...)
        def finish(self) -> dict: ...              # the stop reply's fields (and its product)

- Starting and stopping are immediate commands; at most one activity of each kind (`Activities`).
- It shares devices with the job through the device layer (devices/sharing.py): a frame borrows
  what it needs, and a frame the job's devices make impossible is `state=unknown`, never a wait.
- It never fails a job and never takes the server down: an exception in a frame is logged and that
  frame is unknown; the loop goes on.
- `quit` stops every activity (its product is still written); `break` does not touch them.
"""
from __future__ import annotations

import asyncio
import logging
import threading
import time
from abc import ABC, abstractmethod
from typing import TYPE_CHECKING, Any, ClassVar, Generic, Protocol, TypeVar

from .protocol import WrongMode

if TYPE_CHECKING:
    from drivers.sim.clock import SimClock

log = logging.getLogger("rvs.activities")

KINDS = ("hazard", "track")   # every kind `status` reports on or off
COMMANDS = {"hazard": ("hazard-start", "hazard-stop"), "track": ("track3d-start", "track3d-stop")}
STOP_TIMEOUT_S = 30.0         # wall seconds a stop waits for the frame in progress


class ActivityHost(Protocol):
    """What the loop needs of the server: its clock and its events (host.Host gives them). A protocol,
    so this module imports nothing of the server and the device layer may import it."""

    @property
    def clock(self) -> SimClock: ...

    def publish_threadsafe(self, topic: str, data: dict[str, Any]) -> None: ...


ServerT = TypeVar("ServerT", bound=ActivityHost)


class Activity(ABC, Generic[ServerT]):
    """One background loop; subclasses give `frame` and `finish`. A kind names the server it needs:
    `class HazardActivity(Activity["Host"])` sees the whole host as `self.server`."""

    kind: ClassVar[str]

    def __init__(self, server: ServerT, rate_hz: float):
        self.server = server
        self.rate_hz = float(rate_hz)
        self.frames = 0
        self.started_s = server.clock.now()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    @abstractmethod
    def frame(self, seq: int) -> dict[str, Any]:
        """Take and process one frame; the event's fields after `seq` (at least `state`)."""

    @abstractmethod
    def finish(self) -> dict[str, Any]:
        """After the last frame: write the product, give the stop reply's fields."""

    def unknown(self, seq: int, reason: str) -> dict[str, Any]:
        """The event of a frame that could not be taken or failed; subclasses add their fields."""
        return {"state": "unknown", "reason": reason}

    # -- the loop ---------------------------------------------------------------------------------
    def start(self) -> None:
        self._thread = threading.Thread(target=self._loop, name=f"rvs-{self.kind}", daemon=True)
        self._thread.start()

    @property
    def stopping(self) -> bool:
        return self._stop.is_set()

    def _loop(self) -> None:
        clock = self.server.clock
        period = 1.0 / self.rate_hz
        due = clock.now()
        seq = 0
        while not self._stop.is_set():
            wait = due - clock.now()
            if wait > 0 and clock.wait(self._stop, wait):
                break
            seq += 1
            try:
                event = self.frame(seq)
            except Exception as exc:   # one bad frame must not end the activity, let alone the server
                log.exception("%s frame %d failed", self.kind, seq)
                event = self.unknown(seq, f"{type(exc).__name__}: {exc}")
            self.frames = seq
            self.server.publish_threadsafe(self.kind, {"seq": seq, **event})
            # Keep the rate, but never catch up in a burst after a slow frame.
            due = max(due + period, clock.now())

    def stop(self) -> dict[str, Any]:
        """Stop after the frame in progress, then finish (blocking: run it off the event loop)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(STOP_TIMEOUT_S)
            if self._thread.is_alive():
                log.error("%s: the frame in progress did not end within %.0f s", self.kind, STOP_TIMEOUT_S)
        return self.finish()

    def measured_rate(self) -> float:
        """Frames per simulated second since the start."""
        elapsed = self.server.clock.now() - self.started_s
        return self.frames / elapsed if elapsed > 0 else 0.0


class Activities:
    """The running activities of one server, at most one per kind."""

    def __init__(self) -> None:
        self._running: dict[str, Activity[Any]] = {}

    def running(self, kind: str) -> Activity[Any] | None:
        return self._running.get(kind)

    def require_free(self, kind: str, command: str) -> None:
        """409 wrong-mode when an activity of this kind already runs."""
        if kind in self._running:
            activity = self._running[kind]
            raise WrongMode(f"{command}: {kind} is already running ({activity.frames} frames so far); "
                            f"{COMMANDS[kind][1]} first")

    def start(self, activity: Activity[Any], command: str) -> None:
        self.require_free(activity.kind, command)
        self._running[activity.kind] = activity
        activity.start()
        log.info("%s started at %.1f Hz", activity.kind, activity.rate_hz)

    async def stop(self, kind: str, command: str) -> dict[str, Any]:
        """Stop the running activity of `kind` and give its summary; 409 when none runs."""
        activity = self._running.pop(kind, None)   # at once: a second stop meanwhile finds none
        if activity is None:
            raise WrongMode(f"{command}: no {kind} activity is running ({COMMANDS[kind][0]} starts one)")
        started = time.monotonic()
        summary = await asyncio.get_running_loop().run_in_executor(None, activity.stop)
        log.info("%s stopped after %d frames (%.2f s to stop)", kind, activity.frames, time.monotonic() - started)
        return summary

    async def stop_all(self) -> None:
        """quit: stop every activity; a failure to finish one is logged, never raised."""
        for kind in list(self._running):
            try:
                await self.stop(kind, "quit")
            except Exception:
                log.exception("quit: stopping %s failed", kind)

    def status(self) -> dict[str, str]:
        return {kind: "on" if kind in self._running else "off" for kind in KINDS}
