"""Trigger box and stereo cameras: the ppdev calls, settings, identities, synchronous grabs, and the
emulated pair's images against the simulated world's ground truth.

The parallel port and vmbpy are replaced at the library boundary (ioctl/open functions, a fake
`vmbpy` module); our own classes run as they are. Stereo accuracy uses the low resolution mode to
keep the file fast.
"""
from __future__ import annotations

import errno
import json
import math
import os
import struct
import sys
import threading
import time
import types

import cv2
import numpy as np
import pytest

from drivers.avt import (
    PIKE_F210B_SENSOR,
    CameraError,
    CameraSettings,
    CameraTimeout,
    SettingsError,
    intrinsics_per_mode,
)
from drivers.avt_emulator import EmulatedCamera, emulated_stereo_pair
from drivers.avt_stereo import StereoCameras
from drivers.avt_vimba import VimbaCamera
from drivers.errors import DeviceFault, DeviceTimeout
from drivers.sim.clock import SimClock
from drivers.sim.config import Sun
from drivers.sim.faults import InjectedFaults
from drivers.sim.render import render
from drivers.sim.rover import Rover
from drivers.sim.world import World, WorldConfig
from drivers.trigger import PPCLAIM, PPDATADIR, PPEXCL, PPRELEASE, PPWDATA, EmulatedTrigger, PpdevTrigger, TriggerError
from toolbox.camera import Intrinsics

LOW = CameraSettings(resolution="low")
TILT_DEG = -30.0     # the pair looks 30 degrees down from a ~1.5 m mast


# --------------------------------------------------------------------------------------------
# Trigger box: ppdev against a fake port
# --------------------------------------------------------------------------------------------

class FakeParport:
    """os.open / fcntl.ioctl / os.close / sleep stand-ins that record every call."""

    def __init__(self, open_error: OSError | None = None, failing_request: int | None = None,
                 ioctl_errno: int = errno.EBUSY):
        self.calls: list[tuple] = []
        self.open_error, self.failing_request, self.ioctl_errno = open_error, failing_request, ioctl_errno

    def open_node(self, path, flags):
        self.calls.append(("open", path, flags))
        if self.open_error is not None:
            raise self.open_error
        return 7

    def ioctl(self, fd, request, *argument):
        self.calls.append(("ioctl", fd, request, *argument))
        if request == self.failing_request:
            raise OSError(self.ioctl_errno, os.strerror(self.ioctl_errno))
        return 0

    def close_node(self, fd):
        self.calls.append(("close", fd))

    def sleep(self, seconds):
        self.calls.append(("sleep", seconds))

    def trigger(self, **kwargs) -> PpdevTrigger:
        return PpdevTrigger("/dev/parport0", open_node=self.open_node, ioctl=self.ioctl,
                            close_node=self.close_node, sleep=self.sleep, **kwargs)


def test_ppdev_open_pulse_close_make_the_exact_ioctl_sequence():
    port = FakeParport()
    trigger = port.trigger()
    trigger.open()
    assert port.calls == [("open", "/dev/parport0", os.O_RDWR),
                          ("ioctl", 7, PPEXCL), ("ioctl", 7, PPCLAIM),
                          ("ioctl", 7, PPDATADIR, struct.pack("i", 0)),
                          ("ioctl", 7, PPWDATA, b"\x00")]
    port.calls.clear()
    at = trigger.pulse()
    assert port.calls == [("ioctl", 7, PPWDATA, b"\x01"), ("sleep", 0.001), ("ioctl", 7, PPWDATA, b"\x00")]
    port.calls.clear()
    trigger.close()
    assert port.calls == [("ioctl", 7, PPWDATA, b"\x00"), ("ioctl", 7, PPRELEASE), ("close", 7)]
    status = trigger.status()
    assert (status.is_open, status.pulses, status.last_pulse_s) == (False, 1, at)
    assert (PPCLAIM, PPRELEASE, PPEXCL, PPWDATA, PPDATADIR) == (0x708B, 0x708C, 0x708F, 0x40017086, 0x40047090)


