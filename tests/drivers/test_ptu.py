"""Tests of the PTU-D46 driver against its emulator, over a real pty (the real byte protocol), and
of the emulator itself at the byte level and in simulated time."""
from __future__ import annotations

import math
import os
import pty
import re
import threading
import time
from contextlib import contextmanager

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from drivers.errors import DeviceFault, DeviceTimeout
from drivers.ptu import (
    PtuCommandError,
    PtuD46,
    PtuLimitHit,
    PtuNotResponding,
    PtuPositionError,
    PtuSpeedError,
    PtuTimeout,
)
from drivers.ptu_emulator import D46_RESOLUTION_ARCSEC, PtuEmulator
from drivers.ptu_motion import plan_move
from drivers.serial_emulation import make_raw
from drivers.sim.clock import SimClock
from drivers.sim.faults import FaultSwitch

CLOCK_SPEED = 50.0                       # a 3 s move takes 60 ms of wall time
RES_DEG = D46_RESOLUTION_ARCSEC / 3600   # degrees per position


class ManualClock:
    """A clock the test moves by hand, for exact checks of the emulator's timing."""

    def __init__(self) -> None:
        self.t = 0.0

    def now(self) -> float:
        return self.t

    def to_wall(self, sim_seconds: float) -> float:
        return max(0.0, sim_seconds)


@pytest.fixture
def clock() -> SimClock:
    return SimClock(CLOCK_SPEED)


@contextmanager
def connected(clock, **emulator_options):
    """An emulated unit served on a pty and a driver that opened it: (driver, emulator)."""
    unit = PtuEmulator(clock, **emulator_options)
    with unit.serve_pty() as served, PtuD46(served.path, name="test-ptu", clock=clock,
                                            reply_timeout_s=2.0) as driver:
        yield driver, unit


@pytest.fixture
def emulator(clock):
    return PtuEmulator(clock)


@pytest.fixture
def server(emulator):
    served = emulator.serve_pty()
    yield served
    served.stop()


@pytest.fixture
def ptu(server, clock):
    driver = PtuD46(server.path, name="test-ptu", clock=clock, reply_timeout_s=2.0)
    driver.open()
    yield driver
    driver.close()


def terse_unit(clock) -> PtuEmulator:
    """An emulated unit as the driver leaves it: terse feedback, no echo."""
    return PtuEmulator(clock, echo=False, verbose=False)


# --- start-up, conversion -------------------------------------------------------------------

def test_open_sets_terse_no_echo_and_reads_limits(ptu, emulator):
    assert (emulator.echo, emulator.verbose) == (False, False)
    limits = ptu.limits
    assert limits.pan_resolution_deg == pytest.approx(185.1428 / 3600)
    assert limits.tilt_resolution_deg == pytest.approx(185.1428 / 3600)
    assert (limits.pan_min_deg, limits.pan_max_deg) == pytest.approx((-3090 * RES_DEG, 3090 * RES_DEG))
    assert (limits.tilt_min_deg, limits.tilt_max_deg) == pytest.approx((-907 * RES_DEG, 604 * RES_DEG))
    assert limits.pan_max_speed_deg_s == pytest.approx(2902 * RES_DEG)
    assert limits.tilt_min_speed_deg_s == pytest.approx(31 * RES_DEG)
    assert "Pan-Tilt Controller" in ptu.version()
    ptu.check()


def test_degrees_convert_through_the_units_resolution(ptu, emulator):
    ptu.move_to(45.0, -30.0)
    pan, tilt = ptu.wait_until_stopped(timeout_s=30)
    assert emulator.true_positions() == (round(45.0 / RES_DEG), round(-30.0 / RES_DEG))
    assert (pan, tilt) == pytest.approx(emulator.true_angles_deg(), abs=1e-9)
    assert abs(pan - 45.0) <= RES_DEG / 2 and abs(tilt + 30.0) <= RES_DEG / 2


@pytest.mark.parametrize("framing", [
    {"line_end": b"\r"},                           # the D46 manual's "*<CR>"
    {"reply_prefix": b"\n", "line_end": b"\r\n"},  # a D48E's "\n* 23.142857\r\n"
])
def test_driver_reads_other_reply_framings(clock, framing):
    with connected(clock, **framing) as (driver, unit):
        driver.move_to(5.0, 5.0)
        assert driver.wait_until_stopped(10) == pytest.approx(unit.true_angles_deg(), abs=1e-9)
        with pytest.raises(PtuCommandError, match="Illegal Command Entered"):
            driver.command("XYZ")
        assert driver.position() == pytest.approx(unit.true_angles_deg(), abs=1e-9)


