"""SR4000 emulator: the simulated world seen through a SwissRanger's eyes.

`Sr4000Emulator` implements the `Sr4000` interface. Each acquire() renders the world from the
camera's true pose (read at mid-exposure from a callable) and turns the per-pixel range, albedo and
incidence into what an SR4000 reports, step by step (`simulate_frame`):

1. return signal  amplitude = gain * t_int * albedo * cos(incidence) / r^2, with the LED field
                  falling off as cos^n of the off-axis angle;
2. mixed pixels   where a pixel's footprint straddles a depth edge it sums the phasors of both
                  surfaces: flying pixels between foreground and background, with less amplitude;
3. saturation     where the light collected exceeds the pixel's well; saturated pixels read a
                  random phase, amplitude AMPLITUDE_SATURATED and confidence 0;
4. noise          range sigma grows as amplitude falls (shot noise: sqrt(light + background) / A),
                  and scales with the non-ambiguity range;
5. wrap           the phase measures distance modulo the non-ambiguity range (5 m at 30 MHz);
6. filters        the AM_* mode filters (5x5 adaptive neighbourhood filter, medians);
7. confidence     from the expected noise (so from amplitude) and low on flying pixels;
8. encoding       uint16 distance over the non-ambiguity range, the amplitude threshold forcing
                  distance to 0, AM_CONV_GRAY, and x, y, z along the calibrated rays.

After each frame auto exposure moves the integration time toward the desired histogram position
(gain < 1, so it takes a few frames: the first frames after a scene change are badly exposed).
Acquisition takes the SR4000's frame time in simulated seconds on the shared SimClock.
Random draws come from numpy streams seeded by (seed, frame number): the same seed, poses and
settings give the same frames.

Constants marked "modelled" are plausible values, not MESA's published ones; they sit in
`Sr4000Model` so a calibration against a real camera changes configuration, not code.
Not modelled: multipath / inter-reflection, wiggling and amplitude-dependent bias, sunlight.
"""
from __future__ import annotations

import math
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from drivers.sim.clock import SimClock
from drivers.sim.faults import FaultSwitch
from drivers.sim.render import RenderedView, render
from drivers.sim.world import World
from drivers.sr4000 import (
    AMPLITUDE_SATURATED,
    AUTO_EXPOSURE_OFF,
    CODE_FULL_SCALE,
    CONFIDENCE_FULL,
    AcquireMode,
    ModulationFrequency,
    Sr4000,
    Sr4000Error,
    Sr4000NotAnswering,
    Sr4000NotFound,
    Sr4000Settings,
    Sr4000Timeout,
    TofFrame,
    integration_register,
    integration_time_ms,
)
from toolbox.camera import Intrinsics

# Published calibrations (see the SR4000 reference): MRPT's, and the ROS driver's fallback.
MRPT_INTRINSICS = Intrinsics(width=176, height=144, fx=262.92, fy=262.92, cx=88.0, cy=69.0,
                                k1=-0.826, k2=0.656)
ROS_FALLBACK_INTRINSICS = Intrinsics(width=176, height=144, fx=149.0, fy=149.0, cx=88.0, cy=72.0)
EMULATED_SERIAL = 0x4000E300
EMULATED_VERSION = "emulated SR4000 (RVS simulated world), libMesaSR 1.0.14 API"

MISS_RANGE_M = 1000.0            # rays that hit nothing count as a very far, black surface
_EDGE_STREAM = 0x5EED_ED6E       # seeds the static sub-pixel positions of depth edges
_AUTO_EXPOSURE_MAX_STEP = 2.0    # at most double or halve the integration time per frame


