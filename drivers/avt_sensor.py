"""Camera sensor model: rendered radiance to an exposed 8-bit image, as a PIKE F-210B's CCD makes it.

This file holds
- the sensor's constants (electrons per radiance and microsecond, full well, read noise, DN per
  electron) and the regolith's colour (`DUST_TINT`);
- `expose_image`: render the scene a camera saw at a pulse (`_SceneAtPulse`) and expose it;
- `colour_radiance` (rgb8: dust tint, white balance), `auto_exposure_us` (the exposure that brings
  the mean grey value to the target) and `sensor_image` (shot and read noise, full well, gain,
  8-bit quantisation).

Used by the emulated camera (`drivers.avt_emulator`) and the simulated cameras of drivers/sim.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from drivers.avt import EXPOSURE_MAX_US, EXPOSURE_MIN_US, CameraSettings
from drivers.sim.render import render
from drivers.sim.world import World
from toolbox.camera import Intrinsics

# Sensor model, after a Kodak KAI-2093-class interline CCD (the PIKE F-210B's): electrons per unit
# of rendered radiance per microsecond of exposure (a mid-grey scene gives ~92 DN at 5 ms, 0 dB),
# full well, read noise, and 8-bit conversion with the full well at 255 DN at 0 dB.
ELECTRONS_PER_RADIANCE_US = 8.0
FULL_WELL_E = 20_000.0
READ_NOISE_E = 15.0
DN_PER_ELECTRON = 255.0 / FULL_WELL_E

# Colour of the regolith (rgb reflectance over grey reflectance): dust and bright soil are reddish,
# dark rock is nearly neutral.
DUST_TINT = np.array([1.25, 1.0, 0.72], dtype=np.float32)
DUST_TINT_FULL_ALBEDO = 0.35


@dataclass(frozen=True)
class _SceneAtPulse:
    """What a camera sees at the instant of a pulse: its pose, the sun, its intrinsics, and the world
    as it stood then (a snapshot: a walker moved while the frame renders is not in it, so both
    cameras of a pair, rendered one after the other, see it at the same place)."""

    camera_to_world: np.ndarray
    sun: object
    camera: Intrinsics
    world: World


def expose_image(scene: _SceneAtPulse, settings: CameraSettings,
                 rng: np.random.Generator) -> tuple[np.ndarray, float]:
    """Render the scene and turn radiance into an 8-bit image; return it and the exposure used."""
    view = render(scene.world, scene.camera_to_world, scene.camera, sun=scene.sun)
    radiance = view.intensity
    exposure_us = auto_exposure_us(radiance, settings) if settings.auto_exposure else settings.exposure_us
    if settings.pixel_format == "rgb8":
        radiance = colour_radiance(radiance, view.albedo, settings)
    return sensor_image(radiance, exposure_us, settings.gain_db, rng), exposure_us


def colour_radiance(radiance: np.ndarray, albedo: np.ndarray, settings: CameraSettings) -> np.ndarray:
    """(h, w, 3) RGB radiance: reddish where the surface is bright dust, grey where it is dark rock,
    then the camera's white balance ratios on red and blue."""
    dustiness = np.clip(albedo / np.float32(DUST_TINT_FULL_ALBEDO), 0.0, 1.0)[..., None]
    tint = 1.0 + (DUST_TINT - 1.0) * dustiness
    balance = np.array([settings.white_balance_red, 1.0, settings.white_balance_blue], dtype=np.float32)
    return (radiance[..., None] * tint * balance).astype(np.float32)


def auto_exposure_us(radiance: np.ndarray, settings: CameraSettings) -> float:
    """The exposure that brings the mean grey value to the target (noise-free, before clipping),
    within the allowed exposure range. The emulator settles in one frame; a real camera takes a few."""
    mean_radiance = float(np.mean(radiance))
    if mean_radiance <= 0:
        return EXPOSURE_MAX_US
    gain = 10.0 ** (settings.gain_db / 20.0)
    exposure = settings.target_grey_level / (mean_radiance * ELECTRONS_PER_RADIANCE_US * DN_PER_ELECTRON * gain)
    return float(np.clip(exposure, EXPOSURE_MIN_US, EXPOSURE_MAX_US))


def sensor_image(radiance: np.ndarray, exposure_us: float, gain_db: float, rng: np.random.Generator) -> np.ndarray:
    """Photo-electrons with shot noise (Gaussian approximation of Poisson) and read noise, clipped
    at the full well, amplified by the gain, quantised to 8 bits and clipped at 255."""
    electrons = radiance.astype(np.float32) * np.float32(exposure_us * ELECTRONS_PER_RADIANCE_US)
    noise = rng.standard_normal(electrons.shape, dtype=np.float32)
    electrons += np.sqrt(electrons) * noise
    electrons += np.float32(READ_NOISE_E) * rng.standard_normal(electrons.shape, dtype=np.float32)
    np.clip(electrons, 0.0, FULL_WELL_E, out=electrons)
    digital = electrons * np.float32(DN_PER_ELECTRON * 10.0 ** (gain_db / 20.0))
    return np.clip(np.rint(digital), 0, 255).astype(np.uint8)
