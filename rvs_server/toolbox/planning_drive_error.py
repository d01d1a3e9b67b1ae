"""How far the rover may drive a path blind before its drive error could eat the clearance it keeps.

Between two maps the rover drives open loop: it turns in place towards each waypoint, then drives
straight, from where it believes it stands. A turn is off by a share of its angle plus a little, the
heading creeps while driving, the wheels slip sideways and the distance is off by a few per cent. The
error grows along the drive, and a large first turn tilts every metre after it. Hazards are grown by
the rover's radius plus a margin, so the margin is all the error may take: where the error's
sigmas times its standard deviation exceed what the path keeps beyond the rover's radius, the drive
ends, the rover maps and localises again, and the error starts from zero.

The error is propagated to first order (an extended Kalman filter's prediction step, without the
update) over the pose (x, y, heading), with the model of drivers/sim/motion.py:

    turn executed     = turn x (1 + N(0, turn_scale)) + N(0, turn_noise)
    distance executed = distance x (1 + N(0, distance_scale))
    heading drift     = N(0, drift per metre) x distance, spread evenly along the drive
    lateral slip      = N(0, slip per metre) x distance, sideways to the drive

A real rover's GNC states its own figures; a rover that closes its drives on visual odometry has
smaller ones.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from .grid import GridSpec
from .planning_paths import DrivablePrefix, world_to_cells


class DriveErrorModel(Protocol):
    """Standard deviations of the rover's open-loop motion errors (drivers.sim.config.DriveError is one)."""
    turn_scale: float               # relative error of a turn's angle
    turn_noise_deg: float           # absolute error of every turn
    distance_scale: float           # relative error of a distance
    heading_drift_deg_per_m: float
    lateral_slip_per_m: float


@dataclass(frozen=True)
class DriveErrorProfile:
    points: np.ndarray   # (N, 2) world (x, y) along the path, the start first
    along_m: np.ndarray  # (N,) distance driven to each point
    covariance: np.ndarray  # (N, 2, 2) covariance of the position error there, m^2
    segment: np.ndarray  # (N,) index of the path segment each point lies on (0 for the start)

    @property
    def sigma_m(self) -> np.ndarray:
        """(N,) standard deviation of the position error in its worst direction."""
        return np.sqrt(np.maximum(np.linalg.eigvalsh(self.covariance)[:, -1], 0.0))

    def sigma_towards(self, directions: np.ndarray) -> np.ndarray:
        """(N,) standard deviation of the position error along unit directions (N, 2)."""
        return np.sqrt(np.maximum(np.einsum("ni,nij,nj->n", directions, self.covariance, directions), 0.0))


def drive_error_profile(waypoints_xy: np.ndarray, heading_rad: float, model: DriveErrorModel,
                        sample_m: float = 0.05) -> DriveErrorProfile:
    """The position error's standard deviation along a path driven open loop from its first waypoint,
    the rover facing heading_rad there, sampled every sample_m (and at every waypoint)."""
    if not sample_m > 0:
        raise ValueError(f"sample spacing must be > 0 m, got {sample_m!r}")
    waypoints = np.asarray(waypoints_xy, dtype=np.float64).reshape(-1, 2)
    covariance = np.zeros((3, 3))       # x, y, heading; the start is where the last map put the rover
    heading = float(heading_rad)
    points, along, spread, segment = [waypoints[0]], [0.0], [np.zeros((2, 2))], [0]
    driven = 0.0
    for index, (a, b) in enumerate(zip(waypoints[:-1], waypoints[1:]), start=1):
        length = float(np.linalg.norm(b - a))
        if length == 0:
            continue
        bearing = math.atan2(b[1] - a[1], b[0] - a[0])
        turn = (bearing - heading + math.pi) % (2 * math.pi) - math.pi
        covariance[2, 2] += (model.turn_scale * turn) ** 2 + math.radians(model.turn_noise_deg) ** 2
        heading = bearing
        start = covariance.copy()
        steps = max(1, math.ceil(length / sample_m))
        for k in range(1, steps + 1):
            t = length * k / steps
            covariance_t = _drive_covariance(start, heading, t, model)
            points.append(a + (b - a) * (t / length))
            along.append(driven + t)
            spread.append(covariance_t[:2, :2])
            segment.append(index)
        covariance = covariance_t
        driven += length
    return DriveErrorProfile(np.array(points), np.array(along), np.array(spread), np.array(segment))


