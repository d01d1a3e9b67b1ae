"""Scale and gravity of a monocular hop from its parabolic flight (hopping paper, "Trajectory and scale
estimation", equations 1-13).

Structure from motion gives a hop's camera centres in an arbitrary frame and scale. In flight only
gravity acts, so the centre of mass draws a parabola in a vertical plane; with the known gravity and
the frame timestamps this fixes the metric scale and the direction of gravity.

Two fits, same output (`FlightFit`, the similarity from the SfM frame to the metric hop frame):

`fit_flight_paper` is the paper's chain, one function per step:
    centre_of_mass_positions  eq 1   camera centres -> centre of mass
    ransac_plane              --     the flight plane (plane)
    to_flight_plane           --     project into the plane, first camera at the origin
    fit_conic_through_origin  eq 2-5 least-squares conic, F = 0, smallest eigenvector
    conic_axis_angle          eq 6   rotation that removes the conic's xy term
    orient_parabola           eq 7   pick the axis (two parabola fits) and the flips
    fit_parabola              eq 7   y = a + b x + c x^2
    parabola_distance         eq 8-10 true point-to-parabola distance via Cardano's root
    drop_beyond_mean_distance --     the paper's single outlier pass
    scale_from_parabola       eq 11-13 launch angle, v0 and scale from the apex time

`fit_flight` (the default) does better where the paper admits weakness. The paper uses the
timestamps only through a median of apex-time estimates; here they carry the whole fit. In flight
p(t) = c + v t + gamma t^2 / 2 with gamma the gravity vector in SfM units, which is LINEAR in
(c, v, gamma): 9 unknowns, no plane, conic or orientation steps, and gravity's direction and the
scale (|gamma| = g / scale) come out of one least-squares solve: the maximum-likelihood fit under
Gaussian noise, which reaches the Cramer-Rao bound of the noise (tested). Around it:
  - least median of squares over time-stratified 3-frame samples: outliers found without a threshold
    in the unknown SfM unit, and a robust noise scale;
  - Tukey-weighted iterative refits (robust loss), final inliers at the 99 % radius of 3-D noise;
  - an optional accelerometer gravity prior (direction in the SfM frame with an angular sigma) as
    linear penalty rows on gamma's component across the prior;
  - eq 1's camera-to-centre-of-mass offset inside the same linear solve: the offset is metric and
    the SfM frame is not, so it needs 1 / scale = |gamma| / g, linear in gamma once gravity's
    direction is known (the paper applies eq 1 before it knows the scale);
  - the standard errors of the scale and of gravity's direction from the fit's covariance.
tests/bench/bench_hopping.py measures both fits on synthetic hops (noise, outliers, noisier ends, a
systematic bend, scale drift); tests/toolbox/test_hopping_parabola.py holds the known answers. A bend that is
quadratic in time looks exactly like gravity to any fit: neither fit removes it (bench: 3.5 % timed,
4.0 % paper, median), the accelerometer prior at least keeps gravity's direction.

Hop frame (the output): metres, launch point at the origin, z up (against gravity), x along the
horizontal direction of flight, y = z x x. Rotating it into the world needs the heading (the paper's
sun sensor); geometry.py owns that transform.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from toolbox.hopping.plane import Plane, plane_basis, ransac_plane

MOON_GRAVITY = 1.62  # m/s^2
# Median of the norm of 3-D isotropic Gaussian noise (Maxwell distribution) in units of the per-axis sigma.
MAXWELL_MEDIAN = 1.5382
# 99 % quantile of that norm: sqrt(chi2_3(0.99)).
MAXWELL_99 = 3.3682
TUKEY_C = 4.685
# The robust fits' noise scale never drops below this share of the flight's extent. SfM of a long
# flight bends smoothly by a few tenths of a percent of it (a 199-frame, 11.7 m hop: residuals of
# median 2 cm, p90 25 cm about its best parabola); a noise scale below the bend calls most frames
# outliers and fits a piece of the flight: that hop kept 33 % of its frames, scale 3.0 % off, and
# with this floor 99 %, 1.2 % off. Real outliers (a mismatched frame) lie far beyond 1 % of the extent.
MIN_SIGMA_FRACTION = 0.003


@dataclass(frozen=True)
class FlightFit:
    method: str                   # "timed" (fit_flight) or "paper" (fit_flight_paper)
    scale: float                  # metres per SfM unit
    rotation: np.ndarray          # (3, 3) SfM axes -> hop frame axes
    translation: np.ndarray       # (3,) so that p_hop = scale * rotation @ p_sfm + translation
    gravity_sfm: np.ndarray       # (3,) unit vector of gravity (down) in the SfM frame
    launch_velocity: np.ndarray   # (3,) m/s in the hop frame: (v_horizontal, 0, v_up)
    launch_speed: float           # m/s
    launch_elevation: float       # rad above the horizontal
    apex_time: float              # s after launch
    flight_time: float            # s from launch to the last frame
    landing_point: np.ndarray     # (3,) hop frame: the fitted position at the last frame
    inliers: np.ndarray           # (N,) bool: frames the fit kept
    residuals_m: np.ndarray       # (N,) metres: each frame's distance from the fitted trajectory
    rms_m: float                  # RMS of residuals_m over the inliers
    scale_sigma: float            # 1-sigma of `scale` from the fit's covariance; NaN if not known
    gravity_sigma_rad: float      # 1-sigma of gravity's direction; NaN if not known
    params: dict = field(default_factory=dict, repr=False)  # the fit's own parameters, for reports

    @property
    def similarity(self) -> np.ndarray:
        """4x4 matrix mapping homogeneous SfM points to the hop frame."""
        m = np.eye(4)
        m[:3, :3] = self.scale * self.rotation
        m[:3, 3] = self.translation
        return m

    def to_hop_frame(self, points_sfm: np.ndarray) -> np.ndarray:
        """SfM points (e.g. the dense cloud) into the metric, gravity-aligned hop frame."""
        return self.scale * np.asarray(points_sfm, dtype=np.float64) @ self.rotation.T + self.translation

    def report(self) -> dict:
        return {"method": self.method, "scale": self.scale, "scale_sigma": self.scale_sigma,
                "gravity_sigma_deg": float(np.degrees(self.gravity_sigma_rad)),
                "launch_speed_mps": self.launch_speed,
                "launch_elevation_deg": float(np.degrees(self.launch_elevation)),
                "apex_time_s": self.apex_time, "flight_time_s": self.flight_time,
                "hop_distance_m": float(np.hypot(*self.landing_point[:2])),
                "inliers": int(self.inliers.sum()), "frames": int(len(self.inliers)),
                "rms_m": self.rms_m, "max_inlier_residual_m": float(self.residuals_m[self.inliers].max())}


# ------------------------------------------------------------------------------------------ eq 1
def centre_of_mass_positions(camera_centres: np.ndarray, camera_rotations: np.ndarray,
                             offset_in_camera: np.ndarray, scale: float = 1.0) -> np.ndarray:
    """Eq 1, P' = T P: the centre of mass from each camera pose and its fixed offset in the camera.

    camera_rotations are camera-to-SfM rotations (N, 3, 3). The offset is metric, the SfM frame is
    not, so it is divided by `scale` (metres per SfM unit); the paper leaves this out."""
    offsets = np.einsum("nij,j->ni", np.asarray(camera_rotations, dtype=np.float64),
                        np.asarray(offset_in_camera, dtype=np.float64))
    return np.asarray(camera_centres, dtype=np.float64) + offsets / scale


# ------------------------------------------------------------------------------------- the plane
def to_flight_plane(points: np.ndarray, plane: Plane, origin: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Project points into the flight plane: (N, 2) coordinates with `origin` at (0, 0), and the 3x3
    basis (rows e1, e2, normal) they are expressed in."""
    basis = plane_basis(plane.normal)
    origin_on_plane = plane.project(np.asarray(origin, dtype=np.float64)[None])[0]
    return (plane.project(points) - origin_on_plane) @ basis[:2].T, basis


