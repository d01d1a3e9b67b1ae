"""PTU-D46 motion model of the emulator: trapezoidal velocity profiles in simulated time.

This file holds
- `Trajectory`, one axis's motion: constant-acceleration segments (`_Segment`) end to end, then rest;
- `plan_move`, the D46's profile from any state to rest at a target: jump to the base speed, ramp,
  cruise, ramp down, stop; braking to rest first when moving away from the target or too fast;
- `stop_at_hard_stops`, a trajectory cut where it reaches a limit switch.

Positions are the unit's steps, times simulated seconds. `drivers.ptu_emulator` moves its axes so.
"""
from __future__ import annotations

import math
from typing import NamedTuple


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
    def at_rest(cls, position: float) -> Trajectory:
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
