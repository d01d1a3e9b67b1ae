"""Pan-tilt unit: Directed Perception / FLIR PTU-D46 family (also E46, D48) on its ASCII protocol.

Like every device kind in `drivers/`, this file holds
- the errors (`PtuError` and its subclasses) and `PtuLimits`, what the unit reports about itself;
- `PtuD46`, the real driver: a pyserial URL in (`/dev/ttyS0`, a pty path, `socket://host:port`),
  degrees out, thread-safe;
- `PtuEmulator`, a byte-level model of the unit: command parser, terse/verbose feedback, echo,
  position and speed limits with the unit's own error texts, trapezoidal motion evaluated in
  simulated time, await, slaved mode, halt, reset, unprompted limit notices. `serve_pty()` and
  `serve_tcp()` put it on a real line, so the driver is tested on the real bytes.

Protocol facts come from the PTU-D46 user's manual (v2.14) and open-source drivers. Reply texts the
manual does not show (marked "modelled" below) follow the manual's style.
"""
from __future__ import annotations

import heapq
import logging
import math
import re
import threading
import time
from dataclasses import dataclass, replace
from typing import NamedTuple

import serial

from drivers.errors import DeviceFault, DeviceTimeout
from drivers.serial_emulation import PtyServer, TcpServer
from drivers.sim.clock import SimClock
from drivers.sim.faults import FaultSwitch

log = logging.getLogger(__name__)

ARCSEC_PER_DEGREE = 3600.0
AXES = ("pan", "tilt")


# --------------------------------------------------------------------------------------------
# Errors and limits
# --------------------------------------------------------------------------------------------

class PtuError(DeviceFault):
    """Any PTU fault. The message names the device (and its port), what was sent and what the
    unit said; `device`, `sent` and `reply` keep them apart for callers."""

    def __init__(self, detail: str, *, device: str = "ptu", port: str | None = None,
                 sent: str | None = None, reply: str | None = None):
        self.detail = detail
        self.port = port
        self.sent = sent
        self.reply = reply
        parts = [f"{device} on {port}: {detail}" if port else f"{device}: {detail}"]
        if sent is not None:
            parts.append(f"sent {sent!r}")
        if reply is not None:
            parts.append(f"unit said {reply!r}")
        super().__init__("; ".join(parts), device=device)


class PtuCommandError(PtuError):
    """The unit refused a command (`! Illegal Command Entered`, ...)."""


class PtuPositionError(PtuCommandError):
    """A target outside the position limits; `allowed_deg` is the axis's (min, max)."""

    def __init__(self, detail: str, *, axis: str, allowed_deg: tuple[float, float] | None,
                 requested_deg: float | None = None, **kwargs):
        self.axis = axis
        self.allowed_deg = allowed_deg
        self.requested_deg = requested_deg
        if allowed_deg is not None:
            detail = f"{detail} (allowed {axis} range {allowed_deg[0]:.4f}..{allowed_deg[1]:.4f} deg)"
        super().__init__(detail, **kwargs)


class PtuSpeedError(PtuCommandError):
    """A speed outside the unit's speed bounds; `allowed_deg_s` is the axis's (min, max)."""

    def __init__(self, detail: str, *, axis: str | None, allowed_deg_s: tuple[float, float] | None,
                 requested_deg_s: float | None = None, **kwargs):
        self.axis = axis
        self.allowed_deg_s = allowed_deg_s
        self.requested_deg_s = requested_deg_s
        if allowed_deg_s is not None:
            detail = (f"{detail} (allowed {axis} speed {allowed_deg_s[0]:.4f}.."
                      f"{allowed_deg_s[1]:.4f} deg/s)")
        super().__init__(detail, **kwargs)


class PtuLimitHit(PtuError):
    """The unit reported, unprompted, that an axis hit a limit (`!P`, `!T`); it needs a reset."""

    def __init__(self, detail: str, *, axes: tuple[str, ...], **kwargs):
        self.axes = axes
        super().__init__(detail, **kwargs)


class PtuTimeout(PtuError, DeviceTimeout):
    """A move did not end within its time limit (the unit answers, it is still moving)."""


class PtuNotResponding(PtuError):
    """The unit cannot be reached or gives no valid answer (port gone, silent for the whole read
    timeout, garbage)."""


@dataclass(frozen=True)
class PtuLimits:
    """Range, speed bounds and resolution the unit reported at open() (or after reset())."""

    pan_min_deg: float
    pan_max_deg: float
    tilt_min_deg: float
    tilt_max_deg: float
    pan_min_speed_deg_s: float
    pan_max_speed_deg_s: float
    tilt_min_speed_deg_s: float
    tilt_max_speed_deg_s: float
    pan_resolution_deg: float   # degrees per position (step)
    tilt_resolution_deg: float

    def range_deg(self, axis: str) -> tuple[float, float]:
        if axis == "pan":
            return self.pan_min_deg, self.pan_max_deg
        return self.tilt_min_deg, self.tilt_max_deg

    def speed_range_deg_s(self, axis: str) -> tuple[float, float]:
        if axis == "pan":
            return self.pan_min_speed_deg_s, self.pan_max_speed_deg_s
        return self.tilt_min_speed_deg_s, self.tilt_max_speed_deg_s

    def resolution_deg(self, axis: str) -> float:
        return self.pan_resolution_deg if axis == "pan" else self.tilt_resolution_deg


# --------------------------------------------------------------------------------------------
# The real driver
# --------------------------------------------------------------------------------------------

_LINE_END = re.compile(rb"[\r\n]")
_LIMIT_NOTICES = re.compile(r"^(?:![PT])+")      # "!P" / "!T" have no space; "! msg" has one
_PARTIAL_NOTICES = re.compile(rb"(?:![PT])*!?")
_NUMBER = re.compile(r"[-+]?\d+(?:\.\d+)?")
# Each read waits at most this long, so deadlines are checked often and close() is prompt.
_READ_SLICE_S = 0.02