class Sr4000Model(BaseModel):
    """Physical constants of the emulated camera (counts are 16-bit amplitude units)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    # modelled: amplitude per ms of integration for albedo 1, normal incidence, 1 m, on axis. With the
    # suggested auto exposure a Mars-yard view from a 1.5 m mast settles near 6..10 ms.
    amplitude_gain: float = Field(37_000.0, gt=0)
    illumination_falloff: float = Field(2.0, ge=0)        # LED field ~ cos(off-axis)^n (modelled)
    background_counts: float = Field(2_000.0, ge=0)       # dark + ambient shot-noise floor (modelled)
    saturation_counts: float = Field(40_000.0, gt=0)      # light that fills the pixel well (modelled)
    # Range noise (1 sigma) at the reference amplitude, 30 MHz: the datasheet's few-mm repeatability
    # of a bright target at 2 m.
    reference_amplitude: float = Field(18_000.0, gt=0)
    range_noise_at_reference_m: float = Field(0.004, gt=0)
    amplitude_noise_factor: float = Field(1.0, ge=0)      # amplitude sigma = f * sqrt(light + bg)
    # Depth-edge detection: a pair of neighbours is an edge where its range step departs from the
    # steps beside it by more than threshold_m + per_m * range.
    edge_threshold_m: float = Field(0.03, gt=0)
    edge_threshold_per_m: float = Field(0.01, ge=0)
    # Confidence = full * 1/(1 + (sigma / (fraction * range))^2) * 1/(1 + (flying / edge_m)^2).
    confidence_sigma_fraction: float = Field(0.003, gt=0)  # 1.5 cm of noise at 30 MHz halves it
    edge_confidence_m: float = Field(0.03, gt=0)          # a 3 cm flying-pixel shift halves it
    anf_spread: float = Field(3.0, gt=0)                  # ANF averages neighbours within this many sigma
    gray_reference_m: float = Field(2.0, gt=0)            # AM_CONV_GRAY: amplitude * (d / this)^2
    # Frame time = 4 phase samples x (integration + readout); 4.3 ms readout gives the datasheet's
    # 54 fps at the shortest integration time.
    readout_ms: float = Field(4.3, ge=0)
    auto_exposure_gain: float = Field(0.5, gt=0, le=1)    # fraction of the log error corrected per frame
    auto_exposure_deadband: float = Field(0.08, ge=0)     # relative error left alone (no hunting)


class SceneSample(Protocol):
    """What the emulator needs from a render (RenderedView has it): per-pixel images (rows, cols)."""

    range: np.ndarray          # metres along the ray; inf where nothing was hit
    albedo: np.ndarray
    incidence_cos: np.ndarray


@dataclass(frozen=True)
class Exposure:
    """The camera settings one frame is taken with."""

    integration_time: int
    modulation_frequency: ModulationFrequency
    mode: AcquireMode
    amplitude_threshold: int = 0

    @property
    def non_ambiguity_range_m(self) -> float:
        return self.modulation_frequency.non_ambiguity_range_m


@dataclass(frozen=True, eq=False)
class SimulatedImages:
    """The camera's images of one frame, and the model's intermediate truth for tests and reports.

    distance, amplitude, confidence, x, y, z: as in TofFrame.
    raw_amplitude  float32 signal amplitude before AM_CONV_GRAY (what auto exposure looks at)
    saturated      bool
    sigma_m        float32 expected range noise per pixel before the filters
    mixed_range_m  float64 noise-free range the pixel measures (mixed at edges), wrapped
    flying_m       float64 how far edge mixing moved the pixel from its own surface (0: not mixed)
    """

    distance: np.ndarray
    amplitude: np.ndarray
    confidence: np.ndarray | None
    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    raw_amplitude: np.ndarray
    saturated: np.ndarray
    sigma_m: np.ndarray
    mixed_range_m: np.ndarray
    flying_m: np.ndarray


# --------------------------------------------------------------------------------------------
# The sensor model, step by step
# --------------------------------------------------------------------------------------------

def simulate_frame(scene: SceneSample, directions: np.ndarray, exposure: Exposure, model: Sr4000Model,
                   rng: np.random.Generator, edge_positions: np.ndarray) -> SimulatedImages:
    """One SR4000 frame of a rendered scene.

    directions: unit ray directions (rows, cols, 3) of the camera's calibration; edge_positions:
    (2, rows, cols) uniform [0, 1) numbers that place depth edges between pixel centres (static per
    camera, so flying pixels stay put in a still scene, as they do on the real camera).
    """
    nar = exposure.non_ambiguity_range_m
    true_range = np.where(np.isfinite(scene.range), scene.range, MISS_RANGE_M).astype(np.float64)
    # 1. what each pixel's own surface sends back
    signal = return_signal(true_range, scene.albedo, scene.incidence_cos, directions[..., 2],
                           integration_time_ms(exposure.integration_time), model)
    # 2. mixed returns at depth edges (flying pixels); 3. a full well saturates
    amplitude, light, mixed_range = mix_at_depth_edges(true_range, signal, edge_positions, nar, model)
    saturated = light > model.saturation_counts
    # 4. noise, 5. the phase wraps at the non-ambiguity range
    sigma = range_sigma(amplitude, light, nar, model)
    measured = measure_range(mixed_range, sigma, saturated, nar, rng)
    raw_amplitude = measure_amplitude(amplitude, light, saturated, model, rng)
    # 6. the camera's and the library's filters
    measured = filter_distance(measured, raw_amplitude, sigma, exposure.mode, model)
    # 7. confidence
    flying = np.abs(wrapped_difference(mixed_range, true_range, nar))
    confidence = (confidence_map(sigma, flying, saturated, nar, model)
                  if exposure.mode & AcquireMode.CONF_MAP else None)
    # 8. the images as the camera sends them
    distance = encode_distance(measured, nar)
    distance[raw_amplitude < exposure.amplitude_threshold] = 0
    x, y, z = camera_points(distance, directions, nar)
    amplitude_image = output_amplitude(raw_amplitude, measured, saturated, exposure.mode, model)
    return SimulatedImages(
        distance=distance, amplitude=amplitude_image, confidence=confidence, x=x, y=y, z=z,
        raw_amplitude=raw_amplitude.astype(np.float32), saturated=saturated, sigma_m=sigma.astype(np.float32),
        mixed_range_m=mixed_range, flying_m=flying)


def return_signal(true_range: np.ndarray, albedo: np.ndarray, incidence_cos: np.ndarray,
                  off_axis_cos: np.ndarray, integration_ms: float, model: Sr4000Model) -> np.ndarray:
    """Amplitude (counts) of the pixel's own surface: Lambertian, inverse-square, linear in time."""
    lamp = np.power(off_axis_cos, model.illumination_falloff, dtype=np.float64)
    return model.amplitude_gain * integration_ms * lamp * albedo * incidence_cos / np.square(true_range)


