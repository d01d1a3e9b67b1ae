"""How the simulated rover executes motion commands: turn in place, then drive straight, with error.

A skid-steered rover such as the thesis' Pioneer 3-AT does not turn or roll exactly as told: wheels
slip on loose soil, a turn overshoots or falls short by a share of the angle, the distance driven is
off by a few per cent, and the heading creeps while driving. The defaults are those of a rover that
closes its turns on a gyro (a 90 degree turn is off by about 2 degrees) and counts wheel turns: after
a 4 m leg it is typically 10-20 cm from where it believes. Those errors are what makes
self-localisation necessary, so they are drawn here from seeded normal distributions:

  turn executed     = turn x (1 + N(0, turn_scale)) + N(0, turn_noise)
  distance executed = distance x (1 + N(0, distance_scale))
  heading drift     = N(0, drift per metre) x distance, spread evenly along the drive
  lateral slip      = N(0, slip per metre) x distance, sideways to the drive

The true trajectory is sampled every few centimetres so collisions are checked along the way, not
only at its ends; `plan` draws it before the rover moves, so a drive can step through it in
simulated time and stop part-way (a hazard guard). Nothing here decides where to go; the caller
gives the actions.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .config import DriveError
from .rover import Rover

__all__ = ["DriveError", "Motion", "PlannedMotion", "execute", "plan", "dead_reckon", "turn_and_distance"]


@dataclass(frozen=True)
class Motion:
    """One executed action: where the rover really went, sampled along the way."""

    poses: np.ndarray          # (N, 3) true x, y, heading after each sample, first = start pose
    turn_rad: float            # the turn really made
    distance_m: float          # the (signed) distance really driven
    contacts: int              # samples at which the footprint covered a true obstacle


@dataclass(frozen=True)
class PlannedMotion:
    """Where an action will truly take the rover, sample by sample, before it moves: turn samples
    (at most 10 degrees each) first, then drive samples (at most sample_m each)."""

    poses: np.ndarray          # (N, 3) true x, y, heading; poses[0] is the start
    turn_rad: float            # the turn that will really be made
    distance_m: float          # the (signed) distance that will really be driven
    turn_steps: int            # poses[1:turn_steps + 1] turn on the spot, the rest drive

    @property
    def samples(self) -> int:
        return len(self.poses) - 1


def plan(pose: tuple[float, float, float], turn_rad: float, distance_m: float, error: DriveError,
         rng: np.random.Generator, sample_m: float = 0.05) -> PlannedMotion:
    """The true trajectory of turn_rad then distance_m (negative: backwards) from pose, with error
    drawn from rng; nothing moves."""
    turn = turn_rad * (1 + rng.normal(0, error.turn_scale)) + math.radians(rng.normal(0, error.turn_noise_deg))
    distance = distance_m * (1 + rng.normal(0, error.distance_scale))
    drift = math.radians(rng.normal(0, error.heading_drift_deg_per_m)) * abs(distance)
    slip = rng.normal(0, error.lateral_slip_per_m) * abs(distance)
    x0, y0, h0 = pose
    turn_steps = max(1, math.ceil(abs(turn) / math.radians(10)))
    poses = [(x0, y0, h0)] + [(x0, y0, h0 + turn * k / turn_steps) for k in range(1, turn_steps + 1)]
    heading = h0 + turn
    drive_steps = max(1, math.ceil(abs(distance) / sample_m))
    x, y = x0, y0
    for k in range(1, drive_steps + 1):
        along = distance / drive_steps
        side = slip / drive_steps
        mid = heading + drift * (k - 0.5) / drive_steps
        x += along * math.cos(mid) - side * math.sin(mid)
        y += along * math.sin(mid) + side * math.cos(mid)
        poses.append((x, y, heading + drift * k / drive_steps))
    return PlannedMotion(np.array(poses), turn, distance, turn_steps)


def execute(rover: Rover, turn_rad: float, distance_m: float, error: DriveError, rng: np.random.Generator,
            step_height: float, sample_m: float = 0.05) -> Motion:
    """Turn by turn_rad, then drive distance_m (negative: backwards), with error; moves the rover.

    The rover is left at the executed end. Each sample's footprint is checked against the world's
    true obstacles (rocks taller than step_height): a contact is counted, not prevented, because a
    real rover would bump or climb and the point of the count is to score the planner.
    """
    planned = plan(rover.pose, turn_rad, distance_m, error, rng, sample_m)
    contacts = 0
    for px, py, ph in planned.poses[1:]:
        rover.place(px, py, ph)
        contacts += int(rover.collides(step_height))
    return Motion(planned.poses, planned.turn_rad, planned.distance_m, contacts)


def turn_and_distance(pose: tuple[float, float, float], target_xy: tuple[float, float]) -> tuple[float, float]:
    """The turn (radians, in -pi..pi) and forward distance that take a pose to a point."""
    dx, dy = target_xy[0] - pose[0], target_xy[1] - pose[1]
    bearing = math.atan2(dy, dx)
    turn = (bearing - pose[2] + math.pi) % (2 * math.pi) - math.pi
    return turn, math.hypot(dx, dy)


def dead_reckon(pose: tuple[float, float, float], turn_rad: float, distance_m: float) -> tuple[float, float, float]:
    """Where a perfect execution of the action would leave the rover: the odometry prediction."""
    heading = pose[2] + turn_rad
    return (pose[0] + distance_m * math.cos(heading), pose[1] + distance_m * math.sin(heading), heading)
