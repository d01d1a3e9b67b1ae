"""Tests of scale and gravity from the parabolic flight (rvs_server/toolbox/hopping_parabola.py, hopping
paper eqs 1-13): each step of the paper's chain against known answers, the Cardano distance against
brute force, and the timed fit against the Cramer-Rao bound of the noise and against the paper's fit.

A note on "scale within 1 %": the scale lives only in the vertical curvature of p(t), and with N
frames of per-axis noise sigma over a flight of duration T no unbiased estimator beats
std(gamma_z) = sigma sqrt([(A^T A)^-1]_22) (A = [1, t, t^2 / 2]). For 45 inlier frames with sigma = 2 %
of the hop that is about 2.2 % (60 degrees) to 4 % (45 degrees) of the scale; the fits are tested against
that bound at 2 % noise, and for the 1 % figure at the noise where the bound allows it."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import minimize_scalar
from scipy.spatial.transform import Rotation

from toolbox.hopping.parabola import (
    FlightFit,
    ballistic_design,
    centre_of_mass_positions,
    conic_axis_angle,
    fit_conic_through_origin,
    fit_flight,
    fit_flight_paper,
    fit_parabola,
    orient_parabola,
    parabola_closest_x,
    parabola_distance,
    rotation_2d,
    scale_from_parabola,
)
from toolbox.hopping.plane import fit_plane_lsq, plane_basis, ransac_plane

G = 1.62


def true_hop(frames: int = 50, elevation_deg: float = 60.0, distance: float = 1.0):
    """(times, metric positions (x along the hop, z up), launch speed) of a hop landing at its launch height."""
    elevation = math.radians(elevation_deg)
    speed = math.sqrt(G * distance / math.sin(2 * elevation))
    duration = 2 * speed * math.sin(elevation) / G
    t = np.linspace(0.0, duration, frames)
    p = np.column_stack([speed * math.cos(elevation) * t, np.zeros_like(t),
                         speed * math.sin(elevation) * t - 0.5 * G * t * t])
    return t, p, speed


def to_sfm(points: np.ndarray, seed: int):
    """An arbitrary SfM frame: random rotation, scale 1 / 3.7 and offset; returns (sfm points, scale, rotation)."""
    rotation = Rotation.random(random_state=seed).as_matrix()
    scale = 3.7  # metres per SfM unit
    return points @ rotation.T / scale + np.array([1.0, -2.0, 0.5]), scale, rotation


def noisy_hop(seed: int, noise: float = 0.02, outliers: float = 0.1, frames: int = 50,
              elevation_deg: float = 60.0):
    """A hop in SfM coordinates with per-axis Gaussian noise (a fraction of the hop) and gross outliers."""
    rng = np.random.default_rng(seed)
    t, p, _ = true_hop(frames, elevation_deg)
    p, good = with_outliers(p + rng.normal(0, noise, p.shape), rng, int(round(outliers * frames)), 0.1, 0.5)
    sfm, scale, rotation = to_sfm(p, seed)
    return sfm, t, scale, rotation, good


def with_outliers(p: np.ndarray, rng: np.random.Generator, count: int, low: float, high: float):
    """p with `count` frames (never the first) moved low..high in random directions; (p, good mask)."""
    p = p.copy()
    bad = rng.choice(np.arange(1, len(p)), count, replace=False)
    direction = rng.normal(size=(len(bad), 3))
    p[bad] += direction / np.linalg.norm(direction, axis=1)[:, None] * rng.uniform(low, high, (len(bad), 1))
    good = np.ones(len(p), dtype=bool)
    good[bad] = False
    return p, good


def scale_bound(t: np.ndarray, noise: float) -> float:
    """Cramer-Rao bound on the relative scale error: std(gamma_z) / g with metric positions."""
    design = ballistic_design(t - t[0])
    return noise * math.sqrt(np.linalg.inv(design.T @ design)[2, 2]) / G


def angle_between(a: np.ndarray, b: np.ndarray) -> float:
    return math.degrees(math.acos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1, 1)))


# --- the paper's steps ------------------------------------------------------------------------

def test_ransac_plane_ignores_outliers_and_refits():
    rng = np.random.default_rng(0)
    xy = rng.uniform(-1, 1, (200, 2))
    points = np.column_stack([xy, 0.1 * xy[:, 0] - 0.2 * xy[:, 1] + 0.3 + rng.normal(0, 0.002, 200)])
    points[:40] += rng.normal(0, 0.5, (40, 3))
    plane, inliers = ransac_plane(points, 0.01)
    expected = np.array([-0.1, 0.2, 1.0]) / np.linalg.norm([-0.1, 0.2, 1.0])
    assert angle_between(plane.normal * np.sign(plane.normal[2]), expected) < 0.3
    assert inliers[40:].mean() > 0.98 and inliers[:40].mean() < 0.2
    assert abs(fit_plane_lsq(points[40:]).signed_distance(np.array([[0, 0, 0.3]]))[0]) < 0.003


def test_plane_basis_is_right_handed_and_follows_the_hint():
    basis = plane_basis(np.array([0.0, 0.0, 2.0]), first_axis_hint=np.array([1.0, 1.0, 5.0]))
    np.testing.assert_allclose(basis @ basis.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(basis) == pytest.approx(1.0)
    np.testing.assert_allclose(basis[0], [math.sqrt(0.5), math.sqrt(0.5), 0], atol=1e-12)


def test_conic_fit_and_axis_angle_recover_a_rotated_parabola():
    x = np.linspace(0, 1, 30)
    parabola = np.column_stack([x, 1.5 * x - 1.2 * x * x])  # through the origin
    for turn in np.radians([0.0, 20.0, -35.0, 70.0]):
        xy = parabola @ rotation_2d(turn).T
        conic = fit_conic_through_origin(xy)
        x_, y_ = xy.T
        residual = conic[0] * x_ ** 2 + conic[1] * x_ * y_ + conic[2] * y_ ** 2 + conic[3] * x_ + conic[4] * y_
        assert np.abs(residual).max() < 1e-10
        assert conic[1] ** 2 == pytest.approx(4 * conic[0] * conic[2], abs=1e-9)  # a parabola: b^2 = 4ac
        # The axis is the turn itself, modulo a quarter turn (eq 6 leaves which axis open).
        theta = conic_axis_angle(conic)
        assert math.remainder(theta - turn, math.pi / 2) == pytest.approx(0.0, abs=1e-9)


@pytest.mark.parametrize("turn_deg", [0, 35, 90, 150, 200, 290])
@pytest.mark.parametrize("mirror", [False, True])
def test_orient_parabola_makes_it_open_downwards_and_run_forwards(turn_deg, mirror):
    x = np.linspace(0, 1, 30)
    parabola = np.column_stack([x, 1.5 * x - 1.2 * x * x])
    xy = parabola * ([1, -1] if mirror else [1, 1])
    xy = xy @ rotation_2d(math.radians(turn_deg)).T
    angle, flip = orient_parabola(xy, conic_axis_angle(fit_conic_through_origin(xy)))
    out = xy @ rotation_2d(angle).T
    if flip:
        out[:, 1] *= -1
    np.testing.assert_allclose(out, parabola, atol=1e-9)
    assert flip == mirror


def test_fit_parabola_exact():
    x = np.linspace(-2, 3, 11)
    np.testing.assert_allclose(fit_parabola(x, 0.5 - 2 * x + 0.25 * x * x), [0.5, -2, 0.25], atol=1e-12)


def brute_force_distance(coeffs, px, py) -> float:
    a, b, c = coeffs
    xs = np.linspace(px - 50, px + 50, 200_001)
    d = np.hypot(xs - px, a + b * xs + c * xs * xs - py)
    i = int(np.argmin(d))
    refined = minimize_scalar(lambda x: math.hypot(x - px, a + b * x + c * x * x - py),
                              bracket=(xs[i - 1], xs[i], xs[i + 1]), tol=1e-12)
    return min(refined.fun, d[i])


@settings(max_examples=150, deadline=None)
@given(a=st.floats(-3, 3), b=st.floats(-3, 3), c=st.floats(-3, 3).filter(lambda v: abs(v) > 0.05),
       px=st.floats(-4, 4), py=st.floats(-4, 4))
def test_cardano_distance_equals_brute_force(a, b, c, px, py):
    assert parabola_distance((a, b, c), px, py) == pytest.approx(brute_force_distance((a, b, c), px, py), abs=1e-9)


def test_cardano_picks_the_nearest_of_three_real_roots():
    # Inside y = -x^2 below its centre of curvature (y < -1/2) there are three normals; the nearest
    # point is off the axis, the root on the axis (x = 0) is a local maximum of the distance.
    x = parabola_closest_x((0.0, 0.0, -1.0), np.array([0.0, 0.1]), np.array([-5.0, -5.0]))
    assert abs(x[0]) == pytest.approx(math.sqrt(4.5), abs=1e-12)
    assert x[1] > 2.0  # off the axis, on the side of the point
    assert parabola_distance((0.0, 0.0, -1.0), 0.1, -5.0) == pytest.approx(
        brute_force_distance((0.0, 0.0, -1.0), 0.1, -5.0), abs=1e-9)
    assert parabola_distance((0.0, 0.0, -1.0), 0.0, -5.0) == pytest.approx(math.sqrt(4.5 + 0.25), abs=1e-12)


def test_scale_from_parabola_on_exact_data():
    t, p, speed = true_hop(elevation_deg=55.0)
    coeffs = fit_parabola(p[:, 0], p[:, 2])
    result = scale_from_parabola(coeffs, p[:, 0], t, G)
    assert result["scale"] == pytest.approx(1.0, abs=1e-9)
    assert result["elevation"] == pytest.approx(math.radians(55.0), abs=1e-9)
    assert result["v0"] == pytest.approx(speed, rel=1e-9)
    assert result["t_sym"] == pytest.approx(t[-1] / 2, rel=1e-9)


@pytest.mark.parametrize("fit", [fit_flight, fit_flight_paper])
def test_both_fits_are_exact_on_clean_data(fit):
    t, p, speed = true_hop(elevation_deg=50.0)
    sfm, scale, rotation = to_sfm(p, seed=4)
    result: FlightFit = fit(sfm, t + 12.5)  # any clock origin
    assert result.scale == pytest.approx(scale, rel=1e-9)
    assert angle_between(result.gravity_sfm, rotation @ [0, 0, -1]) < 1e-6
    assert result.launch_speed == pytest.approx(speed, rel=1e-9)
    assert result.launch_elevation == pytest.approx(math.radians(50.0), abs=1e-9)
    # The hop frame is the true metric frame: launch at the origin, x along the hop, z up.
    np.testing.assert_allclose(result.to_hop_frame(sfm), p, atol=1e-9)
    np.testing.assert_allclose(result.similarity @ np.append(sfm[7], 1.0), np.append(p[7], 1.0), atol=1e-9)
    np.testing.assert_allclose(result.landing_point, p[-1], atol=1e-9)
    assert result.inliers.sum() >= 25 and result.rms_m < 1e-9


# --- the timed fit: noise, outliers, prior, eq 1 -----------------------------------------------------

def test_scale_within_one_percent_with_outliers_at_low_noise():
    """50 frames, 10 % gross outliers, 0.25 % noise: where the bound (0.3 %) allows 1 %, every run makes it."""
    for seed in range(20):
        sfm, t, scale, rotation, good = noisy_hop(seed, noise=0.0025)
        result = fit_flight(sfm, t)
        assert abs(result.scale / scale - 1) < 0.01, seed
        assert angle_between(result.gravity_sfm, rotation @ [0, 0, -1]) < 0.5
        assert not result.inliers[~good].any() and result.inliers[good].mean() > 0.93, seed


def bent_long_hop(seed: int):
    """A 10 m, 200-frame hop as SfM reconstructs a long flight: a smooth bend of 0.3 % of its extent
    (three humps over the flight), 0.03 % noise and 5 % gross outliers 3-10 % of the extent off."""
    rng = np.random.default_rng(seed)
    t, p, _ = true_hop(200, 60.0, 10.0)
    extent = np.ptp(p, axis=0).max()
    u = t / t[-1]
    bend = 0.003 * extent * np.column_stack([np.sin(3 * np.pi * u + phase) for phase in rng.uniform(0, 2 * np.pi, 3)])
    p, good = with_outliers(p + bend + rng.normal(0, 0.0003 * extent, p.shape), rng, 10, 0.03 * extent, 0.1 * extent)
    sfm, scale, _ = to_sfm(p, seed)
    return sfm, t, scale, good


def test_a_smoothly_bent_long_flight_is_fitted_whole_and_its_outliers_still_go():
    """Without a floor under the noise scale the robust fit shrinks onto a piece of the bend: it keeps
    under half the frames and the scale is 4-5 % off. With it every good frame stays, every outlier goes."""
    for seed in range(4):
        sfm, t, scale, good = bent_long_hop(seed)
        result = fit_flight(sfm, t)
        assert abs(result.scale / scale - 1) < 0.015, seed
        assert result.inliers[good].mean() > 0.95 and not result.inliers[~good].any(), seed
        bare = fit_flight(sfm, t, min_sigma_fraction=0.0)
        assert bare.inliers[good].mean() < 0.6, seed


def test_scale_at_two_percent_noise_reaches_the_cramer_rao_bound_and_beats_the_paper():
    """50 frames, 2 % noise, 10 % outliers: the timed fit's error is the noise bound's (a 1 % scale is
    not possible at this noise for any method), it knows its own uncertainty, and it beats the paper's fit."""
    timed, paper, reported, bounds = [], [], [], []
    for seed in range(120):
        sfm, t, scale, rotation, good = noisy_hop(seed, noise=0.02)
        result = fit_flight(sfm, t)
        timed.append(result.scale / scale - 1)
        reported.append(result.scale_sigma / result.scale)
        bounds.append(scale_bound(t[good], 0.02))
        paper.append(fit_flight_paper(sfm, t).scale / scale - 1)
    timed, paper = np.abs(timed), np.abs(paper)
    bound = float(np.mean(bounds))
    assert 0.02 < bound < 0.03
    rms = float(np.sqrt(np.mean(timed ** 2)))
    assert rms < 1.25 * bound
    assert 0.7 < np.median(reported) / rms < 1.3
    assert np.median(timed) < 0.6 * np.median(paper)
    assert np.percentile(timed, 90) < 0.5 * np.percentile(paper, 90)