# ------------------------------------------------------------------------------------- eq 2 - 7
def fit_conic_through_origin(xy: np.ndarray) -> np.ndarray:
    """Eqs 3-5: (a, b, c, d, e) of a x^2 + b xy + c y^2 + d x + e y = 0 minimising the algebraic error.

    The normal equations of eq 5 form the symmetric matrix M^T M; its eigenvector of the smallest
    eigenvalue is the non-trivial minimiser with unit norm. Columns are normalised first so the
    quadratic and linear terms weigh alike whatever the unit."""
    xy = np.asarray(xy, dtype=np.float64)
    if len(xy) < 5:
        raise ValueError(f"a conic needs at least 5 points, got {len(xy)}")
    x, y = xy[:, 0], xy[:, 1]
    m = np.column_stack([x * x, x * y, y * y, x, y])
    norms = np.linalg.norm(m, axis=0)
    norms[norms == 0] = 1.0
    eigenvalues, eigenvectors = np.linalg.eigh((m / norms).T @ (m / norms))
    conic = eigenvectors[:, 0] / norms
    return conic / np.linalg.norm(conic)


def conic_axis_angle(conic: np.ndarray) -> float:
    """Eq 6: theta = 1/2 arctan(b / (a - c)); rotating the points by -theta removes the xy term, so the
    axis of symmetry becomes parallel to x or y (arctan2 keeps a == c well defined)."""
    a, b, c = conic[:3]
    return 0.5 * float(np.arctan2(b, a - c))