def test_driver_over_tcp_socket_url(clock):
    unit = PtuEmulator(clock)
    with unit.serve_tcp() as served, PtuD46(served.url, clock=clock, reply_timeout_s=2.0) as driver:
        assert served.url.startswith("socket://127.0.0.1:")
        driver.move_to(-10.0, 10.0)
        assert driver.wait_until_stopped(10) == pytest.approx((-10.0, 10.0), abs=RES_DEG)


# --- motion and timing ----------------------------------------------------------------------

def test_move_takes_the_trapezoid_time():
    # accel 2000 pos/s^2, speed 1000 pos/s, base 100 pos/s, 3000 positions:
    # ramps of (1000-100)/2000 = 0.45 s over 247.5 positions each, cruise 2505 positions = 2.505 s.
    clock = SimClock(20.0)   # slower, so wall-clock latency costs less simulated time
    with connected(clock) as (ptu, emulator):
        ptu.command("PA2000")
        ptu.command("PB100")
        ptu.command("PS1000")
        expected_s = 2 * 0.45 + 2.505
        started = clock.now()
        ptu.move_to(3000 * RES_DEG, 0.0)
        ptu.wait_until_stopped(timeout_s=30)
        elapsed = clock.now() - started
        # Never early (but for the last half position); late by polling and pty round trips.
        assert expected_s - 0.01 <= elapsed <= expected_s + 0.5
        assert emulator.true_positions() == (3000, 0)


def test_trapezoid_profile_in_simulated_time():
    clock = ManualClock()
    unit = terse_unit(clock)
    assert unit.feed(b"PB100 PP3000 ") == b"*\r\n*\r\n"
    for t, expected in [(0.45, 247.5), (1.0, 797.5), (2.955, 2752.5), (3.405, 3000.0)]:
        clock.t = t
        assert unit.true_positions()[0] == pytest.approx(expected, abs=1e-6)
    clock.t = 3.404
    assert unit.is_moving()
    clock.t = 3.406
    assert not unit.is_moving()
    # A short move never reaches full speed: a triangle peaking at sqrt((2*2000*200 + 2*100^2) / 2).
    assert unit.feed(b"PP2800 ") == b"*\r\n"
    peak = math.sqrt((2 * 2000 * 200 + 2 * 100 ** 2) / 2)
    clock.t += 2 * (peak - 100) / 2000 - 1e-4
    assert unit.is_moving()
    clock.t += 2e-4
    assert not unit.is_moving() and unit.true_positions()[0] == 2800


@settings(max_examples=200, deadline=None)
@given(p0=st.floats(-3000, 3000), v0=st.floats(-2900, 2900), target=st.floats(-3000, 3000),
       speed=st.floats(31, 2902), accel=st.floats(100, 20000), base=st.floats(0, 2902))
def test_planned_profiles_are_physical(p0, v0, target, speed, accel, base):
    trajectory = plan_move(0.0, p0, v0, target, speed=speed, accel=accel, base_speed=base)
    assert trajectory.final == target
    previous = p0
    for segment in trajectory.segments:
        # Continuous position, acceleration within the unit's, speed within what was commanded.
        assert segment.p0 == pytest.approx(previous, abs=1e-6)
        assert abs(segment.accel) <= accel * (1 + 1e-9)
        end_position, end_velocity = segment.state_at(segment.end_time)
        assert max(abs(segment.v0), abs(end_velocity)) <= max(speed, abs(v0)) + 1e-6
        previous = end_position
    assert previous == pytest.approx(target, abs=1e-5)