class PtuD46:
    """Driver for a PTU-D46 (or E46/D48) on a serial line, or anything pyserial opens by URL.

    Thread-safe: one re-entrant lock covers each command/reply exchange (and each multi-command
    operation such as open() or move_to()), so a status thread may call position() while a job
    thread moves the unit.

    Time: waits (move timeouts, poll intervals, reset) are in the seconds of `clock`, so the driver
    keeps pace with an emulated unit on a sped-up SimClock; `reply_timeout_s` is wall time, because
    it bounds the serial link's latency, which does not speed up.

    is_moving(): the protocol has no "moving" query. We read the current position (PP/TP) and the
    desired position the unit is driving to (PO/TO); the unit moves while they differ. This follows
    halts and moves made by others, unlike a target remembered here. When they agree we read the
    position once more `settle_check_s` later, because an on-the-fly retarget can pass through the
    target before reversing onto it.

    Unprompted limit notices (`!P`/`!T`: an axis hit a limit switch) may arrive glued to any reply,
    so each reply is stripped of them. They are recorded and raised as PtuLimitHit by the next
    is_moving() or wait_until_stopped() (a crashed move must not be reported as finished), never by
    position(), so a status reader is not disturbed. reset() expects them and discards them.
    """

    def __init__(self, url: str, *, name: str = "ptu", clock: SimClock | None = None, baudrate: int = 9600,
                 reply_timeout_s: float = 4.0, poll_interval_s: float = 0.05,
                 settle_check_s: float = 0.01):
        self.url = url
        self.name = name
        self._baudrate = baudrate  # the factory default is 9600; the unit can be set to others
        self._clock = clock if clock is not None else SimClock(1.0)
        self._reply_timeout_s = reply_timeout_s
        self._poll_interval_s = poll_interval_s
        self._settle_check_s = settle_check_s
        self._lock = threading.RLock()
        self._serial: serial.SerialBase | None = None
        self._rx = bytearray()
        self._limit_hits: list[str] = []
        self._limits: PtuLimits | None = None
        self._position_limits: dict[str, tuple[int, int]] = {}
        self._speed_limits: dict[str, tuple[int, int]] = {}
        self._not_answering: str | None = None
        self._silences = 0   # exchanges left unanswered so far
        self._silence_detail = ""

    @property
    def not_answering(self) -> str | None:
        """Why the last exchange got no reply, or None once the unit answers again. Read without the
        line's lock, so a status reader learns of a silent unit while a job waits on it."""
        return self._not_answering

    @property
    def _label(self) -> str:
        return f"{self.name} on {self.url}"

    @property
    def _who(self) -> dict[str, str]:
        """Names the unit in every error raised here."""
        return {"device": self.name, "port": self.url}

    def __repr__(self) -> str:
        state = "open" if self._serial is not None else "closed"
        return f"PtuD46({self.url!r}, name={self.name!r}, {state})"

    # -- life cycle ---------------------------------------------------------------------------

    def open(self) -> None:
        """Open the line and run the start-up sequence: terse, no echo, independent mode, limits."""
        with self._lock:
            if self._serial is not None:
                return
            try:
                self._serial = serial.serial_for_url(
                    self.url, baudrate=self._baudrate, bytesize=8, parity="N", stopbits=1,
                    timeout=_READ_SLICE_S, write_timeout=self._reply_timeout_s)
            except (serial.SerialException, OSError, ValueError) as exc:
                raise PtuNotResponding(f"cannot open the serial line: {exc}", **self._who) from exc
            self._rx.clear()
            self._limit_hits.clear()
            try:
                # A lone delimiter ends any half-typed command left in the unit's input buffer.
                self._write(b" ", sent=" ")
                # FT/ED first: replies become "* value" without the echoed command. CI and I make
                # PP/TP absolute moves that start at once, which move_to() relies on.
                self._exchange(["FT", "ED", "CI", "I"])
                self._read_limits()
            except BaseException:
                self._close_port()
                raise

    def close(self) -> None:
        with self._lock:
            self._close_port()

    def __enter__(self) -> "PtuD46":
        self.open()
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    @property
    def limits(self) -> PtuLimits:
        if self._limits is None:
            raise PtuError("not open: call open() first", **self._who)
        return self._limits

    # -- queries ------------------------------------------------------------------------------

    def position(self) -> tuple[float, float]:
        """Current (pan, tilt) in degrees."""
        pan, tilt = self._query_ints(["PP", "TP"])
        return self._to_deg("pan", pan), self._to_deg("tilt", tilt)

    def version(self) -> str:
        """The firmware's version text."""
        return self._exchange(["V"])[0]

    def check(self) -> None:
        """Prove the unit answers with a cheap position query; raise PtuNotResponding otherwise."""
        try:
            self._query_ints(["PP"])
        except PtuNotResponding:
            raise
        except PtuError as exc:
            raise PtuNotResponding(f"no valid answer to a position query: {exc.detail}",
                                   **self._who, sent=exc.sent, reply=exc.reply) from exc

    def command(self, text: str, wait_s: float = 0.0) -> str:
        """Send one raw protocol command (e.g. "LD", "PA3000") and return the reply's payload.

        For diagnostics and tests; `wait_s` (clock seconds) extends the reply timeout for commands
        that answer late (A, R)."""
        command = text.strip()
        resetting = command.upper() in ("R", "RP", "RT")
        return self._exchange([command], wait_s=wait_s, limit_notices_expected=resetting)[0]

    # -- motion -------------------------------------------------------------------------------

    def move_to(self, pan_deg: float, tilt_deg: float, speed_deg_s: float | None = None) -> None:
        """Start a move to (pan_deg, tilt_deg) and return at once.

        Targets outside the limits and speeds outside the speed bounds are refused before anything
        is sent; the speed, when given, is set on both axes before the move."""
        targets = {axis: self._checked_target(axis, deg) for axis, deg in zip(AXES, (pan_deg, tilt_deg))}
        commands = []
        if speed_deg_s is not None:
            for axis, letter in zip(AXES, "PT"):
                commands.append(f"{letter}S{self._checked_speed(axis, speed_deg_s)}")
        commands += [f"PP{targets['pan']}", f"TP{targets['tilt']}"]
        self._exchange(commands)
        log.debug("%s: moving to pan %.4f, tilt %.4f deg", self._label, pan_deg, tilt_deg)

    def is_moving(self) -> bool:
        """True while either axis moves (see the class notes); raises PtuLimitHit after `!P`/`!T`."""
        pan, tilt, pan_wanted, tilt_wanted = self._query_ints(["PP", "TP", "PO", "TO"])
        self._raise_limit_hits()
        if (pan, tilt) != (pan_wanted, tilt_wanted):
            return True
        self._clock.sleep(self._settle_check_s)
        moved = tuple(self._query_ints(["PP", "TP"])) != (pan, tilt)
        self._raise_limit_hits()
        return moved

    def wait_until_stopped(self, timeout_s: float) -> tuple[float, float]:
        """Poll until both axes stand still; return the final (pan, tilt) in degrees.

        `timeout_s` is in clock seconds; raises PtuTimeout if the unit still moves then."""
        deadline = self._clock.now() + timeout_s
        while self.is_moving():
            if self._clock.now() >= deadline:
                raise PtuTimeout(f"still moving after {timeout_s:g} s", **self._who)
            self._clock.sleep(self._poll_interval_s)
        return self.position()

    def halt(self) -> None:
        """Stop both axes (they decelerate; use wait_until_stopped() to see them stand)."""
        self._exchange(["H"])

    def reset(self, timeout_s: float = 120.0) -> None:
        """Recalibrate: the unit seeks its limit switches (answering `!T!T!P!P*` after seconds)
        and returns home. Limits are read again, as the unit redetermines them.

        Holds the line for the whole reset (the unit answers nothing meanwhile)."""
        with self._lock:
            self._exchange(["R"], wait_s=timeout_s, limit_notices_expected=True)
            self._limit_hits.clear()  # a reset is the cure for lost synchrony
            self._read_limits()

    # -- conversion and checks ----------------------------------------------------------------

    def _to_deg(self, axis: str, positions: int) -> float:
        return positions * self.limits.resolution_deg(axis)

    def _checked_target(self, axis: str, deg: float) -> int:
        allowed = self.limits.range_deg(axis)
        lowest, highest = self._position_limits[axis]
        if not math.isfinite(deg):
            raise PtuPositionError(f"{axis} target {deg!r} is not a number", axis=axis,
                                   allowed_deg=allowed, requested_deg=deg, **self._who)
        positions = round(deg / self.limits.resolution_deg(axis))
        if not lowest <= positions <= highest:
            raise PtuPositionError(f"{axis} target {deg:.4f} deg refused before sending", axis=axis,
                                   allowed_deg=allowed, requested_deg=deg, **self._who)
        return positions

    def _checked_speed(self, axis: str, deg_s: float) -> int:
        allowed = self.limits.speed_range_deg_s(axis)
        lowest, highest = self._speed_limits[axis]
        positions_s = round(deg_s / self.limits.resolution_deg(axis)) if math.isfinite(deg_s) else -1
        if not lowest <= positions_s <= highest:
            raise PtuSpeedError(f"{axis} speed {deg_s!r} deg/s refused before sending", axis=axis,
                                allowed_deg_s=allowed, requested_deg_s=deg_s, **self._who)
        return positions_s

    def _read_limits(self) -> None:
        replies = self._exchange(["PR", "TR", "PN", "PX", "TN", "TX", "PU", "PL", "TU", "TL"])
        sent = ["PR", "TR", "PN", "PX", "TN", "TX", "PU", "PL", "TU", "TL"]
        numbers = [self._number(reply, command) for reply, command in zip(replies, sent)]
        pan_res, tilt_res = numbers[0] / ARCSEC_PER_DEGREE, numbers[1] / ARCSEC_PER_DEGREE
        pan_min, pan_max, tilt_min, tilt_max, pan_up, pan_low, tilt_up, tilt_low = map(round, numbers[2:])
        self._position_limits = {"pan": (pan_min, pan_max), "tilt": (tilt_min, tilt_max)}
        self._speed_limits = {"pan": (pan_low, pan_up), "tilt": (tilt_low, tilt_up)}
        self._limits = PtuLimits(
            pan_min_deg=pan_min * pan_res, pan_max_deg=pan_max * pan_res,
            tilt_min_deg=tilt_min * tilt_res, tilt_max_deg=tilt_max * tilt_res,
            pan_min_speed_deg_s=pan_low * pan_res, pan_max_speed_deg_s=pan_up * pan_res,
            tilt_min_speed_deg_s=tilt_low * tilt_res, tilt_max_speed_deg_s=tilt_up * tilt_res,
            pan_resolution_deg=pan_res, tilt_resolution_deg=tilt_res)

    def _number(self, payload: str, command: str) -> float:
        # The first number also parses verbose replies ("* -500", "* Current Pan position is -500").
        match = _NUMBER.search(payload)
        if match is None:
            raise PtuCommandError("expected a number in the reply", **self._who,
                                  sent=command, reply=payload)
        return float(match.group())

    def _query_ints(self, commands: list[str]) -> list[int]:
        return [round(self._number(reply, command))
                for reply, command in zip(self._exchange(commands), commands)]

    # -- the line -----------------------------------------------------------------------------

    def _exchange(self, commands: list[str], *, wait_s: float = 0.0,
                  limit_notices_expected: bool = False) -> list[str]:
        """Send commands in one write and return each reply's payload (the text after `*`).

        The unit queues input and answers in order, so pipelining saves round trips. If a command
        fails, the remaining replies are still read, to keep the stream in step, and the first
        failure is raised."""
        silences = self._silences
        with self._lock:
            if self._silences != silences:
                # The unit left another exchange unanswered while this one waited for the line:
                # waiting out the same timeout again would only double the time to report it.
                raise PtuNotResponding(f"{self._silence_detail} (the exchange before this one)", **self._who,
                                       sent=" ".join(commands))
            try:
                payloads = self._exchange_locked(commands, wait_s, limit_notices_expected)
            except PtuNotResponding as exc:
                self._not_answering, self._silence_detail = str(exc), exc.detail
                self._silences += 1
                raise
            self._not_answering = None
            return payloads

    def _exchange_locked(self, commands: list[str], wait_s: float, limit_notices_expected: bool) -> list[str]:
        self._require_open()
        self._drain_stale_input()
        wire = "".join(f"{command} " for command in commands)
        self._write(wire.encode("ascii"), sent=wire)
        deadline = time.monotonic() + self._reply_timeout_s + self._clock.to_wall(wait_s)
        payloads: list[str] = []
        first_failure: PtuCommandError | None = None
        for command in commands:
            try:
                payloads.append(self._read_reply(command, deadline, limit_notices_expected))
            except PtuCommandError as exc:
                first_failure = first_failure or exc
                payloads.append("")
        if first_failure is not None:
            raise first_failure
        return payloads

    def _read_reply(self, command: str, deadline: float, limit_notices_expected: bool) -> str:
        while True:
            text = self._read_line(command, deadline).strip()
            text = self._take_limit_notices(text, limit_notices_expected)
            text = self._strip_echo(text, command)
            text = self._take_limit_notices(text, limit_notices_expected)
            if not text:
                continue
            if text.startswith("*"):
                return text[1:].strip()
            if text.startswith("!"):
                raise self._unit_error(command, text)
            log.warning("%s: ignoring unexpected line %r while waiting for the reply to %r",
                        self._label, text, command)

    def _read_line(self, command: str, deadline: float) -> str:
        """Next non-empty line. CR and LF both end a line, so `*\\r`, `*\\r\\n` and the D48's
        `\\n* 23.14\\r\\n` framing all read the same."""
        while True:
            match = _LINE_END.search(self._rx)
            if match is not None:
                line = bytes(self._rx[:match.start()])
                del self._rx[:match.end()]
                if line.strip():
                    return line.decode("ascii", errors="replace")
                continue
            if time.monotonic() >= deadline:
                partial = bytes(self._rx).decode("ascii", errors="replace")
                self._rx.clear()
                self._discard_input()
                # A unit that says nothing for the whole read timeout is not answering: a fault of
                # the device, not a step over its time limit.
                raise PtuNotResponding(f"stopped answering: no complete reply within {self._reply_timeout_s:g} s",
                                       **self._who, sent=command, reply=partial or None)
            self._rx += self._read_available(command)

    def _read_available(self, command: str) -> bytes:
        serial_port = self._require_open()
        try:
            return serial_port.read(max(1, serial_port.in_waiting))
        except (serial.SerialException, OSError) as exc:
            raise PtuNotResponding(f"serial line failed while reading: {exc}",
                                   **self._who, sent=command) from exc

    def _write(self, data: bytes, sent: str) -> None:
        serial_port = self._require_open()
        log.debug("%s: TX %r", self._label, data)
        try:
            serial_port.write(data)
        except serial.SerialTimeoutException as exc:
            raise PtuNotResponding("stopped answering: the unit does not take input (write timed out)",
                                   **self._who, sent=sent) from exc
        except (serial.SerialException, OSError) as exc:
            raise PtuNotResponding(f"serial line failed while writing: {exc}",
                                   **self._who, sent=sent) from exc

    def _drain_stale_input(self) -> None:
        """Before a command: keep limit notices that arrived meanwhile, drop stale replies."""
        serial_port = self._require_open()
        try:
            waiting = serial_port.in_waiting
            if waiting:
                self._rx += serial_port.read(waiting)
        except (serial.SerialException, OSError) as exc:
            raise PtuNotResponding(f"serial line failed: {exc}", **self._who) from exc
        while (match := _LINE_END.search(self._rx)) is not None:
            line = bytes(self._rx[:match.start()]).decode("ascii", errors="replace").strip()
            del self._rx[:match.end()]
            stale = self._take_limit_notices(line, expected=False)
            if stale:
                log.warning("%s: discarding stale input %r", self._label, stale)
        rest = bytes(self._rx).strip()
        if _PARTIAL_NOTICES.fullmatch(rest):
            # Complete notices are taken now; a lone "!" may be the start of one, so it stays.
            notices = rest[:-1] if rest.endswith(b"!") else rest
            self._take_limit_notices(notices.decode("ascii"), expected=False)
            self._rx[:] = rest[len(notices):]
        else:
            log.warning("%s: discarding stale input %r", self._label, rest)
            self._rx.clear()

    def _discard_input(self) -> None:
        try:
            if self._serial is not None:
                self._serial.reset_input_buffer()
        except (serial.SerialException, OSError):
            pass

    def _take_limit_notices(self, text: str, expected: bool) -> str:
        match = _LIMIT_NOTICES.match(text)
        if match is None:
            return text
        if not expected:
            for notice in re.findall("![PT]", match.group()):
                axis = "pan" if notice == "!P" else "tilt"
                log.warning("%s: unprompted %s, the %s axis hit a limit", self._label, notice, axis)
                self._limit_hits.append(axis)
        return text[match.end():].strip()

    @staticmethod
    def _strip_echo(text: str, command: str) -> str:
        # With echo on (a unit just powered up), a reply line starts with our own command.
        if text[:1].isalpha() and text.upper().startswith(command.upper()):
            rest = text[len(command):]
            if not rest or rest[0].isspace():
                return rest.strip()
        return text

    def _raise_limit_hits(self) -> None:
        with self._lock:
            if not self._limit_hits:
                return
            axes = tuple(dict.fromkeys(self._limit_hits))
            notices = "".join("!P" if axis == "pan" else "!T" for axis in self._limit_hits)
            self._limit_hits.clear()
        raise PtuLimitHit(f"{' and '.join(axes)} axis hit a limit; the unit needs a reset()",
                          axes=axes, **self._who, reply=notices)

    def _unit_error(self, command: str, text: str) -> PtuCommandError:
        message = text[1:].strip()
        lowered = message.lower()
        axis = "pan" if "pan" in lowered else "tilt" if "tilt" in lowered else None
        if "position" in lowered and "allowable" in lowered and axis is not None:
            allowed = self._limits.range_deg(axis) if self._limits else None
            return PtuPositionError("the unit refused the position", axis=axis, allowed_deg=allowed,
                                    **self._who, sent=command, reply=text)
        if "speed" in lowered:
            allowed = self._limits.speed_range_deg_s(axis) if self._limits and axis else None
            return PtuSpeedError("the unit refused the speed", axis=axis, allowed_deg_s=allowed,
                                 **self._who, sent=command, reply=text)
        return PtuCommandError("the unit refused the command", **self._who, sent=command, reply=text)

    def _require_open(self) -> serial.SerialBase:
        if self._serial is None:
            raise PtuNotResponding("the serial line is not open: call open() first", **self._who)
        return self._serial

    def _close_port(self) -> None:
        if self._serial is not None:
            try:
                self._serial.close()
            except (serial.SerialException, OSError):
                pass
            self._serial = None
        self._rx.clear()


