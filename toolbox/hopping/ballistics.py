"""Ballistics of a hop: the range equation, the landing error ellipse, the launch that reaches a target,
and the flight path (hopping paper, "Error ellipse for landing position", equations 14-16, and
"Landing point selection").

Frame: metres and seconds, z up (against gravity), headings counter-clockwise from +x.

The paper propagates the launch errors (speed, elevation, heading, own position; independent and
Gaussian) through the flat-ground range equation d = v^2 sin(2 theta) / g to first order (eqs 15-16).
At the 45-degree optimum the first-order elevation term vanishes (dd/dtheta = 0), so the first-order
ellipse claims an elevation error costs nothing, and it misses that hops fall short on average.
`landing_error_ellipse` uses the exact mean and variance instead: for independent Gaussian errors the
moments of v^2 sin(2 theta), of cos(psi) and of sin(psi) are closed forms.
tests/toolbox/test_hopping_landing.py checks it against a Monte Carlo of the range equation.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from toolbox.hopping.parabola import MOON_GRAVITY

CHI2_2D_95 = 2.4477  # sqrt of the 95 % quantile of chi-square with 2 dof: a 95 % ellipse in sigmas


def hop_range(speed: float | np.ndarray, elevation: float | np.ndarray,
              gravity: float = MOON_GRAVITY) -> np.ndarray:
    """Eq 14: the distance of a hop on flat ground, d = v^2 sin(2 theta) / g."""
    return np.asarray(speed) ** 2 * np.sin(2 * np.asarray(elevation)) / gravity


@dataclass(frozen=True)
class LandingEllipse:
    distance: float        # nominal hop distance, m
    along_bias: float      # mean landing minus nominal, along the hop, m (second order; 0 at first order)
    along_sigma: float     # 1-sigma along the hop direction, m
    across_sigma: float    # 1-sigma across it, m

    def semi_axes(self, n_sigma: float = CHI2_2D_95, margin: float = 0.0) -> tuple[float, float]:
        """(along, across) semi-axes of the n-sigma ellipse grown by a margin (e.g. the rover's radius)."""
        return n_sigma * self.along_sigma + margin, n_sigma * self.across_sigma + margin


def landing_error_ellipse(speed: float, elevation: float, sigma_speed: float, sigma_elevation: float,
                          sigma_heading: float, sigma_position: float, gravity: float = MOON_GRAVITY,
                          exact: bool = True) -> LandingEllipse:
    """Eqs 15-16: the landing spread along and across the hop from the launch errors.

    exact=False is the paper's first order: along^2 = (dd/dv sv)^2 + (dd/dtheta stheta)^2 + ss^2,
    across^2 = (d spsi)^2 + ss^2. exact=True uses the exact moments of the range equation for
    independent Gaussian errors: E[v^2], E[v^4] of a Gaussian speed, E[sin 2theta], E[sin^2 2theta] and
    of cos / sin of the heading error (E[cos x] = exp(-s^2 / 2) for x ~ N(0, s^2)). It keeps the
    mean shift (hops fall short on average) and the elevation error at 45 degrees, where the first
    order sees none."""
    v, th, sv, st, sp = speed, elevation, sigma_speed, sigma_elevation, sigma_heading
    d = v * v * np.sin(2 * th) / gravity
    if not exact:
        d_v, d_t = 2 * v * np.sin(2 * th) / gravity, 2 * v * v * np.cos(2 * th) / gravity
        along = np.sqrt((d_v * sv) ** 2 + (d_t * st) ** 2 + sigma_position ** 2)
        return LandingEllipse(float(d), 0.0, float(along), float(np.sqrt((d * sp) ** 2 + sigma_position ** 2)))
    # Range D = v^2 sin(2 theta) / g with v ~ N(v, sv^2), theta ~ N(th, st^2), independent.
    v2 = v * v + sv * sv
    v4 = v ** 4 + 6 * v * v * sv * sv + 3 * sv ** 4
    sin_mean = np.sin(2 * th) * np.exp(-2 * st * st)
    sin2_mean = (1 - np.cos(4 * th) * np.exp(-8 * st * st)) / 2
    mean, second_moment = v2 * sin_mean / gravity, v4 * sin2_mean / gravity ** 2
    # Landing offset along = D cos(psi), across = D sin(psi), psi ~ N(0, sp^2) independent of D.
    e_cos, e_cos2, e_sin2 = np.exp(-sp * sp / 2), (1 + np.exp(-2 * sp * sp)) / 2, (1 - np.exp(-2 * sp * sp)) / 2
    along_var = second_moment * e_cos2 - (mean * e_cos) ** 2
    return LandingEllipse(float(d), float(mean * e_cos - d), float(np.sqrt(along_var + sigma_position ** 2)),
                          float(np.sqrt(second_moment * e_sin2 + sigma_position ** 2)))


@dataclass(frozen=True)
class Launch:
    speed: float           # m/s
    elevation: float       # rad above the horizontal
    heading: float         # rad, counter-clockwise from +x
    flight_time: float     # s from launch to arrival at the target
    velocity: np.ndarray   # (3,) m/s


def speed_for_target(distance: float, height_change: float, elevation: float,
                     gravity: float = MOON_GRAVITY) -> float:
    """Launch speed at a fixed elevation that lands `distance` away and `height_change` higher:
    from z = d tan(theta) - g d^2 / (2 v^2 cos^2 theta). NaN when the elevation cannot get that high."""
    reach = distance * np.tan(elevation) - height_change
    if not (distance > 0 and reach > 0 and 0 < elevation < np.pi / 2):
        return float("nan")
    return float(np.sqrt(gravity * distance ** 2 / (2 * np.cos(elevation) ** 2 * reach)))


def elevation_for_target(distance: float, height_change: float, speed: float, gravity: float = MOON_GRAVITY,
                         high: bool = True) -> float:
    """Elevation at a fixed launch speed (the spring's one setting) to reach the target: the same equation
    as a quadratic in tan(theta). high=True takes the steep solution (more frames, steeper landing: the
    paper prefers steep hops); NaN when the speed cannot reach."""
    k = gravity * distance ** 2 / (2 * speed ** 2)
    disc = distance ** 2 - 4 * k * (k + height_change)
    if not (distance > 0 and speed > 0 and disc >= 0):
        return float("nan")
    tan = (distance + (1 if high else -1) * np.sqrt(disc)) / (2 * k)
    return float(np.arctan(tan))


def launch_to_target(start: np.ndarray, target: np.ndarray, gravity: float = MOON_GRAVITY,
                     elevation: float | None = np.radians(60.0), speed: float | None = None,
                     high: bool = True) -> Launch | None:
    """Inverse ballistics from start to target (3-D centre positions). A fixed elevation (default, the
    paper's 60 degrees) solves for the speed; a fixed speed (elevation=None) solves for the elevation.
    None when the target is out of reach."""
    start, target = np.asarray(start, dtype=np.float64), np.asarray(target, dtype=np.float64)
    delta = target - start
    distance = float(np.hypot(delta[0], delta[1]))
    if speed is not None and elevation is None:
        elevation = elevation_for_target(distance, delta[2], speed, gravity, high)
    elif elevation is not None and speed is None:
        speed = speed_for_target(distance, delta[2], elevation, gravity)
    else:
        raise ValueError("give exactly one of elevation and speed")
    if not (np.isfinite(speed) and np.isfinite(elevation)):
        return None
    heading = float(np.arctan2(delta[1], delta[0]))
    horizontal = speed * np.cos(elevation)
    velocity = np.array([horizontal * np.cos(heading), horizontal * np.sin(heading), speed * np.sin(elevation)])
    return Launch(float(speed), float(elevation), heading, distance / horizontal, velocity)


def ballistic_positions(start: np.ndarray, velocity: np.ndarray, times: np.ndarray,
                        gravity: float = MOON_GRAVITY) -> np.ndarray:
    """Positions p(t) = start + v t - g t^2 / 2 z at the given times: (N, 3)."""
    times = np.asarray(times, dtype=np.float64)[:, None]
    return np.asarray(start) + np.asarray(velocity) * times - 0.5 * gravity * times ** 2 * np.array([0, 0, 1.0])