def test_retarget_on_the_fly_brakes_passes_the_target_and_returns():
    clock = ManualClock()
    unit = terse_unit(clock)
    unit.feed(b"PB100 PP3000 ")
    clock.t = 1.0                              # at 797.5 positions, 1000 pos/s
    before = unit.true_positions()[0]
    assert unit.feed(b"PP900 ") == b"*\r\n"  # too close to stop: it brakes to 1045 and comes back
    assert unit.true_positions()[0] == before  # no jump in position
    clock.t = 1.0 + (1 - math.sqrt(1 - 0.41)) / 2   # 797.5 + 1000 t - 1000 t^2 = 900, on the way out
    assert unit.true_positions()[0] == pytest.approx(900, abs=2) and unit.is_moving()
    assert unit.feed(b"PP PO ") == b"* 900\r\n* 900\r\n"   # at the target yet moving: why
                                                           # the driver reads twice (is_moving)
    clock.t = 1.0 + 0.45                       # braked to rest at the far point
    assert unit.true_positions()[0] == pytest.approx(797.5 + 247.5)
    clock.t = 10.0
    assert unit.true_positions() == (900, 0) and not unit.is_moving()


def test_pure_velocity_mode_runs_until_told_or_at_the_limit():
    clock = ManualClock()
    unit = terse_unit(clock)
    assert unit.feed(b"CV PS-500 TS100 ") == b"*\r\n" * 3
    clock.t = 1.0
    assert unit.feed(b"PD PS ") == b"* -500\r\n* -500\r\n"
    assert unit.feed(b"PS0 ") == b"*\r\n"   # stops at once: 500 pos/s is below the base speed
    assert unit.true_positions()[0] == -500
    clock.t = 100.0                          # tilt ran into its soft limit and stopped there
    assert unit.true_positions()[1] == 604 and not unit.is_moving()


def test_defaults_save_restore_factory():
    unit = terse_unit(ManualClock())
    assert unit.feed(b"PA3000 DS PA1000 DR PA ") == b"*\r\n" * 4 + b"* 3000\r\n"
    assert unit.feed(b"DF PA ") == b"*\r\n* 2000\r\n"


def test_halt_mid_move_stops_between_start_and_target(ptu, emulator, clock):
    ptu.move_to(100.0, 0.0)   # 1944 positions at 1000 pos/s: about 1.9 s
    clock.sleep(0.8)
    ptu.halt()
    pan, _ = ptu.wait_until_stopped(timeout_s=10)
    assert 10.0 < pan < 90.0
    assert not emulator.is_moving()
    assert emulator.true_angles_deg()[0] == pytest.approx(pan, abs=RES_DEG)


def test_speed_is_set_before_the_move(ptu, emulator, clock):
    ptu.move_to(20.0, 0.0, speed_deg_s=10.0)
    assert emulator.pan.settings.speed == emulator.tilt.settings.speed == round(10.0 / RES_DEG)
    started = clock.now()
    ptu.wait_until_stopped(timeout_s=30)
    assert 1.95 <= clock.now() - started <= 2.5   # 389 positions at 389 pos/s


# --- refusals with the unit's own texts -----------------------------------------------------

def test_out_of_range_targets_are_refused_before_sending(ptu, emulator):
    with pytest.raises(PtuPositionError) as refused:
        ptu.move_to(170.0, 0.0)
    assert refused.value.axis == "pan"
    assert refused.value.allowed_deg == pytest.approx((-3090 * RES_DEG, 3090 * RES_DEG))
    assert "test-ptu" in str(refused.value) and "170" in str(refused.value)
    with pytest.raises(PtuPositionError) as refused:
        ptu.move_to(0.0, -50.0)
    assert refused.value.axis == "tilt"
    assert not emulator.is_moving() and emulator.pan.desired == 0 and emulator.tilt.desired == 0


def test_the_units_position_errors_carry_its_text(ptu):
    with pytest.raises(PtuPositionError, match="Maximum allowable Pan position is 3090") as refused:
        ptu.command("PP4000")
    assert refused.value.sent == "PP4000"
    assert refused.value.allowed_deg == pytest.approx((-3090 * RES_DEG, 3090 * RES_DEG))
    with pytest.raises(PtuPositionError, match="Minimum allowable Tilt position is -907"):
        ptu.command("TP-1000")


def test_out_of_range_speeds_are_refused(ptu, emulator):
    with pytest.raises(PtuSpeedError) as refused:
        ptu.move_to(10.0, 0.0, speed_deg_s=200.0)
    assert refused.value.allowed_deg_s == pytest.approx((31 * RES_DEG, 2902 * RES_DEG))
    assert not emulator.is_moving()
    with pytest.raises(PtuSpeedError, match="Pan speed cannot exceed 2902 positions/sec"):
        ptu.command("PS5000")
    with pytest.raises(PtuSpeedError, match="Motor speed cannot be less than 31 pos/sec"):
        ptu.command("PL20")


