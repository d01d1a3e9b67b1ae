"""Pictures of a simulated world, for people: a top view with rocks outlined and camera views.

Run `python -m drivers.sim.pictures [out_dir]` to build the default world and write
top.png (the whole world), top-detail.png (4 m around the start at full resolution), and views
from the rover's left camera and time-of-flight camera, under two sun positions.
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from toolbox.camera import Intrinsics

from .config import Sun
from .lighting import shade
from .render import RenderedView, render
from .rover import Rover
from .world import World, WorldConfig

OUTLINE_COLOURS = ((0.30, (0, 0, 255)), (0.10, (0, 165, 255)), (0.03, (0, 255, 255)))  # BGR by height


def top_view(world: World, pixel_m: float, x_range: tuple[float, float] | None = None,
             y_range: tuple[float, float] | None = None, outline_min_height: float = 0.03) -> np.ndarray:
    """Orthographic view from above (BGR uint8, north up): sun-lit albedo with cast shadows,
    rocks taller than outline_min_height circled (yellow >= 3 cm, orange >= 10 cm, red >= 30 cm),
    a scale bar and a north arrow."""
    x0, x1 = x_range or (world.grid.x_min, world.grid.x_max)
    y0, y1 = y_range or (world.grid.y_min, world.grid.y_max)
    xs = np.arange(x0 + pixel_m / 2, x1, pixel_m)
    ys = np.arange(y1 - pixel_m / 2, y0, -pixel_m)           # row 0 is the northern edge
    x, y = np.meshgrid(xs, ys)
    radiance = _lit_from_above(world, x.ravel(), y.ravel()).reshape(x.shape)
    image = cv2.cvtColor(_to_grey(radiance), cv2.COLOR_GRAY2BGR)
    _outline_rocks(image, world, x0, y1, pixel_m, outline_min_height)
    _scale_bar(image, pixel_m)
    _north_arrow(image)
    return image


def _lit_from_above(world: World, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    z = world.height_at(x, y)
    normals = world.normal_at(x, y).astype(np.float32)
    points = np.stack([x, y, z], axis=1)
    ok = np.isfinite(z)
    radiance = np.zeros(len(x), dtype=np.float32)
    lit = world.in_sunlight(points[ok], normals[ok])
    radiance[ok] = shade(world.albedo_at(x[ok], y[ok]), normals[ok], lit, world.sun)
    return radiance


def _to_grey(radiance: np.ndarray, white: float | None = None) -> np.ndarray:
    """8-bit grey with a display gamma; `white` maps to 255 (default: the 99.5th percentile)."""
    if white is None:
        finite = radiance[np.isfinite(radiance) & (radiance > 0)]
        white = float(np.percentile(finite, 99.5)) if finite.size else 1.0
    scaled = np.clip(np.nan_to_num(radiance) / white, 0.0, 1.0) ** (1 / 2.2)
    return (scaled * 255 + 0.5).astype(np.uint8)


def _outline_rocks(image, world: World, x0: float, y1: float, pixel_m: float, min_height: float) -> None:
    rocks = world.rocks[world.rocks["height"] >= min_height]
    for rock in rocks[np.argsort(rocks["height"])]:
        colour = next(c for h, c in OUTLINE_COLOURS if rock["height"] >= h)
        centre = (int(round((rock["x"] - x0) / pixel_m)), int(round((y1 - rock["y"]) / pixel_m)))
        radius = max(2, int(round(rock["radius"] / pixel_m)))
        cv2.circle(image, centre, radius, colour, 1, cv2.LINE_AA)


def _scale_bar(image: np.ndarray, pixel_m: float) -> None:
    width_m = image.shape[1] * pixel_m
    bar_m = 10 ** math.floor(math.log10(width_m / 4))
    bar_m *= 5 if width_m / 4 >= 5 * bar_m else 2 if width_m / 4 >= 2 * bar_m else 1
    bar_px = int(round(bar_m / pixel_m))
    h = image.shape[0]
    scale = max(0.5, image.shape[1] / 1600)
    left, base = int(20 * scale), h - int(25 * scale)
    cv2.rectangle(image, (left - 6, base - int(30 * scale)), (left + bar_px + 6, base + 10), (0, 0, 0), -1)
    cv2.rectangle(image, (left, base - 6), (left + bar_px, base), (255, 255, 255), -1)
    label = f"{bar_m:g} m"
    cv2.putText(image, label, (left, base - int(10 * scale)), cv2.FONT_HERSHEY_SIMPLEX, 0.6 * scale,
                (255, 255, 255), max(1, int(scale)), cv2.LINE_AA)


def _north_arrow(image: np.ndarray) -> None:
    scale = max(0.5, image.shape[1] / 1600)
    x, top = image.shape[1] - int(40 * scale), int(20 * scale)
    cv2.arrowedLine(image, (x, top + int(50 * scale)), (x, top), (255, 255, 255), max(1, int(2 * scale)),
                    cv2.LINE_AA, tipLength=0.3)
    cv2.putText(image, "N", (x - int(8 * scale), top + int(75 * scale)), cv2.FONT_HERSHEY_SIMPLEX,
                0.7 * scale, (255, 255, 255), max(1, int(2 * scale)), cv2.LINE_AA)


def camera_image(view: RenderedView, white: float | None = None) -> np.ndarray:
    """The view's sun-lit intensity as an 8-bit grey image (sky black)."""
    return _to_grey(view.intensity, white)


