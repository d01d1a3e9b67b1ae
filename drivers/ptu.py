"""Pan-tilt unit: Directed Perception / FLIR PTU-D46 family (also E46, D48) on its ASCII protocol.

This file holds the protocol driver and what it reports:
- the errors (`PtuError` and its subclasses) and `PtuLimits`, what the unit reports about itself;
- `PtuD46`, the real driver: a pyserial URL in (`/dev/ttyS0`, a pty path, `socket://host:port`),
  degrees out, thread-safe.

The emulator is `drivers.ptu_emulator.PtuEmulator`, a byte-level model of the unit served on a real
line, so the driver is tested on the real bytes; its motion is `drivers.ptu_motion`.

Protocol facts come from the PTU-D46 user's manual (v2.14) and open-source drivers.
"""
from __future__ import annotations

import logging
import math
import re
import threading
import time
from dataclasses import dataclass

import serial

from drivers.errors import DeviceFault, DeviceTimeout
from drivers.sim.clock import SimClock

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

    def __enter__(self) -> PtuD46:
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
        targets = {axis: self._checked_target(axis, deg) for axis, deg in zip(AXES, (pan_deg, tilt_deg), strict=True)}
        commands = []
        if speed_deg_s is not None:
            for axis, letter in zip(AXES, "PT", strict=True):
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
        numbers = [self._number(reply, command) for reply, command in zip(replies, sent, strict=True)]
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
                for reply, command in zip(self._exchange(commands), commands, strict=True)]

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