# --------------------------------------------------------------------------------------------
# Motion model of the emulator: trapezoidal velocity profiles in simulated time
# --------------------------------------------------------------------------------------------

class _Segment(NamedTuple):
    """Constant acceleration from (t0, p0, v0) for `duration` seconds; positions, seconds."""

    t0: float
    p0: float
    v0: float
    accel: float
    duration: float

    @property
    def end_time(self) -> float:
        return self.t0 + self.duration

    def state_at(self, t: float) -> tuple[float, float]:
        tau = min(max(t - self.t0, 0.0), self.duration)
        return self.p0 + self.v0 * tau + 0.5 * self.accel * tau * tau, self.v0 + self.accel * tau


class Trajectory:
    """One axis's motion: segments end to end (velocity may jump between them), then rest at `final`."""

    def __init__(self, segments: list[_Segment], final: float):
        self.segments = segments
        self.final = final

    @classmethod
    def at_rest(cls, position: float) -> "Trajectory":
        return cls([], position)

    @property
    def end_time(self) -> float:
        return self.segments[-1].end_time if self.segments else -math.inf

    def state(self, t: float) -> tuple[float, float]:
        """(position, velocity) at time t."""
        for segment in self.segments:
            if t < segment.end_time:
                return segment.state_at(t)
        return self.final, 0.0


