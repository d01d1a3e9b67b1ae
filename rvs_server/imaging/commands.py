"""Image acquisition commands: grab-tof (SR4000) and grab-stereo (the camera pair on the trigger).

Each grab is a job that writes a product: the raw values as TIFF, a false-colour PNG with a legend,
what the device reported, and, when the devices are simulated, the simulator's truth of that
instant in `truth/` (rover pose, PTU angles, sensor poses, and the noise-free range image).
"""
from __future__ import annotations

import time
from typing import Any, Literal

import numpy as np
from pydantic import Field

from rvs_server.config import CommandConfig, SafeName, Settings
from rvs_server.dispatch import Module
from rvs_server.jobs import JobContext
from rvs_server.products.rasters import write_png, write_tiff
from toolbox.colour import colourise, upscale, with_colour_bar, with_title


class ImagingSettings(Settings):
    settle_frames: int = Field(10, ge=0, le=100, description="frames auto exposure may take to settle")
    grab_timeout_s: float = Field(10.0, gt=0, description="wall seconds a stereo grab may take")


module = Module("imaging", settings=ImagingSettings, summary="time-of-flight and stereo acquisition")


class GrabTofConfig(CommandConfig):
    output: SafeName = Field(..., description="product name (a name, not a path)")
    image: Literal["distance", "amplitude", "confidence", "z", "xyz"] = Field(
        "distance", description="which image the TIFF and PNG hold")
    frames: int = Field(1, ge=1, le=200, description="frames averaged per pixel")
    min_confidence: int = Field(0, ge=0, le=65535, description="pixels below this confidence are dropped")


class GrabStereoConfig(CommandConfig):
    output: SafeName = Field(..., description="product name (a name, not a path)")
    camera: Literal["left", "right", "both"] = "both"


TOF_IMAGES = {
    # image: (how to read it off the averaged frame, unit for the legend, colour range)
    "distance": ("distance code 0..65535 over the non-ambiguity range", "m"),
    "amplitude": ("amplitude counts", "counts"),
    "confidence": ("confidence 0..65535", ""),
    "z": ("z along the optical axis, metres, NaN undefined", "m"),
    "xyz": ("x, y, z in the OpenCV camera frame, metres, NaN undefined", "m"),
}


@module.job("grab-tof", GrabTofConfig, devices=("tof",))
def grab_tof(ctx: JobContext, cfg: GrabTofConfig) -> dict[str, Any]:
    """Acquire (and average) SR4000 frames; TIFF of raw values, false-colour PNG with a legend."""
    camera = ctx.devices.tof.require()
    product = ctx.product(cfg)
    ctx.progress(5, "waiting for auto exposure")
    ctx.safe_point()
    started = time.perf_counter()
    result = ctx.devices.tof.grab(frames=cfg.frames, min_confidence=cfg.min_confidence,
                                  settle_frames=ctx.settings.settle_frames)
    product.timing("acquisition", time.perf_counter() - started)
    ctx.progress(70, f"{cfg.frames} frame(s) averaged; writing")
    ctx.safe_point()
    frame = result.frame
    raw, shown, low, high, label = _tof_image(frame, cfg.image)
    write_tiff(product.add(f"{cfg.image}.tif", TOF_IMAGES[cfg.image][0]), raw)
    write_tiff(product.add("valid_count.tif", "valid samples per pixel (uint16)"), result.valid_count)
    picture = with_colour_bar(upscale(colourise(shown, low, high)), low, high, label)
    write_png(product.add(f"{cfg.image}.png", f"false colour {cfg.image} with legend"),
              with_title(picture, f"grab-tof {product.name}: {cfg.image}, {cfg.frames} frame(s)"))
    defined = float(np.mean(result.defined))
    product.write_json("frame.json", {
        "timestamp_s": frame.timestamp, "frames": result.frames, "settled": result.settled,
        "settle_frames": result.settle_frames, "integration_time": frame.integration_time,
        "modulation_frequency_mhz": frame.modulation_frequency.megahertz,
        "non_ambiguity_range_m": frame.non_ambiguity_range_m, "defined_share": defined,
        "min_confidence": cfg.min_confidence, "rows": frame.shape[0], "cols": frame.shape[1],
    }, "what the camera reported for the averaged frame")
    ctx.save_truth(product)
    _save_tof_truth(ctx, product, camera)
    ctx.progress(100, "written")
    return {**ctx.finish_product(product), "settled": int(result.settled), "defined": f"{defined:.3f}"}