def test_gravity_direction_recovered_and_sharpened_by_an_accelerometer_prior():
    free, prior = [], []
    for seed in range(30):
        sfm, t, scale, rotation, good = noisy_hop(seed, noise=0.02)
        down = rotation @ [0, 0, -1]
        result = fit_flight(sfm, t)
        free.append(angle_between(result.gravity_sfm, down))
        assert free[-1] < 4 * math.degrees(result.gravity_sigma_rad) + 0.1
        # The accelerometers' gravity, itself 0.5 degrees off.
        measured = Rotation.from_rotvec(np.radians(0.5) * np.array([1.0, 0, 0])).apply(down)
        prior.append(angle_between(fit_flight(sfm, t, gravity_prior=measured, prior_sigma_rad=np.radians(0.5))
                                   .gravity_sfm, down))
    assert np.mean(free) < 2.5
    assert np.mean(prior) < 0.5 * np.mean(free)


def test_centre_of_mass_offset_is_applied_in_metres():
    """Eq 1 with a spinning camera: the offset turns with the camera; ignoring it bends the fit."""
    t, p, _ = true_hop(elevation_deg=60.0)
    spin = Rotation.from_rotvec(np.outer(np.linspace(0, 2 * np.pi, len(t)), [0.0, 1.0, 0.0])).as_matrix()
    offset = np.array([0.0, 0.0, 0.08])  # the centre of mass 8 cm in front of the camera
    cameras = p - np.einsum("nij,j->ni", spin, offset)
    sfm, scale, rotation = to_sfm(cameras, seed=2)
    sfm_rotations = np.einsum("ij,njk->nik", rotation, spin)
    np.testing.assert_allclose(centre_of_mass_positions(sfm, sfm_rotations, offset, scale),
                               to_sfm(p, seed=2)[0], atol=1e-12)
    corrected = fit_flight(sfm, t, camera_rotations=sfm_rotations, com_offset_m=offset)
    assert corrected.scale == pytest.approx(scale, rel=1e-6)
    assert abs(fit_flight(sfm, t).scale / scale - 1) > 10 * abs(corrected.scale / scale - 1)