def mix_at_depth_edges(true_range: np.ndarray, signal: np.ndarray, edge_positions: np.ndarray,
                       nar: float, model: Sr4000Model) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sum the phasors of both surfaces where a pixel's footprint straddles a depth edge.

    For each pair of neighbours across an edge, the edge lies at `edge_positions` (0..1) between
    their centres. Footprints tile the image, so the edge falls in one of the two footprints: the
    one whose centre is nearer takes in the other surface over the fraction of its footprint past
    the edge (0..1/2). The phase of the sum lies between the two ranges: a flying pixel.
    Returns (amplitude, light, range): |sum of phasors|, the summed signal (what fills the well),
    and the measured range of the sum, in [0, nar).
    """
    shares = edge_shares(true_range, edge_positions, model)
    amplitude, light = signal.copy(), signal.copy()
    mixed_range = np.mod(true_range, nar)
    taken = sum(share for share, _ in shares)
    rows, cols = np.nonzero(taken)
    if len(rows) == 0:
        return amplitude, light, mixed_range
    # Only the few mixed pixels need phasors.
    scale = np.maximum(taken[rows, cols], 1.0)      # a corner pixel cannot give away more than all
    wavenumber = 2 * np.pi / nar
    own = 1.0 - taken[rows, cols] / scale
    total = own * signal[rows, cols] * np.exp(1j * wavenumber * true_range[rows, cols])
    summed_light = own * signal[rows, cols]
    for share, (dr, dc) in shares:
        weight = share[rows, cols] / scale
        # Clipped: a neighbour off the image gives nothing (its share is 0) but must index somewhere.
        giver = (np.clip(rows + dr, 0, signal.shape[0] - 1), np.clip(cols + dc, 0, signal.shape[1] - 1))
        total += weight * signal[giver] * np.exp(1j * wavenumber * true_range[giver])
        summed_light += weight * signal[giver]
    amplitude[rows, cols] = np.abs(total)
    light[rows, cols] = summed_light
    mixed_range[rows, cols] = np.mod(np.angle(total), 2 * np.pi) / wavenumber
    return amplitude, light, mixed_range


def edge_shares(true_range: np.ndarray, edge_positions: np.ndarray,
                model: Sr4000Model) -> list[tuple[np.ndarray, tuple[int, int]]]:
    """For each neighbour direction (row, col offset), the footprint fraction every pixel takes
    from that neighbour's surface (0 almost everywhere)."""
    shares = []
    for axis, step in ((1, (0, 1)), (0, (1, 0))):
        first, second = _pair_slices(axis)
        position = edge_positions[axis][first]
        edge = depth_edges(true_range, axis, model)
        from_second = np.zeros(true_range.shape)
        from_first = np.zeros(true_range.shape)
        from_second[first] = np.where(edge & (position < 0.5), 0.5 - position, 0.0)
        from_first[second] = np.where(edge & (position > 0.5), position - 0.5, 0.0)
        shares.append((from_second, step))
        shares.append((from_first, (-step[0], -step[1])))
    return shares