def test_ppdev_missing_node_names_the_ppdev_module():
    port = FakeParport(open_error=FileNotFoundError(errno.ENOENT, "No such file or directory"))
    with pytest.raises(TriggerError) as caught:
        port.trigger().open()
    assert isinstance(caught.value, DeviceFault)
    assert caught.value.device == "trigger (/dev/parport0)"
    assert str(caught.value).startswith("trigger (/dev/parport0): ")
    assert "ppdev" in str(caught.value) and "No such file" in str(caught.value)


def test_ppdev_permission_denied_names_group_lp():
    port = FakeParport(open_error=PermissionError(errno.EACCES, "Permission denied"))
    trigger = port.trigger()
    with pytest.raises(TriggerError, match=r"trigger \(/dev/parport0\): permission denied.*group lp"):
        trigger.open()
    assert "group lp" in trigger.status().last_error


def test_ppdev_busy_port_is_reported_and_the_node_closed():
    port = FakeParport(failing_request=PPCLAIM)
    with pytest.raises(TriggerError, match=r"PPCLAIM.*Device or resource busy.*lp driver"):
        port.trigger().open()
    assert port.calls[-1] == ("close", 7)


def test_ppdev_pulse_before_open_and_without_exclusive_claim():
    port = FakeParport()
    trigger = port.trigger(exclusive=False)
    with pytest.raises(TriggerError, match="not open"):
        trigger.pulse()
    trigger.open()
    assert ("ioctl", 7, PPEXCL) not in port.calls


def test_ppdev_pin_comes_down_even_when_the_wait_fails():
    port = FakeParport()

    def interrupted(seconds):
        raise KeyboardInterrupt

    trigger = PpdevTrigger("/dev/parport0", open_node=port.open_node, ioctl=port.ioctl,
                           close_node=port.close_node, sleep=interrupted)
    trigger.open()
    port.calls.clear()
    with pytest.raises(KeyboardInterrupt):
        trigger.pulse()
    assert port.calls == [("ioctl", 7, PPWDATA, b"\x01"), ("ioctl", 7, PPWDATA, b"\x00")]


def test_emulated_trigger_calls_every_input_at_one_instant():
    clock = SimClock(1.0)
    trigger = EmulatedTrigger(clock)
    seen: list[tuple[str, float]] = []
    trigger.connect(lambda t: seen.append(("a", t)))
    trigger.connect(lambda t: seen.append(("b", t)))
    with pytest.raises(TriggerError, match=r"trigger \(emulated\): not open"):
        trigger.pulse()
    trigger.open()
    at = trigger.pulse()
    assert seen == [("a", at), ("b", at)]
    assert trigger.status().pulses == 1


# --------------------------------------------------------------------------------------------
# Settings and resolution modes
# --------------------------------------------------------------------------------------------

def test_settings_round_trip_through_a_file(tmp_path):
    settings = CameraSettings(resolution="medium", pixel_format="rgb8", exposure_us=1234.5, gain_db=6.0,
                              auto_exposure=True, target_grey_level=77, white_balance_red=1.3,
                              white_balance_blue=0.8)
    path = settings.save(tmp_path / "cameras.json")
    assert CameraSettings.load(path) == settings
    assert json.loads(path.read_text())["target_grey_level"] == 77   # the thesis' UniAPI lost this one


def test_settings_file_keys_missing_take_defaults(tmp_path):
    path = tmp_path / "partial.json"
    path.write_text(json.dumps({"exposure_us": 800}))
    assert CameraSettings.load(path) == CameraSettings(exposure_us=800)