def test_report_and_residuals():
    sfm, t, scale, rotation, good = noisy_hop(3, noise=0.01)
    result = fit_flight(sfm, t)
    report = result.report()
    assert report["frames"] == 50 and report["inliers"] == int(good.sum())
    assert 0.008 < report["rms_m"] < 0.025  # 3-D RMS of 1 cm per axis is 1.7 cm
    assert report["hop_distance_m"] == pytest.approx(1.0, abs=0.05)
    assert report["launch_elevation_deg"] == pytest.approx(60.0, abs=3.0)
    assert result.residuals_m[~good].min() > result.residuals_m[good].max()


@pytest.mark.parametrize("centres, times, message", [
    (np.zeros((5, 3)), np.arange(5.0), "at least 6"),
    (np.zeros((8, 2)), np.arange(8.0), r"\(N, 3\)"),
    (np.zeros((8, 3)), np.arange(7.0), "timestamps must be"),
    (np.zeros((8, 3)), np.array([0, 1, 2, 2, 3, 4, 5, 6.0]), "increase"),
])
def test_bad_input_is_refused(centres, times, message):
    with pytest.raises(ValueError, match=message):
        fit_flight(centres, times)


def test_a_straight_line_is_not_a_flight():
    rng = np.random.default_rng(0)
    t = np.linspace(0, 1, 30)
    with pytest.raises(ValueError, match="not a ballistic flight"):
        fit_flight(np.column_stack([t, 2 * t, 0 * t]) + rng.normal(0, 0.01, (30, 3)), t)