def _pair_slices(axis: int) -> tuple[tuple[slice, slice], tuple[slice, slice]]:
    """Index of the first and the second pixel of every neighbour pair along `axis`."""
    if axis == 1:
        return (slice(None), slice(None, -1)), (slice(None), slice(1, None))
    return (slice(None, -1), slice(None)), (slice(1, None), slice(None))


def depth_edges(true_range: np.ndarray, axis: int, model: Sr4000Model) -> np.ndarray:
    """Neighbour pairs along `axis` whose range step is a jump, not the slope of one surface: it
    departs from both steps beside it (the smaller departure counts) by more than the threshold."""
    step = np.diff(true_range, axis=axis)
    padded = np.pad(step, [(1, 1) if a == axis else (0, 0) for a in range(step.ndim)],
                    constant_values=np.nan)
    index = [slice(None)] * step.ndim
    index[axis] = slice(None, -2)
    before = padded[tuple(index)]
    index[axis] = slice(2, None)
    after = padded[tuple(index)]
    with np.errstate(invalid="ignore"):
        departure = np.fmin(np.abs(step - before), np.abs(step - after))
        first, second = _pair_slices(axis)
        nearer = np.minimum(true_range[first], true_range[second])
        return departure > model.edge_threshold_m + model.edge_threshold_per_m * nearer


def range_sigma(amplitude: np.ndarray, light: np.ndarray, nar: float, model: Sr4000Model) -> np.ndarray:
    """1-sigma range noise: sqrt(light + background) / amplitude (shot noise on the phase), scaled to
    the reference, times nar / 5 m (the same phase noise spans more metres at lower frequency); at
    most the spread of a uniformly random phase."""
    reference = model.reference_amplitude
    relative = (reference / np.maximum(amplitude, 1e-6)) * np.sqrt(
        (light + model.background_counts) / (reference + model.background_counts))
    return np.minimum(model.range_noise_at_reference_m * (nar / 5.0) * relative, nar / math.sqrt(12.0))


def measure_range(mixed_range: np.ndarray, sigma: np.ndarray, saturated: np.ndarray, nar: float,
                  rng: np.random.Generator) -> np.ndarray:
    """Noisy range, wrapped into [0, nar); a saturated pixel's clipped samples give a random phase."""
    noisy = mixed_range + sigma * rng.standard_normal(mixed_range.shape)
    noisy[saturated] = rng.uniform(0.0, nar, int(np.count_nonzero(saturated)))
    return np.mod(noisy, nar)