@pytest.mark.parametrize("values, expected", [
    ({"exposure_us": -5}, r"exposure_us = -5 is not allowed: .*greater than or equal to 10"),
    ({"gain_db": 40}, r"gain_db = 40 is not allowed: .*less than or equal to 24"),
    ({"resolution": "huge"}, r"resolution = 'huge' is not allowed: .*'low', 'medium', 'high', 'highest' or 'narrow'"),
    ({"pixel_format": "yuv422"}, r"pixel_format = 'yuv422' is not allowed: .*'mono8' or 'rgb8'"),
    ({"target_grey_level": 300}, r"target_grey_level = 300 is not allowed"),
    ({"shutter": 5}, r"unknown key 'shutter' \(allowed keys: resolution, pixel_format, exposure_us"),
])
def test_bad_settings_name_key_value_and_what_is_allowed(values, expected):
    with pytest.raises(SettingsError, match=expected):
        CameraSettings(**values)
    with pytest.raises(SettingsError, match=expected):
        CameraSettings().with_changes(**values)


def test_bad_settings_files_are_refused_with_the_path(tmp_path):
    with pytest.raises(SettingsError, match="no such file"):
        CameraSettings.load(tmp_path / "absent.json")
    broken = tmp_path / "broken.json"
    broken.write_text("{exposure_us: 5")
    with pytest.raises(SettingsError, match="broken.json: cannot read it as JSON"):
        CameraSettings.load(broken)
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"gain_db": -1}))
    with pytest.raises(SettingsError, match=r"bad.json: camera settings: gain_db = -1"):
        CameraSettings.load(bad)


def test_resolution_modes_bin_or_window_the_sensor():
    modes = intrinsics_per_mode(PIKE_F210B_SENSOR)
    sizes = {mode: (camera.width, camera.height) for mode, camera in modes.items()}
    assert sizes == {"low": (480, 270), "medium": (960, 540), "high": (1440, 810), "highest": (1920, 1080),
                     "narrow": (360, 405)}
    # A point seen by the full sensor lands on the same spot of each mode's pixel grid.
    point = np.array([0.3, -0.2, 4.0])
    u_full, v_full = PIKE_F210B_SENSOR.project(point)
    u_low, v_low = modes["low"].project(point)
    assert u_low == pytest.approx((u_full - 1.5) / 4) and v_low == pytest.approx((v_full - 1.5) / 4)
    u_high, v_high = modes["high"].project(point)
    assert (u_high, v_high) == pytest.approx((u_full - 240, v_full - 135))
    u_narrow, v_narrow = modes["narrow"].project(point)       # binned by 2, then the middle window
    assert (u_narrow, v_narrow) == pytest.approx(((u_full - 0.5) / 2 - 300, (v_full - 0.5) / 2 - 67))


# --------------------------------------------------------------------------------------------
# Emulated cameras: a small seeded world, shared by the tests below
# --------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def world() -> World:
    return World.build(WorldConfig(seed=5, size_m=(12.0, 12.0)))


@pytest.fixture(scope="module")
def rover(world) -> Rover:
    return Rover(world, x=0.0, y=-1.0, heading=math.pi / 2)


def make_pair(world, rover, clock=None, settings=LOW, seed=1, record_times=None, faults=None) -> StereoCameras:
    clock = clock or SimClock(1.0)

    def pose_of(sensor):
        def pose(t):
            if record_times is not None:
                record_times.append((sensor, t))
            return rover.sensor_to_world(sensor, 0.0, TILT_DEG)
        return pose

    pair = emulated_stereo_pair(world, pose_of("left"), pose_of("right"), clock=clock, seed=seed,
                                default_settings=settings, faults=faults)
    pair.open()
    return pair


def test_identities_first_found_is_left_and_can_be_set_and_swapped(world, rover):
    pair = make_pair(world, rover)
    assert pair.ids() == ("emu-left", "emu-right")
    assert pair.camera("left").camera_id == "emu-left"
    pair.swap_ids()
    assert pair.ids() == ("emu-right", "emu-left")
    assert pair.camera("left").label == "camera left (id emu-right)"
    pair.set_ids("emu-left", "emu-right")
    assert pair.ids() == ("emu-left", "emu-right")
    with pytest.raises(ValueError, match=r"no camera with id 'nope'; found: emu-left, emu-right"):
        pair.set_ids("nope", "emu-right")
    with pytest.raises(ValueError, match="two cameras"):
        pair.set_ids("emu-left", "emu-left")
    with pytest.raises(ValueError, match="left, right or both"):
        pair.grab("middle")
    pair.close()