def _tof_image(frame: Any, image: str) -> tuple[np.ndarray, np.ndarray, float, float, str]:
    """(raw array for the TIFF, values for the picture, colour range, legend label)."""
    if image == "distance":
        return frame.distance, frame.distance_m(), 0.0, frame.non_ambiguity_range_m, "distance, m"
    if image == "amplitude":
        values = frame.amplitude.astype(np.float64)
        return frame.amplitude, values, 0.0, float(max(np.percentile(values, 99), 1.0)), "amplitude, counts"
    if image == "confidence":
        confidence = frame.confidence if frame.confidence is not None else np.zeros_like(frame.distance)
        return confidence, confidence.astype(np.float64), 0.0, 65535.0, "confidence"
    z = frame.z.astype(np.float32)
    finite = z[np.isfinite(z) & (z > 0)]
    high = float(np.percentile(finite, 99)) if finite.size else 1.0
    if image == "z":
        return z, z, 0.0, high, "z (depth), m"
    return frame.xyz().astype(np.float32), z, 0.0, high, "xyz (shown: z), m"


def _save_tof_truth(ctx: JobContext, product: Any, camera: Any) -> None:
    """The noise-free radial range of the last frame's rays, for scoring without our code."""
    view = getattr(camera, "last_view", None)
    if view is None or not ctx.devices.simulated:
        return
    write_tiff(product.add("truth/range.tif", "true radial range of each pixel's ray, metres, inf: no hit"),
               np.asarray(view.range, dtype=np.float32))
    product.write_json("truth/camera_to_world.json", np.asarray(camera.last_pose).tolist(),
                       "true camera-to-world pose of the last frame (OpenCV camera frame)")


@module.job("grab-stereo", GrabStereoConfig, devices=("cameras",))
def grab_stereo(ctx: JobContext, cfg: GrabStereoConfig) -> dict[str, Any]:
    """Grab the left, right or both cameras on one trigger pulse; PNG images and their metadata."""
    pair = ctx.devices.cameras.require()
    product = ctx.product(cfg)
    ctx.progress(10, f"triggering {cfg.camera}")
    ctx.safe_point()
    started = time.perf_counter()
    frames = pair.grab(cfg.camera, timeout_s=ctx.devices.cameras.grab_timeout_s)
    product.timing("acquisition", time.perf_counter() - started)
    ctx.progress(70, "writing")
    meta = {}
    for role, frame in frames.items():
        write_png(product.add(f"{role}.png", f"{role} camera image ({frame.pixel_format})"), frame.image)
        meta[role] = {"camera_id": frame.camera_id, "timestamp_s": frame.timestamp_s,
                      "trigger_time_s": frame.trigger_time_s, "frame_number": frame.frame_number,
                      "resolution": frame.resolution, "pixel_format": frame.pixel_format,
                      "exposure_us": frame.exposure_us, "gain_db": frame.gain_db,
                      "shape": list(frame.image.shape)}
    product.write_json("frames.json", meta, "camera ids, timestamps and settings of each image")
    ctx.save_truth(product)
    ctx.progress(100, "written")
    times = {m["timestamp_s"] for m in meta.values()}
    return {**ctx.finish_product(product), "cameras": " ".join(meta), "timestamp": f"{min(times):.6f}"}