def range_image(view: RenderedView, max_range: float) -> np.ndarray:
    """Range as a false-colour BGR image (near red, far blue; black where nothing was hit)."""
    scaled = np.clip(np.nan_to_num(view.range, posinf=max_range) / max_range, 0.0, 1.0)
    colour = cv2.applyColorMap((255 - scaled * 255).astype(np.uint8), cv2.COLORMAP_JET)
    colour[~view.hit] = 0
    return colour


def caption(image: np.ndarray, text: str) -> np.ndarray:
    """A copy of `image` with `text` on a dark band at the top."""
    out = image if image.ndim == 3 else cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    out = out.copy()
    scale = max(0.4, out.shape[1] / 2000)
    cv2.rectangle(out, (0, 0), (out.shape[1], int(34 * scale) + 4), (0, 0, 0), -1)
    cv2.putText(out, text, (8, int(26 * scale)), cv2.FONT_HERSHEY_SIMPLEX, 0.8 * scale, (255, 255, 255),
                max(1, int(1.5 * scale)), cv2.LINE_AA)
    return out


def write_pictures(out_dir: Path, world: World) -> list[Path]:
    """Write the top views and rover camera views of `world` into out_dir; return the paths."""
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []

    def save(name: str, image: np.ndarray) -> None:
        path = out_dir / name
        cv2.imwrite(str(path), image)
        written.append(path)

    sun = world.sun
    summary = (f"seed {world.config.seed}, {world.grid.cols * world.grid.cell:g} m, rock cover "
               f"{world.rock_cover():.1%}, sun az {sun.azimuth_deg:g} el {sun.elevation_deg:g}")
    save("top.png", caption(top_view(world, pixel_m=max(world.grid.cell, world.grid.cols * world.grid.cell / 2000),
                                     outline_min_height=0.10), f"top view: {summary}"))
    save("top-detail.png", caption(top_view(world, pixel_m=world.grid.cell / 2, x_range=(-2.0, 2.0),
                                            y_range=(0.5, 4.5), outline_min_height=0.05),
                                   "top view 4 m x 4 m north of the start, 5 mm/pixel"))
    rover = Rover(world, x=0.0, y=0.0, heading=math.pi / 2)   # facing north
    stereo = Intrinsics.from_fov(1920, 1080, math.radians(60.0))
    tof = Intrinsics(width=176, height=144, fx=262.92, fy=262.92, cx=88.0, cy=69.0, k1=-0.826, k2=0.656)
    left = rover.sensor_to_world("left", pan_deg=0.0, tilt_deg=-20.0)
    view = render(world, left, stereo)
    white = float(np.percentile(view.intensity[view.hit], 99.5))
    save("left-camera.png", caption(camera_image(view, white), f"left camera, tilt -20 deg: {summary}"))
    moved = Sun(azimuth_deg=sun.azimuth_deg + 30.0, elevation_deg=max(10.0, sun.elevation_deg - 15.0))
    save("left-camera-sun-moved.png",
         caption(camera_image(render(world, left, stereo, sun=moved), white),
                 f"same view, sun az {moved.azimuth_deg:g} el {moved.elevation_deg:g}"))
    tof_view = render(world, rover.sensor_to_world("tof", pan_deg=0.0, tilt_deg=-25.0), tof)
    # Active illumination from the camera: albedo * cos(incidence) / range^2, as a ToF amplitude.
    amplitude = tof_view.albedo * tof_view.incidence_cos / np.maximum(tof_view.range, 0.3) ** 2
    tof_pair = np.hstack([cv2.cvtColor(_to_grey(amplitude), cv2.COLOR_GRAY2BGR), range_image(tof_view, 8.0)])
    save("tof-view.png", caption(cv2.resize(tof_pair, None, fx=4, fy=4, interpolation=cv2.INTER_NEAREST),
                                 "SR4000 geometry (176x144, k1 -0.826): active-light amplitude | range 0-8 m"))
    return written


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out_dir", nargs="?", default="/tmp/rvs-sim-pictures")
    parser.add_argument("--seed", type=int, default=WorldConfig().seed)
    parser.add_argument("--cover", type=float, default=WorldConfig().rocks.cover)
    parser.add_argument("--size", type=float, default=WorldConfig().size_m[0])
    args = parser.parse_args(argv)
    config = WorldConfig(seed=args.seed, size_m=(args.size, args.size), rocks={"cover": args.cover})
    started = time.perf_counter()
    world = World.build(config)
    print(f"built in {time.perf_counter() - started:.1f} s")
    for path in write_pictures(Path(args.out_dir), world):
        print(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