def test_an_untriggered_camera_times_out_naming_itself(world, rover):
    pair = make_pair(world, rover)
    camera = pair.camera("left")
    camera.arm()
    started = time.monotonic()
    with pytest.raises(CameraTimeout) as caught:
        camera.wait_frame(0.05)
    assert time.monotonic() - started < 1.0
    assert isinstance(caught.value, DeviceTimeout)
    assert str(caught.value).startswith("camera left (id emu-left): no frame within 0.05 s")
    assert camera.status().state == "idle" and "no trigger pulse" in camera.status().last_error
    pair.close()


def test_a_camera_silent_where_the_other_answered_stopped_answering(world, rover):
    faults = InjectedFaults()
    pair = make_pair(world, rover, clock=SimClock(100.0), faults=faults)
    faults["camera-left"].arm(after=0)
    with pytest.raises(CameraError, match=r"camera left \(id emu-left\): stopped answering: no frame for the "
                                          r"trigger pulse at .* that camera right answered") as caught:
        pair.grab("both", timeout_s=1.0)
    assert not isinstance(caught.value, DeviceTimeout)
    status = pair.status()
    assert status.left.state == "error" and status.right.frames == 1 and status.trigger.last_error is None
    with pytest.raises(CameraError, match="did not come back"):
        pair.reset()                                    # still hung: not found after its reset
    faults["camera-left"].clear()
    pair.reset()
    status = pair.status()
    assert (status.left.state, status.left.frames, status.right.frames) == ("idle", 0, 0)  # counting from 1 again
    assert {f.frame_number for f in pair.grab("both", timeout_s=1.0).values()} == {1}
    pair.close()


def test_a_pulse_no_camera_saw_is_the_trigger_box_failing(world, rover):
    faults = InjectedFaults()
    pair = make_pair(world, rover, clock=SimClock(100.0), faults=faults)
    faults["trigger"].arm(after=1)
    pair.grab("both", timeout_s=1.0)
    with pytest.raises(TriggerError, match=r"trigger \(emulated\): stopped answering: the trigger pulse at .* "
                                           r"reached no camera \(left and right waited 1 s\)"):
        pair.grab("both", timeout_s=1.0)
    status = pair.status()
    assert "reached no camera" in status.trigger.last_error
    assert status.left.state == status.right.state == "idle"   # the cameras are not to blame
    faults["trigger"].clear()
    assert set(pair.grab("both", timeout_s=1.0)) == {"left", "right"}
    assert pair.status().trigger.last_error is None
    pair.close()


def test_a_pulse_before_arming_makes_no_frame(world, rover):
    pair = make_pair(world, rover)
    pair.trigger.pulse()       # nobody armed: both cameras ignore it
    camera = pair.camera("right")
    camera.arm()
    with pytest.raises(CameraTimeout, match=r"camera right \(id emu-right\)"):
        camera.wait_frame(0.05)
    with pytest.raises(CameraError, match="not armed"):
        camera.wait_frame(0.05)
    assert camera.status().frames == 0
    pair.close()