def _braking_distance(speed: float, base_speed: float, accel: float) -> float:
    # Above the base speed the axis ramps down; at or below it, it can stop at once.
    return (speed * speed - base_speed * base_speed) / (2 * accel) if speed > base_speed else 0.0


def plan_move(t0: float, p0: float, v0: float, target: float, *, speed: float, accel: float,
              base_speed: float) -> Trajectory:
    """Trapezoidal profile from state (p0, v0) at t0 to rest at `target`, as the D46 moves.

    The stepper jumps to the base speed at once, ramps at `accel` up to `speed`, cruises, ramps
    down to the base speed and stops at once ("instantaneous speed changes" below the base speed,
    the manual's Figure 4). A short move peaks below `speed` (a triangle). An axis that moves away
    from the target, or too fast to stop before it, first brakes to rest and then sets off back.
    """
    segments: list[_Segment] = []
    t, p = t0, p0
    jump = min(base_speed, speed)

    def add(velocity: float, acceleration: float, duration: float) -> None:
        nonlocal t, p
        if duration > 1e-12:
            segment = _Segment(t, p, velocity, acceleration, duration)
            segments.append(segment)
            t, p = segment.end_time, segment.state_at(segment.end_time)[0]

    distance = target - p
    if v0 != 0 and (distance * v0 <= 0 or _braking_distance(abs(v0), jump, accel) > abs(distance) + 1e-9):
        direction = math.copysign(1.0, v0)
        add(v0, -direction * accel, max(abs(v0) - jump, 0.0) / accel)
        v0, distance = 0.0, target - p
    if abs(distance) < 1e-9 or speed <= 0:
        return Trajectory(segments, target if abs(distance) < 1e-9 else p)

    direction = math.copysign(1.0, distance)
    length = abs(distance)
    start_speed = max(abs(v0), jump)
    if start_speed > speed:
        # Slowed down on the fly: ramp down to the new speed, cruise, then ramp to a stop.
        peak = speed
        ramp_up = (start_speed ** 2 - peak ** 2) / (2 * accel)
        add(direction * start_speed, -direction * accel, (start_speed - peak) / accel)
    else:
        peak = min(speed, math.sqrt((2 * accel * length + start_speed ** 2 + jump ** 2) / 2))
        ramp_up = (peak ** 2 - start_speed ** 2) / (2 * accel)
        add(direction * start_speed, direction * accel, (peak - start_speed) / accel)
    ramp_down = (peak ** 2 - jump ** 2) / (2 * accel)
    cruise = max(length - ramp_up - ramp_down, 0.0)
    add(direction * peak, 0.0, cruise / peak)
    add(direction * peak, -direction * accel, (peak - jump) / accel)
    return Trajectory(segments, target)