def test_acceleration_cannot_change_while_moving(ptu):
    ptu.move_to(50.0, 0.0)
    with pytest.raises(PtuCommandError, match="acceleration cannot be changed on-the-fly"):
        ptu.command("PA3000")
    ptu.wait_until_stopped(timeout_s=10)
    ptu.command("PA3000")
    assert ptu.command("PA") == "3000"


def test_illegal_command(ptu):
    with pytest.raises(PtuCommandError, match="Illegal Command Entered") as refused:
        ptu.command("XYZ")
    assert refused.value.reply == "! Illegal Command Entered"
    assert ptu.position() == (0.0, 0.0)   # the stream stays in step


# --- reset, await, slaved mode --------------------------------------------------------------

def test_reset_calibrates_and_returns_home(ptu, emulator, clock):
    ptu.move_to(30.0, 10.0)
    ptu.wait_until_stopped(timeout_s=10)
    started = clock.now()
    ptu.reset(timeout_s=120)
    assert clock.now() - started > 10.0   # both axes ran to both switches and back
    assert ptu.position() == (0.0, 0.0)
    assert emulator.true_positions() == (0.0, 0.0)
    assert not ptu.is_moving()            # the reset's !T!T!P!P are no limit hits


def test_reset_reply_bytes():
    clock = ManualClock()
    unit = terse_unit(clock)
    assert unit.feed(b"R PP ") == b""
    replies = b""
    while unit.next_event_time() is not None:
        clock.t = unit.next_event_time()
        replies += unit.poll()
    assert replies == b"!T!T!P!P*\r\n* 0\r\n"   # the PP waited in the input buffer
    assert clock.t > 10.0


def test_await_replies_only_when_both_axes_stopped():
    clock = ManualClock()
    unit = terse_unit(clock)
    assert unit.feed(b"PP1000 TP300 A ") == b"*\r\n*\r\n"
    assert unit.feed(b"PP ") == b""            # not read while the await holds the unit
    clock.t = 0.5
    assert unit.poll() == b""
    clock.t = 1.0                              # pan: 1000 positions at 1000 pos/s
    assert unit.poll() == b"*\r\n* 1000\r\n"
    assert unit.feed(b"A ") == b"*\r\n"       # already stopped: at once


def test_slaved_mode_executes_on_await():
    clock = ManualClock()
    unit = terse_unit(clock)
    assert unit.feed(b"S PP500 TP-200 ") == b"*\r\n" * 3
    clock.t = 5.0
    assert unit.true_positions() == (0.0, 0.0) and not unit.is_moving()
    assert unit.feed(b"A ") == b""
    clock.t = 5.5
    assert unit.poll() == b"*\r\n"
    assert unit.true_positions() == (500, -200)
    assert unit.feed(b"I PP0 ") == b"*\r\n*\r\n"
    assert unit.is_moving()


# --- bytes: verbose feedback, echo, illegal input -------------------------------------------

def test_verbose_feedback_and_echo_bytes():
    clock = ManualClock()
    unit = PtuEmulator(clock)   # as powered up: echo on, verbose
    assert unit.feed(b"PP ") == b"PP * Current Pan position is 0\r\n"
    assert unit.feed(b"pn\r") == b"pn\r* Minimum Pan position is -3090\r\n"
    assert unit.feed(b"PR ") == b"PR * 185.1428 seconds arc per Pan position\r\n"
    assert unit.feed(b"PA ") == b"PA * Pan acceleration is 2000 positions/sec^2\r\n"
    assert unit.feed(b"PU ") == b"PU * Maximum Pan speed is 2902 positions/sec\r\n"
    assert unit.feed(b"PS9999 ") == b"PS9999 ! Pan speed cannot exceed 2902 positions/sec\r\n"
    assert unit.feed(b"T") == b"T"             # a command split across reads
    assert unit.feed(b"P ") == b"P * Current Tilt position is 0\r\n"
    assert unit.feed(b"L ") == b"L * Limit bounds are ENABLED (soft limits enabled)\r\n"
    assert unit.feed(b"FT ") == b"FT *\r\n"
    assert unit.feed(b"PP ") == b"PP * 0\r\n"
    assert unit.feed(b"F ") == b"F * ASCII terse mode\r\n"
    assert unit.feed(b"ED ") == b"ED *\r\n"
    assert unit.feed(b"PP ") == b"* 0\r\n"
    assert unit.feed(b"EE ") == b"*\r\n"
    assert unit.feed(b"tp ") == b"tp * 0\r\n"


