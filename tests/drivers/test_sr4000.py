"""Tests of the SR4000 drivers: the settings file, the ctypes backend against a fake libmesasr
compiled here from tests/drivers/fakes/fake_mesasr.c, the emulator against the simulated world's truth,
and grab() / previews over the interface."""
from __future__ import annotations

import ctypes
import shutil
import subprocess
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from drivers.errors import DeviceFault, DeviceTimeout
from drivers.sim.clock import SimClock
from drivers.sim.faults import FaultSwitch
from drivers.sim.render import render
from drivers.sim.world import World, WorldConfig
from drivers.sr4000 import (
    AMPLITUDE_SATURATED,
    CONFIDENCE_FULL,
    AcquireMode,
    ModulationFrequency,
    Sr4000,
    Sr4000LibraryMissing,
    Sr4000NotAnswering,
    Sr4000NotFound,
    Sr4000Settings,
    Sr4000SettingsError,
    Sr4000Timeout,
    TofFrame,
    false_colour,
    frequency_for_range,
    grab,
    integration_time_ms,
    preview,
    wait_for_exposure,
)
from drivers.sr4000_emulator import (
    MRPT_INTRINSICS,
    Exposure,
    Sr4000Emulator,
    Sr4000Model,
    auto_exposure_step,
    frame_time_s,
    simulate_frame,
)
from drivers.sr4000_mesasr import MesaSr4000

FAKE_SOURCE = Path(__file__).parent / "fakes" / "fake_mesasr.c"
FAST_CLOCK = 1000.0                      # frame times still pass, in microseconds of wall time
UNFILTERED = AcquireMode.COR_FIX_PTRN | AcquireMode.CONF_MAP | AcquireMode.SW_TRIGGER
HALF_CONFIDENCE = CONFIDENCE_FULL // 2


# --------------------------------------------------------------------------------------------
# Settings
# --------------------------------------------------------------------------------------------

def test_settings_round_trip_through_the_text_file(tmp_path):
    settings = Sr4000Settings.checked(integration_time=77, amplitude_threshold=1234,
                                      modulation_frequency="15MHz", auto_exposure=False, median=True,
                                      confidence_map=False, auto_exposure_desired_pos=90)
    path = settings.save(tmp_path / "tof.txt")
    text = path.read_text()
    assert "modulation_frequency = 15MHz" in text and "integer 0..255" in text
    assert Sr4000Settings.load(path) == settings


def test_missing_keys_take_defaults_and_comments_are_ignored(tmp_path):
    path = tmp_path / "tof.txt"
    path.write_text("# only two keys\nintegration_time = 0x20   # hex is fine\n\nmedian = yes\n")
    loaded = Sr4000Settings.load(path)
    assert loaded == Sr4000Settings(integration_time=32, median=True)
    assert Sr4000Settings.load_or_default(tmp_path / "absent.txt") == Sr4000Settings()


@pytest.mark.parametrize("line, key, allowed", [
    ("integration_time = 256", "integration_time", "0..255"),
    ("integration_time = fast", "integration_time", "0..255"),
    ("amplitude_threshold = -1", "amplitude_threshold", "0..65535"),
    ("modulation_frequency = 20MHz", "modulation_frequency", "30MHz (1)"),
    ("median = maybe", "median", "true or false"),
    ("exposure = 3", "exposure", "one of the keys"),
    ("integration_time 30", "integration_time 30", "key = value"),
])
def test_settings_file_refuses_bad_values_by_key(tmp_path, line, key, allowed):
    path = tmp_path / "tof.txt"
    path.write_text(f"timeout_ms = 500\n{line}\n")
    with pytest.raises(Sr4000SettingsError) as caught:
        Sr4000Settings.load(path)
    error = caught.value
    assert error.key == key and allowed in error.allowed
    assert f"{path}:2" in str(error) and key in str(error)


def test_cross_field_rules_are_refused_precisely():
    with pytest.raises(Sr4000SettingsError,
                       match=r"auto_exposure_min = 200 refused; allowed: <= auto_exposure_max \(150\)"):
        Sr4000Settings.checked(auto_exposure_min=200)
    with pytest.raises(Sr4000SettingsError, match="AM_HW_TRIGGER needs AM_SW_TRIGGER"):
        Sr4000Settings.checked(hardware_trigger=True, software_trigger=False)
    with pytest.raises(Sr4000SettingsError, match="mode = '0x40' refused"):
        Sr4000Settings().with_mode_flags(0x40)