def measure_amplitude(amplitude: np.ndarray, light: np.ndarray, saturated: np.ndarray,
                      model: Sr4000Model, rng: np.random.Generator) -> np.ndarray:
    noise = model.amplitude_noise_factor * np.sqrt(light + model.background_counts)
    measured = np.abs(amplitude + noise * rng.standard_normal(amplitude.shape))
    measured[saturated] = model.saturation_counts
    return measured


def filter_distance(distance: np.ndarray, amplitude: np.ndarray, sigma: np.ndarray, mode: AcquireMode,
                    model: Sr4000Model) -> np.ndarray:
    """The AM_* filters: the camera's 5x5 ANF first, then the library's software filters."""
    distance = distance.astype(np.float32)
    if mode & AcquireMode.DENOISE_ANF:
        distance = adaptive_neighbourhood_filter(distance, amplitude, sigma, 5, model.anf_spread)
    if mode & AcquireMode.SW_ANF:
        distance = adaptive_neighbourhood_filter(distance, amplitude, sigma, 7, model.anf_spread)
    if mode & AcquireMode.MEDIAN:
        distance = cv2.medianBlur(distance, 3)
    if mode & AcquireMode.MEDIANCROSS:
        distance = cross_median(distance)
    return distance


def adaptive_neighbourhood_filter(distance: np.ndarray, amplitude: np.ndarray, sigma: np.ndarray,
                                  size: int, spread: float) -> np.ndarray:
    """Edge-preserving average, a stand-in for MESA's undocumented ANF with its published effect
    (less noise, edges kept). Each neighbour is carried back to the pixel along the local slope of
    the surface and counts if it then lies within `spread` times the pixel's noise of the pixel's
    robust (3x3 median) value, weighted by its amplitude (its reliability). Following the slope
    keeps sloping ground from biasing or excluding neighbours; the slope is the smaller one-sided
    difference (minmod), so it is taken from the smooth side of an edge."""
    half = size // 2
    reference = cv2.medianBlur(distance, 3)
    slope_rows, slope_cols = _minmod_slope(reference, 0), _minmod_slope(reference, 1)
    padded_distance = np.pad(distance, half, mode="edge")
    padded_amplitude = np.pad(amplitude.astype(np.float32), half, mode="edge")
    inverse_spread = (1.0 / (spread * np.maximum(sigma, 1e-6))).astype(np.float32)
    weighted = np.zeros_like(distance)
    total = np.zeros_like(distance)
    rows, cols = distance.shape
    for dr in range(-half, half + 1):
        for dc in range(-half, half + 1):
            window = (slice(half + dr, half + dr + rows), slice(half + dc, half + dc + cols))
            carried = padded_distance[window] - (dr * slope_rows + dc * slope_cols)
            closeness = np.square((carried - reference) * inverse_spread)
            # 1 - x^2/2 clipped at 0: a cheap bell (Epanechnikov) instead of exp.
            weight = padded_amplitude[window] * np.maximum(1.0 - 0.5 * closeness, 0.0)
            weighted += weight * carried
            total += weight
    return np.where(total > 0, weighted / np.maximum(total, 1e-30), distance)


def _minmod_slope(image: np.ndarray, axis: int) -> np.ndarray:
    """Per-pixel slope along `axis`: the smaller of the two one-sided differences, 0 where they
    disagree in sign (a peak, a pit or noise)."""
    step = np.diff(image, axis=axis)
    pad = [(1, 1) if a == axis else (0, 0) for a in range(image.ndim)]
    padded = np.pad(step, pad, mode="constant")
    index = [slice(None)] * image.ndim
    index[axis] = slice(None, -1)
    backward = padded[tuple(index)]
    index[axis] = slice(1, None)
    forward = padded[tuple(index)]
    smaller = np.sign(forward) * np.minimum(np.abs(backward), np.abs(forward))
    return np.where(backward * forward > 0, smaller, 0.0).astype(image.dtype)


