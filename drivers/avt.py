"""Stereo camera pair: Allied Vision cameras on a hardware trigger, real (vmbpy) or emulated.

What the thesis' wrapper (rvs-libcam-avt) offered, kept here:
- left/right identities (first camera found = left; `ids()`, `set_ids()`, `swap_ids()`);
- `reset()` (full hardware reset, then defaults) and `reinit()` (defaults only);
- `status()`, readable from any thread while a grab runs;
- resolution modes low/medium/high/highest, pixel formats mono8 and rgb8, exposure, gain, white
  balance and target grey level, saved to and loaded from a file (all of them: the thesis' UniAPI
  lost the target grey level on save);
- `grab("left" | "right" | "both")`: arm the cameras, one pulse of the trigger box, wait for a frame
  from each camera, so both images are exposed at the same instant.

This file holds the settings (`CameraSettings`), the errors, `Camera` (the interface), `Frame`,
`StereoCameras` (the pair on top of any two cameras and a trigger box), and two backends:

- `VimbaCamera`: current Allied Vision GigE / USB3 cameras (Alvium, Mako, Manta) through `vmbpy`,
  the Python API of Vimba X (pip name `vmbpy`; an optional extra, imported only when a camera is
  opened). The thesis' PIKE F-210B cameras are IEEE 1394b FireWire cameras: Vimba X and vmbpy do
  NOT support them (FireWire is not GenICam). They are reached through IIDC / libdc1394 (Debian
  libdc1394-25, libdc1394-dev), which this backend does not cover.
- `EmulatedCamera`: renders the simulated world (drivers.sim.render) from the camera's true pose
  at the instant of each trigger pulse, then applies exposure, gain, shot and read noise, and
  8-bit quantisation. Like the real camera in hardware-trigger mode it never makes a frame by
  itself. A frame carries the simulated time of its trigger pulse; rendering takes wall time, which
  never leaks into that timestamp.

Resolution modes on a W x H sensor (1920 x 1080 for the PIKE F-210B):
    low      4 x 4 binning, full field of view        480 x 270
    medium   2 x 2 binning, full field of view        960 x 540
    high     centred window of 3/4 W x 3/4 H, no      1440 x 810  (75 % of the field of view,
             binning                                                full detail)
    highest  the whole sensor                         1920 x 1080
"""
from __future__ import annotations

import contextlib
import importlib
import json
import logging
import queue
import threading
import time
import zlib
from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from drivers.errors import DeviceFault, DeviceTimeout
from drivers.sim.clock import SimClock
from drivers.sim.faults import FaultSwitch
from drivers.sim.render import PinholeCamera, render
from drivers.sim.world import World
from drivers.trigger import EmulatedTrigger, TriggerBox, TriggerStatus

log = logging.getLogger(__name__)

ResolutionMode = Literal["low", "medium", "high", "highest"]
PixelFormat = Literal["mono8", "rgb8"]
RESOLUTION_MODES: tuple[str, ...] = ("low", "medium", "high", "highest")
PIXEL_FORMATS: tuple[str, ...] = ("mono8", "rgb8")
ROLES: tuple[str, ...] = ("left", "right")
EXPOSURE_MIN_US, EXPOSURE_MAX_US = 10.0, 10_000_000.0

# Binning factor and the centred window's share of the sensor's width and height, per mode.
MODE_BINNING = {"low": 4, "medium": 2, "high": 1, "highest": 1}
MODE_WINDOW = {"low": 1.0, "medium": 1.0, "high": 0.75, "highest": 1.0}

# The thesis' camera: 1920 x 1080 pixels of 7.4 um (PIKE F-210B). The thesis names no lens; a
# 12 mm lens (61 degrees across) is assumed.
PIKE_F210B_SENSOR = PinholeCamera(width=1920, height=1080, fx=12.0 / 7.4e-3, fy=12.0 / 7.4e-3,
                                  cx=959.5, cy=539.5)


# --------------------------------------------------------------------------------------------
# Settings
# --------------------------------------------------------------------------------------------

class SettingsError(ValueError):
    """Camera settings refused: the message names each key, its value and what is allowed."""


