"""Flight physics of the hopping rover: the ballistic arc, touchdown on the terrain, bounces and rest.

Pure functions over any surface that answers `height_at(x, y)` (a World, or a synthetic height
function in tests). Frames: world x east, y north, z up; metres, seconds, radians; headings
counter-clockwise from +x and elevations above the horizontal, as in toolbox.hopping.ballistics.

In flight only gravity acts, so the centre of mass follows p(t) = p0 + v t - g t^2 / 2 z exactly (no
integration error). The body is a sphere of radius r around the centre of mass. It touches the
ground when any point of its lower half reaches the surface: points sampled on the lower hemisphere
(the bottom, rings and the equator) are tested against the height field, so a rock's side stops the
body as well as the ground under it. The arc is stepped every few milliseconds until a sample is
below the surface, then the instant of contact is bisected.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from scipy.spatial.transform import Rotation

BISECTION_TOLERANCE_S = 1e-7
CHUNK_STEPS = 256          # arc steps tested per height query
MAX_FLIGHT_S = 120.0       # far beyond any hop; only guards against a surface that is never reached
MIN_BOUNCE_SPEED = 0.01    # m/s: slower than this the body just stays down


class HeightSurface(Protocol):
    def height_at(self, x, y) -> np.ndarray:
        """Height of the surface at (x, y) (arrays broadcast); NaN off the terrain."""


class OffTerrain(ValueError):
    """The body left the terrain (the surface has no height there)."""


@dataclass(frozen=True)
class Contact:
    """Where an arc ends: the first instant the body touches the surface."""

    time: float              # s after the start of the arc
    centre: np.ndarray       # (3,) centre of mass at contact
    velocity: np.ndarray     # (3,) velocity arriving at contact
    point: np.ndarray        # (3,) the surface point touched


def launch_velocity(speed: float, elevation: float, heading: float) -> np.ndarray:
    """Velocity (3,) of a launch at `speed`, `elevation` above the horizontal, toward `heading`."""
    horizontal = speed * math.cos(elevation)
    return np.array([horizontal * math.cos(heading), horizontal * math.sin(heading), speed * math.sin(elevation)])


def ballistic_positions(start: np.ndarray, velocity: np.ndarray, times: np.ndarray, gravity: float) -> np.ndarray:
    """Centre of mass (N, 3) at the given times: start + v t - g t^2 / 2 z."""
    times = np.asarray(times, dtype=np.float64)[:, None]
    positions = np.asarray(start, np.float64) + np.asarray(velocity, np.float64) * times
    positions[:, 2] -= 0.5 * gravity * times[:, 0] ** 2
    return positions


def ballistic_velocity(velocity: np.ndarray, time: float, gravity: float) -> np.ndarray:
    return np.asarray(velocity, np.float64) - np.array([0.0, 0.0, gravity * time])


def body_samples(radius: float, rings: int = 3, sectors: int = 16) -> np.ndarray:
    """Points (K, 3) on the lower hemisphere of the body, relative to its centre: the bottom, then
    `rings` rings evenly spaced in polar angle up to the equator, `sectors` points each (the first at
    azimuth 0). Spacing of a few centimetres at r = 0.15 m: no rock that could stop the body fits between."""
    polar = np.linspace(0.0, math.pi / 2, rings + 1)[1:]         # from straight down, up to the equator
    azimuth = np.arange(sectors) * (2 * math.pi / sectors)
    p, a = np.meshgrid(polar, azimuth, indexing="ij")
    ring_points = np.stack([np.sin(p) * np.cos(a), np.sin(p) * np.sin(a), -np.cos(p)], axis=-1).reshape(-1, 3)
    return radius * np.vstack([[0.0, 0.0, -1.0], ring_points])


def clearance(surface: HeightSurface, centres: np.ndarray, samples: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For body centres (N, 3): the least height of a body sample above the surface (N,) (negative:
    the body is in the ground; NaN: a sample is off the terrain) and which sample that is (N,)."""
    points = centres[:, None, :] + samples[None, :, :]
    gap = points[..., 2] - surface.height_at(points[..., 0], points[..., 1])
    worst = np.argmin(np.where(np.isnan(gap), -np.inf, gap), axis=1)
    least = gap[np.arange(len(centres)), worst]
    least[np.isnan(gap).any(axis=1)] = np.nan
    return least, worst


def first_contact(surface: HeightSurface, start: np.ndarray, velocity: np.ndarray, gravity: float,
                  samples: np.ndarray, time_step: float) -> Contact:
    """Follow the arc from `start` (body clear of the surface, or just touching it) until the body
    first touches the surface. Raises OffTerrain if it leaves the terrain first."""
    t0 = 0.0
    while t0 < MAX_FLIGHT_S:
        times = t0 + time_step * np.arange(1, CHUNK_STEPS + 1)
        gap, _ = clearance(surface, ballistic_positions(start, velocity, times, gravity), samples)
        # The first step that is in the ground or off the terrain ends the search.
        stops = np.flatnonzero(~(gap >= 0))
        if stops.size:
            i = stops[0]
            if np.isnan(gap[i]):
                where = ballistic_positions(start, velocity, [times[i]], gravity)[0]
                raise OffTerrain(f"the hop leaves the terrain near ({where[0]:.2f}, {where[1]:.2f})")
            return _bisect_contact(surface, start, velocity, gravity, samples, times[i - 1] if i else t0, times[i])
        t0 = times[-1]
    raise OffTerrain(f"no touchdown within {MAX_FLIGHT_S:g} s")


