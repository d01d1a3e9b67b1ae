"""Stereo camera pair: Allied Vision cameras on a hardware trigger; the interface every backend implements.

What the thesis' wrapper (rvs-libcam-avt) offered, kept here and in `drivers.avt_stereo`:
- left/right identities (first camera found = left; `ids()`, `set_ids()`, `swap_ids()`);
- `reset()` (full hardware reset, then defaults) and `reinit()` (defaults only);
- `status()`, readable from any thread while a grab runs;
- resolution modes low/medium/high/highest, pixel formats mono8 and rgb8, exposure, gain, white
  balance and target grey level, saved to and loaded from a file (all of them: the thesis' UniAPI
  lost the target grey level on save);
- `grab("left" | "right" | "both")`: arm the cameras, one pulse of the trigger box, wait for a frame
  from each camera, so both images are exposed at the same instant.

This file holds what every backend shares: the settings (`CameraSettings`, `SettingsError`), the
resolution modes and their intrinsics (`mode_window`, `mode_intrinsics`, `intrinsics_per_mode`), the
errors (`CameraError`, `CameraTimeout`), `Frame`, `CameraStatus` and `Camera` (the interface).

`drivers.avt_stereo.StereoCameras` is the pair on top of any two cameras and a trigger box. Backends:

- `drivers.avt_vimba.VimbaCamera`: current Allied Vision GigE / USB3 cameras (Alvium, Mako, Manta)
  through `vmbpy`, the Python API of Vimba X (pip name `vmbpy`; an optional extra, imported only
  when a camera is opened). The thesis' PIKE F-210B cameras are IEEE 1394b FireWire cameras: Vimba X
  and vmbpy do NOT support them (FireWire is not GenICam). They are reached through IIDC /
  libdc1394 (Debian libdc1394-25, libdc1394-dev), which this backend does not cover.
- `drivers.avt_emulator.EmulatedCamera`: renders the simulated world (drivers.sim.render) from the
  camera's true pose at the instant of each trigger pulse, then applies exposure, gain, shot and
  read noise, and 8-bit quantisation (the sensor model, `drivers.avt_sensor`). Like the real camera
  in hardware-trigger mode it never makes a frame by itself. A frame carries the simulated time of
  its trigger pulse; rendering takes wall time, which never leaks into that timestamp.

Resolution modes on a W x H sensor (1920 x 1080 for the PIKE F-210B):
    low      4 x 4 binning, full field of view        480 x 270
    medium   2 x 2 binning, full field of view        960 x 540
    high     centred window of 3/4 W x 3/4 H, no      1440 x 810  (75 % of the field of view,
             binning                                                full detail)
    highest  the whole sensor                         1920 x 1080
    narrow   2 x 2 binning, centred window of         360 x 405   (the middle 25 x 28 degrees at
             3/8 W x 3/4 H                                          medium's detail, as few pixels
                                                                    as low: a target the PTU keeps
                                                                    in the middle, such as a walker
                                                                    being tracked)
"""
from __future__ import annotations

import json
import logging
import threading
from abc import ABC, abstractmethod
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from drivers.errors import DeviceFault, DeviceTimeout
from drivers.sim.clock import SimClock
from toolbox.camera import Intrinsics

log = logging.getLogger(__name__)

ResolutionMode = Literal["low", "medium", "high", "highest", "narrow"]
PixelFormat = Literal["mono8", "rgb8"]
RESOLUTION_MODES: tuple[str, ...] = ("low", "medium", "high", "highest", "narrow")
PIXEL_FORMATS: tuple[str, ...] = ("mono8", "rgb8")
ROLES: tuple[str, ...] = ("left", "right")
EXPOSURE_MIN_US, EXPOSURE_MAX_US = 10.0, 10_000_000.0

# Binning factor and the centred window's share of the sensor's (width, height), per mode.
MODE_BINNING = {"low": 4, "medium": 2, "high": 1, "highest": 1, "narrow": 2}
MODE_WINDOW = {"low": (1.0, 1.0), "medium": (1.0, 1.0), "high": (0.75, 0.75), "highest": (1.0, 1.0),
               "narrow": (0.375, 0.75)}

# The thesis' camera: 1920 x 1080 pixels of 7.4 um (PIKE F-210B). The thesis names no lens; a
# 12 mm lens (61 degrees across) is assumed.
PIKE_F210B_SENSOR = Intrinsics(width=1920, height=1080, fx=12.0 / 7.4e-3, fy=12.0 / 7.4e-3,
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

    def with_changes(self, **changes) -> CameraSettings:
        return CameraSettings(**{**self.model_dump(), **changes})

    def save(self, path: str | Path) -> Path:
        """Write every setting to a JSON file."""
        path = Path(path)
        path.write_text(json.dumps(self.model_dump(), indent=2) + "\n")
        return path

    @classmethod
    def load(cls, path: str | Path) -> CameraSettings:
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
    share_w, share_h = MODE_WINDOW[mode]
    width, height = int(round(binned_w * share_w)), int(round(binned_h * share_h))
    return ModeWindow(binning, width, height, (binned_w - width) // 2, (binned_h - height) // 2)


def mode_intrinsics(sensor: Intrinsics, mode: str) -> Intrinsics:
    """The pinhole model of a mode, from the full sensor's.

    Binned pixel u covers sensor pixels b*u .. b*u + b - 1, so its centre is at b*u + (b - 1)/2;
    a window shifts the principal point by its offset. Distortion (normalised) does not change.
    """
    window = mode_window(sensor.width, sensor.height, mode)
    b = window.binning
    return Intrinsics(width=window.width, height=window.height, fx=sensor.fx / b, fy=sensor.fy / b,
                         cx=(sensor.cx - (b - 1) / 2) / b - window.offset_x,
                         cy=(sensor.cy - (b - 1) / 2) / b - window.offset_y, k1=sensor.k1, k2=sensor.k2)


def intrinsics_per_mode(sensor: Intrinsics = PIKE_F210B_SENSOR) -> dict[str, Intrinsics]:
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

    def __enter__(self) -> Camera:
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