def test_mode_flags_and_frequencies():
    assert Sr4000Settings().mode_flags() == (AcquireMode.COR_FIX_PTRN | AcquireMode.CONV_GRAY
                                             | AcquireMode.DENOISE_ANF | AcquireMode.CONF_MAP
                                             | AcquireMode.SW_TRIGGER)
    assert Sr4000Settings().with_mode_flags(AcquireMode.MEDIAN).mode_flags() == (
        AcquireMode.COR_FIX_PTRN | AcquireMode.MEDIAN)
    assert frequency_for_range(4.0) is ModulationFrequency.MF_30MHz
    assert frequency_for_range(7.0) is ModulationFrequency.MF_15MHz
    assert frequency_for_range(4.9, calibrated_only=False) is ModulationFrequency.MF_30MHz
    assert frequency_for_range(3.0, calibrated_only=False) is ModulationFrequency.MF_40MHz
    with pytest.raises(Sr4000SettingsError, match="max_distance_m = 11.0 refused"):
        frequency_for_range(11.0)
    assert integration_time_ms(0) == pytest.approx(0.3) and integration_time_ms(255) == pytest.approx(25.8)


# --------------------------------------------------------------------------------------------
# The ctypes backend against a fake libmesasr
# --------------------------------------------------------------------------------------------

class FakeLibrary:
    """The compiled fake and its test controls (same dlopen handle as the driver's)."""

    def __init__(self, path: Path):
        self.path = path
        self._lib = ctypes.CDLL(str(path))
        self._lib.FAKE_CallLog.restype = ctypes.c_char_p
        self._lib.FAKE_SetOpenResult.argtypes = [ctypes.c_int]
        self._lib.FAKE_SetAcquireResult.argtypes = [ctypes.c_int]

    def reset(self) -> None:
        self._lib.FAKE_ClearLog()
        self._lib.FAKE_SetOpenResult(1)
        self._lib.FAKE_SetAcquireResult(0)

    def calls(self) -> list[str]:
        return self._lib.FAKE_CallLog().decode().splitlines()

    def fail_open(self, result: int) -> None:
        self._lib.FAKE_SetOpenResult(result)

    def fail_acquire(self, result: int) -> None:
        self._lib.FAKE_SetAcquireResult(result)


@pytest.fixture(scope="module")
def fake_library_path(tmp_path_factory) -> Path:
    gcc = shutil.which("gcc")
    if gcc is None:
        pytest.skip("gcc is not installed: cannot build the fake libmesasr (tests/drivers/fakes/fake_mesasr.c)")
    path = tmp_path_factory.mktemp("fake-mesasr") / "libmesasr.so"
    subprocess.run([gcc, "-shared", "-fPIC", "-O1", "-Wall", "-Wextra", "-Werror", "-o", str(path),
                    str(FAKE_SOURCE)], check=True, capture_output=True)
    return path


@pytest.fixture
def fake(fake_library_path) -> FakeLibrary:
    library = FakeLibrary(fake_library_path)
    library.reset()
    yield library
    library.reset()


def test_open_sends_every_setting_with_the_right_c_types(fake):
    settings = Sr4000Settings.checked(integration_time=200, amplitude_threshold=1000)
    with MesaSr4000(library=str(fake.path), settings=settings, name="tof-test") as camera:
        assert camera.serial == 0x4000ABCD                      # unsigned int restype, > 2^31
        assert (camera.rows, camera.cols) == (144, 176)
        assert camera.version == "libmesasr 1.0.14.706" and "SR4000 (fake)" in camera.device_string
        assert camera.mode() == settings.mode_flags()
        assert camera.modulation_frequency() is ModulationFrequency.MF_30MHz
        assert camera.amplitude_threshold() == 1000
    assert fake.calls() == [
        "SR_OpenUSB 0", "SR_SetModulationFrequency 1", "SR_SetAutoExposure 1 150 5 70",
        "SR_SetIntegrationTime 200", "SR_SetAmplitudeThreshold 1000", "SR_SetMode 0xd11",
        "SR_SetTimeout 1000", "SR_Close"]