def test_a_stereo_grab_gives_two_images_of_the_same_instant(world, rover):
    asked = []
    pair = make_pair(world, rover, record_times=asked)
    frames = pair.grab("both", timeout_s=2.0)
    left, right = frames["left"], frames["right"]
    assert (left.camera_id, right.camera_id) == ("emu-left", "emu-right")
    assert (left.role, right.role) == ("left", "right")
    assert left.image.shape == right.image.shape == (270, 480) and left.image.dtype == np.uint8
    # Both carry the pulse's simulated instant, and their poses were taken at it: rendering time,
    # which passed before the frames were ready, is not in the timestamp.
    assert left.timestamp_s == right.timestamp_s == left.trigger_time_s == pair.trigger.status().last_pulse_s
    assert sorted(asked) == [("left", left.timestamp_s), ("right", left.timestamp_s)]
    assert not np.array_equal(left.image, right.image)
    status = pair.status()
    assert status.left.frames == status.right.frames == 1 and status.left.last_frame_s == left.timestamp_s
    only_right = pair.grab("right")
    assert list(only_right) == ["right"] and pair.status().left.frames == 1
    pair.close()


def test_status_is_readable_from_another_thread_during_a_grab(world, rover):
    # The medium-resolution render keeps the grab busy long enough to be watched.
    pair = make_pair(world, rover, settings=CameraSettings(resolution="medium"))
    grabbed: dict = {}
    worker = threading.Thread(target=lambda: grabbed.update(pair.grab(timeout_s=5.0)))
    states, slowest = set(), 0.0
    worker.start()
    while worker.is_alive():
        started = time.perf_counter()
        status = pair.status()
        slowest = max(slowest, time.perf_counter() - started)
        states.add((status.grabbing, status.left.state))
        time.sleep(0.002)
    worker.join()
    assert set(grabbed) == {"left", "right"}
    assert slowest < 0.05
    assert (True, "exposing") in states
    assert pair.status().left.state == "idle" and not pair.status().grabbing
    pair.close()


def test_reset_and_reinit_restore_the_defaults(world, rover, tmp_path):
    pair = make_pair(world, rover, clock=SimClock(100.0))
    changed = LOW.with_changes(exposure_us=900.0, gain_db=3.0, pixel_format="rgb8")
    pair.apply(changed)
    assert pair.camera("right").settings == changed
    pair.reinit()
    assert pair.camera("left").settings == pair.camera("right").settings == LOW
    pair.apply(changed)
    pair.reset()
    assert pair.camera("left").settings == pair.camera("right").settings == LOW
    pair.save_settings(tmp_path / "pair.json")
    pair.apply(changed)
    assert pair.load_settings(tmp_path / "pair.json") == LOW and pair.settings == LOW
    pair.close()


def test_exposure_and_gain_scale_the_brightness(world, rover):
    pair = make_pair(world, rover)
    means = {}
    for name, settings in {"base": LOW.with_changes(exposure_us=2000.0),
                           "long": LOW.with_changes(exposure_us=4000.0),
                           "gain": LOW.with_changes(exposure_us=2000.0, gain_db=20 * math.log10(2.0))}.items():
        pair.apply(settings)
        means[name] = float(pair.grab("left")["left"].image.mean())
    assert means["long"] / means["base"] == pytest.approx(2.0, rel=0.1)
    assert means["gain"] / means["base"] == pytest.approx(2.0, rel=0.1)
    pair.apply(LOW.with_changes(exposure_us=200_000.0))
    assert np.mean(pair.grab("left")["left"].image == 255) > 0.5     # overexposed: clipped at 255
    pair.apply(LOW.with_changes(auto_exposure=True, target_grey_level=60, exposure_us=50.0))
    frame = pair.grab("left")["left"]
    assert frame.image.mean() == pytest.approx(60, abs=4) and frame.exposure_us != 50.0
    pair.close()


def test_rgb8_is_tinted_and_white_balanced(world, rover):
    pair = make_pair(world, rover, settings=LOW.with_changes(pixel_format="rgb8"))
    image = pair.grab("left")["left"].image.astype(float)
    assert image.shape == (270, 480, 3)
    red, green, blue = image[..., 0].mean(), image[..., 1].mean(), image[..., 2].mean()
    assert red > green > blue          # reddish regolith
    pair.apply(pair.settings.with_changes(white_balance_blue=1.4))
    assert pair.grab("left")["left"].image[..., 2].mean() > 1.25 * blue
    pair.close()