class CameraSettings(BaseModel):
    """What a camera is set to. Any bad value is refused with a SettingsError.

    Build changed copies with `with_changes(...)` (it validates; pydantic's model_copy does not).
    White balance ratios (red and blue over green) only act on rgb8; the target grey level only
    with auto_exposure, where the camera picks the exposure that brings the image mean to it.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    resolution: ResolutionMode = "highest"
    pixel_format: PixelFormat = "mono8"
    exposure_us: float = Field(5000.0, ge=EXPOSURE_MIN_US, le=EXPOSURE_MAX_US)
    gain_db: float = Field(0.0, ge=0.0, le=24.0)
    auto_exposure: bool = False
    target_grey_level: int = Field(100, ge=1, le=254)
    white_balance_red: float = Field(1.0, ge=0.2, le=4.0)
    white_balance_blue: float = Field(1.0, ge=0.2, le=4.0)

    def __init__(self, **values):
        try:
            super().__init__(**values)
        except ValidationError as exc:
            raise SettingsError(_describe_validation(exc)) from None

    def with_changes(self, **changes) -> "CameraSettings":
        return CameraSettings(**{**self.model_dump(), **changes})

    def save(self, path: str | Path) -> Path:
        """Write every setting to a JSON file."""
        path = Path(path)
        path.write_text(json.dumps(self.model_dump(), indent=2) + "\n")
        return path

    @classmethod
    def load(cls, path: str | Path) -> "CameraSettings":
        """Read settings from a JSON file; keys the file lacks take their defaults."""
        path = Path(path)
        try:
            values = json.loads(path.read_text())
        except FileNotFoundError:
            raise SettingsError(f"camera settings file {path}: no such file") from None
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise SettingsError(f"camera settings file {path}: cannot read it as JSON: {exc}") from None
        if not isinstance(values, dict):
            raise SettingsError(f"camera settings file {path}: expected a JSON object of settings, "
                                f"got {type(values).__name__}")
        try:
            return cls(**values)
        except SettingsError as exc:
            raise SettingsError(f"camera settings file {path}: {exc}") from None


def _describe_validation(exc: ValidationError) -> str:
    """'key = value: what is allowed' for each refused value."""
    allowed_keys = ", ".join(CameraSettings.model_fields)
    parts = []
    for error in exc.errors():
        key = ".".join(str(part) for part in error["loc"]) or "settings"
        if error["type"] == "extra_forbidden":
            parts.append(f"unknown key {key!r} (allowed keys: {allowed_keys})")
        else:
            parts.append(f"{key} = {error.get('input')!r} is not allowed: {error['msg']}")
    return "camera settings: " + "; ".join(parts)


# --------------------------------------------------------------------------------------------
# Resolution modes and their intrinsics
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class ModeWindow:
    """How a resolution mode reads the sensor: binning, then a window in binned pixels."""

    binning: int
    width: int
    height: int
    offset_x: int
    offset_y: int


def mode_window(sensor_width: int, sensor_height: int, mode: str) -> ModeWindow:
    binning = MODE_BINNING[mode]
    binned_w, binned_h = sensor_width // binning, sensor_height // binning
    width = int(round(binned_w * MODE_WINDOW[mode]))
    height = int(round(binned_h * MODE_WINDOW[mode]))
    return ModeWindow(binning, width, height, (binned_w - width) // 2, (binned_h - height) // 2)


def mode_intrinsics(sensor: PinholeCamera, mode: str) -> PinholeCamera:
    """The pinhole model of a mode, from the full sensor's.

    Binned pixel u covers sensor pixels b*u .. b*u + b - 1, so its centre is at b*u + (b - 1)/2;
    a window shifts the principal point by its offset. Distortion (normalised) does not change.
    """
    window = mode_window(sensor.width, sensor.height, mode)
    b = window.binning
    return PinholeCamera(width=window.width, height=window.height, fx=sensor.fx / b, fy=sensor.fy / b,
                         cx=(sensor.cx - (b - 1) / 2) / b - window.offset_x,
                         cy=(sensor.cy - (b - 1) / 2) / b - window.offset_y, k1=sensor.k1, k2=sensor.k2)


def intrinsics_per_mode(sensor: PinholeCamera = PIKE_F210B_SENSOR) -> dict[str, PinholeCamera]:
    return {mode: mode_intrinsics(sensor, mode) for mode in RESOLUTION_MODES}


# --------------------------------------------------------------------------------------------
# Errors, frames, status
# --------------------------------------------------------------------------------------------

class CameraError(DeviceFault):
    """A camera fault; the message names the camera ("camera left (id ...)") and what it said."""

    def __init__(self, detail: str, *, device: str):
        self.detail = detail
        super().__init__(f"{device}: {detail}", device=device)


class CameraTimeout(CameraError, DeviceTimeout):
    """No frame arrived in time."""


@dataclass(frozen=True)
class Frame:
    """One image and where it came from.

    timestamp_s: when the exposure started, in clock seconds, as the backend knows it (the
        emulator: the simulated instant of the trigger pulse; vmbpy: the host time the frame
        arrived). trigger_time_s: the time of the grab's trigger pulse, set by StereoCameras.grab.
    """

    image: np.ndarray              # (h, w) uint8 for mono8, (h, w, 3) uint8 RGB for rgb8
    camera_id: str
    role: str | None
    timestamp_s: float
    frame_number: int
    resolution: str
    pixel_format: str
    exposure_us: float
    gain_db: float
    trigger_time_s: float | None = None
    device_timestamp: int | None = None   # the camera's own tick count, where it gives one


@dataclass(frozen=True)
class CameraStatus:
    """A snapshot of one camera's state, safe to read from any thread.

    state: closed, idle, armed (waiting for a trigger), exposing (triggered, frame on its way),
    or error (the last operation failed; last_error says how).
    """

    camera_id: str
    role: str | None
    state: str
    trigger_mode: str
    resolution: str
    pixel_format: str
    exposure_us: float
    gain_db: float
    frames: int
    last_frame_s: float | None
    last_error: str | None

    @property
    def busy(self) -> bool:
        return self.state in ("armed", "exposing")


# --------------------------------------------------------------------------------------------
# The camera interface
# --------------------------------------------------------------------------------------------

class Camera(ABC):
    """One hardware-triggered camera.

    Use: open(); apply(settings); arm(); <trigger pulse>; wait_frame(timeout_s). A frame is made
    only by a trigger pulse that comes after arm(). status() never waits for a grab: it reads a
    snapshot under its own lock.
    """

    trigger_mode = "hardware"

    def __init__(self, camera_id: str, *, clock: SimClock | None, default_settings: CameraSettings | None):
        self.camera_id = camera_id
        self.role: str | None = None
        self.default_settings = default_settings or CameraSettings()
        self._clock = clock if clock is not None else SimClock(1.0)
        self._settings = self.default_settings
        self._status_lock = threading.Lock()
        self._state = "closed"
        self._frames = 0
        self._last_frame_s: float | None = None
        self._last_error: str | None = None

    @property
    def label(self) -> str:
        """How errors name the camera: 'camera left (id X)'."""
        return f"camera {self.role} (id {self.camera_id})" if self.role else f"camera (id {self.camera_id})"

    @property
    def settings(self) -> CameraSettings:
        return self._settings

    # -- what each backend does ---------------------------------------------------------------

    @abstractmethod
    def open(self) -> None: ...

    @abstractmethod
    def close(self) -> None: ...

    @abstractmethod
    def apply(self, settings: CameraSettings) -> None:
        """Set the camera to `settings` (all of them)."""

    @abstractmethod
    def reset(self) -> None:
        """Full hardware reset, then the default settings."""

    @abstractmethod
    def arm(self) -> None:
        """Get ready for one hardware-triggered frame; frames of earlier pulses are dropped."""

    @abstractmethod
    def disarm(self) -> None:
        """Cancel arm() (when the trigger could not be sent)."""

    @abstractmethod
    def wait_frame(self, timeout_s: float) -> Frame:
        """The frame of the pulse that followed arm(); CameraTimeout if none came in time."""

    # -- shared -------------------------------------------------------------------------------

    def reinit(self) -> None:
        """Write the default settings to the camera again (no reset)."""
        self.apply(self.default_settings)

    def status(self) -> CameraStatus:
        with self._status_lock:
            s = self._settings
            return CameraStatus(self.camera_id, self.role, self._state, self.trigger_mode, s.resolution,
                                s.pixel_format, s.exposure_us, s.gain_db, self._frames, self._last_frame_s,
                                self._last_error)

    def __enter__(self) -> "Camera":
        self.open()
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    def _set_state(self, state: str, error: str | None = None) -> None:
        with self._status_lock:
            self._state = state
            if error is not None:
                self._last_error = error

    def _count_frame(self, frame: Frame) -> None:
        with self._status_lock:
            self._state = "idle"
            self._frames += 1
            self._last_frame_s = frame.timestamp_s
            self._last_error = None

    def _fault(self, detail: str) -> CameraError:
        self._set_state("error", detail)
        return CameraError(detail, device=self.label)

    def not_answering(self, detail: str) -> CameraError:
        """The pair found this camera silent where another answered: a fault of the camera."""
        return self._fault(f"stopped answering: {detail}")

    def _timeout(self, detail: str) -> CameraTimeout:
        self._set_state("idle", detail)
        return CameraTimeout(detail, device=self.label)

    def _require_open(self) -> None:
        with self._status_lock:
            closed = self._state == "closed"
        if closed:
            raise CameraError("not open: call open() first", device=self.label)


# --------------------------------------------------------------------------------------------
# The stereo pair
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class StereoStatus:
    left: CameraStatus
    right: CameraStatus
    trigger: TriggerStatus
    grabbing: bool


class StereoCameras:
    """Two cameras as left and right, one trigger box, and synchronous grabs.

    `cameras` are in the order they were found: the first is left, the second right, as in the
    thesis; set_ids() may pick any two of them. Settings are applied to both cameras.
    """

    def __init__(self, cameras: Sequence[Camera], trigger: TriggerBox,
                 default_settings: CameraSettings | None = None):
        if len(cameras) < 2:
            found = ", ".join(c.camera_id for c in cameras) or "none"
            raise DeviceFault(f"stereo cameras: need two cameras, found {len(cameras)} ({found})",
                              device="stereo cameras")
        self._cameras = {camera.camera_id: camera for camera in cameras}
        self.trigger = trigger
        self._grab_lock = threading.Lock()   # one grab at a time; status() does not take it
        self._grabbing = threading.Event()
        self._roles: dict[str, Camera] = {}
        self._is_open = False
        if default_settings is not None:
            for camera in cameras:
                camera.default_settings = default_settings
                camera.apply(default_settings)
        self.set_ids(cameras[0].camera_id, cameras[1].camera_id)

    # -- identities -----------------------------------------------------------------------------

    def ids(self) -> tuple[str, str]:
        """(left id, right id)."""
        return self._roles["left"].camera_id, self._roles["right"].camera_id

    def found_ids(self) -> list[str]:
        return list(self._cameras)

    def set_ids(self, left: str, right: str) -> None:
        for camera_id in (left, right):
            if camera_id not in self._cameras:
                raise ValueError(f"no camera with id {camera_id!r}; found: {', '.join(self._cameras)}")
        if left == right:
            raise ValueError(f"left and right must be two cameras, got {left!r} for both")
        with self._grab_lock:
            chosen = {"left": self._cameras[left], "right": self._cameras[right]}
            if self._is_open:   # the pair stays open: open the newcomers, close those left out
                for camera in chosen.values():
                    camera.open()
                for camera in self._roles.values():
                    if camera not in chosen.values():
                        camera.close()
            for camera in self._cameras.values():
                camera.role = None
            self._roles = chosen
            for role, camera in self._roles.items():
                camera.role = role

    def swap_ids(self) -> None:
        left, right = self.ids()
        self.set_ids(right, left)

    def camera(self, role: str) -> Camera:
        if role not in ROLES:
            raise ValueError(f"camera role must be one of {', '.join(ROLES)}, got {role!r}")
        return self._roles[role]

    # -- life cycle and settings ----------------------------------------------------------------

    def open(self) -> None:
        with self._grab_lock:
            self.trigger.open()
            for camera in self._roles.values():
                camera.open()
            self._is_open = True

    def close(self) -> None:
        with self._grab_lock:
            self._is_open = False
            try:
                for camera in self._roles.values():
                    camera.close()
            finally:
                self.trigger.close()

    def __enter__(self) -> "StereoCameras":
        self.open()
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    @property
    def settings(self) -> CameraSettings:
        return self._roles["left"].settings

    def apply(self, settings: CameraSettings) -> None:
        with self._grab_lock:
            for camera in self._roles.values():
                camera.apply(settings)

    def save_settings(self, path: str | Path) -> Path:
        return self.settings.save(path)

    def load_settings(self, path: str | Path) -> CameraSettings:
        settings = CameraSettings.load(path)
        self.apply(settings)
        return settings

    def reset(self) -> None:
        with self._grab_lock:
            for camera in self._roles.values():
                camera.reset()

    def reinit(self) -> None:
        with self._grab_lock:
            for camera in self._roles.values():
                camera.reinit()

    def status(self) -> StereoStatus:
        return StereoStatus(self._roles["left"].status(), self._roles["right"].status(), self.trigger.status(),
                            self._grabbing.is_set())

    # -- grabbing -------------------------------------------------------------------------------

    def grab(self, which: str = "both", timeout_s: float = 2.0) -> dict[str, Frame]:
        """Arm the chosen cameras, pulse the trigger box once, wait for each camera's frame.

        Returns {"left": Frame, "right": Frame} (or just the one asked for). Every frame carries
        the pulse's clock time as trigger_time_s.
        """
        roles = self._roles_for(which)
        with self._grab_lock:
            self._grabbing.set()
            try:
                cameras = {role: self._roles[role] for role in roles}
                for camera in cameras.values():
                    camera.arm()
                try:
                    pulse_time = self.trigger.pulse()
                except BaseException:
                    for camera in cameras.values():
                        camera.disarm()
                    raise
                return self._collect(cameras, pulse_time, timeout_s)
            finally:
                self._grabbing.clear()

    @staticmethod
    def _roles_for(which: str) -> tuple[str, ...]:
        if which == "both":
            return ROLES
        if which in ROLES:
            return (which,)
        raise ValueError(f"grab: which must be left, right or both, got {which!r}")

    def _collect(self, cameras: dict[str, Camera], pulse_time: float, timeout_s: float) -> dict[str, Frame]:
        """Wait for every camera, even after one failed, so no frame is left in flight."""
        frames: dict[str, Frame] = {}
        errors: dict[str, DeviceFault] = {}
        for role, camera in cameras.items():
            try:
                frames[role] = replace(camera.wait_frame(timeout_s), trigger_time_s=pulse_time)
            except DeviceFault as exc:
                errors[role] = exc
        if errors:
            raise self._culprit(cameras, frames, errors, pulse_time, timeout_s)
        return frames

    def _culprit(self, cameras: dict[str, Camera], frames: dict[str, Frame], errors: dict[str, DeviceFault],
                 pulse_time: float, timeout_s: float) -> DeviceFault:
        """Who failed a grab. A camera's own error names it. A camera can only time out alone, so
        the pair judges silence from the others: silent while another answered the same pulse, the
        camera stopped answering; every camera silent, the pulse never reached them, and the
        trigger box is at fault."""
        silent = [role for role, exc in errors.items() if isinstance(exc, CameraTimeout)]
        reported = [exc for role, exc in errors.items() if role not in silent]
        if reported:
            return reported[0]
        waited = f"waited {timeout_s:g} s"
        if frames:
            answered = " and ".join(f"camera {role}" for role in frames)
            return cameras[silent[0]].not_answering(f"no frame for the trigger pulse at {pulse_time:.3f} s that "
                                                    f"{answered} answered ({waited})")
        if len(silent) > 1:
            return self.trigger.unseen(pulse_time, f"{' and '.join(silent)} {waited}")
        return cameras[silent[0]].not_answering(f"no frame for the trigger pulse at {pulse_time:.3f} s ({waited}); "
                                                "a grab of both cameras tells the camera from the trigger box")


# --------------------------------------------------------------------------------------------
# The emulated camera
# --------------------------------------------------------------------------------------------

# Sensor model, after a Kodak KAI-2093-class interline CCD (the PIKE F-210B's): electrons per unit
# of rendered radiance per microsecond of exposure (a mid-grey scene gives ~92 DN at 5 ms, 0 dB),
# full well, read noise, and 8-bit conversion with the full well at 255 DN at 0 dB.
ELECTRONS_PER_RADIANCE_US = 8.0
FULL_WELL_E = 20_000.0
READ_NOISE_E = 15.0
DN_PER_ELECTRON = 255.0 / FULL_WELL_E
READOUT_S = 1.0 / 31.0                 # the PIKE F-210B's frame time at full resolution
EMULATED_RESET_S = 1.0                 # a reset re-enumerates the camera; it takes a moment
FRAME_WALL_LIMIT_S = 300.0             # how long a triggered frame may take to render (wall time)

# Colour of the regolith (rgb reflectance over grey reflectance): dust and bright soil are reddish,
# dark rock is nearly neutral.
DUST_TINT = np.array([1.25, 1.0, 0.72], dtype=np.float32)
DUST_TINT_FULL_ALBEDO = 0.35


@dataclass
class _Exposure:
    """One triggered frame on its way: set when the pulse arrives, filled in by the renderer."""

    armed_at: float
    triggered: threading.Event = field(default_factory=threading.Event)
    done: threading.Event = field(default_factory=threading.Event)
    trigger_time: float | None = None
    frame: Frame | None = None
    error: BaseException | None = None


Pose = Callable[[float], np.ndarray]


class EmulatedCamera(Camera):
    """A hardware-triggered camera looking at the simulated world.

    `pose(t)` gives the camera's true camera-to-world 4x4 (OpenCV axes) at simulated time t;
    `intrinsics` maps each resolution mode to its PinholeCamera (see intrinsics_per_mode). The
    camera connects itself to `trigger` (the cable); on a pulse after arm() it notes the instant,
    the pose and the sun at that instant, and renders in a thread of its own. `seed` makes the
    sensor noise repeatable (it is mixed with the camera's name and the frame number). `fault`
    (drivers/sim/faults.py) counts the frames asked of it; once tripped the camera ignores pulses.
    """

    trigger_mode = "hardware (emulated)"

    def __init__(self, name: str, world: World, pose: Pose, intrinsics: Mapping[str, PinholeCamera],
                 clock: SimClock, trigger: EmulatedTrigger, seed: int = 0, *,
                 default_settings: CameraSettings | None = None, fault: FaultSwitch | None = None):
        super().__init__(name, clock=clock, default_settings=default_settings)
        self._fault_switch = fault or FaultSwitch(name)   # each frame triggered while armed is one request
        missing = [mode for mode in RESOLUTION_MODES if mode not in intrinsics]
        if missing:
            raise ValueError(f"{self.label}: intrinsics lack resolution modes {', '.join(missing)}")
        self.world = world
        self._pose = pose
        self._intrinsics = dict(intrinsics)
        self._seed = seed
        self._lock = threading.Lock()           # arm/trigger hand-over
        self._exposure: _Exposure | None = None
        self._armed = False
        world.surface.scene   # build the ray-casting scene now, not in two render threads at once
        trigger.connect(self._on_trigger)

    def intrinsics(self, mode: str | None = None) -> PinholeCamera:
        """The pinhole model of a resolution mode (default: the current one)."""
        return self._intrinsics[mode or self.settings.resolution]

    def pose_at(self, t: float) -> np.ndarray:
        return np.asarray(self._pose(t), dtype=np.float64)

    # -- life cycle -----------------------------------------------------------------------------

    def open(self) -> None:
        with self._status_lock:
            if self._state == "closed":
                self._state = "idle"

    def close(self) -> None:
        self.disarm()
        self._set_state("closed")

    def apply(self, settings: CameraSettings) -> None:
        if not isinstance(settings, CameraSettings):
            raise TypeError(f"{self.label}: settings must be CameraSettings, got {type(settings).__name__}")
        with self._status_lock:
            self._settings = settings   # a frame already triggered keeps the settings it was exposed with

    def reset(self) -> None:
        """Re-enumerate: default settings, frame numbers from 1 again. A hung camera (injected
        fault) does not come back, as a real one is then not found after its reset."""
        self._require_open()
        self.disarm()
        self._set_state("idle")
        self._clock.sleep(EMULATED_RESET_S)
        if self._fault_switch.broken:
            raise self.not_answering(f"did not come back within {EMULATED_RESET_S:g} s of a reset")
        with self._status_lock:
            self._frames = 0
        self.reinit()

    # -- acquisition ----------------------------------------------------------------------------

    def arm(self) -> None:
        self._require_open()
        with self._lock:
            self._exposure = _Exposure(armed_at=self._clock.now())
            self._armed = True
            self._set_state("armed")

    def disarm(self) -> None:
        with self._lock:
            self._armed = False
            self._exposure = None
            with self._status_lock:
                if self._state in ("armed", "exposing"):
                    self._state = "idle"

    def set_frame_number(self, number: int) -> None:
        """Make the next frame `number` (and draw its noise), so a resumed acquisition repeats the
        frames an uninterrupted one would have taken."""
        with self._status_lock:
            self._frames = int(number) - 1

    def _on_trigger(self, at: float) -> None:
        """The trigger input: called by the trigger box at the pulse's simulated time."""
        with self._lock:
            if not self._armed or self._exposure is None:
                return      # not acquiring: the camera ignores the pulse
            if not self._fault_switch.answers():
                return      # hung (injected fault): no exposure, no frame, no word
            self._armed = False
            exposure = self._exposure
            exposure.trigger_time = at
            settings = self._settings
            with self._status_lock:   # lock order everywhere: _lock, then _status_lock
                frame_number = self._frames + 1
                self._state = "exposing"
        scene = _SceneAtPulse(self.pose_at(at), self.world.sun, self.intrinsics(settings.resolution))
        exposure.triggered.set()
        threading.Thread(target=self._develop, args=(exposure, scene, settings, frame_number),
                         name=f"render {self.camera_id}", daemon=True).start()

    def _develop(self, exposure: _Exposure, scene: "_SceneAtPulse", settings: CameraSettings,
                 frame_number: int) -> None:
        try:
            rng = np.random.default_rng([self._seed, zlib.crc32(self.camera_id.encode()), frame_number])
            image, exposure_us = expose_image(self.world, scene, settings, rng)
            exposure.frame = Frame(image=image, camera_id=self.camera_id, role=self.role,
                                   timestamp_s=exposure.trigger_time, frame_number=frame_number,
                                   resolution=settings.resolution, pixel_format=settings.pixel_format,
                                   exposure_us=exposure_us, gain_db=settings.gain_db)
        except BaseException as exc:   # handed to wait_frame, which raises it as a CameraError
            exposure.error = exc
        finally:
            exposure.done.set()

    def wait_frame(self, timeout_s: float) -> Frame:
        with self._lock:
            exposure = self._exposure
        if exposure is None:
            raise self._fault("not armed: call arm() before the trigger pulse")
        if not self._clock.wait(exposure.triggered, timeout_s):
            self.disarm()
            raise self._timeout(f"no frame within {timeout_s:g} s of arming: no trigger pulse arrived "
                                "(camera in hardware-trigger mode)")
        # Once triggered, the frame is on its way: rendering is the emulator's cost, not the camera's.
        if not exposure.done.wait(FRAME_WALL_LIMIT_S):
            raise self._fault(f"emulator did not finish rendering within {FRAME_WALL_LIMIT_S:g} s")
        with self._lock:
            if self._exposure is exposure:
                self._exposure = None
        if exposure.error is not None:
            raise self._fault(f"emulator failed to render the frame: {exposure.error!r}") from exposure.error
        frame = exposure.frame
        # The camera delivers no earlier than exposure plus read-out after the pulse.
        self._clock.sleep(frame.timestamp_s + frame.exposure_us * 1e-6 + READOUT_S - self._clock.now())
        self._count_frame(frame)
        return frame


@dataclass(frozen=True)
class _SceneAtPulse:
    """What a camera sees at the instant of a pulse: its pose, the sun, its intrinsics."""

    camera_to_world: np.ndarray
    sun: object
    camera: PinholeCamera


def expose_image(world: World, scene: _SceneAtPulse, settings: CameraSettings,
                 rng: np.random.Generator) -> tuple[np.ndarray, float]:
    """Render the scene and turn radiance into an 8-bit image; return it and the exposure used."""
    view = render(world, scene.camera_to_world, scene.camera, sun=scene.sun)
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


def emulated_stereo_pair(world: World, left_pose: Pose, right_pose: Pose, *, clock: SimClock,
                         trigger: EmulatedTrigger | None = None,
                         sensor: PinholeCamera = PIKE_F210B_SENSOR, seed: int = 0,
                         default_settings: CameraSettings | None = None,
                         ids: tuple[str, str] = ("emu-left", "emu-right"),
                         faults: Mapping[str, FaultSwitch] | None = None) -> StereoCameras:
    """Two emulated cameras on one emulated trigger box, left found first. `faults` holds the
    switches of "camera-left", "camera-right" (the cameras on the left and right mounts) and
    "trigger" (the emulated box made here), as the simulated test bed keeps them."""
    faults = faults or {}
    trigger = trigger or EmulatedTrigger(clock, fault=faults.get("trigger"))
    intrinsics = intrinsics_per_mode(sensor)
    cameras = [EmulatedCamera(camera_id, world, pose, intrinsics, clock, trigger, seed,
                              default_settings=default_settings, fault=faults.get(mount))
               for camera_id, pose, mount in zip(ids, (left_pose, right_pose), ("camera-left", "camera-right"))]
    return StereoCameras(cameras, trigger, default_settings)


# --------------------------------------------------------------------------------------------
# The real camera through vmbpy (Vimba X)
# --------------------------------------------------------------------------------------------

VMBPY_PACKAGE = "vmbpy"


def import_vmbpy(device: str = "camera"):
    """vmbpy, imported on first use, so the project runs without Vimba X installed."""
    try:
        return importlib.import_module(VMBPY_PACKAGE)
    except ImportError as exc:
        raise CameraError(f"the Python package '{VMBPY_PACKAGE}' (Allied Vision Vimba X) is not installed "
                          f"or cannot load its libraries: {exc}; install it with `pip install {VMBPY_PACKAGE}` "
                          "(FireWire cameras such as the PIKE F-210B need libdc1394 instead)",
                          device=device) from exc


def discover_vimba_cameras() -> list[str]:
    """Ids of the cameras Vimba X finds, in the order it lists them (the first becomes left)."""
    vmbpy = import_vmbpy("cameras")
    try:
        with vmbpy.VmbSystem.get_instance() as system:
            return [camera.get_id() for camera in system.get_all_cameras()]
    except Exception as exc:
        raise CameraError(f"cannot list cameras: {exc}", device="cameras (Vimba X)") from exc


def vimba_stereo_pair(trigger: TriggerBox, *, clock: SimClock | None = None,
                      default_settings: CameraSettings | None = None) -> StereoCameras:
    return StereoCameras([VimbaCamera(camera_id, clock=clock, default_settings=default_settings)
                          for camera_id in discover_vimba_cameras()], trigger, default_settings)


# GenICam feature names; older AVT GigE models use the *Abs names.
EXPOSURE_FEATURES = ("ExposureTime", "ExposureTimeAbs")
GAIN_FEATURES = ("Gain", "GainAbs")
BALANCE_FEATURES = ("BalanceRatio", "BalanceRatioAbs")
RGB_PIXEL_FORMATS = ("RGB8", "RGB8Packed")


class VimbaCamera(Camera):
    """A current Allied Vision camera (GigE / USB3) through vmbpy, on the hardware trigger.

    open() starts Vimba X, opens the camera and sets FrameStart triggered by Line1. arm() starts
    streaming (once) and drops frames of earlier pulses; each pulse then delivers one frame to the
    stream handler, which copies it into a queue that wait_frame() reads. Frame timestamps are the
    host clock time on arrival (the camera's own tick count is kept in device_timestamp).
    """

    trigger_mode = "hardware (FrameStart on Line1)"

    def __init__(self, camera_id: str, *, clock: SimClock | None = None,
                 default_settings: CameraSettings | None = None, buffer_count: int = 3,
                 reset_timeout_s: float = 30.0):
        super().__init__(camera_id, clock=clock, default_settings=default_settings)
        self._buffer_count = buffer_count
        self._reset_timeout_s = reset_timeout_s
        self._lock = threading.RLock()
        self._vmbpy = None
        self._stack: contextlib.ExitStack | None = None
        self._device = None
        self._frames_in: queue.Queue[Frame | CameraError] = queue.Queue()

    def __repr__(self) -> str:
        return f"VimbaCamera({self.camera_id!r}, role={self.role!r})"

    # -- life cycle -----------------------------------------------------------------------------

    def open(self) -> None:
        with self._lock:
            if self._device is not None:
                return
            self._vmbpy = import_vmbpy(self.label)
            stack = contextlib.ExitStack()
            try:
                with self._vimba("open the camera"):
                    system = stack.enter_context(self._vmbpy.VmbSystem.get_instance())
                    self._device = stack.enter_context(system.get_camera_by_id(self.camera_id))
                self._stack = stack
                self._set_state("idle")
                self._configure_trigger()
                self._write_settings(self._settings)
            except BaseException:
                self._device, self._stack = None, None
                stack.close()
                self._set_state("closed")
                raise

    def close(self) -> None:
        with self._lock:
            stack, self._stack = self._stack, None
            device, self._device = self._device, None
            try:
                if device is not None and device.is_streaming():
                    with self._vimba("stop streaming"):
                        device.stop_streaming()
            finally:
                if stack is not None:
                    stack.close()
                self._set_state("closed")

    def apply(self, settings: CameraSettings) -> None:
        if not isinstance(settings, CameraSettings):
            raise TypeError(f"{self.label}: settings must be CameraSettings, got {type(settings).__name__}")
        with self._lock:
            if self._device is not None:
                self._stop_streaming()    # size and format features are locked while streaming
                self._write_settings(settings)
            with self._status_lock:
                self._settings = settings

    def reset(self) -> None:
        """DeviceReset: the camera reboots and re-enumerates; wait for it, reopen, write defaults."""
        with self._lock:
            self._require_open()
            self._stop_streaming()
            with self._vimba("reset (DeviceReset)"):
                self._device.get_feature_by_name("DeviceReset").run()
            self.close()
            self._reopen_after_reset()
            self.reinit()

    def _reopen_after_reset(self) -> None:
        deadline = time.monotonic() + self._reset_timeout_s
        while True:
            self._clock.sleep(1.0)
            try:
                self.open()
                return
            except CameraError as exc:
                if time.monotonic() >= deadline:  # a camera that is not found is not answering: ERR 503
                    raise self.not_answering(f"did not come back within {self._reset_timeout_s:g} s of a "
                                             f"reset: {exc.detail}") from exc

    # -- acquisition ----------------------------------------------------------------------------

    def arm(self) -> None:
        with self._lock:
            self._require_open()
            self._drain()
            if not self._device.is_streaming():
                with self._vimba("start streaming"):
                    self._device.start_streaming(self._on_frame, buffer_count=self._buffer_count)
        self._set_state("armed")

    def disarm(self) -> None:
        self._drain()
        with self._status_lock:
            if self._state == "armed":
                self._state = "idle"

    def wait_frame(self, timeout_s: float) -> Frame:
        try:
            item = self._frames_in.get(timeout=timeout_s)
        except queue.Empty:
            raise self._timeout(f"no frame within {timeout_s:g} s of arming: did the trigger pulse reach "
                                "Line1?") from None
        if isinstance(item, CameraError):
            self._set_state("error", item.detail)
            raise item
        self._count_frame(item)
        return item

    def _on_frame(self, device, stream, vimba_frame) -> None:
        """vmbpy's stream handler (its own thread): copy the image out, give the buffer back."""
        try:
            status = vimba_frame.get_status()
            if status != self._vmbpy.FrameStatus.Complete:
                self._frames_in.put(CameraError(f"incomplete frame (status {status!r})", device=self.label))
                return
            image = self._image_of(vimba_frame)
            settings = self._settings
            self._frames_in.put(Frame(image=image, camera_id=self.camera_id, role=self.role,
                                      timestamp_s=self._clock.now(), frame_number=self._frames + 1,
                                      resolution=settings.resolution, pixel_format=settings.pixel_format,
                                      exposure_us=settings.exposure_us, gain_db=settings.gain_db,
                                      device_timestamp=vimba_frame.get_timestamp()))
        except Exception as exc:   # never let an exception die in vmbpy's thread unseen
            self._frames_in.put(CameraError(f"cannot read a frame: {exc}", device=self.label))
        finally:
            with contextlib.suppress(Exception):
                device.queue_frame(vimba_frame)

    def _image_of(self, vimba_frame) -> np.ndarray:
        """A copy of the frame's pixels (the buffer goes back to the camera), debayered for rgb8."""
        rgb8 = self._vmbpy.PixelFormat.Rgb8
        if self._settings.pixel_format == "rgb8" and vimba_frame.get_pixel_format() != rgb8:
            vimba_frame = vimba_frame.convert_pixel_format(rgb8)
        image = np.array(vimba_frame.as_numpy_ndarray(), copy=True)
        return image[..., 0] if image.ndim == 3 and image.shape[2] == 1 else image

    def _drain(self) -> None:
        while True:
            try:
                self._frames_in.get_nowait()
            except queue.Empty:
                return

    def _stop_streaming(self) -> None:
        if self._device is not None and self._device.is_streaming():
            with self._vimba("stop streaming"):
                self._device.stop_streaming()

    # -- features -------------------------------------------------------------------------------

    def _configure_trigger(self) -> None:
        self._set_feature("TriggerSelector", "FrameStart")
        self._set_feature("TriggerSource", "Line1")
        self._set_feature("TriggerMode", "On")
        self._set_feature("AcquisitionMode", "Continuous")

    def _write_settings(self, settings: CameraSettings) -> None:
        self._write_resolution(settings.resolution)
        self._write_pixel_format(settings.pixel_format)
        self._set_if_present("GainAuto", "Off")
        self._set_first(GAIN_FEATURES, settings.gain_db)
        if settings.auto_exposure:
            # GigE cameras take the target as a percentage of full scale.
            self._set_feature("ExposureAutoTarget", round(settings.target_grey_level * 100 / 255))
            self._set_feature("ExposureAuto", "Continuous")
        else:
            self._set_if_present("ExposureAuto", "Off")
            self._set_first(EXPOSURE_FEATURES, settings.exposure_us)
        if settings.pixel_format == "rgb8":
            self._write_white_balance(settings)

    def _write_resolution(self, mode: str) -> None:
        sensor_w = int(self._get_first(("SensorWidth", "WidthMax")))
        sensor_h = int(self._get_first(("SensorHeight", "HeightMax")))
        window = mode_window(sensor_w, sensor_h, mode)
        if window.binning > 1 or self._has_feature("BinningHorizontal"):
            self._set_feature("BinningHorizontal", window.binning)
            self._set_feature("BinningVertical", window.binning)
        # Offsets first to 0, so the new size always fits; then size, then the centring offsets.
        self._set_if_present("OffsetX", 0)
        self._set_if_present("OffsetY", 0)
        self._set_feature("Width", self._snapped("Width", window.width))
        self._set_feature("Height", self._snapped("Height", window.height))
        self._set_if_present("OffsetX", self._snapped("OffsetX", window.offset_x))
        self._set_if_present("OffsetY", self._snapped("OffsetY", window.offset_y))

    def _write_pixel_format(self, pixel_format: str) -> None:
        available = [str(entry) for entry in self._get_feature("PixelFormat").get_available_entries()]
        wanted = ("Mono8",) if pixel_format == "mono8" else RGB_PIXEL_FORMATS + ("BayerRG8", "BayerGB8",
                                                                                "BayerGR8", "BayerBG8")
        for name in wanted:
            if name in available:
                self._set_feature("PixelFormat", name)   # Bayer formats are converted on arrival
                return
        raise self._fault(f"offers no pixel format for {pixel_format} (it offers {', '.join(available)})")

    def _write_white_balance(self, settings: CameraSettings) -> None:
        if not self._has_feature("BalanceRatioSelector"):
            return
        self._set_if_present("BalanceWhiteAuto", "Off")
        for channel, ratio in (("Red", settings.white_balance_red), ("Blue", settings.white_balance_blue)):
            self._set_feature("BalanceRatioSelector", channel)
            self._set_first(BALANCE_FEATURES, ratio)

    def _snapped(self, name: str, value: int) -> int:
        """Round down to the feature's increment, as cameras accept sizes in steps (often 4 or 8)."""
        feature = self._get_feature(name)
        step = int(feature.get_increment() or 1)
        low = int(feature.get_range()[0])
        return max(low, low + (value - low) // step * step)

    def _has_feature(self, name: str) -> bool:
        try:
            self._device.get_feature_by_name(name)
            return True
        except Exception:
            return False

    def _get_feature(self, name: str):
        with self._vimba(f"read feature {name}"):
            return self._device.get_feature_by_name(name)

    def _get_first(self, names: Sequence[str]):
        for name in names:
            if self._has_feature(name):
                with self._vimba(f"read {name}"):
                    return self._device.get_feature_by_name(name).get()
        raise self._fault(f"has none of the features {', '.join(names)}")

    def _set_feature(self, name: str, value) -> None:
        with self._vimba(f"set {name} = {value!r}"):
            self._device.get_feature_by_name(name).set(value)

    def _set_if_present(self, name: str, value) -> None:
        if self._has_feature(name):
            self._set_feature(name, value)

    def _set_first(self, names: Sequence[str], value) -> None:
        for name in names:
            if self._has_feature(name):
                self._set_feature(name, value)
                return
        raise self._fault(f"has none of the features {', '.join(names)}")

    @contextlib.contextmanager
    def _vimba(self, what: str):
        """Turn whatever vmbpy raises into a CameraError naming the camera and the operation."""
        try:
            yield
        except CameraError:
            raise
        except Exception as exc:
            raise self._fault(f"cannot {what}: vmbpy said {type(exc).__name__}: {exc}") from exc