def test_frame_images_strides_and_axes(fake):
    with MesaSr4000(library=str(fake.path)) as camera:
        frame = camera.acquire()
    rows, cols = np.mgrid[0:144, 0:176]
    assert frame.distance.dtype == np.uint16 and frame.distance.shape == (144, 176)
    np.testing.assert_array_equal(frame.distance, 100 * rows + cols + 1)
    np.testing.assert_array_equal(frame.amplitude, 1000 + cols)
    np.testing.assert_array_equal(frame.confidence, 0xFFFF - 10 * rows)
    # MESA's X left / Y up become OpenCV's x right / y down; one interleaved buffer, 12-byte pitch.
    assert "SR_CoordTrfFlt 12 12 12" in fake.calls()
    np.testing.assert_array_equal(frame.x, -np.float32(0.001) * cols.astype(np.float32))
    np.testing.assert_array_equal(frame.y, -np.float32(0.002) * rows.astype(np.float32))
    np.testing.assert_allclose(frame.z, frame.distance * 5.0 / 65535.0, rtol=1e-6)
    np.testing.assert_allclose(frame.distance_m(), frame.z, rtol=1e-6)
    assert frame.x.dtype == frame.y.dtype == frame.z.dtype == np.float32


def test_settings_changes_reach_the_library_and_bad_ones_do_not(fake):
    with MesaSr4000(library=str(fake.path)) as camera:
        fake.reset()
        camera.set_auto_exposure(255, 0, 0, 0)
        camera.set_integration_time(255)
        camera.set_amplitude_threshold(65535)
        camera.set_max_distance(8.0)
        camera.set_mode(AcquireMode.MEDIAN | AcquireMode.SW_TRIGGER)
        camera.set_timeout(250)
        assert fake.calls() == ["SR_SetAutoExposure 255 0 0 0", "SR_SetIntegrationTime 255",
                                "SR_SetAmplitudeThreshold 65535", "SR_SetModulationFrequency 6",
                                "SR_SetMode 0x405", "SR_SetTimeout 250"]
        assert camera.integration_time() == 255 and not camera.settings().auto_exposure
        fake.reset()
        for bad in (lambda: camera.set_integration_time(256), lambda: camera.set_amplitude_threshold(-1),
                    lambda: camera.set_modulation_frequency("21MHz"), lambda: camera.set_mode(0x40),
                    lambda: camera.set_auto_exposure(20, 10, 5, 70)):
            with pytest.raises(Sr4000SettingsError):
                bad()
        assert fake.calls() == []
        frame = camera.acquire()
        assert frame.confidence is None                          # AM_CONF_MAP is off
        assert frame.modulation_frequency is ModulationFrequency.MF_15MHz


def test_ethernet_open(fake):
    with MesaSr4000(address="192.168.1.42", library=str(fake.path)):
        pass
    assert fake.calls()[0] == "SR_OpenETH 192.168.1.42"


def test_missing_library_is_a_precise_device_fault(tmp_path):
    camera = MesaSr4000(library=str(tmp_path / "libmesasr.so"), name="tof-left")   # not loaded yet
    with pytest.raises(Sr4000LibraryMissing) as caught:
        camera.open()
    message = str(caught.value)
    assert isinstance(caught.value, DeviceFault) and caught.value.device == "tof-left"
    assert message.startswith("tof-left: cannot load the MESA library")
    assert str(tmp_path / "libmesasr.so") in message and "libmesasr-dev" in message and ".deb" in message
    assert not camera.is_open and camera.status().state == "closed"


def test_a_library_without_the_mesa_functions_is_refused():
    with pytest.raises(Sr4000LibraryMissing, match="has no SR_OpenUSB"):
        MesaSr4000(library="libc.so.6").open()


@pytest.mark.parametrize("result", [0, -3])
def test_no_camera_answering_is_a_precise_device_fault(fake, result):
    fake.fail_open(result)
    camera = MesaSr4000(usb_serial=0x40000397, library=str(fake.path), name="tof-test")
    with pytest.raises(Sr4000NotFound) as caught:
        camera.open()
    assert str(caught.value) == (f"tof-test: no SR4000 answered on USB (serial 0x40000397; 0 = first "
                                 f"found) (SR_OpenUSB returned {result})")
    assert not camera.is_open


def test_acquisition_failure_names_the_call_and_is_kept_in_the_status(fake):
    with MesaSr4000(library=str(fake.path), name="tof-test") as camera:
        fake.fail_acquire(-5)
        with pytest.raises(Sr4000NotAnswering, match=r"tof-test: acquisition failed: stopped answering .*"
                                                      r"SR_Acquire returned -5") as caught:
            camera.acquire()
        assert not isinstance(caught.value, DeviceTimeout)   # a silent camera is a fault, ERR 503
        status = camera.status()
        assert status.state == "idle" and "SR_Acquire returned -5" in status.last_error


