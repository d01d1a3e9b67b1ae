"""PTU-D46 emulator: a byte-level model of the unit, for `drivers.ptu.PtuD46` to talk to.

`PtuEmulator` holds the command parser, terse/verbose feedback, echo, position and speed limits with
the unit's own error texts, trapezoidal motion (`drivers.ptu_motion`) evaluated in simulated time,
await, slaved mode, halt, reset, unprompted limit notices. `serve_pty()` and `serve_tcp()` put it on
a real line, so the driver is tested on the real bytes.

Protocol facts come from the PTU-D46 user's manual (v2.14) and open-source drivers. The verbose reply
texts are checked one by one in docs/ptu-verbose-replies.md: the D46 v2.14 and D300 v2.18/v2.19
manuals' examples first, then, where the manuals are silent, drivers written against real units
(flirptu, Miro's DpPanTilt); texts no source shows are marked "modelled" below.
"""
from __future__ import annotations

import heapq
import math
import re
import threading
from dataclasses import dataclass, replace

from drivers.ptu import ARCSEC_PER_DEGREE
from drivers.ptu_motion import Trajectory, _braking_distance, _Segment, plan_move, stop_at_hard_stops
from drivers.serial_emulation import PtyServer, TcpServer
from drivers.sim.faults import FaultSwitch

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

    def true_positions(self, at_s: float | None = None) -> tuple[float, float]:
        """Where the axes truly stand (positions) at clock time `at_s`, default now."""
        with self._lock:
            t = self._clock.now() if at_s is None else at_s
            return self.pan.state(t)[0], self.tilt.state(t)[0]

    def true_angles_deg(self, at_s: float | None = None) -> tuple[float, float]:
        pan, tilt = self.true_positions(at_s)
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
            return self._value(speed, f"Target {name} speed is {speed} positions/sec")   # flirptu, Miro
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
        return self._value("DISABLED", "Limit bounds are DISABLED (hard limits only: use care)")  # Miro

    def _limits_on(self, now: float) -> bytes:
        self.limits_enforced = True
        return self._ok()

    def _limits_off(self, now: float) -> bytes:
        self.limits_enforced = False
        return self._ok()

    def _mode_query(self, now: float) -> bytes:   # flirptu (independent); velocity modelled on it
        if self.velocity_mode:
            return self._value("VELOCITY", "PTU is in Pure Velocity Mode")
        return self._value("INDEPENDENT", "PTU is in Independent Mode")

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

    def _echo_query(self, now: float) -> bytes:   # verbose: flirptu, Miro; terse modelled
        return self._value("ON" if self.echo else "OFF", f"Echoing {'ON' if self.echo else 'OFF'}")

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
