"""The emulated stereo pair through a standard matcher (OpenCV StereoSGBM, via the toolbox's stereo
chain) against the ray-cast truth, and the time to render a pair beside the bare render call.

On each seeded scene the pair sits on the rover's mast (about 1.5 m) looking 30 degrees down; it is
rectified from the cameras' true poses, matched, and the depth of every valid pixel at 2-6 m is
compared with the true depth of the same pixel.

    .venv/bin/python tests/bench/measure_stereo.py [--seeds 1 2 3] [--resolution medium]
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))
from drivers.avt import RESOLUTION_MODES, CameraSettings  # noqa: E402
from drivers.avt_emulator import emulated_stereo_pair  # noqa: E402
from drivers.sim.clock import SimClock  # noqa: E402
from drivers.sim.config import WorldConfig  # noqa: E402
from drivers.sim.render import render  # noqa: E402
from drivers.sim.rover import Rover  # noqa: E402
from drivers.sim.world import World  # noqa: E402
from toolbox.camera import Intrinsics, project  # noqa: E402
from toolbox.geometry import relative_pose  # noqa: E402
from toolbox.mapping.stereo import StereoCalibration, rectification, stereo_points  # noqa: E402


def intrinsics_of(camera) -> Intrinsics:
    return Intrinsics(camera.width, camera.height, camera.fx, camera.fy, camera.cx, camera.cy, camera.k1, camera.k2)


def measure(seed: int, resolution: str) -> tuple[float, float, float, float, float]:
    world = World.build(WorldConfig(seed=seed, size_m=(20.0, 20.0)))
    rover = Rover(world, heading=np.radians(40 * seed))
    left_pose, right_pose = rover.sensor_to_world("left", 0, -30), rover.sensor_to_world("right", 0, -30)
    clock = SimClock(1.0)
    pair = emulated_stereo_pair(world, lambda t: left_pose, lambda t: right_pose, clock=clock, seed=seed,
                                default_settings=CameraSettings(resolution=resolution))
    pair.open()
    started = time.perf_counter()
    frames = pair.grab(timeout_s=60)
    grab_s = time.perf_counter() - started
    k = pair.camera("left").intrinsics(resolution)
    started = time.perf_counter()
    view = render(world, left_pose, k)
    _ = view.intensity
    render_s = time.perf_counter() - started
    pair.close()
    calib = StereoCalibration(intrinsics_of(k), intrinsics_of(k), relative_pose(left_pose, right_pose))
    points, valid = stereo_points(frames["left"].image, frames["right"].image, rectification(calib))
    # The points lie on the rectified image's grid: project each back into the original left image
    # and compare its depth with the true depth of that pixel.
    truth = view.depth
    measured = points[valid]
    uv = np.rint(project(measured, intrinsics_of(k))).astype(np.int64)
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < k.width) & (uv[:, 1] >= 0) & (uv[:, 1] < k.height)
    true_z = truth[uv[inside, 1], uv[inside, 0]]
    band = (true_z >= 2.0) & (true_z <= 6.0)
    error = np.abs(measured[inside][band, 2] - true_z[band])
    in_band = (truth >= 2.0) & (truth <= 6.0)
    share = min(1.0, band.sum() / max(in_band.sum(), 1))
    return float(np.median(error)), float(np.percentile(error, 90)), share, grab_s, render_s


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    parser.add_argument("--resolution", default="medium", choices=RESOLUTION_MODES)
    args = parser.parse_args()
    for seed in args.seeds:
        median, p90, share, grab_s, render_s = measure(seed, args.resolution)
        print(f"seed {seed} {args.resolution}: depth error at 2-6 m median {median * 1000:.1f} mm, "
              f"p90 {p90 * 1000:.1f} mm, pixels with a depth {share:.0%}; stereo grab {grab_s:.2f} s "
              f"(both cameras) vs bare render of one view {render_s:.2f} s, ratio {grab_s / render_s:.2f}")


if __name__ == "__main__":
    main()