def _bisect_contact(surface, start, velocity, gravity, samples, clear: float, inside: float) -> Contact:
    """Bisect [clear, inside] (clear: the body above the surface, inside: in it) to the touchdown; the
    contact is reported at the clear side, so the body is never in the ground."""
    while inside - clear > BISECTION_TOLERANCE_S:
        middle = 0.5 * (clear + inside)
        gap, _ = clearance(surface, ballistic_positions(start, velocity, [middle], gravity), samples)
        if gap[0] >= 0:
            clear = middle
        else:
            inside = middle
    centre = ballistic_positions(start, velocity, [clear], gravity)[0]
    touched = ballistic_positions(start, velocity, [inside], gravity)
    _, worst = clearance(surface, touched, samples)
    point = touched[0] + samples[worst[0]]
    point[2] = float(surface.height_at(point[0], point[1]))
    return Contact(float(clear), centre, ballistic_velocity(velocity, clear, gravity), point)


def bounce_contacts(surface: HeightSurface, landing: Contact, gravity: float, samples: np.ndarray,
                    time_step: float, count: int, restitution: float, spread: float,
                    elevation_range: tuple[float, float], rng: np.random.Generator) -> list[Contact]:
    """The secondary hops after `landing`: each leaves with restitution times the arrival speed,
    toward a heading uniform within +-spread of the arrival heading, at a uniform elevation in the
    range. Ends early when the body is too slow to leave the ground."""
    contacts, current = [], landing
    for _ in range(count):
        arrival = current.velocity
        speed = restitution * float(np.linalg.norm(arrival))
        heading = math.atan2(arrival[1], arrival[0]) + rng.uniform(-spread, spread)
        elevation = rng.uniform(*elevation_range)
        if speed < MIN_BOUNCE_SPEED:
            break
        current = first_contact(surface, current.centre, launch_velocity(speed, elevation, heading), gravity,
                                samples, time_step)
        contacts.append(current)
    return contacts


def resting_centre(surface: HeightSurface, x: float, y: float, samples: np.ndarray) -> np.ndarray:
    """Centre (3,) of the body lowered straight down at (x, y) until it rests on the surface."""
    heights = surface.height_at(x + samples[:, 0], y + samples[:, 1])
    if np.isnan(heights).any():
        raise OffTerrain(f"the body at ({x:.3f}, {y:.3f}) is off the terrain")
    return np.array([x, y, float(np.max(heights - samples[:, 2]))])


def resting_attitude(surface: HeightSurface, x: float, y: float, yaw: float, radius: float) -> np.ndarray:
    """Body-to-world rotation (3, 3) of the body resting at (x, y) facing `yaw`: z along the normal of
    the plane fitted to the ground under the body (a disc of its radius), x the yaw direction in that plane."""
    angles = np.arange(8) * (math.pi / 4)
    dx = np.r_[0.0, radius * np.cos(angles)]
    dy = np.r_[0.0, radius * np.sin(angles)]
    heights = surface.height_at(x + dx, y + dy)
    if np.isnan(heights).any():
        raise OffTerrain(f"the body at ({x:.3f}, {y:.3f}) is off the terrain")
    (_, slope_x, slope_y), *_ = np.linalg.lstsq(np.stack([np.ones_like(dx), dx, dy], axis=1), heights, rcond=None)
    up = np.array([-slope_x, -slope_y, 1.0])
    up /= np.linalg.norm(up)
    forward = np.array([math.cos(yaw), math.sin(yaw), 0.0])
    forward -= up * (forward @ up)
    forward /= np.linalg.norm(forward)
    return np.column_stack([forward, np.cross(up, forward), up])


def flight_body_poses(launch_body_to_world: np.ndarray, velocity: np.ndarray, spin: np.ndarray,
                      times: np.ndarray, gravity: float) -> np.ndarray:
    """Body-to-world poses (N, 4, 4) at the given times after launch: the centre on the arc, the
    attitude turning at the constant body-frame rate `spin` (rad/s): R(t) = R0 exp([spin] t)."""
    times = np.asarray(times, dtype=np.float64)
    poses = np.tile(np.eye(4), (len(times), 1, 1))
    turn = Rotation.from_rotvec(np.outer(times, spin)).as_matrix()
    poses[:, :3, :3] = launch_body_to_world[:3, :3] @ turn
    poses[:, :3, 3] = ballistic_positions(launch_body_to_world[:3, 3], velocity, times, gravity)
    return poses