def _drive_covariance(start: np.ndarray, heading: float, length: float, model: DriveErrorModel) -> np.ndarray:
    """The pose covariance after driving `length` straight along `heading` from a pose with covariance `start`."""
    c, s = math.cos(heading), math.sin(heading)
    # A heading error tilts the whole leg: the end moves sideways by length x the error.
    jacobian = np.array([[1.0, 0.0, -s * length], [0.0, 1.0, c * length], [0.0, 0.0, 1.0]])
    # The leg's own noise: distance along, slip sideways, and drift, which turns the heading by its full
    # amount at the end and moves the end sideways by half of it times the length (spread evenly).
    noise_map = np.array([[c, -s, -s * length / 2], [s, c, c * length / 2], [0.0, 0.0, 1.0]])
    noise = np.diag([(model.distance_scale * length) ** 2, (model.lateral_slip_per_m * length) ** 2,
                     (math.radians(model.heading_drift_deg_per_m) * length) ** 2])
    return jacobian @ start @ jacobian.T + noise_map @ noise @ noise_map.T


def cut_for_drive_error(waypoints_xy: np.ndarray, heading_rad: float, hazard_distance_m: np.ndarray, spec: GridSpec,
                        body_radius_m: float, model: DriveErrorModel, sigmas: float,
                        min_drive_m: float = 0.0) -> tuple[DrivablePrefix, float]:
    """The waypoints up to where `sigmas` standard deviations of the drive error towards the nearest
    hazard first exceed the room the path keeps beyond the rover's body (the distance to that hazard,
    `hazard_distance_m` over `spec`, minus `body_radius_m`), and that error there (sigmas x sigma,
    metres; 0 if nothing was cut). Towards the hazard: beside a rock only the sideways error counts,
    not the error along the way.

    A rover that starts closer to a hazard than its body radius (pushed there by an earlier drive) may
    drive on while it comes no closer, until it has room again; from there on the rule holds. Nor is a
    drive cut shorter than min_drive_m: a rover that stopped a hair from the clearance's edge would
    otherwise be cut to nothing, look again, and be cut to nothing again. Over that first stretch the
    error is millimetres. sigmas = 0 switches the cut off."""
    waypoints = np.asarray(waypoints_xy, dtype=np.float64).reshape(-1, 2)
    if sigmas <= 0 or len(waypoints) < 2:
        return DrivablePrefix(waypoints, True), 0.0
    profile = drive_error_profile(waypoints, heading_rad, model, sample_m=spec.cell)
    cells, inside = world_to_cells(spec, profile.points)
    rows, cols = np.where(inside, cells[:, 0], 0), np.where(inside, cells[:, 1], 0)
    room = np.where(inside, hazard_distance_m[rows, cols] - body_radius_m, -np.inf)  # off the map: no room
    towards = _towards_nearest(hazard_distance_m, spec.cell)[rows, cols]
    any_way = ~towards.any(axis=1)
    error = sigmas * np.where(any_way, profile.sigma_m, profile.sigma_towards(towards))
    # Pushed inside the body radius, the rover may drive while it does not come closer, until it has room.
    leaving = np.logical_and.accumulate((room <= 0) & np.r_[True, np.diff(room) >= -1e-9])
    cut_at = np.r_[0.0, profile.along_m[:-1]]      # a cut keeps the drive up to the sample before
    over = ~leaving & (error > room) & (cut_at >= min_drive_m)
    if not over.any():
        return DrivablePrefix(waypoints, True), 0.0
    first = int(np.argmax(over))
    last = max(first - 1, 0)
    head = waypoints[:profile.segment[last]]
    return DrivablePrefix(np.vstack([head, profile.points[last]]), False), float(error[first])


def _towards_nearest(distance_m: np.ndarray, cell: float) -> np.ndarray:
    """(rows, cols, 2) unit world (x, y) directions towards the nearest hazard: down the distance map's
    gradient. Where it has none (on a ridge between two hazards, far from any), (0, 0) stands for every
    direction: the worst one is taken there."""
    finite = np.where(np.isfinite(distance_m), distance_m, 0.0)
    d_row, d_col = np.gradient(finite, cell)
    direction = -np.stack([d_col, d_row], axis=-1)      # rows run along y, columns along x
    norm = np.linalg.norm(direction, axis=-1, keepdims=True)
    return np.where(norm > 0.5, direction / np.maximum(norm, 1e-12), 0.0)
