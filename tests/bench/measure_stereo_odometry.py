"""Stereo visual odometry (toolbox.odometry.stereo) against the simulator's truth.

Steps: on each seeded world the rover grabs a keyframe pair, is placed 0.5, 1.0 and 1.5 m ahead
with heading changes of 0, 5 and 10 degrees, grabs again, and the estimated key_from_new of the
left camera is compared with the true one (from the true camera poses; the rover settles on the
terrain, so height, roll and pitch change too). The rig the estimate uses comes from the calibrated
mounts (what the server knows); the truth from the true ones.

Traverse (--chain): 5 m in 0.5 m steps with small turns, estimated frame to frame (re-keyed every
step) and with a keyframe kept while it overlaps enough; the error of the composed motion over 5 m.

    .venv/bin/python tests/bench/measure_stereo_odometry.py [--seeds 1 2 3 4 5] [--tilt -20]
        [--resolution medium] [--chain] [--one-way] [--no-offset]

ms is the CPU time of one stereo_motion call on one core.
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))
from drivers.avt import RESOLUTION_MODES, CameraSettings  # noqa: E402
from drivers.avt_emulator import emulated_stereo_pair  # noqa: E402
from drivers.sim.clock import SimClock  # noqa: E402
from drivers.sim.config import WorldConfig  # noqa: E402
from drivers.sim.rover import Rover  # noqa: E402
from drivers.sim.world import World  # noqa: E402
from toolbox.camera import Intrinsics  # noqa: E402
from toolbox.geometry import relative_pose  # noqa: E402
from toolbox.odometry.estimate import OdometryFailure  # noqa: E402
from toolbox.odometry.stereo import StereoOdometryParams, StereoRig, stereo_keyframe, stereo_motion  # noqa: E402

STEPS_M = (0.5, 1.0, 1.5)
TURNS_DEG = (0.0, 5.0, 10.0)


def intrinsics_of(camera) -> Intrinsics:
    return Intrinsics(camera.width, camera.height, camera.fx, camera.fy, camera.cx, camera.cy, camera.k1, camera.k2)


class Scene:
    """A seeded world, a rover on it and its emulated stereo pair at a fixed pan and tilt."""

    def __init__(self, seed: int, tilt_deg: float, resolution: str, size_m: float = 24.0):
        self.world = World.build(WorldConfig(seed=seed, size_m=(size_m, size_m)))
        self.rover = Rover(self.world)
        self.tilt, self.resolution, self.seed = tilt_deg, resolution, seed
        self.poses: dict[str, np.ndarray] = {}
        self.pair = emulated_stereo_pair(self.world, lambda t: self.poses["left"], lambda t: self.poses["right"],
                                         clock=SimClock(1.0), seed=seed,
                                         default_settings=CameraSettings(resolution=resolution))
        self.pair.open()
        camera = intrinsics_of(self.pair.camera("left").intrinsics(resolution))
        calibrated = [self.rover.sensor_to_world(s, 0, tilt_deg, calibrated=True) for s in ("left", "right")]
        self.rig = StereoRig(camera, camera, relative_pose(*calibrated))

    def grab(self, x: float, y: float, heading: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(left, right, true left camera-to-world) with the rover at (x, y, heading)."""
        self.rover.place(x, y, heading)
        self.poses = {s: self.rover.sensor_to_world(s, 0, self.tilt) for s in ("left", "right")}
        frames = self.pair.grab(timeout_s=60)
        return frames["left"].image, frames["right"].image, self.poses["left"]

    def close(self) -> None:
        self.pair.close()