def test_grab_waits_for_the_auto_exposure_of_a_real_backend(fake):
    with MesaSr4000(library=str(fake.path)) as camera:
        assert wait_for_exposure(camera, max_frames=3) == (False, 3)    # 30 -> 55 -> 67 -> 73
        result = grab(camera, frames=4, min_confidence=0xFFFF - 500, settle_frames=10)
        assert result.settled and 1 <= result.settle_frames <= 6 and camera.integration_time() == 79
    rows = np.arange(144)[:, None]
    expected_valid = np.broadcast_to(0xFFFF - 10 * rows >= 0xFFFF - 500, (144, 176))
    np.testing.assert_array_equal(result.valid_count, np.where(expected_valid, 4, 0))
    assert np.all(np.isnan(result.frame.x[~expected_valid]))
    assert np.all(result.frame.distance[~expected_valid] == 0)
    rows, cols = np.mgrid[0:144, 0:176]
    ramp = 100 * rows + cols + 1
    np.testing.assert_array_equal(result.frame.distance[expected_valid], ramp[expected_valid])


class ScriptedSr4000(Sr4000):
    """A backend that replays given distance images: grab() needs nothing but the interface."""

    def __init__(self, distances: list[np.ndarray]):
        super().__init__("scripted", Sr4000Settings.checked(auto_exposure=False))
        self._distances = iter(distances)

    def _acquire(self) -> TofFrame:
        distance = next(self._distances).astype(np.uint16)
        z = distance * np.float32(5.0 / 0xFFFF)
        return TofFrame(distance=distance, amplitude=np.full(distance.shape, 5000, np.uint16),
                        confidence=np.full(distance.shape, 0xFFFF, np.uint16), x=np.zeros_like(z),
                        y=np.zeros_like(z), z=z, timestamp=0.0,
                        modulation_frequency=ModulationFrequency.MF_30MHz, integration_time=30)

    def _open(self): pass
    def _close(self): pass
    def _write_integration_time(self, register): pass
    def _write_amplitude_threshold(self, threshold): pass
    def _write_modulation_frequency(self, frequency): pass
    def _write_auto_exposure(self, *values): pass
    def _write_mode(self, flags): pass
    def _write_timeout(self, milliseconds): pass
    def _read_integration_time(self): return 30
    def _read_mode(self): return int(self._settings.mode_flags())


def test_grab_drops_samples_that_wrapped():
    near_range_end, wrapped = 65000, 300           # 4.96 m, and the same pixel flipped to 0.02 m
    images = [np.full((2, 3), near_range_end) for _ in range(7)] + [np.full((2, 3), wrapped)] * 3
    images[0][0, 0] = 0                            # one sample with no measurement
    with ScriptedSr4000(images) as camera:
        result = grab(camera, frames=10, min_valid=7)
    assert result.settled and result.settle_frames == 0
    np.testing.assert_array_equal(result.valid_count, [[6, 7, 7], [7, 7, 7]])
    assert result.frame.distance[0, 0] == 0 and np.isnan(result.frame.z[0, 0])    # 6 < min_valid
    assert np.all(result.frame.distance.ravel()[1:] == near_range_end)
    np.testing.assert_allclose(result.frame.z.ravel()[1:], near_range_end * 5.0 / 0xFFFF, rtol=1e-6)


# --------------------------------------------------------------------------------------------
# The emulator against the simulated world
# --------------------------------------------------------------------------------------------

def mast_pose(world: World, x: float, y: float, heading_deg: float, tilt_deg: float,
              height_m: float) -> np.ndarray:
    """Camera-to-world 4x4 (OpenCV camera axes) of a camera `height_m` above the ground at (x, y),
    looking toward `heading_deg` (clockwise from north) and `tilt_deg` below the horizon."""
    heading, tilt = np.radians(heading_deg), np.radians(tilt_deg)
    forward = np.array([np.sin(heading) * np.cos(tilt), np.cos(heading) * np.cos(tilt), -np.sin(tilt)])
    right = np.array([np.cos(heading), -np.sin(heading), 0.0])
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2] = right, np.cross(forward, right), forward
    pose[:3, 3] = (x, y, float(world.height_at(x, y)) + height_m)
    return pose


@pytest.fixture(scope="module")
def world() -> World:
    return World.build(WorldConfig(seed=11, size_m=(12.0, 12.0)))