def test_illegal_input_bytes():
    unit = terse_unit(ManualClock())
    assert unit.feed(b"XYZ ") == b"! Illegal Command Entered\r\n"
    assert unit.feed(b"PQ ") == b"! Illegal Command Entered\r\n"
    assert unit.feed(b"PP12x ") == b"! Illegal Argument\r\n"
    assert unit.feed(b"P" * 100 + b" ") == b"! Illegal Command Entered\r\n"
    assert unit.feed(b"  \r\r  ") == b""      # empty commands are ignored
    assert unit.feed(b"PP ") == b"* 0\r\n"


# --- limit hits -----------------------------------------------------------------------------

def test_unprompted_limit_notice_bytes():
    clock = ManualClock()
    unit = terse_unit(clock)
    assert unit.feed(b"PP4000 ") == b"! Maximum allowable Pan position is 3090\r\n"
    assert unit.feed(b"LD PP4000 ") == b"*\r\n*\r\n"
    clock.t = unit.next_event_time()
    assert unit.poll() == b"!P"
    assert unit.true_positions()[0] == 3290     # stopped at the hard stop
    assert unit.feed(b"PP PO ") == b"* 3290\r\n* 3290\r\n"


def test_unprompted_limit_hit_surfaces_in_the_driver(ptu, emulator, clock):
    ptu.command("LD")
    ptu.command("PP3500")   # past the hard stop at 3290
    with pytest.raises(PtuLimitHit) as hit:
        ptu.wait_until_stopped(timeout_s=20)
    assert hit.value.axes == ("pan",) and hit.value.reply == "!P"
    assert ptu.position()[0] == pytest.approx(3290 * RES_DEG)
    assert not ptu.is_moving()   # raised once


def test_limit_notice_between_replies_does_not_disturb_position_reads(ptu, emulator, clock):
    ptu.command("LD")
    ptu.command("TP-1200")  # past the tilt hard stop at -1107
    clock.sleep(3.0)        # the !T arrives (at 1.1 s) while nobody is reading
    assert ptu.position()[1] == pytest.approx(-1107 * RES_DEG)
    with pytest.raises(PtuLimitHit) as hit:
        ptu.is_moving()
    assert hit.value.axes == ("tilt",)


# --- a silent or vanished unit --------------------------------------------------------------

def test_stopped_emulator_gives_an_error_not_a_hang(emulator, server, clock):
    driver = PtuD46(server.path, clock=clock, reply_timeout_s=0.3)
    driver.open()
    server.stop()
    started = time.monotonic()
    with pytest.raises((PtuTimeout, PtuNotResponding)):
        driver.position()
    with pytest.raises(PtuNotResponding):
        driver.check()
    assert time.monotonic() - started < 3.0
    driver.close()


def test_a_silent_line_is_a_unit_not_answering():
    master, slave = pty.openpty()
    make_raw(slave)
    try:
        driver = PtuD46(os.ttyname(slave), name="mute", reply_timeout_s=0.2)
        started = time.monotonic()
        with pytest.raises(PtuNotResponding, match="mute on .*: stopped answering") as timed_out:
            driver.open()
        assert timed_out.value.sent == "FT" and not isinstance(timed_out.value, DeviceTimeout)
        assert driver.not_answering and "stopped answering" in driver.not_answering
        assert time.monotonic() - started < 2.0
        with pytest.raises(PtuNotResponding):
            driver.check()   # open() failed, so the line is closed
    finally:
        os.close(master)
        os.close(slave)


def test_an_injected_fault_hangs_the_unit_mid_move_until_cleared(clock):
    fault = FaultSwitch("ptu")
    unit = PtuEmulator(clock, fault=fault)
    with unit.serve_pty() as served, PtuD46(served.path, name="test-ptu", clock=clock,
                                            reply_timeout_s=0.3) as driver:
        driver.move_to(90.0, 0.0, speed_deg_s=3.0)   # 30 s simulated, 0.6 s of wall time
        fault.arm(after=1)                       # PP answered, TP and everything after it not
        with pytest.raises(PtuNotResponding, match="test-ptu on .*: stopped answering") as silent:
            driver.position()
        assert silent.value.reply is None and driver.not_answering
        assert fault.state().tripped and fault.state().unanswered >= 1
        assert unit.is_moving()                  # the axes go on with the move they were making
        fault.clear()
        pan, _ = driver.position()               # the stale request was dropped: the line is usable
        assert 0.0 < pan < 90.0 and driver.not_answering is None


