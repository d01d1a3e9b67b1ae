"""One hazard-guard frame at a time, against the truth: what the guard's corridor calls a hazard on
lanes the truth says are clear, and whether it sees a rock dropped ahead.

    .venv/bin/python tests/bench/measure_corridor.py [--sensor stereo] [--seeds 31 32] [--frames 20]
        [--cover 0.15] [--disparities 64] [--min-disparity 16] [--step-min-cells 5] [--tilt -35]

No server and no driving: on each seeded world (the hazard campaign's, tests/bench/hazard_campaign.py)
the rover is placed on clear lanes at random, the sensor takes one frame at the guard's pan and tilt,
and the frame goes through the guard's own chain (frame points, toolbox.mapping.corridor). A hazard
in the swept corridor of a clear lane is a false one: its distance, cause and the true ground there
are printed. Every other frame a rock of 12-30 cm is dropped 1.6-3.8 m ahead, and the frame must
put a hazard within 0.15 m of it. The campaign (hours) says how a guard drives; this (a minute)
says why it stops, so a change can be tried on hundreds of frames before the campaign runs.
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "tests" / "bench"))

from hazard_campaign import CLEAN_RUN_M, SceneWorld  # noqa: E402

from drivers.avt import CameraSettings  # noqa: E402
from drivers.avt_emulator import emulated_stereo_pair  # noqa: E402
from drivers.sim.clock import SimClock  # noqa: E402
from drivers.sim.rover import Rover  # noqa: E402
from rvs_server.hazard.guard import causes as causes_of  # noqa: E402
from toolbox.colour import grey  # noqa: E402
from toolbox.geometry import relative_pose  # noqa: E402
from toolbox.mapping import hazard as H  # noqa: E402
from toolbox.mapping.corridor import CorridorParams, corridor_view  # noqa: E402
from toolbox.mapping.dem import view_points  # noqa: E402
from toolbox.mapping.stereo import (  # noqa: E402
    Rectification,
    SgbmConfig,
    StereoCalibration,
    rectification,
    stereo_points,
)

# A false hazard this close to the leading edge may stop a drive: nearer frames do not see it again
# (the view's foot lies about 0.8 m ahead of the edge), and the guard remembers it. Farther ones are
# seen again, closer and surer, before the rover reaches them.
NEAR_M = 1.5


@dataclass(frozen=True)
class Pair:
    """One low-mode stereo pair taken by a rover, with what the guard makes points of it with."""

    images: tuple[np.ndarray, np.ndarray]   # grey left, right
    rect: Rectification                     # from the calibrated mounts
    camera: np.ndarray                      # the left camera's calibrated pose (4x4)

    def points(self, config: SgbmConfig, max_range: float) -> np.ndarray:
        """World points of the pair matched with `config`, those beyond `max_range` dropped."""
        points, valid = stereo_points(*self.images, self.rect, config)
        valid &= points[..., 2] < max_range
        return view_points(points, valid, self.camera)


def stereo_pair(rover: Rover, tilt: float, seed: int) -> Pair:
    """One low-mode stereo pair at pan 0 and `tilt`, rendered from the true mounts, to be made into
    points with the calibrated ones, as the guard does."""
    left_true, right_true = (rover.sensor_to_world(role, 0.0, tilt) for role in ("left", "right"))
    pair = emulated_stereo_pair(rover.world, lambda t: left_true, lambda t: right_true, clock=SimClock(1.0),
                                seed=seed, default_settings=CameraSettings(resolution="low"))
    pair.open()
    try:
        frames = pair.grab(timeout_s=60)
        k_left, k_right = (pair.camera(role).intrinsics("low") for role in ("left", "right"))
    finally:
        pair.close()
    left_level, right_level = (rover.sensor_to_world(role, 0.0, 0.0, calibrated=True) for role in ("left", "right"))
    rect = rectification(StereoCalibration(k_left, k_right, relative_pose(left_level, right_level)))
    return Pair((grey(frames["left"].image), grey(frames["right"].image)), rect,
                rover.sensor_to_world("left", 0.0, tilt, calibrated=True))


def clear_poses(scene: SceneWorld, count: int, rng: np.random.Generator) -> list[tuple[float, float, float]]:
    """Up to `count` poses at the start of lanes the truth says are clear for a clean run."""
    lanes = scene.lanes
    rows, cols = np.nonzero(~lanes.forbidden)
    poses: list[tuple[float, float, float]] = []
    for index in rng.permutation(len(rows))[:count * 50]:
        x, y = lanes.x0 + (cols[index] + 0.5) * lanes.cell, lanes.y0 + (rows[index] + 0.5) * lanes.cell
        for h in rng.permutation(np.radians(np.arange(0, 360, 10))):
            if scene.lane_clear(x, y, float(h), CLEAN_RUN_M):
                poses.append((float(x), float(y), float(h)))
                break
        if len(poses) == count:
            break
    return poses


def explain(scene: SceneWorld, pose: list[float], args: argparse.Namespace, config: SgbmConfig,
            params: CorridorParams) -> None:
    """Every hazard cell of one frame's corridor with the true ground under it, and the frame's
    height error against the truth by distance ahead."""
    x, y, h = pose[0], pose[1], math.radians(pose[2])
    rover = Rover(scene.world, x=x, y=y, heading=h)
    points = stereo_pair(rover, args.tilt, 0).points(config, args.max_range)
    view = corridor_view(points, (x, y, h), params, 1)
    maps = H.hazard_maps(view.heights, params.cell, params.hazard)
    xs, ys = view.spec.centres()
    gx, gy = np.broadcast_arrays(xs[None, :], ys[:, None])
    error = view.heights - scene.world.height_at(gx, gy)
    ahead = (gx - x) * math.cos(h) + (gy - y) * math.sin(h)
    for low in np.arange(0.0, 4.5, 0.5):
        band = (ahead >= low) & (ahead < low + 0.5) & np.isfinite(error)
        if band.any():
            p95 = np.percentile(np.abs(error[band]), 95)
            print(f"  {low:.1f}-{low + 0.5:.1f} m ahead of the centre: {band.sum()} cells, height error median "
                  f"{np.median(error[band]) * 100:+.1f} cm, p95 |e| {p95 * 100:.1f} cm")
    rows, cols = np.nonzero(view.swept & H.is_hazard(view.code))
    for r, c in zip(rows, cols, strict=True):
        truth = float(np.nanmax(scene.world.protrusion_at(xs[c] + np.linspace(-0.1, 0.1, 5)[:, None],
                                                          ys[r] + np.linspace(-0.1, 0.1, 5)[None, :])))
        print(f"  hazard at {xs[c]:.3f},{ys[r]:.3f} ({ahead[r, c]:.2f} m ahead): {causes_of(int(view.code[r, c]))}, "
              f"slope {maps.slope_deg[r, c]:.1f} deg, step {maps.step[r, c] * 100:.1f} cm, roughness "
              f"{maps.roughness[r, c] * 100:.1f} cm; height error {error[r, c] * 100:+.1f} cm; true protrusion "
              f"within 0.1 m {truth * 100:.1f} cm")
    print(f"nearest: {view.nearest}; seen {view.seen:.0%}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[31, 32])
    parser.add_argument("--frames", type=int, default=20, help="frames per seed")
    parser.add_argument("--cover", type=float, default=0.15)
    parser.add_argument("--disparities", type=int, default=64)
    parser.add_argument("--min-disparity", type=int, default=16, help="hazard.toml stereo_min_disparity")
    parser.add_argument("--step-min-cells", type=int, default=5)
    parser.add_argument("--tilt", type=float, default=-35.0)
    parser.add_argument("--max-range", type=float, default=4.0)
    parser.add_argument("--pose", type=float, nargs=3, metavar=("X", "Y", "HEADING_DEG"),
                        help="one frame from this pose on the first seed, its hazards against the truth")
    parser.add_argument("--verbose", action="store_true")
    args = parser.parse_args()
    config = SgbmConfig(min_disparity=args.min_disparity, num_disparities=args.disparities, block_size=5)
    params = CorridorParams(body_length=0.55, body_width=0.50, side_margin=0.10, reach=4.0, cell=0.05,
                            hazard=H.HazardConfig(step_min_cells=args.step_min_cells))
    totals = {"clear": 0, "false": 0, "near": 0, "rocks": 0, "seen": 0}
    causes: dict[str, int] = {}
    seconds: list[float] = []
    if args.pose:
        explain(SceneWorld(args.seeds[0], args.cover), args.pose, args, config, params)
        return
    for seed in args.seeds:
        scene = SceneWorld(seed, args.cover)
        rng = np.random.default_rng(seed)
        for index, (x, y, h) in enumerate(clear_poses(scene, args.frames, rng)):
            rover = Rover(scene.world, x=x, y=y, heading=h)
            rock = None
            if index % 2:
                distance, offset, height = rng.uniform(1.6, 3.8), rng.uniform(-0.2, 0.2), rng.uniform(0.12, 0.30)
                at = (x + distance * math.cos(h) - offset * math.sin(h),
                      y + distance * math.sin(h) + offset * math.cos(h))
                rock = (scene.world.add_rock(*at, height=height), at, height, distance)
            started = time.perf_counter()
            points = stereo_pair(rover, args.tilt, seed * 1000 + index).points(config, args.max_range)
            view = corridor_view(points, (x, y, h), params, 1)
            seconds.append(time.perf_counter() - started)
            if rock is None:
                totals["clear"] += 1
                if view.nearest is not None:
                    totals["false"] += 1
                    hit = view.nearest
                    totals["near"] += hit.distance <= NEAR_M
                    cause = causes_of(hit.cause)
                    causes[cause] = causes.get(cause, 0) + 1
                    truth = float(np.nanmax(scene.world.protrusion_at(
                        hit.x + np.linspace(-0.1, 0.1, 5)[:, None], hit.y + np.linspace(-0.1, 0.1, 5)[None, :])))
                    print(f"seed {seed} frame {index}: false hazard {hit.distance:.2f} m ahead ({cause}), true "
                          f"protrusion within 0.1 m {truth * 100:.1f} cm, seen {view.seen:.0%}")
            else:
                rock_id, at, height, distance = rock
                totals["rocks"] += 1
                rows, cols = np.nonzero(view.swept & H.is_hazard(view.code))
                xs, ys = view.spec.centre_of(rows, cols)
                found = bool(len(xs)) and float(np.min(np.hypot(xs - at[0], ys - at[1]))) <= 0.15 + height / 2
                totals["seen"] += found
                if not found or args.verbose:
                    print(f"seed {seed} frame {index}: rock {height * 100:.0f} cm at {distance:.2f} m "
                          f"{'found' if found else 'MISSED'}")
                scene.world.remove_obstacle(rock_id)
    print(f"sensor stereo, disparities {args.min_disparity}+{args.disparities}, step_min_cells "
          f"{args.step_min_cells}, tilt {args.tilt}: clear frames with a false hazard {totals['false']}/"
          f"{totals['clear']} ({totals['near']} within {NEAR_M:g} m), causes {causes}; rocks found "
          f"{totals['seen']}/{totals['rocks']}; frame to corridor median {np.median(seconds) * 1000:.0f} ms "
          "(render included)")


if __name__ == "__main__":
    main()