def pose_seeing(world: World, bands: list[tuple[float, float]], tilt_deg: float,
                height_m: float = 1.5) -> np.ndarray:
    """The mast pose at the origin, among eight headings, whose view covers each range band best
    (most pixels in its least-covered band), so the tests do not hang on one world's hills."""
    def coverage(pose):
        ranges = render(world, pose, MRPT_INTRINSICS, shadows=False).range
        return min(np.count_nonzero((ranges >= low) & (ranges < high)) for low, high in bands)
    poses = [mast_pose(world, 0.0, 0.0, heading, tilt_deg, height_m) for heading in range(0, 360, 45)]
    return max(poses, key=coverage)


@pytest.fixture(scope="module")
def mast(world) -> np.ndarray:
    """1.5 m mast, 35 degrees down, facing ground from 1.5 to 5 m."""
    return pose_seeing(world, [(1.5, 3.0), (3.5, 5.0)], 35.0)


def emulator(world, pose, seed=3, clock_speed=FAST_CLOCK, **settings) -> Sr4000Emulator:
    pose_now = pose if callable(pose) else (lambda: pose)
    camera = Sr4000Emulator(world, pose_now, SimClock(clock_speed), seed=seed,
                            settings=Sr4000Settings.checked(**settings))
    return camera.open()


def range_errors(camera: Sr4000Emulator, frame) -> dict[str, np.ndarray]:
    """Per-pixel truth and errors of the last frame: measured minus true range along each ray, and
    emulated points in the world against the ray hits."""
    view, images = camera.last_view, camera.last_images
    measured = frame.distance_m().astype(np.float64)
    points_world = frame.xyz().astype(np.float64) @ camera.last_pose[:3, :3].T + camera.last_pose[:3, 3]
    return {"true": view.range.astype(np.float64), "error": measured - view.range,
            "point_error": np.linalg.norm(points_world - view.points, axis=-1),
            "points_world": points_world, "sigma": images.sigma_m.astype(np.float64),
            "clean": view.hit & (images.flying_m < 1e-6) & ~images.saturated & (frame.distance > 0)
            & (view.range < 0.95 * frame.non_ambiguity_range_m)}


def test_unfiltered_errors_match_the_noise_model_and_the_world(world, mast):
    camera = emulator(world, mast)
    camera.set_mode(UNFILTERED)
    wait_for_exposure(camera, 10)
    frame = camera.acquire()
    e = range_errors(camera, frame)
    clean = e["clean"]
    assert clean.sum() > 5000
    z = e["error"][clean] / e["sigma"][clean]
    assert abs(z.mean()) < 0.05 and 0.9 < z.std() < 1.1
    # Points sit on their rays: the world-frame error is the range error.
    np.testing.assert_allclose(e["point_error"][clean], np.abs(e["error"][clean]), atol=2e-4)
    # And on the terrain: heights at the emulated x, y agree with the points within the noise.
    pts = e["points_world"][clean]
    dz = pts[:, 2] - world.height_at(pts[:, 0], pts[:, 1])
    assert np.median(np.abs(dz)) < 0.01


def test_default_filters_keep_every_band_within_the_expected_noise(world, mast):
    camera = emulator(world, mast)
    wait_for_exposure(camera, 10)
    e = range_errors(camera, camera.acquire())
    ground = camera.last_view.rock < 0
    checked = 0
    for low, high in ((1.5, 2.5), (2.5, 3.5), (3.5, 4.75)):
        band = e["clean"] & (e["true"] >= low) & (e["true"] < high)
        if band.sum() < 200:
            continue
        checked += 1
        expected = np.sqrt(np.mean(np.square(e["sigma"][band])))
        rmse = np.sqrt(np.mean(np.square(e["error"][band])))
        bias = abs(np.mean(e["error"][band]))
        assert rmse < expected and bias < 0.3 * expected + 0.002, (low, rmse, bias, expected)
        # The adaptive neighbourhood filter removes noise on smooth ground (it blurs small rocks).
        ground_rmse = np.sqrt(np.mean(np.square(e["error"][band & ground])))
        assert ground_rmse < 0.8 * expected, (low, ground_rmse, expected)
    assert checked >= 2