def rotation_2d(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s], [s, c]])


def fit_parabola(x: np.ndarray, y: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Eq 7: least-squares (a, b, c) of y = a + b x + c x^2."""
    x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    design = np.column_stack([np.ones_like(x), x, x * x])
    w = np.ones_like(x) if weights is None else np.sqrt(np.asarray(weights, dtype=np.float64))
    return np.linalg.lstsq(design * w[:, None], y * w, rcond=None)[0]


def parabola_sse(x: np.ndarray, y: np.ndarray) -> float:
    coeffs = fit_parabola(x, y)
    return float(np.sum((coeffs[0] + coeffs[1] * x + coeffs[2] * x * x - y) ** 2))


def orient_parabola(xy: np.ndarray, theta: float) -> tuple[float, bool]:
    """Eq 7 and the flips after it: the in-plane angle and whether to flip the plane over so the
    parabola's axis is y, it opens downwards (c < 0) and the flight runs towards x >= 0.

    Returns (angle, flip): new coordinates are rotation_2d(angle) @ p, then y -> -y if flip (in 3-D,
    a half turn about x that also turns the plane's normal over, so the frame stays right-handed)."""
    angle = -theta  # eq 6: the axis of symmetry is now parallel to x or y
    rotated = xy @ rotation_2d(angle).T
    # Two parabolas, y(x) and x(y): the lower error tells which axis is the axis of symmetry.
    if parabola_sse(rotated[:, 1], rotated[:, 0]) < parabola_sse(rotated[:, 0], rotated[:, 1]):
        angle += np.pi / 2
        rotated = xy @ rotation_2d(angle).T
    # The flight starts at the origin and runs towards x >= 0.
    if np.median(rotated[:, 0]) < 0:
        angle += np.pi
        rotated = -rotated
    flip = fit_parabola(rotated[:, 0], rotated[:, 1])[2] > 0  # gravity pulls towards -y
    return float(angle), bool(flip)


# ------------------------------------------------------------------------------------ eq 8 - 10
def parabola_closest_x(coeffs: np.ndarray, px: np.ndarray, py: np.ndarray) -> np.ndarray:
    """Eqs 8-10: the x of the closest point on y = a + b x + c x^2 to each point (px, py).

    d(r^2)/dx = 0 is the cubic of eq 9; it is depressed (x = chi - b / 2c) and solved in closed form.
    The paper assumes one real root (Cardano, eq 10); points on the concave side beyond the evolute
    have three, so those take the trigonometric form and the root nearest the point. One Newton step
    polishes the root against cancellation."""
    a, b, c = (float(v) for v in coeffs)
    shape = np.broadcast(np.asarray(px), np.asarray(py)).shape
    px, py = (np.broadcast_to(np.asarray(v, dtype=np.float64), shape).ravel() for v in (px, py))
    if abs(c) < 1e-12:  # a straight line: orthogonal projection
        return ((px + b * (py - a)) / (1.0 + b * b)).reshape(shape)
    k3, k2 = 2 * c * c, 3 * b * c
    k1 = b * b + 2 * c * (a - py) + 1.0
    k0 = b * (a - py) - px
    p = (3 * k3 * k1 - k2 * k2) / (3 * k3 * k3)
    q = (2 * k2 ** 3 - 9 * k3 * k2 * k1 + 27 * k3 * k3 * k0) / (27 * k3 ** 3)
    shift = -k2 / (3 * k3)
    disc = q * q / 4 + p ** 3 / 27
    root_disc = np.sqrt(np.maximum(disc, 0.0))
    one_root = np.cbrt(-q / 2 + root_disc) + np.cbrt(-q / 2 - root_disc) + shift  # eq 10
    # Three real roots where disc < 0 (then p < 0): chi_k = 2 sqrt(-p/3) cos(phi/3 - 2 pi k / 3).
    m = 2 * np.sqrt(np.maximum(-p / 3, 0.0))
    safe_p = np.where(p < 0, p, -1.0)
    phi = np.arccos(np.clip(3 * q / (2 * safe_p) * np.sqrt(-3 / safe_p), -1.0, 1.0))
    roots = np.stack([one_root] + [m * np.cos(phi / 3 - 2 * np.pi * k / 3) + shift for k in range(3)])
    roots[1:, disc >= 0] = one_root[disc >= 0]
    # Newton polish on the cubic, then the root closest to the point.
    value = ((k3 * roots + k2) * roots + k1) * roots + k0
    slope = (3 * k3 * roots + 2 * k2) * roots + k1
    roots = roots - np.where(np.abs(slope) > 0, value / np.where(slope == 0, 1, slope), 0)
    dist2 = (roots - px) ** 2 + (a + b * roots + c * roots ** 2 - py) ** 2
    return np.take_along_axis(roots, np.argmin(dist2, axis=0)[None], axis=0)[0].reshape(shape)


def parabola_distance(coeffs: np.ndarray, px: np.ndarray, py: np.ndarray) -> np.ndarray:
    """Eq 8: the true (orthogonal) distance from each point to the parabola y = a + b x + c x^2."""
    a, b, c = (float(v) for v in coeffs)
    x = parabola_closest_x(coeffs, px, py)
    return np.hypot(x - px, a + b * x + c * x * x - py)


def drop_beyond_mean_distance(distances: np.ndarray) -> np.ndarray:
    """The paper's outlier pass: keep the points no farther from the parabola than the mean distance."""
    return distances <= np.mean(distances)


# ----------------------------------------------------------------------------------- eq 11 - 13
def scale_from_parabola(coeffs: np.ndarray, x: np.ndarray, times: np.ndarray,
                        gravity: float = MOON_GRAVITY) -> dict:
    """Eqs 11-13 on the oriented parabola (launch at the origin, times from launch):
    tan(elevation) = b (eq 11), x_sym = -b / 2c, t_sym = median(t_i x_sym / x_i) (constant horizontal
    speed), v0 = t_sym g / sin(elevation) (eq 12), scale = v0 cos(elevation) t_sym / x_sym (eq 13)."""
    a, b, c = (float(v) for v in coeffs)
    if not c < 0:
        raise ValueError(f"the parabola does not open downwards (c = {c:g}): not a ballistic flight")
    x, times = np.asarray(x, dtype=np.float64), np.asarray(times, dtype=np.float64)
    elevation = float(np.arctan(b))
    x_sym = -b / (2 * c)
    usable = (x > 1e-3 * np.ptp(x)) & (times > 0)
    if not usable.any():
        raise ValueError("no frame after launch to time the apex with")
    t_sym = float(np.median(times[usable] * x_sym / x[usable]))
    v0 = t_sym * gravity / np.sin(elevation)
    return {"elevation": elevation, "x_sym": x_sym, "t_sym": t_sym, "v0": float(v0),
            "scale": float(v0 * np.cos(elevation) * t_sym / x_sym)}


def fit_flight_paper(centres: np.ndarray, timestamps: np.ndarray, gravity: float = MOON_GRAVITY,
                     plane_tolerance: float = 0.03, rng: np.random.Generator | int | None = 0) -> FlightFit:
    """The paper's chain: flight plane, conic, rotation, parabola, outlier pass, scale (eqs 2-13).

    centres: (N, 3) centre-of-mass positions in the SfM frame, in time order, the first at launch;
    plane_tolerance: RANSAC threshold as a fraction of the trajectory's extent (the unit is unknown)."""
    centres, times = _check_flight_input(centres, timestamps)
    times = times - times[0]
    # RANSAC flight plane through the camera centres.
    extent = float(np.ptp(centres, axis=0).max())
    plane, on_plane = ransac_plane(centres, plane_tolerance * extent, rng=rng)
    # Into the plane, the first camera (the launch) at the origin.
    xy, basis = to_flight_plane(centres, plane, centres[0])
    # Conic through the origin (eqs 3-5) and the rotation that aligns its axis (eq 6).
    theta = conic_axis_angle(fit_conic_through_origin(xy[on_plane]))
    angle, flip = orient_parabola(xy[on_plane], theta)
    xy = xy @ rotation_2d(angle).T
    if flip:
        xy[:, 1] *= -1
    # Parabola (eq 7), Cardano distances (eqs 8-10), drop points beyond the mean distance, refit.
    coeffs = fit_parabola(xy[on_plane, 0], xy[on_plane, 1])
    in_plane_distance = parabola_distance(coeffs, xy[:, 0], xy[:, 1])
    keep = on_plane.copy()
    keep[on_plane] = drop_beyond_mean_distance(in_plane_distance[on_plane])
    coeffs = fit_parabola(xy[keep, 0], xy[keep, 1])
    # Launch angle, v0 and scale (eqs 11-13).
    result = scale_from_parabola(coeffs, xy[keep, 0], times[keep], gravity)
    scale = result["scale"]
    # The 3-D axes: x along the plane's rotated first axis, z along its rotated second, y = z x x.
    e1, e2, normal = basis
    c, s = np.cos(angle), np.sin(angle)
    x_axis, z_axis = c * e1 - s * e2, s * e1 + c * e2
    if flip:
        z_axis = -z_axis
    rotation = np.array([x_axis, np.cross(z_axis, x_axis), z_axis])
    launch = plane.project(centres[:1])[0]
    distance = np.hypot(parabola_distance(coeffs, xy[:, 0], xy[:, 1]), plane.signed_distance(centres))
    residuals = scale * distance
    elevation = result["elevation"]
    v_h = result["v0"] * np.cos(elevation)
    x_last = xy[-1, 0]
    return FlightFit(
        method="paper", scale=scale, rotation=rotation, translation=-scale * rotation @ launch,
        gravity_sfm=-z_axis, launch_velocity=np.array([v_h, 0.0, result["v0"] * np.sin(elevation)]),
        launch_speed=result["v0"], launch_elevation=elevation, apex_time=result["t_sym"],
        flight_time=float(times[-1]),
        landing_point=scale * np.array([x_last, 0.0, coeffs[0] + coeffs[1] * x_last + coeffs[2] * x_last ** 2]),
        inliers=keep, residuals_m=residuals, rms_m=float(np.sqrt(np.mean(residuals[keep] ** 2))),
        scale_sigma=float("nan"), gravity_sigma_rad=float("nan"),
        params={"parabola": coeffs, "conic_angle": theta, "plane_inliers": on_plane, **result})


# ----------------------------------------------------------------------------- the timed fit
def ballistic_design(tau: np.ndarray) -> np.ndarray:
    """Rows [1, tau, tau^2 / 2]: p(tau) = design @ [c; v; gamma]."""
    tau = np.asarray(tau, dtype=np.float64)
    return np.column_stack([np.ones_like(tau), tau, 0.5 * tau * tau])


def ballistic_blocks(tau: np.ndarray, offsets: np.ndarray | None = None, down: np.ndarray | None = None,
                     gravity: float = MOON_GRAVITY) -> np.ndarray:
    """(N, 3, P) design blocks: frame i's position = blocks[i] @ [c, v, gamma (, mu)].

    With eq 1's offsets (R_i o, the camera-to-centre-of-mass vector in SfM axes and metres) the camera
    is at p_com - R_i o / scale. Given gravity's current direction `down`, 1 / scale = |gamma| / g ~
    (down . gamma) / g is linear in gamma, so the offset joins the same 9-unknown solve; without a
    direction yet, mu = 1 / scale is a free 10th unknown (exact too, only less constrained)."""
    rows = ballistic_design(tau)
    blocks = np.einsum("nk,ij->nikj", rows, np.eye(3)).reshape(len(rows), 3, 9)
    if offsets is None:
        return blocks
    offsets = np.asarray(offsets, dtype=np.float64)
    if down is None:
        return np.concatenate([blocks, -offsets[:, :, None]], axis=2)
    blocks[:, :, 6:] -= np.einsum("ni,j->nij", offsets, down) / gravity
    return blocks


def ballistic_residuals(solution: np.ndarray, points: np.ndarray, blocks: np.ndarray) -> np.ndarray:
    """Distance of each frame from the trajectory position at its own time."""
    return np.linalg.norm(points - blocks @ solution, axis=1)


def fit_ballistic_lmeds(points: np.ndarray, tau: np.ndarray, blocks: np.ndarray, samples: int = 400,
                        rng: np.random.Generator | int | None = 0) -> tuple[np.ndarray, float]:
    """Least median of squares over minimal samples: (solution [c, v, gamma (, mu)]; robust per-axis
    noise sigma). Three frames fix the trajectory exactly; one frame from each part of the flight keeps
    the samples well conditioned. No threshold is needed, which matters in an unknown unit."""
    rng = np.random.default_rng(rng)
    n, unknowns = len(points), blocks.shape[2]
    parts = np.array_split(np.argsort(tau), -(-unknowns // 3))
    picks = np.column_stack([rng.choice(part, samples) for part in parts])
    a = blocks[picks].reshape(samples, -1, unknowns)
    b = points[picks].reshape(samples, -1)
    solutions = np.einsum("kij,kj->ki", np.linalg.pinv(a), b)           # (K, P)
    residuals = np.linalg.norm(points[None] - np.einsum("nij,kj->kni", blocks, solutions), axis=2)
    medians = np.median(residuals, axis=1)
    best = int(np.argmin(medians))
    # Maxwell median -> per-axis sigma, with Rousseeuw's small-sample correction.
    sigma = medians[best] / MAXWELL_MEDIAN * (1 + 5 / max(n - len(parts), 1))
    return solutions[best], float(sigma)


def fit_ballistic_weighted(points: np.ndarray, blocks: np.ndarray, weights: np.ndarray, sigma: float,
                           gravity_prior: np.ndarray | None = None, prior_sigma_rad: float = np.inf,
                           gamma_norm: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Weighted least squares of all 9 unknowns at once: (solution [c, v, gamma], its (9, 9) covariance).

    A gravity prior adds three rows lambda (I - g g^T) gamma = 0 (gamma's part across the prior
    direction g, linear in gamma), lambda = sigma / (|gamma| prior_sigma) so the prior weighs as an
    angle against position residuals of sigma."""
    w = np.repeat(np.sqrt(weights), 3)
    unknowns = blocks.shape[2]
    rows, rhs = blocks.reshape(-1, unknowns) * w[:, None], points.ravel() * w
    if gravity_prior is not None and np.isfinite(prior_sigma_rad):
        g = np.asarray(gravity_prior, dtype=np.float64)
        g = g / np.linalg.norm(g)
        lam = sigma / (gamma_norm * max(prior_sigma_rad, 1e-9))
        prior_rows = np.zeros((3, unknowns))
        prior_rows[:, 6:9] = lam * (np.eye(3) - np.outer(g, g))
        rows, rhs = np.vstack([rows, prior_rows]), np.concatenate([rhs, np.zeros(3)])
    solution, *_ = np.linalg.lstsq(rows, rhs, rcond=None)
    covariance = sigma ** 2 * np.linalg.pinv(rows.T @ rows)
    return solution, covariance


def tukey_weights(residuals: np.ndarray, sigma: float, c: float = TUKEY_C) -> np.ndarray:
    u = residuals / (c * sigma)
    return np.where(u < 1, (1 - u * u) ** 2, 0.0)


def fit_ballistic_robust(points: np.ndarray, tau: np.ndarray, gravity: float = MOON_GRAVITY,
                         gravity_prior: np.ndarray | None = None, prior_sigma_rad: float = np.inf,
                         offsets: np.ndarray | None = None, frame_weights: np.ndarray | None = None,
                         iterations: int = 30, rng: np.random.Generator | int | None = 0,
                         min_sigma_fraction: float = MIN_SIGMA_FRACTION) -> dict:
    """LMedS start, then Tukey-weighted refits with the noise scale re-estimated from the inliers, never
    below min_sigma_fraction of the points' extent.

    With eq 1's offsets a first fit keeps 1 / scale free; its gravity direction then linearises the
    exact model, rebuilt at every refit (the direction is well determined, so this settles quickly)."""
    down = None
    if offsets is not None:
        blocks = ballistic_blocks(tau, offsets)
        free = _robust_solve(points, tau, blocks, gravity_prior, prior_sigma_rad, frame_weights, iterations, rng,
                             min_sigma_fraction=min_sigma_fraction)
        down = free["solution"][6:9] / np.linalg.norm(free["solution"][6:9])
    blocks = ballistic_blocks(tau, offsets, down, gravity)
    fit = _robust_solve(points, tau, blocks, gravity_prior, prior_sigma_rad, frame_weights, iterations, rng,
                        offsets=offsets, gravity=gravity, min_sigma_fraction=min_sigma_fraction)
    return {"coeffs": fit["solution"][:9].reshape(3, 3), **fit}


def _robust_solve(points: np.ndarray, tau: np.ndarray, blocks: np.ndarray, gravity_prior: np.ndarray | None,
                  prior_sigma_rad: float, frame_weights: np.ndarray | None, iterations: int,
                  rng: np.random.Generator | int | None, offsets: np.ndarray | None = None,
                  gravity: float = MOON_GRAVITY, min_sigma_fraction: float = MIN_SIGMA_FRACTION) -> dict:
    solution, sigma = fit_ballistic_lmeds(points, tau, blocks, rng=rng)
    frame_weights = np.ones(len(points)) if frame_weights is None else np.asarray(frame_weights, float)
    floor = max(min_sigma_fraction, 1e-12) * float(np.ptp(points, axis=0).max())
    sigma = max(sigma, floor)
    for _ in range(iterations):
        weights = tukey_weights(ballistic_residuals(solution, points, blocks), sigma) * frame_weights
        new, covariance = fit_ballistic_weighted(points, blocks, weights, sigma, gravity_prior, prior_sigma_rad,
                                                 float(np.linalg.norm(solution[6:9])))
        if offsets is not None and blocks.shape[2] == 9:  # the linearised offset model follows gravity
            blocks = ballistic_blocks(tau, offsets, new[6:9] / np.linalg.norm(new[6:9]), gravity)
        # Re-estimate sigma from the inliers' residuals (3 axes per frame, P unknowns).
        residuals = ballistic_residuals(new, points, blocks)
        inside = residuals < MAXWELL_99 * sigma
        new_sigma = max(float(np.sqrt(np.sum(residuals[inside] ** 2) / max(3 * inside.sum() - len(new), 1))),
                        floor)
        converged = np.abs(new - solution).max() <= 1e-10 * np.abs(solution).max() and \
            abs(new_sigma - sigma) <= 1e-6 * sigma
        solution, sigma = new, new_sigma
        if converged:
            break
    residuals = ballistic_residuals(solution, points, blocks)
    return {"solution": solution, "covariance": covariance, "sigma": sigma, "residuals": residuals,
            "inliers": residuals < MAXWELL_99 * sigma}


def fit_flight(centres: np.ndarray, timestamps: np.ndarray, gravity: float = MOON_GRAVITY,
               gravity_prior: np.ndarray | None = None, prior_sigma_rad: float = np.radians(1.0),
               camera_rotations: np.ndarray | None = None, com_offset_m: np.ndarray | None = None,
               frame_weights: np.ndarray | None = None, launch_time: float | None = None,
               rng: np.random.Generator | int | None = 0, min_sigma_fraction: float = MIN_SIGMA_FRACTION) -> FlightFit:
    """Scale, gravity and launch state of a hop from its SfM camera centres and frame times (see the
    module docstring). centres: (N, 3) SfM frame; timestamps: (N,) seconds; gravity_prior: gravity's
    direction in the SfM frame from the accelerometers (at rest before launch, through the first camera's
    SfM rotation), trusted to prior_sigma_rad; camera_rotations (camera-to-SfM) and com_offset_m (the
    centre of mass in the camera frame, metres) apply eq 1 inside the fit; frame_weights: optional
    per-frame weights (e.g. inverse SfM variance); launch_time: defaults to the first frame's time;
    min_sigma_fraction: the noise scale's floor as a share of the flight's extent (MIN_SIGMA_FRACTION).
    The launch point and the trajectory are the centre of mass's."""
    centres, times = _check_flight_input(centres, timestamps)
    tau = times - (times[0] if launch_time is None else float(launch_time))
    offsets = None
    if com_offset_m is not None:
        if camera_rotations is None:
            raise ValueError("com_offset_m needs camera_rotations")
        offsets = centre_of_mass_positions(np.zeros_like(centres), camera_rotations, com_offset_m)
    fit = fit_ballistic_robust(centres, tau, gravity, gravity_prior, prior_sigma_rad, offsets, frame_weights,
                               rng=rng, min_sigma_fraction=min_sigma_fraction)
    launch, velocity, gamma = fit["coeffs"]
    gamma_norm = float(np.linalg.norm(gamma))
    if not gamma_norm > 0:
        raise ValueError("the frames show no acceleration: not a ballistic flight")
    down = gamma / gamma_norm
    covariance = fit["covariance"][6:9, 6:9]
    gamma_sigma = float(np.sqrt(down @ covariance @ down))
    if gamma_norm < 5 * gamma_sigma:
        raise ValueError(f"the frames' acceleration is not significant ({gamma_norm / gamma_sigma:.1f} sigma): "
                         "not a ballistic flight")
    scale = gravity / gamma_norm
    up = -down
    horizontal = velocity - (velocity @ up) * up
    if np.linalg.norm(horizontal) < 1e-9 * np.linalg.norm(velocity):
        raise ValueError("the flight is vertical: no horizontal direction to align x with")
    x_axis = horizontal / np.linalg.norm(horizontal)
    rotation = np.array([x_axis, np.cross(up, x_axis), up])
    launch_velocity = scale * rotation @ velocity
    across = np.eye(3) - np.outer(down, down)
    residuals = scale * fit["residuals"]
    inliers = fit["inliers"]
    last = ballistic_design(tau[-1:]) @ fit["coeffs"]
    translation = -scale * rotation @ launch
    return FlightFit(
        method="timed", scale=scale, rotation=rotation, translation=translation, gravity_sfm=down,
        launch_velocity=launch_velocity, launch_speed=float(np.linalg.norm(launch_velocity)),
        launch_elevation=float(np.arctan2(launch_velocity[2], launch_velocity[0])),
        apex_time=float(launch_velocity[2] / gravity), flight_time=float(tau[-1]),
        landing_point=scale * rotation @ last[0] + translation,
        inliers=inliers, residuals_m=residuals, rms_m=float(np.sqrt(np.mean(residuals[inliers] ** 2))),
        scale_sigma=float(scale * gamma_sigma / gamma_norm),
        gravity_sigma_rad=float(np.sqrt(np.trace(across @ covariance @ across) / 2) / gamma_norm),
        params={"coeffs": fit["coeffs"], "sigma_sfm": fit["sigma"], "sigma_m": scale * fit["sigma"]})


def _check_flight_input(centres: np.ndarray, timestamps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    centres = np.asarray(centres, dtype=np.float64)
    times = np.asarray(timestamps, dtype=np.float64)
    if centres.ndim != 2 or centres.shape[1] != 3:
        raise ValueError(f"centres must be (N, 3), got {centres.shape}")
    if times.shape != (len(centres),):
        raise ValueError(f"timestamps must be ({len(centres)},), got {times.shape}")
    if len(centres) < 6:
        raise ValueError(f"a flight needs at least 6 frames, got {len(centres)}")
    if not (np.isfinite(centres).all() and np.isfinite(times).all()):
        raise ValueError("centres and timestamps must be finite")
    if np.any(np.diff(times) <= 0):
        raise ValueError("timestamps must increase strictly, in frame order")
    return centres, times
