"""Absolute heading from a sun sensor: where the sun stands in the rover's frame, against where the
ephemeris says it stands in the world.

A sun sensor on the rover's body measures the unit vector toward the sun in the body frame. Levelled
with the inclinometer's roll and pitch, its azimuth in the rover's horizontal frame differs from the
sun's world azimuth by exactly the heading:

    body_to_world = Rz(heading) Ry(pitch) Rx(roll)      (toolbox.geometry.rotation_rpy)
    level  = Ry(pitch) Rx(roll) sun_body                 the sun in the yawed-only frame
    heading = azimuth(sun_world) - azimuth(level)        azimuths counter-clockwise from x (east)

Its error has two parts: the sensor's own angular error, which projects onto the horizontal plane
enlarged by 1 / cos(elevation), and the roll and pitch errors, which tilt the level frame and move
the azimuth by up to tan(elevation) times as much. A sun near the zenith says nothing about heading.
"""
from __future__ import annotations

import math

import numpy as np

from toolbox.geometry import rotation_x, rotation_y

__all__ = ["MAX_ELEVATION_DEG", "sun_heading", "sun_heading_sigma", "sun_world_vector"]

MAX_ELEVATION_DEG = 80.0   # above this the heading error grows past tan(80) = 5.7 times the tilt error


def sun_world_vector(azimuth_deg: float, elevation_deg: float) -> np.ndarray:
    """Unit vector toward the sun in the world frame (x east, y north, z up) from the ephemeris'
    azimuth (clockwise from north) and elevation."""
    az, el = math.radians(azimuth_deg), math.radians(elevation_deg)
    return np.array([math.sin(az) * math.cos(el), math.cos(az) * math.cos(el), math.sin(el)])


def sun_heading(sun_body: np.ndarray, roll: float, pitch: float, sun_world: np.ndarray) -> float:
    """The rover's heading (radians, counter-clockwise from east, within +-pi) from the sun sensor's
    body-frame vector, the inclinometer's roll and pitch (radians) and the sun's world vector."""
    level = rotation_y(pitch) @ rotation_x(roll) @ np.asarray(sun_body, dtype=np.float64)
    heading = math.atan2(sun_world[1], sun_world[0]) - math.atan2(level[1], level[0])
    return math.atan2(math.sin(heading), math.cos(heading))


def sun_heading_sigma(sensor_sigma: float, tilt_sigma: float, elevation: float) -> float:
    """1-sigma heading error (radians) of sun_heading: the sensor's angular sigma seen on the
    horizontal plane, and the inclinometer's tilt sigma coupled through the sun's elevation (all
    radians)."""
    return math.hypot(sensor_sigma / math.cos(elevation), tilt_sigma * math.tan(elevation))