def test_distances_wrap_at_the_non_ambiguity_range(world):
    pose = pose_seeing(world, [(6.8, 7.2)], 12.0)
    at_30 = emulator(world, pose, auto_exposure=False, integration_time=255, amplitude_threshold=0)
    frame = at_30.acquire()
    true_range = at_30.last_view.range
    target = (true_range > 6.8) & (true_range < 7.2) & (at_30.last_images.flying_m < 1e-6)
    assert target.sum() > 50
    reads = frame.distance_m()[target]
    assert 1.85 < np.median(reads) < 2.15                          # 7 m reads about 2 m at 30 MHz
    assert np.mean(np.abs(reads - (true_range[target] - 5.0)) < 0.2) > 0.9
    at_15 = emulator(world, pose, auto_exposure=False, integration_time=255, modulation_frequency="15MHz")
    reads_15 = at_15.acquire().distance_m()[target]
    assert 6.85 < np.median(reads_15) < 7.15                       # within 10 m at 15 MHz


def test_low_confidence_grows_with_range_and_falls_on_dark_ground(world, mast):
    camera = emulator(world, mast)
    wait_for_exposure(camera, 10)
    frame = camera.acquire()
    true_range, albedo = camera.last_view.range, camera.last_view.albedo
    low = frame.confidence < HALF_CONFIDENCE
    near, far = (true_range >= 1.5) & (true_range < 3.0), (true_range >= 4.0) & (true_range < 5.5)
    assert near.sum() > 500 and far.sum() > 500, "the test world offers no view from 1.5 to 5.5 m"
    assert low[near].mean() < 0.05 and low[far].mean() > 3 * low[near].mean() + 0.02
    assert frame.confidence[far].mean() < 0.8 * frame.confidence[near].mean()
    # Where about half the pixels are flagged, the darker ones are flagged more.
    bands = [(true_range >= a) & (true_range < a + 1) for a in np.arange(1.5, 4.6, 0.5)]
    band = min((b for b in bands if b.sum() > 400), key=lambda b: abs(low[b].mean() - 0.5))
    dark = band & (albedo < np.percentile(albedo[band], 25))
    bright = band & (albedo > np.percentile(albedo[band], 75))
    assert low[dark].mean() > low[bright].mean() + 0.05
    assert frame.confidence[dark].mean() < 0.9 * frame.confidence[bright].mean()


def test_flying_pixels_lie_between_the_surfaces_of_depth_edges_with_low_confidence(world, mast):
    camera = emulator(world, mast, seed=5)
    wait_for_exposure(camera, 10)
    frame = camera.acquire()
    images, true_range = camera.last_images, camera.last_view.range
    flying = (images.flying_m > 0.05) & (true_range < 4.5)          # away from the wrap at 5 m
    assert flying.sum() > 20
    padded = np.pad(true_range, 1, mode="edge")
    windows = np.lib.stride_tricks.sliding_window_view(padded, (3, 3))
    nearest, farthest = windows.min(axis=(-1, -2)), windows.max(axis=(-1, -2))
    mixed = images.mixed_range_m[flying]
    assert np.all((mixed > nearest[flying] - 1e-6) & (mixed < farthest[flying] + 1e-6))
    assert np.all(farthest[flying] - nearest[flying] > 0.05)       # only at depth edges
    others = ~flying & camera.last_view.hit & (true_range < 4.5)
    typical = np.median(frame.confidence[others])
    assert np.median(frame.confidence[flying]) < min(HALF_CONFIDENCE, 0.6 * typical)


def test_short_range_with_long_integration_saturates_and_auto_exposure_recovers(world):
    close = mast_pose(world, 0.0, 0.0, 0.0, 90.0, 0.5)
    camera = emulator(world, close, auto_exposure=False, integration_time=255)
    frame = camera.acquire()
    assert frame.saturated.mean() > 0.9
    assert np.all(frame.confidence[frame.saturated] == 0)
    assert np.all(frame.amplitude[frame.saturated] == AMPLITUDE_SATURATED)
    camera.set_integration_time(0)
    assert camera.acquire().saturated.mean() == 0.0
    camera.set_auto_exposure(0, 255, 5, 70)
    camera.set_integration_time(255)
    settled, used = wait_for_exposure(camera, 15)
    assert settled and used <= 12
    assert camera.acquire().saturated.mean() < 0.01