def cross_median(distance: np.ndarray) -> np.ndarray:
    """Median of each pixel and its four neighbours (AM_MEDIANCROSS)."""
    padded = np.pad(distance, 1, mode="edge")
    stack = np.stack([padded[1:-1, 1:-1], padded[:-2, 1:-1], padded[2:, 1:-1],
                      padded[1:-1, :-2], padded[1:-1, 2:]])
    return np.median(stack, axis=0).astype(distance.dtype)


def wrapped_difference(a: np.ndarray, b: np.ndarray, nar: float) -> np.ndarray:
    """a - b on the circle of circumference nar, in [-nar/2, nar/2)."""
    return np.mod(a - b + nar / 2, nar) - nar / 2


def confidence_map(sigma: np.ndarray, flying: np.ndarray, saturated: np.ndarray, nar: float,
                   model: Sr4000Model) -> np.ndarray:
    """uint16 confidence: falls with the expected noise (so with amplitude) and on flying pixels;
    0 where saturated."""
    from_noise = 1.0 / (1.0 + np.square(sigma / (model.confidence_sigma_fraction * nar)))
    from_edges = 1.0 / (1.0 + np.square(flying / model.edge_confidence_m))
    confidence = np.rint(CONFIDENCE_FULL * from_noise * from_edges).astype(np.uint16)
    confidence[saturated] = 0
    return confidence


def encode_distance(measured: np.ndarray, nar: float) -> np.ndarray:
    """uint16 code over [0, nar]; 1 at least, since 0 means "no measurement"."""
    return np.clip(np.rint(measured * (CODE_FULL_SCALE / nar)), 1, CODE_FULL_SCALE).astype(np.uint16)


def output_amplitude(raw: np.ndarray, measured: np.ndarray, saturated: np.ndarray, mode: AcquireMode,
                     model: Sr4000Model) -> np.ndarray:
    amplitude = raw * np.square(measured / model.gray_reference_m) if mode & AcquireMode.CONV_GRAY else raw
    out = np.clip(np.rint(amplitude), 0, AMPLITUDE_SATURATED - 1).astype(np.uint16)
    out[saturated] = AMPLITUDE_SATURATED
    return out


def camera_points(distance: np.ndarray, directions: np.ndarray, nar: float):
    """x, y, z (float32, OpenCV camera frame) of the distance codes along the calibrated rays."""
    metres = distance.astype(np.float32) * np.float32(nar / CODE_FULL_SCALE)
    points = metres[..., None] * directions
    return points[..., 0], points[..., 1], points[..., 2]


def auto_exposure_step(raw_amplitude: np.ndarray, saturated: np.ndarray, register: int,
                       settings: tuple[int, int, int, int], model: Sr4000Model) -> int:
    """Next integration-time register, as SR_SetAutoExposure describes it: in the amplitude
    histogram reduced to 8 bits, find the position with `percent_over_pos` % of pixels above it,
    and move the integration time (slowly) so that position reaches `desired_pos`."""
    lowest, highest, percent_over_pos, desired_pos = settings
    histogram_values = np.where(saturated, 255.0, np.minimum(raw_amplitude / 256.0, 255.0))
    position = float(np.percentile(histogram_values, 100 - percent_over_pos))
    ratio = desired_pos / position if position > 0 else _AUTO_EXPOSURE_MAX_STEP
    if not _outside_deadband(ratio, register, model):
        return int(min(max(register, lowest), highest))
    factor = ratio ** model.auto_exposure_gain
    factor = min(max(factor, 1 / _AUTO_EXPOSURE_MAX_STEP), _AUTO_EXPOSURE_MAX_STEP)
    proposed = integration_register(integration_time_ms(register) * factor)
    if proposed == register:   # at least one step while outside the deadband
        proposed += 1 if ratio > 1 else -1
    return int(min(max(proposed, lowest), highest))