def test_moving_the_sun_changes_the_image(world, rover):
    pair = make_pair(world, rover)
    original = world.sun
    try:
        before = pair.grab("left")["left"].image.astype(float)
        world.sun = Sun(azimuth_deg=original.azimuth_deg + 150.0, elevation_deg=12.0)
        after = pair.grab("left")["left"].image.astype(float)
    finally:
        world.sun = original
    again = pair.grab("left")["left"].image.astype(float)
    assert np.mean(np.abs(after - before)) > 5 * np.mean(np.abs(again - before))
    assert after.mean() < before.mean()        # a low sun lights the ground less and casts long shadows
    pair.close()


# --------------------------------------------------------------------------------------------
# Stereo depth from the emulated pair against the ray-cast truth
# --------------------------------------------------------------------------------------------

def _matrix(camera: Intrinsics) -> np.ndarray:
    return np.array([[camera.fx, 0.0, camera.cx], [0.0, camera.fy, camera.cy], [0.0, 0.0, 1.0]])


def _distortion(camera: Intrinsics) -> np.ndarray:
    return np.array([camera.k1, camera.k2, 0.0, 0.0, 0.0])


def rectify_and_match(left: EmulatedCamera, right: EmulatedCamera, frames):
    """Rectify with the pair's known calibration, run SGBM; return depth, the rectification
    rotation of the left camera and its new projection matrix."""
    cl, cr = left.intrinsics(), right.intrinsics()
    right_from_left = np.linalg.inv(right.pose_at(0.0)) @ left.pose_at(0.0)
    rotation, translation = right_from_left[:3, :3].copy(), right_from_left[:3, 3].reshape(3, 1).copy()
    size = (cl.width, cl.height)
    r1, r2, p1, p2, *_ = cv2.stereoRectify(_matrix(cl), _distortion(cl), _matrix(cr), _distortion(cr), size,
                                           rotation, translation, flags=cv2.CALIB_ZERO_DISPARITY, alpha=0)
    rectified = []
    for camera, frame, r, p in ((cl, frames["left"], r1, p1), (cr, frames["right"], r2, p2)):
        maps = cv2.initUndistortRectifyMap(_matrix(camera), _distortion(camera), r, p, size, cv2.CV_32FC1)
        rectified.append(cv2.remap(frame.image, *maps, cv2.INTER_LINEAR))
    focal, baseline = p1[0, 0], -p2[0, 3] / p2[0, 0]
    disparities = int(math.ceil(focal * baseline / 1.5 / 16)) * 16     # down to 1.5 m
    block = 5
    matcher = cv2.StereoSGBM_create(minDisparity=0, numDisparities=disparities, blockSize=block,
                                    P1=8 * block * block, P2=32 * block * block, uniquenessRatio=10,
                                    speckleWindowSize=100, speckleRange=2, disp12MaxDiff=1,
                                    mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY)
    disparity = matcher.compute(*rectified).astype(np.float32) / 16.0
    depth = np.where(disparity > 0, focal * baseline / np.maximum(disparity, 1e-6), np.nan)
    return depth, r1, p1


def test_stereo_depth_from_the_emulated_pair_matches_the_ray_cast_truth(world, rover):
    pair = make_pair(world, rover)
    frames = pair.grab()
    left = pair.camera("left")
    depth, r1, p1 = rectify_and_match(left, pair.camera("right"), frames)
    # Truth in the rectified left camera: same centre, rotated by the rectification.
    rectified_pose = left.pose_at(0.0).copy()
    rectified_pose[:3, :3] = rectified_pose[:3, :3] @ r1.T
    camera = left.intrinsics()
    truth = render(world, rectified_pose, Intrinsics(width=camera.width, height=camera.height, fx=p1[0, 0],
                                                        fy=p1[1, 1], cx=p1[0, 2], cy=p1[1, 2])).depth
    in_band = (truth >= 2.0) & (truth <= 6.0)
    valid = in_band & np.isfinite(depth)
    error = np.abs(depth[valid] - truth[valid])
    median, p90, share = float(np.median(error)), float(np.percentile(error, 90)), valid.sum() / in_band.sum()
    print(f"stereo depth error at 480x270, 2-6 m: median {median:.3f} m, p90 {p90:.3f} m, valid {share:.0%}")
    assert in_band.sum() > 0.5 * truth.size
    assert median < 0.03 and p90 < 0.15 and share > 0.7
    pair.close()