def test_auto_exposure_settles_within_a_few_frames_after_a_scene_change(world, mast):
    close = mast_pose(world, 0.0, 0.0, 0.0, 90.0, 0.6)
    pose = {"now": mast}
    camera = emulator(world, lambda: pose["now"])
    settled, used = wait_for_exposure(camera, 10)
    assert settled and used <= 6
    position = np.percentile(np.minimum(camera.last_images.raw_amplitude / 256, 255), 95)
    assert 70 / 1.2 < position < 70 * 1.2
    pose["now"] = close                                    # the PTU turned toward the ground
    first = camera.acquire()
    assert first.saturated.mean() > 0.05                   # badly exposed at first
    settled, used = wait_for_exposure(camera, 12)
    assert settled and used <= 10                          # 2x per frame at most: ~60x takes 6+
    assert camera.acquire().saturated.mean() < 0.01


def test_amplitude_threshold_forces_distance_to_zero_and_grab_marks_undefined(world, mast):
    camera = emulator(world, mast, auto_exposure=False, integration_time=40, amplitude_threshold=3000)
    frame = camera.acquire()
    dim = camera.last_images.raw_amplitude < 3000
    assert 0.05 < dim.mean() < 0.95
    np.testing.assert_array_equal(frame.distance == 0, dim)
    assert np.all(frame.z[dim] == 0) and np.all(np.isnan(frame.distance_m()[dim]))
    result = grab(camera, frames=3, settle_frames=0)
    undefined = result.valid_count == 0
    assert np.all(np.isnan(result.frame.xyz()[undefined]))
    assert np.all(result.frame.distance[undefined] == 0)
    assert np.all(np.isfinite(result.frame.xyz()[~undefined]))


def test_grab_averages_noise_down(world, mast):
    camera = emulator(world, mast)
    camera.set_mode(UNFILTERED)
    wait_for_exposure(camera, 10)
    single = range_errors(camera, camera.acquire())
    result = grab(camera, frames=8, min_confidence=HALF_CONFIDENCE, settle_frames=5)
    assert result.settled and result.frames == 8
    averaged = result.frame.distance_m() - camera.last_view.range
    both = single["clean"] & (result.valid_count == 8) & (camera.last_view.range < 4.0)
    ratio = np.sqrt(np.mean(averaged[both] ** 2) / np.mean(single["error"][both] ** 2))
    assert ratio < 0.5                                           # about 1/sqrt(8) = 0.35
    dropped = result.valid_count < 8
    assert np.median(result.frame.confidence[dropped]) < np.median(result.frame.confidence[~dropped])


def test_the_same_seed_gives_the_same_frames(world, mast):
    a, b, c = (emulator(world, mast, seed=seed).acquire() for seed in (8, 8, 9))
    np.testing.assert_array_equal(a.distance, b.distance)
    np.testing.assert_array_equal(a.amplitude, b.amplitude)
    np.testing.assert_array_equal(a.confidence, b.confidence)
    assert not np.array_equal(a.distance, c.distance)
    one, two = emulator(world, mast, seed=8), emulator(world, mast, seed=8)
    for _ in range(3):
        np.testing.assert_array_equal(one.acquire().x, two.acquire().x)
    assert one.integration_time() == two.integration_time()


def test_frame_time_follows_the_integration_time_in_simulated_seconds(world, mast):
    camera = emulator(world, mast, clock_speed=5.0, auto_exposure=False, integration_time=255)
    first, second = camera.acquire(), camera.acquire()
    period = frame_time_s(255, camera.model)
    assert period == pytest.approx(4 * (25.8 + 4.3) / 1000)
    assert second.timestamp - first.timestamp >= period * 0.99
    assert frame_time_s(0, camera.model) == pytest.approx(1 / 54, rel=0.01)   # datasheet's 54 fps


def test_hardware_trigger_waits_and_times_out(world, mast):
    camera = emulator(world, mast, clock_speed=10.0, hardware_trigger=True, timeout_ms=300)
    with pytest.raises(Sr4000Timeout, match="no hardware trigger within 300 ms") as caught:
        camera.acquire()
    assert isinstance(caught.value, DeviceTimeout) and caught.value.device == "sr4000-emulator"
    threading.Timer(0.005, camera.hardware_trigger).start()
    assert camera.acquire().sequence == 1


def test_an_injected_fault_silences_the_camera_until_cleared(world, mast):
    fault = FaultSwitch("tof")
    camera = Sr4000Emulator(world, lambda: mast, SimClock(FAST_CLOCK), seed=3, fault=fault,
                            settings=Sr4000Settings.checked(timeout_ms=400)).open()
    fault.arm(after=1)
    camera.acquire()                                    # the one frame it still gives
    started = camera.clock.now()
    with pytest.raises(Sr4000NotAnswering, match=r"sr4000-emulator: acquisition failed: stopped answering "
                                                  r"\(no frame within 400 ms\) \(SR_Acquire returned -1\)"):
        camera.acquire()
    assert camera.clock.now() - started >= 0.4          # SR_Acquire waited out its timeout
    assert "stopped answering" in camera.status().last_error
    camera.close()
    with pytest.raises(Sr4000NotFound, match="no SR4000 answered"):
        camera.open()                                   # a hung camera does not enumerate
    fault.clear()
    camera.open()
    assert camera.acquire().sequence == 2 and camera.status().last_error is None