def _outside_deadband(ratio: float, register: int, model: Sr4000Model) -> bool:
    """Worth a change: the error exceeds the deadband and half of the next register step (at short
    times one 0.1 ms step is a large relative change; without this the loop hunts between two)."""
    now = integration_time_ms(register)
    neighbour = integration_time_ms(register + 1 if ratio > 1 else max(register - 1, 0))
    half_step = 0.5 * abs(math.log(neighbour / now)) if neighbour != now else 0.0
    return abs(math.log(max(ratio, 1e-9))) > max(math.log1p(model.auto_exposure_deadband), half_step)


def frame_time_s(integration_time: int, model: Sr4000Model) -> float:
    """Four phase samples, each an integration plus a readout."""
    return 4 * (integration_time_ms(integration_time) + model.readout_ms) / 1000.0


# --------------------------------------------------------------------------------------------
# The emulated device
# --------------------------------------------------------------------------------------------

@dataclass
class _DeviceRegisters:
    """What the emulated camera holds, as written through the libMesaSR-like primitives."""

    integration_time: int = 0
    amplitude_threshold: int = 0
    modulation_frequency: ModulationFrequency = ModulationFrequency.MF_30MHz
    auto_exposure: tuple[int, int, int, int] = (AUTO_EXPOSURE_OFF, 0, 0, 0)
    mode: AcquireMode = AcquireMode.COR_FIX_PTRN
    timeout_ms: int = 1000