def _time_to_reach(segment: _Segment, position: float) -> float:
    """Earliest time within the segment at which it passes `position` (it is monotonic)."""
    a, v, c = 0.5 * segment.accel, segment.v0, segment.p0 - position
    if abs(a) < 1e-15:
        tau = -c / v if v else 0.0
    else:
        root = math.sqrt(max(v * v - 4 * a * c, 0.0))
        candidates = [tau for tau in ((-v - root) / (2 * a), (-v + root) / (2 * a)) if tau >= -1e-12]
        tau = min(candidates) if candidates else 0.0
    return min(max(tau, 0.0), segment.duration)


def stop_at_hard_stops(trajectory: Trajectory, low: float, high: float) -> tuple[Trajectory, float | None]:
    """Cut a trajectory where it reaches a hard stop; return it and the time of the hit (or None)."""
    kept: list[_Segment] = []
    for segment in trajectory.segments:
        end_position = segment.state_at(segment.end_time)[0]
        if max(segment.p0, end_position) > high:
            bound = high
        elif min(segment.p0, end_position) < low:
            bound = low
        else:
            kept.append(segment)
            continue
        kept.append(segment._replace(duration=_time_to_reach(segment, bound)))
        return Trajectory(kept, bound), kept[-1].end_time
    return trajectory, None


# --------------------------------------------------------------------------------------------
# The emulator
# --------------------------------------------------------------------------------------------

# A PTU-D46-17 as its manual describes it.
D46_RESOLUTION_ARCSEC = 185.1428
D46_PAN_LIMITS = (-3090, 3090)
D46_TILT_LIMITS = (-907, 604)
D46_VERSION = "Pan-Tilt Controller v2.14.0(D46/E), (C)2006 Directed Perception, Inc., All Rights Reserved"

ILLEGAL_COMMAND = "Illegal Command Entered"
ILLEGAL_ARGUMENT = "Illegal Argument"   # modelled
_DELIMITERS = b" \r\n"                   # the manual: space or CR; LF is tolerated as well
_MAX_TOKEN = 40                          # longer tokens overflow and are refused whole
_MAX_BACKLOG = 4096                      # input held while the unit is busy (await, reset)
_AXIS_CODES = "PORNXSDABUL"


@dataclass
class AxisSettings:
    """Per-axis speed settings in positions/s and positions/s^2, as PS PA PB PU PL set them."""

    speed: int = 1000
    accel: int = 2000
    base_speed: int = 1000
    upper_speed: int = 2902
    lower_speed: int = 31


def _widened(limits: tuple[int, int], margin: int) -> tuple[int, int]:
    return limits[0] - margin, limits[1] + margin


class _EmulatedAxis:
    def __init__(self, letter: str, soft: tuple[int, int], hard: tuple[int, int], resolution_arcsec: float,
                 settings: AxisSettings):
        self.letter = letter
        self.name = "Pan" if letter == "P" else "Tilt"
        self.soft = soft
        self.hard = hard
        self.resolution_arcsec = resolution_arcsec
        self.settings = settings
        self.trajectory = Trajectory.at_rest(0.0)
        self.desired = 0                     # what PO reports: the position the axis drives to
        self.pending: int | None = None      # slaved mode: a target waiting for 'A'
        self.limit_hit_at: float | None = None
        self.velocity = 0                    # signed speed commanded in pure velocity mode

    def state(self, t: float) -> tuple[float, float]:
        return self.trajectory.state(t)

    def position(self, t: float) -> int:
        return math.floor(self.state(t)[0] + 0.5)

    def moving(self, t: float) -> bool:
        return t < self.trajectory.end_time

    def go_to(self, t: float, target: float) -> None:
        p, v = self.state(t)
        s = self.settings
        planned = plan_move(t, p, v, target, speed=s.speed, accel=s.accel, base_speed=s.base_speed)
        self._follow(planned)
        self.desired = round(target)

    def halt(self, t: float) -> None:
        p, v = self.state(t)
        self.pending = None
        if v == 0:
            self._follow(Trajectory.at_rest(p))
        else:
            direction = math.copysign(1.0, v)
            jump = min(self.settings.base_speed, self.settings.speed)
            accel = self.settings.accel
            braking = max(abs(v) - jump, 0.0) / accel
            stop = p + direction * _braking_distance(abs(v), jump, accel)
            segments = [_Segment(t, p, v, -direction * accel, braking)] if braking > 0 else []
            self._follow(Trajectory(segments, stop))
        self.desired = round(self.trajectory.final)

    def _follow(self, trajectory: Trajectory) -> None:
        self.trajectory, self.limit_hit_at = stop_at_hard_stops(trajectory, *self.hard)