def test_status_is_readable_while_a_frame_is_acquired(world, mast):
    camera = emulator(world, mast, clock_speed=1.0, auto_exposure=False, integration_time=255)
    seen = []
    worker = threading.Thread(target=camera.acquire)
    worker.start()
    deadline = time.monotonic() + 2.0
    while worker.is_alive() and time.monotonic() < deadline:
        seen.append(camera.status().state)
    worker.join()
    assert "busy" in seen
    status = camera.status()
    assert status.state == "idle" and status.frames_acquired == 1 and status.serial == camera.serial
    assert status.trigger == "software" and status.integration_time == 255


def test_model_functions_on_a_synthetic_step():
    """A flat wall at 2 m with a box face at 1 m in its middle: edges, mixing, saturation in
    isolation from the world."""
    @dataclass
    class Scene:
        range: np.ndarray
        albedo: np.ndarray
        incidence_cos: np.ndarray

    shape = (144, 176)
    true_range = np.full(shape, 2.0)
    true_range[40:100, 60:120] = 1.0
    scene = Scene(true_range, np.full(shape, 0.1, np.float32), np.ones(shape, np.float32))
    directions = np.zeros(shape + (3,), np.float32)
    directions[..., 2] = 1.0
    model = Sr4000Model()
    exposure = Exposure(20, ModulationFrequency.MF_30MHz, UNFILTERED)
    edges = np.random.default_rng(0).random((2,) + shape)
    images = simulate_frame(scene, directions, exposure, model, np.random.default_rng(1), edges)
    flying = images.flying_m > 0.05
    border = np.zeros(shape, bool)
    border[39:41, 60:120] = border[99:101, 60:120] = border[40:100, 59:61] = border[40:100, 119:121] = True
    assert flying.any() and np.all(border[flying])                 # only along the box outline
    assert 0.15 < flying[border].mean() < 0.85                     # one of each pair, at random
    assert np.all((images.mixed_range_m[flying] > 1.0) & (images.mixed_range_m[flying] < 2.0))
    long = simulate_frame(scene, directions, Exposure(255, ModulationFrequency.MF_30MHz, UNFILTERED),
                          model, np.random.default_rng(1), edges)
    assert long.saturated[50:90, 70:110].all() and not long.saturated[0:30].any()
    limits = (1, 150, 5, 70)
    assert auto_exposure_step(long.raw_amplitude, long.saturated, 255, limits, model) <= 150   # clamped
    assert auto_exposure_step(long.raw_amplitude, long.saturated, 140, limits, model) < 140    # too bright
    assert auto_exposure_step(images.raw_amplitude / 10, images.saturated, 20, limits, model) > 20
    in_band = np.full(shape, 70 * 256.0)
    assert auto_exposure_step(in_band, np.zeros(shape, bool), 20, limits, model) == 20


# --------------------------------------------------------------------------------------------
# Previews
# --------------------------------------------------------------------------------------------

def test_false_colour_ramp_and_previews(world, mast):
    rgb = false_colour(np.array([[-1.0, 0.0, 2.5, 5.0, 9.0, np.nan]]), 0.0, 5.0)
    assert rgb.dtype == np.uint8 and rgb.shape == (1, 6, 3)
    assert rgb[0, 0].tolist() == rgb[0, 1].tolist() == [0, 0, 128]      # dark blue at and below low
    assert rgb[0, 2].tolist() == [128, 255, 0]                           # between green and yellow
    assert rgb[0, 3].tolist() == rgb[0, 4].tolist() == [128, 0, 0]      # dark red at and above high
    assert rgb[0, 5].tolist() == [0, 0, 0]                               # undefined: black
    with pytest.raises(ValueError, match="high > low"):
        false_colour(np.zeros(3), 1.0, 1.0)
    frame = emulator(world, mast).acquire()
    for image in ("distance", "amplitude", "confidence"):
        assert preview(frame, image).shape == (144, 176, 3)
