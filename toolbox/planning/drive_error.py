"""How far the rover may drive a path blind before its drive error could eat the clearance it keeps.

Between two maps the rover drives open loop: it turns in place towards each waypoint, then drives
straight, from where it believes it stands. A turn is off by a share of its angle plus a little, the
heading creeps while driving, the wheels slip sideways and the distance is off by a few per cent. The
error grows along the drive, and a large first turn tilts every metre after it. Hazards are grown by
the rover's radius plus a margin, so the margin is about all the error may take: where the error's
sigmas times its standard deviation exceed the room between the rover's footprint and the nearest
hazard, the drive ends, the rover maps and localises again, and the error starts from zero. The
footprint is a rectangle that faces along each leg, so a rock beside the path leaves more room than
one off a corner.

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

from toolbox.grid import GridSpec
from toolbox.planning.paths import DrivablePrefix, world_to_cells


class DriveErrorModel(Protocol):
    """Standard deviations of the rover's open-loop motion errors (drivers.sim.config.DriveError is one)."""
    turn_scale: float               # relative error of a turn's angle
    turn_noise_deg: float           # absolute error of every turn
    distance_scale: float           # relative error of a distance
    heading_drift_deg_per_m: float
    lateral_slip_per_m: float


@dataclass(frozen=True)
class DriveErrorProfile:
    points: np.ndarray      # (N, 2) world (x, y) along the path, the start first
    heading: np.ndarray     # (N,) the heading the rover drives with there (the start: the one it stands with)
    along_m: np.ndarray     # (N,) distance driven to each point
    covariance: np.ndarray  # (N, 3, 3) covariance of the pose error (x, y, heading) there, m^2 and rad^2
    segment: np.ndarray     # (N,) index of the path segment each point lies on (0 for the start)

    @property
    def sigma_m(self) -> np.ndarray:
        """(N,) standard deviation of the position error in its worst direction."""
        return np.sqrt(np.maximum(np.linalg.eigvalsh(self.covariance[:, :2, :2])[:, -1], 0.0))

    def sigma_of(self, offsets: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """(N, M) standard deviation, along unit world directions (N, M, 2), of the error of body points at
        body-frame offsets (M, 2) (x ahead, y left): the centre's error plus the heading's, times the lever."""
        c, s = np.cos(self.heading)[:, None], np.sin(self.heading)[:, None]
        # d(world offset)/d(heading): the offset rotated by heading + 90 degrees.
        lever = np.stack([-s * offsets[:, 0] - c * offsets[:, 1], c * offsets[:, 0] - s * offsets[:, 1]], axis=-1)
        # The point's error is J (dx, dy, dheading) with J = [I | lever]; project it on the direction.
        along = np.concatenate([directions, np.einsum("nmi,nmi->nm", directions, lever)[..., None]], axis=-1)
        return np.sqrt(np.maximum(np.einsum("nmi,nij,nmj->nm", along, self.covariance, along), 0.0))


def drive_error_profile(waypoints_xy: np.ndarray, heading_rad: float, model: DriveErrorModel,
                        sample_m: float = 0.05) -> DriveErrorProfile:
    """The pose error's covariance along a path driven open loop from its first waypoint, the rover
    facing heading_rad there, sampled every sample_m (and at every waypoint)."""
    if not sample_m > 0:
        raise ValueError(f"sample spacing must be > 0 m, got {sample_m!r}")
    waypoints = np.asarray(waypoints_xy, dtype=np.float64).reshape(-1, 2)
    covariance = np.zeros((3, 3))       # x, y, heading; the start is where the last map put the rover
    heading = float(heading_rad)
    points, headings, along, spread, segment = [waypoints[0]], [heading], [0.0], [covariance], [0]
    driven = 0.0
    for index, (a, b) in enumerate(zip(waypoints[:-1], waypoints[1:], strict=True), start=1):
        length = float(np.linalg.norm(b - a))
        if length == 0:
            continue
        bearing = math.atan2(b[1] - a[1], b[0] - a[0])
        turn = (bearing - heading + math.pi) % (2 * math.pi) - math.pi
        covariance = covariance.copy()
        covariance[2, 2] += (model.turn_scale * turn) ** 2 + math.radians(model.turn_noise_deg) ** 2
        heading = bearing
        start = covariance
        steps = max(1, math.ceil(length / sample_m))
        for k in range(1, steps + 1):
            t = length * k / steps
            covariance = _drive_covariance(start, heading, t, model)
            points.append(a + (b - a) * (t / length))
            headings.append(heading)
            along.append(driven + t)
            spread.append(covariance)
            segment.append(index)
        driven += length
    return DriveErrorProfile(np.array(points), np.array(headings), np.array(along), np.array(spread),
                             np.array(segment))


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


def footprint_outline(length_m: float, width_m: float, spacing_m: float, filled: bool = False) -> np.ndarray:
    """(M, 2) body-frame points (x ahead, y left) around a rectangular footprint, at most spacing_m apart;
    filled: over all of it."""
    if not (length_m > 0 and width_m > 0 and spacing_m > 0):
        raise ValueError(f"footprint {length_m!r} x {width_m!r} m and spacing {spacing_m!r} m must be > 0")
    a, b = length_m / 2, width_m / 2
    if filled:
        x = np.linspace(-a, a, max(2, math.ceil(length_m / spacing_m) + 1))
        y = np.linspace(-b, b, max(2, math.ceil(width_m / spacing_m) + 1))
        return np.stack(np.meshgrid(x, y), axis=-1).reshape(-1, 2)
    corners = np.array([[a, b], [-a, b], [-a, -b], [a, -b], [a, b]])
    sides = []
    for p, q in zip(corners[:-1], corners[1:], strict=True):
        n = max(1, math.ceil(np.linalg.norm(q - p) / spacing_m))
        sides.append(p + (q - p) * (np.arange(n)[:, None] / n))
    return np.vstack(sides)


def cut_for_drive_error(waypoints_xy: np.ndarray, heading_rad: float, hazard_distance_m: np.ndarray, spec: GridSpec,
                        footprint_m: tuple[float, float], model: DriveErrorModel, sigmas: float,
                        min_drive_m: float = 0.0) -> tuple[DrivablePrefix, float]:
    """The waypoints up to where `sigmas` standard deviations of the drive error first exceed the room
    between the rover's footprint (length, width) and the nearest hazard, and that error there (metres;
    0 if nothing was cut). `hazard_distance_m` over `spec` is each cell's distance to the nearest hazard.

    The rover drives each leg facing along it, so its footprint there is known: beside a rock the room is
    what the side keeps, ahead of one what a corner keeps. Each point of the outline gets the room the
    distance map gives there, and the error of that point towards the hazard: the centre's position error
    and the heading error times the point's lever.

    A rover that starts closer to a hazard than its body allows (pushed there by an earlier drive) may
    drive on while it comes no closer, until it has room again; from there on the rule holds. Nor is a
    drive cut shorter than min_drive_m: a rover that stopped a hair from the clearance's edge would
    otherwise be cut to nothing, look again, and be cut to nothing again. Over that first stretch the
    error is millimetres. sigmas = 0 switches the cut off."""
    waypoints = np.asarray(waypoints_xy, dtype=np.float64).reshape(-1, 2)
    if sigmas <= 0 or len(waypoints) < 2:
        return DrivablePrefix(waypoints, True), 0.0
    profile = drive_error_profile(waypoints, heading_rad, model, sample_m=spec.cell)
    outline = footprint_outline(*footprint_m, spacing_m=spec.cell)
    distance, towards = _sample(hazard_distance_m, _towards_nearest(hazard_distance_m, spec.cell), spec,
                                _place(outline, profile))
    # Where the direction is unknown: the position's worst spread plus the heading's times the lever.
    worst = profile.sigma_m[:, None] + np.sqrt(profile.covariance[:, 2, 2])[:, None] * np.hypot(*outline.T)
    assert towards is not None   # _sample gives directions when it is given them
    error = sigmas * np.where(towards.any(axis=-1), profile.sigma_of(outline, towards), worst)
    margin = distance - error                      # (N, M): room left at each outline point after the error
    # The outline's room; with a hazard inside the footprint (pushed onto it: only a rover leaving can
    # be), less than none: the centre's distance less the circumscribed radius, which grows as it leaves.
    inside = footprint_outline(*footprint_m, spacing_m=spec.cell, filled=True)
    covered = _sample(hazard_distance_m, None, spec, _place(inside, profile))[0]
    centre = _sample(hazard_distance_m, None, spec, profile.points)[0]
    room = np.where((covered < spec.cell / 2).any(axis=1), np.minimum(centre - math.hypot(*footprint_m) / 2, 0.0),
                    distance.min(axis=1))
    # Pushed too close, the rover may drive while it does not come closer, until it has room.
    leaving = np.logical_and.accumulate((room <= 0) & np.r_[True, np.diff(room) >= -1e-9])
    cut_at = np.r_[0.0, profile.along_m[:-1]]      # a cut keeps the drive up to the sample before
    over = ~leaving & ((margin < 0).any(axis=1) | (room <= 0)) & (cut_at >= min_drive_m)
    if not over.any():
        return DrivablePrefix(waypoints, True), 0.0
    first = int(np.argmax(over))
    last = max(first - 1, 0)
    head = waypoints[:profile.segment[last]]
    binding = int(np.argmin(margin[first]))
    return DrivablePrefix(np.vstack([head, profile.points[last]]), False), float(error[first, binding])


def _place(offsets: np.ndarray, profile: DriveErrorProfile) -> np.ndarray:
    """(N, M, 2) world points of body-frame offsets (M, 2) at each pose of the profile."""
    c, s = np.cos(profile.heading)[:, None], np.sin(profile.heading)[:, None]
    return profile.points[:, None, :] + np.stack([c * offsets[:, 0] - s * offsets[:, 1],
                                                  s * offsets[:, 0] + c * offsets[:, 1]], axis=-1)


def _sample(distance_m: np.ndarray, towards: np.ndarray | None, spec: GridSpec,
            points: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """The distance map (and directions) at world points (..., 2); off the map: distance -inf, no direction."""
    cells, inside = world_to_cells(spec, points.reshape(-1, 2))
    rows, cols = np.where(inside, cells[:, 0], 0), np.where(inside, cells[:, 1], 0)
    distance = np.where(inside, distance_m[rows, cols], -np.inf).reshape(points.shape[:-1])
    if towards is None:
        return distance, None
    return distance, np.where(inside[:, None], towards[rows, cols], 0.0).reshape(points.shape)
def _towards_nearest(distance_m: np.ndarray, cell: float) -> np.ndarray:
    """(rows, cols, 2) unit world (x, y) directions towards the nearest hazard: down the distance map's
    gradient. Where it has none (on a ridge between two hazards, far from any), (0, 0) stands for every
    direction: the worst one is taken there."""
    finite = np.where(np.isfinite(distance_m), distance_m, 0.0)
    d_row, d_col = np.gradient(finite, cell)
    direction = -np.stack([d_col, d_row], axis=-1)      # rows run along y, columns along x
    norm = np.linalg.norm(direction, axis=-1, keepdims=True)
    return np.where(norm > 0.5, direction / np.maximum(norm, 1e-12), 0.0)