class Sr4000Emulator(Sr4000):
    """An SR4000 looking at the simulated world.

    world        the World to render
    camera_pose  callable returning the true camera-to-world 4x4 (OpenCV camera frame) now;
                 called at mid-exposure of every frame
    clock        the SimClock frame times are spent on
    intrinsics   the calibration rays are cast and x, y, z computed with (176 x 144; default MRPT's)
    seed         noise and edge-placement streams; same seed + poses + settings = same frames
    model        physical constants (Sr4000Model)

    fault        its injected fault (drivers/sim/faults.py), one request per frame: once tripped
                 acquire() gives no frame (SR_Acquire fails after timeout_ms) and open() finds no camera

    With AM_HW_TRIGGER set, acquire() waits for hardware_trigger() (at most timeout_ms, simulated).
    After each acquire(), `last_view` (the RenderedView), `last_pose` and `last_images` (with the
    model's intermediate truth) hold what the frame was made from.
    """

    def __init__(self, world: World, camera_pose: Callable[[], np.ndarray], clock: SimClock, *,
                 intrinsics: Intrinsics = MRPT_INTRINSICS, seed: int = 0,
                 settings: Sr4000Settings | None = None, model: Sr4000Model | None = None,
                 name: str = "sr4000-emulator", serial: int = EMULATED_SERIAL, fault: FaultSwitch | None = None):
        super().__init__(name, settings)
        self._fault = fault or FaultSwitch("tof")   # each frame asked for is one request
        self.world, self.clock, self.intrinsics, self.seed = world, clock, intrinsics, seed
        self.model = model or Sr4000Model()
        self.rows, self.cols = intrinsics.height, intrinsics.width
        self._camera_pose = camera_pose
        self._serial = serial
        self._directions = intrinsics.ray_directions().astype(np.float32)
        edge_stream = np.random.default_rng([seed, _EDGE_STREAM])
        self._edge_positions = edge_stream.random((2, self.rows, self.cols))
        self._registers = _DeviceRegisters()
        self._trigger = threading.Event()
        self._sequence = 0
        self.last_view: RenderedView | None = None
        self.last_pose: np.ndarray | None = None
        self.last_images: SimulatedImages | None = None

    def hardware_trigger(self) -> None:
        """A pulse on the trigger input (what the trigger box sends)."""
        self._trigger.set()

    # -- lifecycle -----------------------------------------------------------------------------
    def _open(self) -> None:
        if self._fault.broken:   # a hung camera does not enumerate, as SR_OpenUSB then finds none
            raise Sr4000NotFound("no SR4000 answered (emulated camera with an injected fault)", device=self.name,
                                 call="SR_OpenUSB", returned=0)
        self.serial, self.version = self._serial, EMULATED_VERSION
        self._trigger.clear()

    def _close(self) -> None:
        pass

    def set_frame_number(self, number: int) -> None:
        """Make the next frame draw the noise of frame `number`, so an acquisition that is resumed
        after a break or a restart repeats the frames an uninterrupted one would have taken."""
        self._sequence = int(number)

    # -- acquisition ---------------------------------------------------------------------------
    def _acquire(self) -> TofFrame:
        registers = self._registers
        exposure = Exposure(registers.integration_time, registers.modulation_frequency, registers.mode,
                            registers.amplitude_threshold)
        self._wait_for_trigger(exposure.mode, registers.timeout_ms)
        if not self._fault.answers():
            self._no_frame(registers.timeout_ms)
        started = self.clock.now()
        frame_time = frame_time_s(exposure.integration_time, self.model)
        self.clock.sleep(frame_time / 2)
        timestamp = self.clock.now()
        pose = self._true_pose()
        view = render(self.world, pose, self.intrinsics, shadows=False)
        rng = np.random.default_rng([self.seed, self._sequence])
        images = simulate_frame(view, self._directions, exposure, self.model, rng, self._edge_positions)
        if registers.auto_exposure[0] != AUTO_EXPOSURE_OFF:
            registers.integration_time = auto_exposure_step(images.raw_amplitude, images.saturated,
                                                            registers.integration_time,
                                                            registers.auto_exposure, self.model)
        self.clock.sleep(started + frame_time - self.clock.now())
        self._sequence += 1
        self.last_view, self.last_pose, self.last_images = view, pose, images
        return TofFrame(distance=images.distance, amplitude=images.amplitude, confidence=images.confidence,
                        x=images.x, y=images.y, z=images.z, timestamp=timestamp,
                        modulation_frequency=exposure.modulation_frequency,
                        integration_time=exposure.integration_time, sequence=self._sequence)

    def _no_frame(self, timeout_ms: int) -> None:
        """A camera that stopped answering: SR_Acquire waits out its timeout and returns -1, which
        the real backend reports the same way (MesaSr4000._acquire)."""
        self.clock.sleep(timeout_ms / 1000.0)
        raise Sr4000NotAnswering(f"acquisition failed: stopped answering (no frame within {timeout_ms} ms)",
                                 device=self.name, call="SR_Acquire", returned=-1)

    def _true_pose(self) -> np.ndarray:
        pose = np.asarray(self._camera_pose(), dtype=np.float64)
        if pose.shape != (4, 4) or not np.all(np.isfinite(pose)):
            raise Sr4000Error(f"camera_pose() gave {pose.shape} {pose!r}, not a finite 4x4 transform",
                              device=self.name)
        return pose

    def _wait_for_trigger(self, mode: AcquireMode, timeout_ms: int) -> None:
        if not mode & AcquireMode.HW_TRIGGER:
            return
        if not self.clock.wait(self._trigger, timeout_ms / 1000.0):
            raise Sr4000Timeout(f"no hardware trigger within {timeout_ms} ms", device=self.name,
                                call="SR_Acquire", returned=-1)
        self._trigger.clear()

    # -- registers -----------------------------------------------------------------------------
    def _write_integration_time(self, register: int) -> None:
        self._registers.integration_time = register

    def _write_amplitude_threshold(self, threshold: int) -> None:
        self._registers.amplitude_threshold = threshold

    def _write_modulation_frequency(self, frequency: ModulationFrequency) -> None:
        self._registers.modulation_frequency = frequency

    def _write_auto_exposure(self, min_time: int, max_time: int, percent_over_pos: int,
                             desired_pos: int) -> None:
        self._registers.auto_exposure = (min_time, max_time, percent_over_pos, desired_pos)

    def _write_mode(self, flags: AcquireMode) -> None:
        self._registers.mode = AcquireMode(flags)

    def _write_timeout(self, milliseconds: int) -> None:
        self._registers.timeout_ms = milliseconds

    def _read_integration_time(self) -> int:
        return self._registers.integration_time

    def _read_mode(self) -> int:
        return int(self._registers.mode)
