"""Measure the simulated world: build time, peak memory, mesh size and render speed.

Run in a fresh process (peak memory is the process's high-water mark):
    .venv/bin/python tests/bench/bench_world.py [--cover 0.07] [--size 40] [--repeats 5]
Render times are medians, each beside Open3D's raw cast_rays of the same rays in the same run.
"""
from __future__ import annotations

import argparse
import math
import resource
import statistics
import sys
import time

import numpy as np

from drivers.sim.config import WorldConfig
from drivers.sim.render import camera_rays, render
from drivers.sim.rover import Rover
from drivers.sim.world import World
from toolbox.camera import Intrinsics

SR4000 = Intrinsics(width=176, height=144, fx=262.92, fy=262.92, cx=88.0, cy=69.0, k1=-0.826, k2=0.656)
HD = Intrinsics.from_fov(1920, 1080, math.radians(60.0))


def peak_rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024   # Linux reports KiB


def median_ms(action, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        started = time.perf_counter()
        action()
        times.append(time.perf_counter() - started)
    return 1000 * statistics.median(times)


def measure_build(config: WorldConfig) -> World:
    print(f"after imports: peak RSS {peak_rss_mib():.0f} MiB")
    started = time.perf_counter()
    world = World.build(config)
    built = time.perf_counter() - started
    ground = int(np.count_nonzero(world.rock_of_triangle < 0))
    rocks = len(world.rock_of_triangle) - ground
    print(f"world {world.grid.cols * world.grid.cell:g} m at {world.grid.cell * 100:g} cm, seed {config.seed}: "
          f"built in {built:.2f} s, peak RSS {peak_rss_mib():.0f} MiB")
    print(f"  {len(world.rocks)} rocks, cover {world.rock_cover():.2%} (asked {config.rocks.cover:.0%}); "
          f"triangles {ground / 1e6:.2f} M ground + {rocks / 1e6:.2f} M rocks")
    started = time.perf_counter()
    world.height_at(0.0, 0.0)                         # builds Open3D's scene on first use
    print(f"  ray-casting scene built in {time.perf_counter() - started:.2f} s, peak RSS {peak_rss_mib():.0f} MiB")
    return world


def measure_render(world: World, camera: Intrinsics, pose: np.ndarray, repeats: int) -> None:
    directions = camera.ray_directions().reshape(-1, 3) @ pose[:3, :3].T.astype(np.float32)
    rays = camera_rays(pose[:3, 3], directions)
    raw = median_ms(lambda: world.surface.cast(rays), repeats)
    geometry = median_ms(lambda: render(world, pose, camera).range, repeats)
    intensity = median_ms(lambda: render(world, pose, camera).intensity, repeats)

    def everything():
        view = render(world, pose, camera)
        for name in ("hit", "range", "depth", "points", "normals", "albedo", "lit", "intensity",
                     "incidence_cos", "rock"):
            getattr(view, name)
    full = median_ms(everything, repeats)
    print(f"  {camera.width}x{camera.height}: raw cast_rays {raw:.1f} ms; render range {geometry:.1f} ms "
          f"({geometry / raw:.1f}x), intensity with shadows {intensity:.1f} ms ({intensity / raw:.1f}x), "
          f"all outputs {full:.1f} ms ({full / raw:.1f}x)")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cover", type=float, default=WorldConfig().rocks.cover)
    parser.add_argument("--size", type=float, default=WorldConfig().size_m[0])
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args(argv)
    config = WorldConfig(size_m=(args.size, args.size), rocks={"cover": args.cover})
    world = measure_build(config)
    rover = Rover(world, heading=math.pi / 2)
    print("render (rover at the origin facing north, PTU tilt -20 deg):")
    measure_render(world, SR4000, rover.sensor_to_world("tof", tilt_deg=-20.0), args.repeats)
    measure_render(world, HD, rover.sensor_to_world("left", tilt_deg=-20.0), args.repeats)
    print(f"peak RSS at the end {peak_rss_mib():.0f} MiB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
