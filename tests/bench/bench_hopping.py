"""Benchmark: the hopping toolbox against the paper's own methods, on synthetic hops in one run.

1. Scale and gravity (hopping_parabola): the paper's geometric chain (fit_flight_paper: plane, conic,
   parabola, Cardano outlier pass, eqs 11-13) beside the timed fit (fit_flight) on the same hops,
   with the weaknesses the paper and the reference file name: Gaussian noise, gross outliers, noisier
   ends (camera near the ground), a systematic bend and scale drift of the SfM trajectory, and an
   accelerometer gravity prior. The Cramer-Rao bound of the noise is printed for the Gaussian case.
2. Position correction (hopping_icp): Open3D point-to-point, point-to-plane, point-to-plane + Tukey,
   and the crop loop (6 DoF and yaw + translation) on 20k-point clouds overlapping by half,
   0.3 m and 2 degrees off (the reference file's set-up).
3. The landing error ellipse (hopping_ballistics): first order (paper) and exact moments against a
   Monte Carlo of the range equation; and the time plan_landing takes.

    .venv/bin/python tests/bench/bench_hopping.py [--hops 200] [--seed 0]
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from functools import partial
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))
from toolbox.hopping.ballistics import hop_range, landing_error_ellipse  # noqa: E402
from toolbox.hopping.icp import (  # noqa: E402
    align_with_overlap_elimination,
    apply_transform,
    estimate_normals,
    icp_point_to_plane,
    icp_point_to_point,
    transform_change,
)
from toolbox.hopping.landing import LandingParams, plan_landing  # noqa: E402
from toolbox.hopping.parabola import ballistic_design, fit_flight, fit_flight_paper  # noqa: E402

G = 1.62


# ------------------------------------------------------------------------------- 1. flight
def synthetic_hop(rng, noise=0.02, outliers=0.0, noisy_ends=0.0, bend=0.0, drift=0.0, frames=50,
                  elevation_deg=60.0):
    """A 1 m hop seen by SfM: (sfm centres, times, true scale, true down in SfM, inlier mask)."""
    elevation = math.radians(elevation_deg)
    speed = math.sqrt(G / math.sin(2 * elevation))
    t = np.linspace(0, 2 * speed * math.sin(elevation) / G, frames)
    p = np.column_stack([speed * math.cos(elevation) * t, 0 * t, speed * math.sin(elevation) * t - G * t * t / 2])
    u = t / t[-1]
    # Noise grows near the ground at both ends (fast motion, blur, few views of close ground).
    sigma = noise * (1 + noisy_ends * (1 - p[:, 2] / p[:, 2].max()))
    p = p + rng.normal(size=p.shape) * sigma[:, None]
    # A systematic bend sideways and upwards, and scale drift along the sequence.
    p += bend * np.column_stack([0 * u, 4 * u * (1 - u), 2 * u * (1 - u)])
    p *= (1 + drift * (u - 0.5))[:, None]
    good = np.ones(frames, dtype=bool)
    if outliers:
        bad = rng.choice(np.arange(1, frames), int(round(outliers * frames)), replace=False)
        direction = rng.normal(size=(len(bad), 3))
        p[bad] += direction / np.linalg.norm(direction, axis=1)[:, None] * rng.uniform(0.1, 0.5, (len(bad), 1))
        good[bad] = False
    rotation = Rotation.random(random_state=rng).as_matrix()
    scale = rng.uniform(0.5, 5.0)
    return p @ rotation.T / scale + rng.normal(size=3), t, scale, rotation @ [0, 0, -1.0], good


SCENARIOS = {
    "2% noise": dict(noise=0.02),
    "2% noise, 10% outliers": dict(noise=0.02, outliers=0.1),
    "1% noise x4 near ground, 10% out": dict(noise=0.01, noisy_ends=3.0, outliers=0.1),
    "1% noise, 3% bend": dict(noise=0.01, bend=0.03),
    "1% noise, 4% scale drift": dict(noise=0.01, drift=0.04),
    "0.25% noise, 10% outliers": dict(noise=0.0025, outliers=0.1),
}


def bench_flight(hops: int, seed: int) -> None:
    print(f"1. Scale and gravity from the flight: {hops} hops of 50 frames per scenario, 60 degrees, 1 m")
    print(f"   {'scenario':34s} {'method':14s} {'|ds| med':>9s} {'p90':>7s} {'max':>7s} {'grav med':>9s} "
          f"{'fails':>5s} {'ms/fit':>7s}")
    for name, settings in SCENARIOS.items():
        rows = {"paper": [], "timed": [], "timed + prior": []}
        times = {key: 0.0 for key in rows}
        fails = {key: 0 for key in rows}
        for k in range(hops):
            rng = np.random.default_rng((seed, k))
            sfm, t, scale, down, good = synthetic_hop(rng, **settings)
            prior = Rotation.from_rotvec(math.radians(0.5) * np.cross(down, [1.0, 0, 0])
                                         / np.linalg.norm(np.cross(down, [1.0, 0, 0]))).apply(down)
            for key, fit in (("paper", partial(fit_flight_paper, sfm, t)), ("timed", partial(fit_flight, sfm, t)),
                             ("timed + prior", partial(fit_flight, sfm, t, gravity_prior=prior,
                                                       prior_sigma_rad=math.radians(0.5)))):
                start = time.perf_counter()
                try:
                    result = fit()
                except (ValueError, np.linalg.LinAlgError):
                    fails[key] += 1
                    continue
                finally:
                    times[key] += time.perf_counter() - start
                angle = math.degrees(math.acos(np.clip(result.gravity_sfm @ down, -1, 1)))
                rows[key].append((abs(result.scale / scale - 1), angle))
        for key, values in rows.items():
            errors = np.array(values)
            print(f"   {name:34s} {key:14s} {np.median(errors[:, 0]):9.2%} {np.percentile(errors[:, 0], 90):7.2%} "
                  f"{errors[:, 0].max():7.2%} {np.median(errors[:, 1]):8.2f}d {fails[key]:5d} "
                  f"{1000 * times[key] / hops:7.2f}")
        if set(settings) == {"noise"}:
            t = synthetic_hop(np.random.default_rng(0), **settings)[1]
            design = ballistic_design(t)
            bound = settings["noise"] * math.sqrt(np.linalg.inv(design.T @ design)[2, 2]) / G
            print(f"   {'':34s} {'Cramer-Rao':14s} {0.6745 * bound:9.2%} {1.645 * bound:7.2%}"
                  f"   (1-sigma {bound:.2%})")


# ------------------------------------------------------------------------------- 2. ICP
def terrain(seed: int, rocks: int = 60):
    rng = np.random.default_rng(seed)
    centres = np.column_stack([rng.uniform(-1, 16, rocks), rng.uniform(-1, 7, rocks)])
    radius, height = rng.uniform(0.1, 0.5, rocks), rng.uniform(0.05, 0.4, rocks)

    def z(x, y):
        d2 = (x[:, None] - centres[:, 0]) ** 2 + (y[:, None] - centres[:, 1]) ** 2
        rocks = np.sum(height * np.exp(-d2 / (2 * radius ** 2)), axis=1)
        return 0.15 * np.sin(0.5 * x) + 0.1 * np.cos(0.7 * y + 0.3 * x) + rocks
    return z


def bench_icp(seeds: int) -> None:
    print("\n2. Position correction: 20k points per cloud, 50 % overlap, 0.3 m and 2 degrees off (random axes)")
    methods = ["point-to-point", "point-to-plane", "p2plane + Tukey", "crop loop 6 DoF", "crop loop yaw"]
    results = {m: [] for m in methods}
    for seed in range(seeds):
        rng = np.random.default_rng(seed)
        z = terrain(seed)
        x0, y0 = rng.uniform(0, 10, 20000), rng.uniform(0, 6, 20000)
        x1, y1 = rng.uniform(5, 15, 20000), rng.uniform(0, 6, 20000)
        previous = np.column_stack([x0, y0, z(x0, y0)]) + rng.normal(0, 0.005, (20000, 3))
        current = np.column_stack([x1, y1, z(x1, y1)]) + rng.normal(0, 0.005, (20000, 3))
        axis, move = rng.normal(size=3), rng.normal(size=3)
        error = np.eye(4)
        error[:3, :3] = Rotation.from_rotvec(math.radians(2) * axis / np.linalg.norm(axis)).as_matrix()
        error[:3, 3] = 0.3 * move / np.linalg.norm(move)
        yaw_error = np.eye(4)
        yaw_error[:3, :3] = Rotation.from_euler("z", 2, degrees=True).as_matrix()
        yaw_error[:3, 3] = error[:3, 3]
        moved, moved_yaw = apply_transform(error, current), apply_transform(yaw_error, current)
        normals = estimate_normals(previous, 0.15)
        runs = {
            "point-to-point": (error, lambda a=moved, b=previous: icp_point_to_point(a, b, np.eye(4), 1.0)[0]),
            "point-to-plane": (error, lambda a=moved, b=previous, n=normals: icp_point_to_plane(
                a, b, n, np.eye(4), 1.0, None)[0]),
            "p2plane + Tukey": (error, lambda a=moved, b=previous, n=normals: icp_point_to_plane(
                a, b, n, np.eye(4), 0.6, 0.1)[0]),
            "crop loop 6 DoF": (error, lambda a=moved, b=previous: align_with_overlap_elimination(
                a, b, voxel=0.05).transform),
            "crop loop yaw": (yaw_error, lambda a=moved_yaw, b=previous: align_with_overlap_elimination(
                a, b, voxel=0.05, dof="yaw").transform),
        }
        for name, (truth, run) in runs.items():
            start = time.perf_counter()
            transform = run()
            elapsed = time.perf_counter() - start
            metres, radians = transform_change(np.linalg.inv(truth), transform)
            results[name].append((metres, math.degrees(radians), elapsed))
    print(f"   {'method':18s} {'error med':>10s} {'max':>8s} {'deg med':>8s} {'ms':>6s}")
    for name, values in results.items():
        v = np.array(values)
        print(f"   {name:18s} {100 * np.median(v[:, 0]):8.2f}cm {100 * v[:, 0].max():6.2f}cm "
              f"{np.median(v[:, 1]):8.3f} {1000 * np.median(v[:, 2]):6.0f}")
    print("   (crop loop yaw: the error is yaw + translation only, as when both clouds are gravity-aligned)")


# ------------------------------------------------------------------------------- 3. landing
def bench_landing() -> None:
    print("\n3. Landing error ellipse vs a Monte Carlo of the range equation (10^6 samples), along-track sigma")
    rng = np.random.default_rng(0)
    print(f"   {'case':34s} {'MC':>8s} {'first order':>12s} {'exact':>8s} {'MC bias':>8s} {'exact bias':>10s}")
    for name, (speed, elev, sv, st, sp, ss) in {
        "45 deg, 5% speed, 5 deg elevation": (1.4, 45, 0.07, 5, 4, 0.03),
        "45 deg, elevation error only": (1.4, 45, 0.0, 6, 0, 0.0),
        "60 deg, 5% speed, 5 deg elevation": (1.4, 60, 0.07, 5, 4, 0.03),
        "60 deg, 10% speed, 10 deg": (1.4, 60, 0.14, 10, 8, 0.03),
    }.items():
        n = 1_000_000
        v = rng.normal(speed, sv, n)
        th = rng.normal(math.radians(elev), math.radians(st), n)
        psi = rng.normal(0, math.radians(sp), n)
        along = hop_range(v, th, G) * np.cos(psi) + rng.normal(0, ss, n) - hop_range(speed, math.radians(elev), G)
        args = (speed, math.radians(elev), sv, math.radians(st), math.radians(sp), ss, G)
        first, exact = landing_error_ellipse(*args, exact=False), landing_error_ellipse(*args)
        print(f"   {name:34s} {along.std():8.4f} {first.along_sigma:12.4f} {exact.along_sigma:8.4f} "
              f"{along.mean():8.4f} {exact.along_bias:10.4f}")
    rng = np.random.default_rng(1)
    xy = rng.uniform(-3.2, 3.2, (120_000, 2))
    points = np.column_stack([xy, 0.03 * xy[:, 0] + rng.normal(0, 0.004, len(xy))])
    for cell in (0.04, 0.02):
        start = time.perf_counter()
        plan = plan_landing(points, np.array([0, 0, 0.1]), goal_heading=0.5, params=LandingParams(cell=cell))
        print(f"   plan_landing, 120k points, {plan.spec.rows}x{plan.spec.cols} cells of {cell} m: "
              f"{1000 * (time.perf_counter() - start):.0f} ms, found={plan.found}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--hops", type=int, default=200)
    parser.add_argument("--icp-seeds", type=int, default=5)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    bench_flight(args.hops, args.seed)
    bench_icp(args.icp_seeds)
    bench_landing()


if __name__ == "__main__":
    main()