# --------------------------------------------------------------------------------------------
# The vmbpy backend against a fake vmbpy module
# --------------------------------------------------------------------------------------------

def test_missing_vmbpy_is_a_device_fault_naming_the_package(monkeypatch):
    monkeypatch.setitem(sys.modules, "vmbpy", None)    # makes `import vmbpy` raise ImportError
    camera = VimbaCamera("DEV_1")
    with pytest.raises(CameraError, match=r"camera \(id DEV_1\): the Python package 'vmbpy'.*pip install vmbpy"):
        camera.open()
    assert camera.status().state == "closed"


class FakeFeature:
    def __init__(self, camera, name, value, entries=(), value_range=(0, 1 << 30), increment=None):
        self.camera, self.name, self.value = camera, name, value
        self.entries, self.range, self.increment = entries, value_range, increment

    def get(self):
        return self.value

    def set(self, value):
        if self.entries and value not in self.entries:
            raise ValueError(f"{value!r} is not an entry of {self.name}")
        self.camera.writes.append((self.name, value))
        self.value = value

    def get_range(self):
        return self.range

    def get_increment(self):
        return self.increment

    def get_available_entries(self):
        return self.entries

    def run(self):
        self.camera.writes.append((self.name, "run"))


class FakeVimbaFrame:
    def __init__(self, image, timestamp):
        self.image, self.timestamp = image, timestamp

    def get_status(self):
        return "Complete"

    def get_pixel_format(self):
        return "Mono8"

    def as_numpy_ndarray(self):
        return self.image[..., None]

    def get_timestamp(self):
        return self.timestamp


class FakeVimbaCamera:
    """What vmbpy's Camera offers to our backend; frames come on pulses of an EmulatedTrigger
    when the camera streams with FrameStart triggered on Line1, as the hardware does."""

    def __init__(self, camera_id, trigger: EmulatedTrigger, exposure_name="ExposureTime"):
        self.camera_id, self.writes, self.handler, self.queued = camera_id, [], None, 0
        def feature(*args, **kwargs):
            return FakeFeature(self, *args, **kwargs)

        self.features = {f.name: f for f in [
            feature("SensorWidth", 1920), feature("SensorHeight", 1080),
            feature("BinningHorizontal", 1, value_range=(1, 8)), feature("BinningVertical", 1, value_range=(1, 8)),
            feature("Width", 1920, value_range=(8, 1920), increment=8),
            feature("Height", 1080, value_range=(8, 1080), increment=2),
            feature("OffsetX", 0, increment=8), feature("OffsetY", 0, increment=2),
            feature("PixelFormat", "Mono8", entries=("Mono8", "Mono12")),
            feature("TriggerSelector", "AcquisitionStart", entries=("FrameStart", "AcquisitionStart")),
            feature("TriggerSource", "Software", entries=("Line1", "Software")),
            feature("TriggerMode", "Off", entries=("On", "Off")),
            feature("AcquisitionMode", "Continuous", entries=("Continuous", "SingleFrame")),
            feature("ExposureAuto", "Off", entries=("Off", "Continuous")),
            feature(exposure_name, 5000.0), feature("GainAuto", "Off", entries=("Off", "Continuous")),
            feature("Gain", 0.0), feature("DeviceReset", None)]}
        trigger.connect(self._on_pulse)

    def get_id(self):
        return self.camera_id

    def __enter__(self):
        return self

    def __exit__(self, *exc_info):
        self.handler = None

    def get_feature_by_name(self, name):
        if name not in self.features:
            raise LookupError(f"feature {name} not found")   # vmbpy raises its VmbFeatureError
        return self.features[name]

    def is_streaming(self):
        return self.handler is not None

    def start_streaming(self, handler, buffer_count=5):
        self.handler = handler

    def stop_streaming(self):
        self.handler = None

    def queue_frame(self, frame):
        self.queued += 1

    def _on_pulse(self, at):
        f = self.features
        armed = (f["TriggerSelector"].value, f["TriggerSource"].value, f["TriggerMode"].value) == (
            "FrameStart", "Line1", "On")
        if self.handler is None or not armed:
            return
        image = np.full((f["Height"].value, f["Width"].value), 42, np.uint8)
        handler = self.handler
        threading.Thread(target=handler, args=(self, None, FakeVimbaFrame(image, 123456))).start()