def errors(estimate: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """(translation error m, rotation error deg) of an estimated relative pose."""
    rotation = estimate[:3, :3].T @ truth[:3, :3]
    angle = math.degrees(math.acos(np.clip((np.trace(rotation) - 1) / 2, -1.0, 1.0)))
    return float(np.linalg.norm(estimate[:3, 3] - truth[:3, 3])), angle


def steps(scene: Scene, params: StereoOdometryParams, start: tuple[float, float, float]) -> list[dict]:
    x0, y0, h0 = start
    left, right, key_pose = scene.grab(x0, y0, h0)
    key = stereo_keyframe(left, right, scene.rig, params)
    rows = []
    for step in STEPS_M:
        for turn in TURNS_DEG:
            heading = h0 + math.radians(turn)
            # Drive along the mean heading of the arc (the end point of a turn of that size).
            mid = h0 + math.radians(turn) / 2
            left, right, new_pose = scene.grab(x0 + step * math.cos(mid), y0 + step * math.sin(mid), heading)
            truth = relative_pose(new_pose, key_pose)   # new camera to key camera = key_from_new
            # CPU time of this process on one core (cv2 held to one thread): the machine is shared,
            # and wall time measures the neighbours.
            started = time.process_time()
            try:
                estimate, _ = stereo_motion(key, left, right, scene.rig, params)
            except OdometryFailure as failure:
                rows.append(dict(step=step, turn=turn, failure=str(failure)))
                continue
            ms = (time.process_time() - started) * 1000
            dt, dr = errors(estimate.key_from_new, truth)
            distance = float(np.linalg.norm(truth[:3, 3]))
            rows.append(dict(step=step, turn=turn, mm=dt * 1000, pct=100 * dt / distance, deg=dr,
                             deg_per_m=dr / distance, inliers=estimate.inliers, ms=ms,
                             sigma_mm=1000 * math.sqrt(np.trace(estimate.covariance[3:, 3:]))))
    return rows


def traverse(scene: Scene, start: tuple[float, float, float], length_m: float = 5.0,
             step_m: float = 0.5) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """The pairs (left, right, true left pose) along `length_m` in steps of `step_m` with a gentle
    weave (turns of up to 3 degrees), the first at the start."""
    x, y, heading = start
    looks = [scene.grab(x, y, heading)]
    for i in range(int(round(length_m / step_m))):
        turn = math.radians(3.0 * math.sin(i))
        x, y = x + step_m * math.cos(heading + turn / 2), y + step_m * math.sin(heading + turn / 2)
        heading += turn
        looks.append(scene.grab(x, y, heading))
    return looks


def chain(looks, rig: StereoRig, params: StereoOdometryParams, keep_overlap: float) -> tuple[float, float, int]:
    """(error % of distance, deg/m, keyframes used) of the motion composed along a traverse; the
    keyframe is kept while the estimate's overlap is at least keep_overlap (above 1: re-key every
    step, i.e. frame to frame)."""
    key = stereo_keyframe(looks[0][0], looks[0][1], rig, params)
    world_from_key, world_from_new, keyframes = np.eye(4), np.eye(4), 1
    for left, right, _ in looks[1:]:
        estimate, new = stereo_motion(key, left, right, rig, params)
        world_from_new = world_from_key @ estimate.key_from_new
        if estimate.overlap < keep_overlap:
            world_from_key, key, keyframes = world_from_new, new, keyframes + 1
    truth = relative_pose(looks[-1][2], looks[0][2])
    dt, dr = errors(world_from_new, truth)
    distance = float(np.linalg.norm(truth[:3, 3]))
    return 100 * dt / distance, dr / distance, keyframes


KEYFRAME_POLICIES = {"re-key every step": 1.01, "keyframe kept while overlap >= 25%": 0.25}


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3, 4, 5])
    parser.add_argument("--tilt", type=float, default=-20.0)
    parser.add_argument("--resolution", default="medium", choices=RESOLUTION_MODES)
    parser.add_argument("--chain", action="store_true", help="also the 5 m traverse with and without keyframe reuse")
    parser.add_argument("--one-way", action="store_true", help="refine with the keyframe's points only")
    parser.add_argument("--no-offset", action="store_true", help="trust the rig's disparity (no offset fitted)")
    args = parser.parse_args()
    cv2.setNumThreads(1)
    params = StereoOdometryParams(both_ways=not args.one_way, disparity_offset=not args.no_offset)
    rows, chains = [], []
    for seed in args.seeds:
        scene = Scene(seed, args.tilt, args.resolution)
        start = (-2.0, 0.0, math.radians(72.0 * seed))
        start = (-2.0 * math.cos(start[2]), -2.0 * math.sin(start[2]), start[2])
        for row in steps(scene, params, start):
            rows.append(row)
            if "failure" in row:
                print(f"seed {seed} step {row['step']:.1f} m turn {row['turn']:4.1f} deg: FAILED {row['failure']}")
            else:
                print(f"seed {seed} step {row['step']:.1f} m turn {row['turn']:4.1f} deg: {row['mm']:6.1f} mm "
                      f"({row['pct']:5.2f} %), {row['deg']:.3f} deg ({row['deg_per_m']:.3f} deg/m), "
                      f"{row['inliers']:4d} inliers, sigma {row['sigma_mm']:.1f} mm, {row['ms']:4.0f} ms")
        if args.chain:
            looks = traverse(scene, start)
            for label, keep in KEYFRAME_POLICIES.items():
                try:
                    pct, dpm, keys = chain(looks, scene.rig, params, keep)
                except OdometryFailure as failure:
                    print(f"seed {seed} traverse 5 m ({label}): FAILED {failure}")
                    continue
                chains.append((label, pct, dpm, keys))
                print(f"seed {seed} traverse 5 m ({label}): {pct:.2f} %, {dpm:.4f} deg/m, {keys} keyframes")
        scene.close()
    good = [r for r in rows if "failure" not in r]
    print(f"\n{args.resolution}, tilt {args.tilt:.0f} deg, {'one way' if args.one_way else 'both ways'}, "
          f"{'no' if args.no_offset else 'with'} disparity offset: "
          f"converged {len(good)}/{len(rows)}")
    for step in STEPS_M:
        of = [r for r in good if r["step"] == step]
        if of:
            print(f"step {step:.1f} m: median {np.median([r['pct'] for r in of]):.2f} %, "
                  f"{np.median([r['deg_per_m'] for r in of]):.4f} deg/m, {np.median([r['deg'] for r in of]):.3f} deg, "
                  f"{np.median([r['inliers'] for r in of]):.0f} inliers, {np.median([r['ms'] for r in of]):.0f} ms")
    if good:
        print(f"all: median {np.median([r['pct'] for r in good]):.2f} %, "
              f"{np.median([r['deg_per_m'] for r in good]):.4f} deg/m, "
              f"ms median {np.median([r['ms'] for r in good]):.0f}"
              f" max {max(r['ms'] for r in good):.0f}")
    for label in KEYFRAME_POLICIES:
        of = [c for c in chains if c[0] == label]
        if of:
            print(f"traverse 5 m, {label}: median {np.median([c[1] for c in of]):.2f} %, "
                  f"{np.median([c[2] for c in of]):.4f} deg/m, keyframes {np.median([c[3] for c in of]):.0f}")


if __name__ == "__main__":
    main()