def test_missing_device_is_not_responding():
    with pytest.raises(PtuNotResponding, match="cannot open"):
        PtuD46("/dev/does-not-exist-ptu").open()


def test_errors_are_device_faults_the_server_can_map():
    for error in (PtuCommandError, PtuPositionError, PtuSpeedError, PtuLimitHit, PtuNotResponding):
        assert issubclass(error, DeviceFault) and not issubclass(error, DeviceTimeout)
    assert issubclass(PtuTimeout, DeviceTimeout)
    fault = PtuCommandError("the unit refused the command", device="ptu", port="/dev/ttyS0",
                            sent="XYZ", reply="! Illegal Command Entered")
    assert fault.device == "ptu"
    assert str(fault) == ("ptu on /dev/ttyS0: the unit refused the command; sent 'XYZ'; "
                          "unit said '! Illegal Command Entered'")


# --- threads --------------------------------------------------------------------------------

def test_position_reads_from_another_thread_during_a_move(ptu, clock):
    readings: list[float] = []
    failures: list[BaseException] = []
    moving = threading.Event()
    moving.set()

    def status_reader():
        while moving.is_set():
            try:
                readings.append(ptu.position()[0])
            except BaseException as exc:   # collected, asserted in the main thread
                failures.append(exc)
                return

    reader = threading.Thread(target=status_reader)
    reader.start()
    try:
        ptu.move_to(150.0, 10.0)
        final = ptu.wait_until_stopped(timeout_s=30)
    finally:
        moving.clear()
        reader.join(5)
    assert not failures
    assert len(readings) > 10
    assert all(a <= b for a, b in zip(readings[:-1], readings[1:], strict=True))   # a clean, monotonic stream
    assert 0.0 <= min(readings) and max(readings) <= final[0]


# --- arbitrary input ------------------------------------------------------------------------

@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.binary(max_size=300))
def test_arbitrary_bytes_never_break_the_emulator(data):
    clock = ManualClock()
    unit = PtuEmulator(clock)
    unit.feed(data + b"\r")  # the CR ends any half command, which may start a reset
    clock.t += 1e4           # long enough for any await, reset or velocity run to end
    unit.poll()
    unit.feed(b"ED FT ")
    assert unit.feed(b"PP ") == b"* %d\r\n" % unit.pan.position(clock.t)


_COMMANDS = ["PP", "TP", "PO", "TO", "PS", "TS", "PD", "TD", "PA", "TA", "PB", "TB", "PU", "TU",
             "PL", "TL", "PN", "PX", "TN", "TX", "PR", "TR", "L", "LE", "LD", "C", "CI", "CV", "I",
             "S", "A", "H", "HP", "HT", "R", "RP", "RT", "F", "FT", "FV", "E", "V", "O", "DS", "DR",
             "DF", "ED", "X", "PZ", "?"]
_ARGUMENTS = st.one_of(st.just(""), st.integers(-5000, 5000).map(str),
                       st.text(alphabet="0123456789+-x", max_size=4))
_FRAME = re.compile(rb"(?:![PT])*(?:\*(?: [ -~]+)?|! [ -~]+)")


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(st.tuples(st.sampled_from(_COMMANDS), _ARGUMENTS, st.floats(0, 20)), max_size=30))
def test_every_command_gets_one_well_formed_reply(steps):
    clock = ManualClock()
    unit = PtuEmulator(clock, echo=False)
    out = bytearray()
    for command, argument, pause_s in steps:
        out += unit.feed(f"{command}{argument} ".encode())
        clock.t += pause_s
        out += unit.poll()
    while unit.next_event_time() is not None:   # run until idle: awaits and resets queue up
        clock.t = max(clock.t, unit.next_event_time())
        out += unit.poll()
    *frames, tail = bytes(out).split(b"\r\n")
    assert re.fullmatch(rb"(?:![PT])*", tail)     # only unprompted notices lack a line end
    assert len(frames) == len(steps)
    for frame in frames:
        assert _FRAME.fullmatch(frame), frame