def fake_vmbpy(cameras) -> types.ModuleType:
    module = types.ModuleType("vmbpy")

    class System:
        def __enter__(self):
            return self

        def __exit__(self, *exc_info):
            return None

        def get_all_cameras(self):
            return tuple(cameras)

        def get_camera_by_id(self, camera_id):
            for camera in cameras:
                if camera.camera_id == camera_id:
                    return camera
            raise LookupError(f"no camera {camera_id}")

    system = System()
    module.VmbSystem = types.SimpleNamespace(get_instance=lambda: system)
    module.FrameStatus = types.SimpleNamespace(Complete="Complete")
    module.PixelFormat = types.SimpleNamespace(Rgb8="Rgb8", Mono8="Mono8")
    return module


def test_vimba_backend_sets_the_trigger_and_features_and_grabs_on_a_pulse(monkeypatch):
    trigger = EmulatedTrigger(SimClock(1.0))
    devices = [FakeVimbaCamera("DEV_A", trigger),
               FakeVimbaCamera("DEV_B", trigger, exposure_name="ExposureTimeAbs")]
    monkeypatch.setitem(sys.modules, "vmbpy", fake_vmbpy(devices))
    from drivers.avt_vimba import vimba_stereo_pair
    pair = vimba_stereo_pair(trigger, default_settings=LOW.with_changes(exposure_us=2500.0, gain_db=2.0))
    pair.open()
    assert pair.ids() == ("DEV_A", "DEV_B")
    writes = devices[0].writes
    assert writes[:4] == [("TriggerSelector", "FrameStart"), ("TriggerSource", "Line1"), ("TriggerMode", "On"),
                          ("AcquisitionMode", "Continuous")]
    for expected in [("BinningHorizontal", 4), ("BinningVertical", 4), ("Width", 480), ("Height", 270),
                     ("PixelFormat", "Mono8"), ("ExposureAuto", "Off"), ("ExposureTime", 2500.0), ("Gain", 2.0)]:
        assert expected in writes
    assert ("ExposureTimeAbs", 2500.0) in devices[1].writes
    frames = pair.grab(timeout_s=2.0)
    assert frames["left"].image.shape == (270, 480) and frames["left"].device_timestamp == 123456
    assert frames["left"].trigger_time_s == frames["right"].trigger_time_s
    assert devices[0].queued == 1     # the buffer went back to the camera
    pair.apply(LOW.with_changes(resolution="high"))
    assert devices[0].features["Width"].value == 1440 and devices[0].features["Height"].value == 810
    assert (devices[0].features["OffsetX"].value, devices[0].features["OffsetY"].value) == (240, 134)
    with pytest.raises(CameraError, match=r"camera left \(id DEV_A\): offers no pixel format for rgb8 "
                                          r"\(it offers Mono8, Mono12\)"):
        pair.apply(LOW.with_changes(pixel_format="rgb8"))
    camera = pair.camera("right")
    camera.arm()
    with pytest.raises(CameraTimeout, match=r"camera right \(id DEV_B\): no frame within 0.05 s"):
        camera.wait_frame(0.05)
    pair.close()