class PtuEmulator:
    """A PTU-D46 that answers byte for byte, with its motion evaluated in simulated time.

    Feed it the host's bytes with feed(); it returns what the unit sends at once. poll() returns
    what the unit sends on its own by now (an await finishing, a reset's `!T!T!P!P*`, an unprompted
    `!P`). While an await or a reset runs the unit reads no commands: later input waits, unechoed,
    as in the unit's input buffer. It starts as the unit powers up: echo on, verbose feedback.

    Ground truth for tests: true_angles_deg() and is_moving(). Serve it on a line with serve_pty()
    or serve_tcp(). Thread-safe; `clock` needs now() (and to_wall() when served).

    `fault` (drivers/sim/faults.py) counts every command the unit reads; once it trips the unit
    hangs: it reads and answers nothing until the fault is cleared.
    """

    def __init__(self, clock, *, pan_limits: tuple[int, int] = D46_PAN_LIMITS,
                 tilt_limits: tuple[int, int] = D46_TILT_LIMITS, hard_stop_margin: int = 200,
                 resolution_arcsec: float = D46_RESOLUTION_ARCSEC, max_speed: int = 2902,
                 min_speed: int = 31, echo: bool = True, verbose: bool = True,
                 line_end: bytes = b"\r\n", reply_prefix: bytes = b"", version: str = D46_VERSION,
                 fault: FaultSwitch | None = None):
        self._clock = clock
        self._fault = fault or FaultSwitch("ptu")   # each command the unit reads is one request
        self._lock = threading.RLock()
        self._factory = AxisSettings(upper_speed=max_speed, lower_speed=min_speed)
        self._max_speed = max_speed
        self._min_speed = min_speed
        self._saved = {"P": replace(self._factory), "T": replace(self._factory)}
        # The limit switches (hard stops) sit beyond the soft limits; with limits disabled (LD)
        # the axes may travel up to them.
        self.pan = _EmulatedAxis("P", pan_limits, _widened(pan_limits, hard_stop_margin),
                                 resolution_arcsec, replace(self._factory))
        self.tilt = _EmulatedAxis("T", tilt_limits, _widened(tilt_limits, hard_stop_margin),
                                  resolution_arcsec, replace(self._factory))
        self.echo = echo
        self.verbose = verbose
        self.limits_enforced = True
        self.velocity_mode = False     # CV; CI is the default independent mode
        self.slaved = False            # S; I is the default immediate mode
        self.version = version
        self._line_end = line_end
        self._reply_prefix = reply_prefix
        self._backlog = bytearray()
        self._token = bytearray()
        self._token_overflow = False
        self._busy_until = -math.inf
        self._events: list[tuple[float, int, bytes]] = []   # (time, order, bytes) to send later
        self._event_order = 0
        self._unit_commands = self._command_table()

    # -- the byte interface ---------------------------------------------------------------------

    def feed(self, data: bytes) -> bytes:
        with self._lock:
            if self._fault.broken:
                return self._hung(self._clock.now())
            room = _MAX_BACKLOG - len(self._backlog)
            self._backlog += data[:max(room, 0)]   # a full input buffer drops bytes, like a UART
            return self._advance(self._clock.now())

    def poll(self) -> bytes:
        with self._lock:
            if self._fault.broken:
                return self._hung(self._clock.now())
            return self._advance(self._clock.now())

    def _hung(self, now: float) -> bytes:
        """A hung controller (injected fault): it reads nothing and says nothing, not even what it
        had queued; the axes still end the move they were making."""
        self._backlog.clear()
        self._token.clear()
        self._due_output(now)
        return b""

    def next_event_time(self) -> float | None:
        """Simulated time at which poll() may next have output."""
        with self._lock:
            times = [self._events[0][0]] if self._events else []
            times += [axis.limit_hit_at for axis in self._axes() if axis.limit_hit_at is not None]
            return min(times) if times else None

    def wall_time_to_next_event(self) -> float | None:
        at = self.next_event_time()
        return None if at is None else self._clock.to_wall(at - self._clock.now())

    # -- ground truth ---------------------------------------------------------------------------

    def true_positions(self) -> tuple[float, float]:
        with self._lock:
            now = self._clock.now()
            return self.pan.state(now)[0], self.tilt.state(now)[0]

    def true_angles_deg(self) -> tuple[float, float]:
        pan, tilt = self.true_positions()
        return (pan * self.pan.resolution_arcsec / ARCSEC_PER_DEGREE,
                tilt * self.tilt.resolution_arcsec / ARCSEC_PER_DEGREE)

    def is_moving(self) -> bool:
        with self._lock:
            now = self._clock.now()
            return any(axis.moving(now) for axis in self._axes())

    # -- serving --------------------------------------------------------------------------------

    def serve_pty(self) -> PtyServer:
        """Serve on a new pseudo-terminal; open `server.path` like `/dev/ttyS0`; `server.stop()`."""
        return PtyServer(self).start()

    def serve_tcp(self, host: str = "127.0.0.1", port: int = 0) -> TcpServer:
        """Serve on a TCP port; open `server.url` (`socket://host:port`); `server.stop()`."""
        return TcpServer(self, host, port).start()

    # -- parsing --------------------------------------------------------------------------------

    def _axes(self) -> tuple[_EmulatedAxis, _EmulatedAxis]:
        return self.pan, self.tilt

    def _advance(self, now: float) -> bytes:
        out = bytearray(self._due_output(now))
        consumed = 0
        for byte in self._backlog:
            if self._busy_until > now:
                break
            consumed += 1
            if self.echo:
                out.append(byte)
            if byte in _DELIMITERS:
                if (self._token or self._token_overflow) and not self._fault.answers():
                    self._hung(now)   # it hangs on this command: no reply to it or to any later one
                    return bytes(out)
                if self._token or self._token_overflow:
                    out += self._execute(bytes(self._token), now)
                self._token.clear()
                self._token_overflow = False
            elif len(self._token) < _MAX_TOKEN:
                self._token.append(byte)
            else:
                self._token_overflow = True
        del self._backlog[:consumed]
        return bytes(out)

    def _due_output(self, now: float) -> bytes:
        due = []
        while self._events and self._events[0][0] <= now:
            due.append(heapq.heappop(self._events))
        for axis in self._axes():
            if axis.limit_hit_at is not None and axis.limit_hit_at <= now:
                # The axis stopped at its hard stop: that is now the position it holds.
                due.append((axis.limit_hit_at, -1, f"!{axis.letter}".encode()))
                axis.desired = round(axis.trajectory.final)
                axis.limit_hit_at = None
        due.sort()
        return b"".join(item[2] for item in due)

    def _schedule(self, at: float, data: bytes) -> None:
        self._event_order += 1
        heapq.heappush(self._events, (at, self._event_order, data))

    # -- replies --------------------------------------------------------------------------------

    def _frame(self, text: str) -> bytes:
        return self._reply_prefix + text.encode("ascii") + self._line_end

    def _ok(self) -> bytes:
        return self._frame("*")

    def _value(self, terse: object, verbose: str) -> bytes:
        return self._frame(f"* {verbose if self.verbose else terse}")

    def _error(self, message: str) -> bytes:
        return self._frame(f"! {message}")

    # -- commands -------------------------------------------------------------------------------

    def _execute(self, raw: bytes, now: float) -> bytes:
        if self._token_overflow:
            return self._error(ILLEGAL_COMMAND)
        token = raw.decode("latin-1").upper()
        if len(token) >= 2 and token[0] in "PT" and token[1] in _AXIS_CODES:
            axis = self.pan if token[0] == "P" else self.tilt
            return self._axis_command(axis, token[1], token[2:], now)
        handler = self._unit_commands.get(token)
        return handler(now) if handler else self._error(ILLEGAL_COMMAND)

    def _command_table(self) -> dict:
        return {
            "A": self._await, "I": self._immediate, "S": self._slave,
            "H": self._halt_both, "HP": self._halt_pan, "HT": self._halt_tilt,
            "R": self._reset_both, "RP": self._reset_pan, "RT": self._reset_tilt,
            "RE": self._accept, "RD": self._accept,
            "L": self._limit_query, "LE": self._limits_on, "LD": self._limits_off,
            "C": self._mode_query, "CI": self._independent_mode, "CV": self._velocity_mode,
            "F": self._feedback_query, "FT": self._terse, "FV": self._verbose_mode,
            "E": self._echo_query, "EE": self._echo_on, "ED": self._echo_off,
            "V": self._version, "O": self._supply,
            "DS": self._save_defaults, "DR": self._restore_defaults, "DF": self._factory_defaults,
        }

    def _axis_command(self, axis: _EmulatedAxis, code: str, argument: str, now: float) -> bytes:
        if argument == "":
            return self._axis_query(axis, code, now)
        if not re.fullmatch(r"[+-]?\d{1,10}", argument) or code in "RNX":
            return self._error(ILLEGAL_ARGUMENT)
        value = int(argument)
        if code == "P":
            return self._position_command(axis, value, now)
        if code == "O":
            return self._position_command(axis, axis.position(now) + value, now)
        if code == "S":
            return self._speed_command(axis, value, now)
        if code == "D":
            current = axis.velocity if self.velocity_mode else axis.settings.speed
            return self._speed_command(axis, current + value, now)
        return self._setting_command(axis, code, value, now)

    def _axis_query(self, axis: _EmulatedAxis, code: str, now: float) -> bytes:
        s, name = axis.settings, axis.name
        if code == "P":
            position = axis.position(now)
            return self._value(position, f"Current {name} position is {position}")
        if code == "O":
            # The manual's own example words the desired-position query like PP.
            return self._value(axis.desired, f"Current {name} position is {axis.desired}")
        if code == "R":
            resolution = f"{axis.resolution_arcsec:.4f}"
            return self._value(resolution, f"{resolution} seconds arc per {name} position")
        if code == "N":
            return self._value(axis.soft[0], f"Minimum {name} position is {axis.soft[0]}")
        if code == "X":
            return self._value(axis.soft[1], f"Maximum {name} position is {axis.soft[1]}")
        if code == "S":
            speed = axis.velocity if self.velocity_mode else s.speed
            return self._value(speed, f"Target {name} speed is {speed} positions/sec")   # modelled
        if code == "D":
            speed = round(axis.state(now)[1])
            return self._value(speed, f"Current {name} speed is {speed} positions/sec")
        if code == "A":
            return self._value(s.accel, f"{name} acceleration is {s.accel} positions/sec^2")
        if code == "B":
            return self._value(s.base_speed, f"Current {name} base speed is {s.base_speed} positions/sec")
        if code == "U":
            return self._value(s.upper_speed, f"Maximum {name} speed is {s.upper_speed} positions/sec")
        return self._value(s.lower_speed, f"Minimum {name} speed is {s.lower_speed} positions/sec")

    def _position_command(self, axis: _EmulatedAxis, target: int, now: float) -> bytes:
        if self.limits_enforced:
            if target > axis.soft[1]:
                return self._error(f"Maximum allowable {axis.name} position is {axis.soft[1]}")
            if target < axis.soft[0]:
                return self._error(f"Minimum allowable {axis.name} position is {axis.soft[0]}")
        if self.slaved:
            axis.pending = target
        else:
            axis.go_to(now, target)
        return self._ok()

    def _speed_command(self, axis: _EmulatedAxis, value: int, now: float) -> bytes:
        s = axis.settings
        magnitude = abs(value) if self.velocity_mode else value
        if magnitude > s.upper_speed:
            return self._error(f"{axis.name} speed cannot exceed {s.upper_speed} positions/sec")
        if magnitude < s.lower_speed and not (self.velocity_mode and value == 0):
            # modelled on the "cannot exceed" text
            return self._error(f"{axis.name} speed cannot be less than {s.lower_speed} positions/sec")
        if self.velocity_mode:
            # Pure velocity mode: the sign is the direction; run until stopped or at a limit.
            axis.velocity = value
            if value == 0:
                axis.halt(now)
                return self._ok()
            s.speed = magnitude
            low, high = axis.soft if self.limits_enforced else (axis.hard[0] - 1e6, axis.hard[1] + 1e6)
            axis.go_to(now, high if value > 0 else low)
            return self._ok()
        s.speed = value
        if axis.moving(now):
            axis.go_to(now, axis.desired)   # speed changes apply on the fly
        return self._ok()

    def _setting_command(self, axis: _EmulatedAxis, code: str, value: int, now: float) -> bytes:
        s, name = axis.settings, axis.name
        # The unit recomputes its ramp tables for these, which it cannot do while moving.
        what = {"A": "acceleration", "B": "base speed", "U": "upper speed limit",
                "L": "lower speed limit"}[code]
        if code in "ABU" and axis.moving(now):
            return self._error(f"{name} {what} cannot be changed on-the-fly")   # modelled
        if code == "A":
            if value < 1:
                return self._error(ILLEGAL_ARGUMENT)
            s.accel = value
        elif code == "B":
            if value < 0:
                return self._error(ILLEGAL_ARGUMENT)
            if value > s.upper_speed:
                # modelled
                return self._error(f"{name} base speed cannot exceed {s.upper_speed} positions/sec")
            s.base_speed = value
        elif code == "U":
            if value > self._max_speed:
                return self._error(f"{name} speed cannot exceed {self._max_speed} positions/sec")
            if value < s.lower_speed:
                return self._error(f"{name} speed cannot be less than {s.lower_speed} positions/sec")
            s.upper_speed = value
            s.speed = min(s.speed, value)
            s.base_speed = min(s.base_speed, value)
        else:
            if value < self._min_speed:
                return self._error(f"Motor speed cannot be less than {self._min_speed} pos/sec")
            if value > s.upper_speed:
                return self._error(f"{name} speed cannot exceed {s.upper_speed} positions/sec")
            s.lower_speed = value
            s.speed = max(s.speed, value)
        return self._ok()

    # Unit-wide commands; each takes the current time.

    def _accept(self, now: float) -> bytes:
        return self._ok()

    def _await(self, now: float) -> bytes:
        for axis in self._axes():
            if axis.pending is not None:
                axis.go_to(now, axis.pending)
                axis.pending = None
        done = max(axis.trajectory.end_time for axis in self._axes())
        if done <= now:
            return self._ok()
        self._busy_until = done
        self._schedule(done, self._ok())
        return b""

    def _immediate(self, now: float) -> bytes:
        self.slaved = False
        return self._ok()

    def _slave(self, now: float) -> bytes:
        self.slaved = True
        return self._ok()

    def _halt_both(self, now: float) -> bytes:
        self.pan.halt(now)
        self.tilt.halt(now)
        return self._ok()

    def _halt_pan(self, now: float) -> bytes:
        self.pan.halt(now)
        return self._ok()

    def _halt_tilt(self, now: float) -> bytes:
        self.tilt.halt(now)
        return self._ok()

    def _reset_both(self, now: float) -> bytes:
        return self._reset([self.tilt, self.pan], now)

    def _reset_pan(self, now: float) -> bytes:
        return self._reset([self.pan], now)

    def _reset_tilt(self, now: float) -> bytes:
        return self._reset([self.tilt], now)

    def _reset(self, axes: list[_EmulatedAxis], now: float) -> bytes:
        """Calibration: each axis in turn (tilt first) runs to its upper then its lower limit
        switch, the unit printing `!T` or `!P` at each, and goes home; `*` once all are home."""
        next_start = now   # an axis starts once the previous one has found both switches
        done = now
        for axis in axes:
            axis.halt(now)
            s = axis.settings
            segments = list(axis.trajectory.segments)
            position = axis.trajectory.final
            t = max(axis.trajectory.end_time, now)
            if next_start > t:
                segments.append(_Segment(t, position, 0.0, 0.0, next_start - t))
                t = next_start
            for beyond_switch in (axis.hard[1] + 1e6, axis.hard[0] - 1e6):
                leg = plan_move(t, position, 0.0, beyond_switch, speed=s.speed, accel=s.accel,
                                base_speed=s.base_speed)
                leg, hit = stop_at_hard_stops(leg, *axis.hard)
                segments += leg.segments
                t, position = (hit if hit is not None else t), leg.final
                self._schedule(t, f"!{axis.letter}".encode())
            next_start = t
            home = plan_move(t, position, 0.0, 0.0, speed=s.speed, accel=s.accel, base_speed=s.base_speed)
            axis.trajectory = Trajectory(segments + home.segments, 0.0)
            axis.limit_hit_at = None
            axis.desired = 0
            axis.velocity = 0
            done = max(done, axis.trajectory.end_time)
        self._busy_until = done
        self._schedule(done, self._ok())
        return b""

    def _limit_query(self, now: float) -> bytes:
        if self.limits_enforced:
            return self._value("ENABLED", "Limit bounds are ENABLED (soft limits enabled)")
        return self._value("DISABLED", "Limit bounds are DISABLED (soft limits disabled)")  # modelled

    def _limits_on(self, now: float) -> bytes:
        self.limits_enforced = True
        return self._ok()

    def _limits_off(self, now: float) -> bytes:
        self.limits_enforced = False
        return self._ok()

    def _mode_query(self, now: float) -> bytes:   # modelled
        if self.velocity_mode:
            return self._value("VELOCITY", "Pure velocity speed control mode")
        return self._value("INDEPENDENT", "Independent speed and position control mode")

    def _independent_mode(self, now: float) -> bytes:
        self.velocity_mode = False
        return self._ok()

    def _velocity_mode(self, now: float) -> bytes:
        self.velocity_mode = True
        return self._ok()

    def _feedback_query(self, now: float) -> bytes:
        return self._frame("* ASCII verbose mode" if self.verbose else "* ASCII terse mode")

    def _terse(self, now: float) -> bytes:
        self.verbose = False
        return self._ok()

    def _verbose_mode(self, now: float) -> bytes:
        self.verbose = True
        return self._ok()

    def _echo_query(self, now: float) -> bytes:   # modelled
        return self._value("ON" if self.echo else "OFF", f"Echoing is {'ON' if self.echo else 'OFF'}")

    def _echo_on(self, now: float) -> bytes:
        self.echo = True
        return self._ok()

    def _echo_off(self, now: float) -> bytes:
        self.echo = False
        return self._ok()

    def _version(self, now: float) -> bytes:
        return self._frame(f"* {self.version}")

    def _supply(self, now: float) -> bytes:
        return self._frame("* Input 30 VDC @ 86 degF")

    def _save_defaults(self, now: float) -> bytes:
        self._saved = {axis.letter: replace(axis.settings) for axis in self._axes()}
        return self._ok()

    def _restore_defaults(self, now: float) -> bytes:
        for axis in self._axes():
            axis.settings = replace(self._saved[axis.letter])
        return self._ok()

    def _factory_defaults(self, now: float) -> bytes:
        for axis in self._axes():
            axis.settings = replace(self._factory)
        return self._ok()
