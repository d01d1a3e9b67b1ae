"""Time-of-flight camera: MESA Imaging SwissRanger SR4000, the interface every backend implements.

This file holds what both backends share:
- the errors (`Sr4000Error` and kin, DeviceFaults naming the device and what libmesasr said) and
  `Sr4000SettingsError` for refused values (key, value, what is allowed);
- the vocabulary of libMesaSR: `ModulationFrequency` (the `ModulationFrq` enum), `AcquireMode`
  (the `AM_*` bit flags), integration-time and distance encodings;
- `Sr4000Settings`, saved to and loaded from a `key = value` text file with defaults for missing
  keys, as the thesis' rvs-libtof did;
- `TofFrame` (one acquisition), `Sr4000Status` (a snapshot readable from any thread);
- `Sr4000`, the interface: open / settings / acquire / status, validation done once here, the
  backend only moves values to and from the device;
- the rvs-libtof behaviour written once over the interface: `wait_for_exposure`, `grab` (settle,
  average N frames, rejecting low-confidence and wrapped samples) and the false-colour previews.

Backends: `drivers.sr4000_mesasr.MesaSr4000` (ctypes over libmesasr.so) and
`drivers.sr4000_emulator.Sr4000Emulator` (renders the simulated world).

Frames: x, y, z are metres in the OpenCV camera frame (x right, y down, z forward along the optical
axis, origin at the optical centre); the real backend converts from MESA's own axes.
"""
from __future__ import annotations

import enum
import math
import threading
import warnings
from abc import ABC, abstractmethod
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from drivers.errors import DeviceFault, DeviceTimeout

ROWS = 144
COLS = 176
CODE_FULL_SCALE = 0xFFFF           # distance code of the non-ambiguity range; 0 means "no measurement"
AMPLITUDE_SATURATED = 0xFFFF       # amplitude of a saturated pixel (the signal clipped at full scale)
CONFIDENCE_FULL = 0xFFFF           # IT_CONF_MAP: 0xFFFF is the highest confidence


# --------------------------------------------------------------------------------------------
# Errors
# --------------------------------------------------------------------------------------------

class Sr4000Error(DeviceFault):
    """Any SR4000 fault. The message names the device, the libmesasr call and what it returned."""

    def __init__(self, detail: str, *, device: str = "sr4000", call: str | None = None,
                 returned: Any = None):
        self.detail, self.call, self.returned = detail, call, returned
        message = f"{device}: {detail}"
        if call is not None:
            message += f" ({call} returned {returned!r})" if returned is not None else f" ({call})"
        super().__init__(message, device=device)


class Sr4000Timeout(Sr4000Error, DeviceTimeout):
    """No frame within the configured timeout (e.g. a hardware trigger that never came)."""


class Sr4000NotAnswering(Sr4000Error):
    """SR_Acquire gave no frame: the camera stopped answering (unplugged, hung, or past its timeout).
    A fault of the device (ERR 503), not a step over a time limit."""


class Sr4000LibraryMissing(Sr4000Error):
    """libmesasr.so cannot be loaded, or lacks a function we need."""


class Sr4000NotFound(Sr4000Error):
    """No camera answered at the serial number or address asked for."""


class Sr4000SettingsError(ValueError):
    """A setting refused before anything reached the camera: names the key, the value and what is
    allowed. Bad input, not a device fault."""

    def __init__(self, key: str, value: Any, allowed: str, where: str | None = None):
        self.key, self.value, self.allowed = key, value, allowed
        prefix = f"{where}: " if where else ""
        super().__init__(f"{prefix}{key} = {value!r} refused; allowed: {allowed}")


# --------------------------------------------------------------------------------------------
# libMesaSR vocabulary
# --------------------------------------------------------------------------------------------

class ModulationFrequency(enum.IntEnum):
    """libMesaSR's `ModulationFrq` values the SR4000 accepts (definesSR.h numbering)."""

    MF_40MHz = 0
    MF_30MHz = 1
    MF_15MHz = 6
    MF_29MHz = 8
    MF_31MHz = 9
    MF_14_5MHz = 10
    MF_15_5MHz = 11

    @property
    def megahertz(self) -> float:
        return _MODULATION_TABLE[self][0]

    @property
    def non_ambiguity_range_m(self) -> float:
        """c / (2 f), as MESA rounds it; distance code 0xFFFF is this range, beyond it distances wrap."""
        return _MODULATION_TABLE[self][1]

    @property
    def calibrated(self) -> bool:
        """The SR4000 is calibrated at 30 or 15 MHz; other frequencies measure less accurately."""
        return self in (ModulationFrequency.MF_30MHz, ModulationFrequency.MF_15MHz)

    @property
    def label(self) -> str:
        return f"{self.megahertz:g}MHz"

    @classmethod
    def parse(cls, text: str | int) -> ModulationFrequency:
        """From a label ("30MHz", "14.5 MHz"), an enum name ("MF_30MHz") or the enum number."""
        if isinstance(text, ModulationFrequency):
            return text
        if isinstance(text, int) or str(text).strip().isdigit():
            return cls(int(text))
        cleaned = str(text).strip().replace(" ", "").upper()
        for member in cls:
            if cleaned in (member.name.upper(), member.label.upper()):
                return member
        raise ValueError(f"unknown modulation frequency {text!r}")


_MODULATION_TABLE = {
    ModulationFrequency.MF_40MHz: (40.0, 3.75),
    ModulationFrequency.MF_30MHz: (30.0, 5.0),
    ModulationFrequency.MF_15MHz: (15.0, 10.0),
    ModulationFrequency.MF_29MHz: (29.0, 5.17),
    ModulationFrequency.MF_31MHz: (31.0, 4.84),
    ModulationFrequency.MF_14_5MHz: (14.5, 10.34),
    ModulationFrequency.MF_15_5MHz: (15.5, 9.68),
}
MODULATION_CHOICES = ", ".join(f"{m.label} ({int(m)})" for m in ModulationFrequency)


def frequency_for_range(max_distance_m: float, calibrated_only: bool = True) -> ModulationFrequency:
    """The modulation whose non-ambiguity range is the shortest that still covers `max_distance_m`
    (the shorter the range, the finer the distance resolution). rvs-libtof's "by wanted maximum
    distance"; only the frequencies in the table are possible."""
    candidates = [m for m in ModulationFrequency if m.calibrated or not calibrated_only]
    covering = [m for m in candidates if m.non_ambiguity_range_m >= max_distance_m]
    if not math.isfinite(max_distance_m) or max_distance_m <= 0 or not covering:
        longest = max(m.non_ambiguity_range_m for m in candidates)
        raise Sr4000SettingsError("max_distance_m", max_distance_m, f"0 < distance <= {longest:g} m"
                                  + (" (calibrated frequencies only)" if calibrated_only else ""))
    return min(covering, key=lambda m: m.non_ambiguity_range_m)


class AcquireMode(enum.IntFlag):
    """`SR_SetMode` flags (definesSR.h `AcquireMode`)."""

    COR_FIX_PTRN = 0x01      # fixed-pattern-noise correction; always on
    MEDIAN = 0x04            # 3x3 median filter on distance
    TOGGLE_FRQ = 0x08        # SR3000 only: toggles 19/21 MHz each frame; no effect on an SR4000
    CONV_GRAY = 0x10         # amplitude scaled by distance^2 so it looks like a grey image
    SW_ANF = 0x20            # 7x7 software adaptive neighbourhood filter
    CONF_MAP = 0x100         # compute the confidence map
    HW_TRIGGER = 0x200       # wait for the hardware trigger (needs SW_TRIGGER too)
    SW_TRIGGER = 0x400       # light on only when a frame is asked for
    DENOISE_ANF = 0x800      # 5x5 hardware adaptive neighbourhood filter
    MEDIANCROSS = 0x1000     # 3x3 cross median (5 values)


SUGGESTED_MODE = (AcquireMode.COR_FIX_PTRN | AcquireMode.CONV_GRAY | AcquireMode.DENOISE_ANF
                  | AcquireMode.CONF_MAP)

# Settings' boolean keys and the flag each one sets.
MODE_KEYS: dict[str, AcquireMode] = {
    "median": AcquireMode.MEDIAN,
    "toggle_frequency": AcquireMode.TOGGLE_FRQ,
    "convert_gray": AcquireMode.CONV_GRAY,
    "software_anf": AcquireMode.SW_ANF,
    "confidence_map": AcquireMode.CONF_MAP,
    "hardware_trigger": AcquireMode.HW_TRIGGER,
    "software_trigger": AcquireMode.SW_TRIGGER,
    "denoise_anf": AcquireMode.DENOISE_ANF,
    "median_cross": AcquireMode.MEDIANCROSS,
}

AUTO_EXPOSURE_OFF = 255   # SR_SetAutoExposure's minIntTime value that turns auto exposure off


def integration_time_ms(register: int) -> float:
    """SR4000 integration time of register value n (0..255): 0.3 + 0.1 n ms."""
    return 0.3 + 0.1 * register


def integration_register(milliseconds: float) -> int:
    """Nearest register value for an integration time in ms, within 0..255."""
    return int(min(255, max(0, round((milliseconds - 0.3) / 0.1))))


# --------------------------------------------------------------------------------------------
# Settings
# --------------------------------------------------------------------------------------------

class Sr4000Settings(BaseModel):
    """What rvs-libtof's settings struct held, plus the correction modes as booleans.

    `integration_time` is the register value (0..255 -> 0.3 + 0.1 n ms); with auto exposure on it is
    only the starting point. Auto exposure follows SR_SetAutoExposure: the camera moves the
    integration time, within [auto_exposure_min, auto_exposure_max], until the amplitude histogram
    position above which `percent_over_pos` % of pixels lie reaches `desired_pos` (0..255).
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    amplitude_threshold: int = Field(0, ge=0, le=0xFFFF)
    modulation_frequency: ModulationFrequency = ModulationFrequency.MF_30MHz
    integration_time: int = Field(30, ge=0, le=255)
    auto_exposure: bool = True
    auto_exposure_min: int = Field(1, ge=0, le=254)
    auto_exposure_max: int = Field(150, ge=0, le=255)
    auto_exposure_percent_over_pos: int = Field(5, ge=0, le=100)
    auto_exposure_desired_pos: int = Field(70, ge=0, le=255)
    median: bool = False
    toggle_frequency: bool = False
    convert_gray: bool = True
    software_anf: bool = False
    confidence_map: bool = True
    hardware_trigger: bool = False
    software_trigger: bool = True
    denoise_anf: bool = True
    median_cross: bool = False
    timeout_ms: int = Field(1000, ge=1, le=600_000)

    @model_validator(mode="after")
    def _consistent(self) -> Sr4000Settings:
        if self.auto_exposure_min > self.auto_exposure_max:
            raise Sr4000SettingsError("auto_exposure_min", self.auto_exposure_min,
                                      f"<= auto_exposure_max ({self.auto_exposure_max})")
        if self.hardware_trigger and not self.software_trigger:
            raise Sr4000SettingsError("hardware_trigger", True, "only with software_trigger = true "
                                      "(AM_HW_TRIGGER needs AM_SW_TRIGGER)")
        return self

    # -- construction with precise errors ------------------------------------------------------
    @classmethod
    def checked(cls, where: str | None = None, **values: Any) -> Sr4000Settings:
        """Validate `values` (missing keys take defaults); refuse the first bad one by key."""
        unknown = sorted(set(values) - set(cls.model_fields))
        if unknown:
            raise Sr4000SettingsError(unknown[0], values[unknown[0]],
                                      "one of the keys " + ", ".join(cls.model_fields), where)
        if "modulation_frequency" in values:
            try:
                values["modulation_frequency"] = ModulationFrequency.parse(values["modulation_frequency"])
            except ValueError:
                raise Sr4000SettingsError("modulation_frequency", values["modulation_frequency"],
                                          MODULATION_CHOICES, where) from None
        try:
            return cls(**values)
        except ValidationError as exc:
            raise _settings_error(exc, where) from None

    def updated(self, **changes: Any) -> Sr4000Settings:
        """A copy with `changes` applied, validated like checked()."""
        return Sr4000Settings.checked(**{**self.model_dump(), **changes})

    # -- mode flags ----------------------------------------------------------------------------
    def mode_flags(self) -> AcquireMode:
        flags = AcquireMode.COR_FIX_PTRN
        for key, flag in MODE_KEYS.items():
            if getattr(self, key):
                flags |= flag
        return flags

    def with_mode_flags(self, flags: int) -> Sr4000Settings:
        known = sum(AcquireMode)
        if int(flags) & ~known or int(flags) < 0:
            raise Sr4000SettingsError("mode", hex(int(flags)), "an OR of the AM_* flags "
                                      + ", ".join(f"{f.name} {int(f):#x}" for f in AcquireMode))
        return self.updated(**{key: bool(int(flags) & flag) for key, flag in MODE_KEYS.items()})

    @property
    def non_ambiguity_range_m(self) -> float:
        return self.modulation_frequency.non_ambiguity_range_m

    # -- text file -----------------------------------------------------------------------------
    def to_text(self) -> str:
        lines = ["# SR4000 settings (RVS). key = value; '#' starts a comment; a missing key takes its",
                 "# default. Integration time n: 0..255 -> 0.3 + 0.1 n ms. Auto exposure: min..max",
                 "# integration time, percent_over_pos (0..100), desired_pos (0..255)."]
        for key, value in self.model_dump().items():
            text = value.label if isinstance(value, ModulationFrequency) else (
                str(value).lower() if isinstance(value, bool) else str(value))
            lines.append(f"{key} = {text:<10} # {_allowed_text(key)}")
        return "\n".join(lines) + "\n"

    def save(self, path: str | Path) -> Path:
        path = Path(path)
        path.write_text(self.to_text())
        return path

    @classmethod
    def from_text(cls, text: str, where: str = "settings") -> Sr4000Settings:
        """Parse `key = value` lines; errors name the file and line (`where:line`)."""
        values: dict[str, Any] = {}
        line_of: dict[str, int] = {}
        for number, raw in enumerate(text.splitlines(), start=1):
            line = raw.split("#", 1)[0].strip()
            if not line:
                continue
            if "=" not in line:
                raise Sr4000SettingsError(line, None, "lines of the form key = value",
                                          f"{where}:{number}")
            key, value = (part.strip() for part in line.split("=", 1))
            if key in values:
                raise Sr4000SettingsError(key, value, "each key once", f"{where}:{number}")
            values[key] = _parse_value(key, value, f"{where}:{number}")
            line_of[key] = number
        try:
            return cls.checked(**values)
        except Sr4000SettingsError as exc:
            line = f"{where}:{line_of[exc.key]}" if exc.key in line_of else where
            raise Sr4000SettingsError(exc.key, exc.value, exc.allowed, line) from None

    @classmethod
    def load(cls, path: str | Path) -> Sr4000Settings:
        """Read a settings file; missing keys take their defaults. A missing file is an error (use
        load_or_default for rvs-libtof's "defaults when there is no file")."""
        path = Path(path)
        return cls.from_text(path.read_text(), where=str(path))

    @classmethod
    def load_or_default(cls, path: str | Path) -> Sr4000Settings:
        path = Path(path)
        return cls.load(path) if path.exists() else cls()


def _allowed_text(key: str) -> str:
    if key == "modulation_frequency":
        return MODULATION_CHOICES
    info = Sr4000Settings.model_fields[key]
    if info.annotation is bool:
        return "true or false"
    low = next((m.ge for m in info.metadata if hasattr(m, "ge")), None)
    high = next((m.le for m in info.metadata if hasattr(m, "le")), None)
    text = f"integer {low}..{high}"
    if key == "integration_time":
        text += " (0.3 + 0.1 n ms)"
    if key == "auto_exposure_min":
        text += " and <= auto_exposure_max"
    return text


def _parse_value(key: str, text: str, where: str) -> Any:
    if key not in Sr4000Settings.model_fields:
        raise Sr4000SettingsError(key, text, "one of the keys " + ", ".join(Sr4000Settings.model_fields),
                                  where)
    if key == "modulation_frequency":
        return text
    annotation = Sr4000Settings.model_fields[key].annotation
    if annotation is bool:
        lowered = text.lower()
        if lowered not in ("true", "false", "1", "0", "yes", "no", "on", "off"):
            raise Sr4000SettingsError(key, text, "true or false", where)
        return lowered in ("true", "1", "yes", "on")
    try:
        return int(text, 0)
    except ValueError:
        raise Sr4000SettingsError(key, text, _allowed_text(key), where) from None


def _settings_error(exc: ValidationError, where: str | None) -> Sr4000SettingsError:
    error = exc.errors()[0]
    refused = error.get("ctx", {}).get("error")
    if isinstance(refused, Sr4000SettingsError):   # raised by a cross-field check
        return Sr4000SettingsError(refused.key, refused.value, refused.allowed, where)
    key = str(error["loc"][0]) if error["loc"] else "settings"
    return Sr4000SettingsError(key, error.get("input"), _allowed_text(key) if key in
                               Sr4000Settings.model_fields else error["msg"], where)


# --------------------------------------------------------------------------------------------
# Frames and status
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class TofFrame:
    """One acquisition, rows x cols (144 x 176 on an SR4000).

    distance    uint16 code, 0..0xFFFF over [0, non-ambiguity range]; 0 means no measurement (the
                amplitude threshold removed it). Metres: `distance_m()`.
    amplitude   uint16; `AMPLITUDE_SATURATED` marks saturated pixels. With AM_CONV_GRAY it is scaled
                by distance^2 (a grey-looking image), without it it is the raw signal amplitude.
    confidence  uint16, 0xFFFF most confident; None when AM_CONF_MAP is off.
    x, y, z     float32 metres in the OpenCV camera frame: x right, y down, z forward along the
                optical axis, origin at the optical centre. 0 where distance is 0 (as the camera).
    timestamp   seconds of the backend's clock at the middle of the exposure.
    """

    distance: np.ndarray
    amplitude: np.ndarray
    confidence: np.ndarray | None
    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    timestamp: float
    modulation_frequency: ModulationFrequency
    integration_time: int
    sequence: int = 0

    @property
    def shape(self) -> tuple[int, int]:
        return self.distance.shape

    @property
    def non_ambiguity_range_m(self) -> float:
        return self.modulation_frequency.non_ambiguity_range_m

    def distance_m(self) -> np.ndarray:
        """Radial distance in metres, float32; NaN where there is no measurement."""
        metres_per_code = np.float32(self.non_ambiguity_range_m / CODE_FULL_SCALE)
        metres = self.distance.astype(np.float32) * metres_per_code
        metres[self.distance == 0] = np.nan
        return metres

    def xyz(self) -> np.ndarray:
        """(rows, cols, 3) float32 camera-frame points."""
        return np.stack([self.x, self.y, self.z], axis=-1)

    @property
    def saturated(self) -> np.ndarray:
        return self.amplitude == AMPLITUDE_SATURATED


@dataclass(frozen=True)
class Sr4000Status:
    """A snapshot of the camera's state, as rvs-libtof's mutex-guarded status struct held it."""

    name: str
    state: str = "closed"              # closed | idle | busy
    serial: int | None = None
    trigger: str = "software"          # software | hardware | continuous
    auto_exposure: bool = True
    integration_time: int = 0
    modulation_frequency: ModulationFrequency = ModulationFrequency.MF_30MHz
    frames_acquired: int = 0
    last_timestamp: float | None = None
    last_error: str | None = None


class _StatusBoard:
    """The status behind its own lock: readable from any thread, even while a frame is acquired."""

    def __init__(self, name: str):
        self._lock = threading.Lock()
        self._status = Sr4000Status(name=name)

    def read(self) -> Sr4000Status:
        with self._lock:
            return self._status

    def update(self, **changes: Any) -> None:
        with self._lock:
            self._status = replace(self._status, **changes)

    def count_frame(self, frame: TofFrame) -> None:
        with self._lock:
            self._status = replace(self._status, frames_acquired=self._status.frames_acquired + 1,
                                   last_timestamp=frame.timestamp, last_error=None)


def _trigger_of(settings: Sr4000Settings) -> str:
    if settings.hardware_trigger:
        return "hardware"
    return "software" if settings.software_trigger else "continuous"


# --------------------------------------------------------------------------------------------
# The interface
# --------------------------------------------------------------------------------------------

class Sr4000(ABC):
    """An SR4000, real or emulated: libMesaSR's calls with validation done here, once.

    Thread-safe: one re-entrant lock covers each call to the device (so a settings change never
    lands in the middle of an acquisition); `status()` has its own lock and answers at once, even
    while acquire() runs in another thread.

    Backends implement the `_open`, `_close`, `_acquire`, `_write_*` and `_read_*` primitives.
    """

    def __init__(self, name: str, settings: Sr4000Settings | None = None):
        self.name = name
        self._settings = settings or Sr4000Settings()
        self._lock = threading.RLock()
        self._status = _StatusBoard(name)
        self._is_open = False
        self.rows, self.cols = ROWS, COLS
        self.serial: int | None = None
        self.version = ""

    # -- lifecycle -----------------------------------------------------------------------------
    def open(self) -> Sr4000:
        """Open the camera and send it every setting."""
        with self._lock:
            if self._is_open:
                return self
            self._open()
            self._is_open = True
            try:
                self._push(self._settings, full=True)
            except BaseException:
                self.close()
                raise
            self._status.update(state="idle", serial=self.serial, **self._status_fields())
            return self

    def close(self) -> None:
        with self._lock:
            if not self._is_open:
                return
            self._is_open = False
            self._status.update(state="closed")
            self._close()

    @property
    def is_open(self) -> bool:
        return self._is_open

    def __enter__(self) -> Sr4000:
        return self.open()

    def __exit__(self, *exc) -> None:
        self.close()

    # -- settings ------------------------------------------------------------------------------
    def settings(self) -> Sr4000Settings:
        """The settings in force; integration_time is the camera's current one (auto exposure
        moves it)."""
        with self._lock:
            if self._is_open:
                return self._settings.model_copy(update={"integration_time": self.integration_time()})
            return self._settings

    def apply(self, settings: Sr4000Settings) -> None:
        """Send every setting that differs from those in force."""
        self._change_to(settings)

    def set_integration_time(self, register: int) -> None:
        """0..255 -> 0.3 + 0.1 n ms. With auto exposure on, the camera moves it from there."""
        self._change(integration_time=register)

    def set_amplitude_threshold(self, threshold: int) -> None:
        """Distance is forced to 0 where the amplitude is below `threshold` (0..65535)."""
        self._change(amplitude_threshold=threshold)

    def set_modulation_frequency(self, frequency: ModulationFrequency | str | int) -> None:
        self._change(modulation_frequency=frequency)

    def set_max_distance(self, max_distance_m: float, calibrated_only: bool = True) -> ModulationFrequency:
        """Choose the modulation by the wanted maximum distance (see frequency_for_range)."""
        frequency = frequency_for_range(max_distance_m, calibrated_only)
        self.set_modulation_frequency(frequency)
        return frequency

    def set_auto_exposure(self, min_time: int, max_time: int, percent_over_pos: int,
                          desired_pos: int) -> None:
        """SR_SetAutoExposure; min_time = 255 turns auto exposure off (the others are then kept)."""
        if min_time == AUTO_EXPOSURE_OFF:
            self._change(auto_exposure=False)
            return
        self._change(auto_exposure=True, auto_exposure_min=min_time, auto_exposure_max=max_time,
                     auto_exposure_percent_over_pos=percent_over_pos,
                     auto_exposure_desired_pos=desired_pos)

    def set_mode(self, flags: int) -> None:
        """SR_SetMode with the AM_* flags; AM_COR_FIX_PTRN is always added."""
        with self._lock:
            self._change_to(self._settings.with_mode_flags(flags))

    def set_timeout(self, milliseconds: int) -> None:
        self._change(timeout_ms=milliseconds)

    def integration_time(self) -> int:
        """The integration-time register value in force now (SR_GetIntegrationTime)."""
        with self._lock:
            return self._read_integration_time() if self._is_open else self._settings.integration_time

    def mode(self) -> AcquireMode:
        """SR_GetMode."""
        with self._lock:
            return AcquireMode(self._read_mode()) if self._is_open else self._settings.mode_flags()

    def modulation_frequency(self) -> ModulationFrequency:
        return self._settings.modulation_frequency

    # -- acquisition and status ----------------------------------------------------------------
    def acquire(self) -> TofFrame:
        """Take one frame (SR_Acquire, the images, SR_CoordTrfFlt)."""
        with self._lock:
            if not self._is_open:
                raise Sr4000Error("not open: call open() first", device=self.name)
            self._status.update(state="busy")
            try:
                frame = self._acquire()
            except DeviceFault as exc:
                self._status.update(last_error=str(exc))
                raise
            finally:
                self._status.update(state="idle" if self._is_open else "closed")
            self._status.count_frame(frame)
            self._status.update(integration_time=self._read_integration_time())
            return frame

    def status(self) -> Sr4000Status:
        """A snapshot; never waits for the device."""
        return self._status.read()

    # -- plumbing ------------------------------------------------------------------------------
    def _change(self, **changes: Any) -> None:
        with self._lock:
            self._change_to(self._settings.updated(**changes))

    def _change_to(self, new: Sr4000Settings) -> None:
        with self._lock:
            if self._is_open:
                self._push(new, full=False)
            self._settings = new
            self._status.update(**self._status_fields())

    def _push(self, new: Sr4000Settings, full: bool) -> None:
        """Write what changed, in an order that makes sense to the camera: the frequency first,
        auto exposure before the integration time (so turning it off lets a fixed time stick)."""
        old = self._settings

        def changed(*keys: str) -> bool:
            return full or any(getattr(old, key) != getattr(new, key) for key in keys)

        if changed("modulation_frequency"):
            self._write_modulation_frequency(new.modulation_frequency)
        if changed("auto_exposure", "auto_exposure_min", "auto_exposure_max",
                   "auto_exposure_percent_over_pos", "auto_exposure_desired_pos"):
            if new.auto_exposure:
                self._write_auto_exposure(new.auto_exposure_min, new.auto_exposure_max,
                                          new.auto_exposure_percent_over_pos,
                                          new.auto_exposure_desired_pos)
            else:
                self._write_auto_exposure(AUTO_EXPOSURE_OFF, 0, 0, 0)
        if changed("integration_time"):
            self._write_integration_time(new.integration_time)
        if changed("amplitude_threshold"):
            self._write_amplitude_threshold(new.amplitude_threshold)
        if full or old.mode_flags() != new.mode_flags():
            self._write_mode(new.mode_flags())
        if changed("timeout_ms"):
            self._write_timeout(new.timeout_ms)

    def _status_fields(self) -> dict[str, Any]:
        s = self._settings
        return {"trigger": _trigger_of(s), "auto_exposure": s.auto_exposure,
                "modulation_frequency": s.modulation_frequency,
                "integration_time": self._read_integration_time() if self._is_open else s.integration_time}

    # -- backend primitives --------------------------------------------------------------------
    @abstractmethod
    def _open(self) -> None:
        """Connect; set rows, cols, serial and version."""

    @abstractmethod
    def _close(self) -> None: ...

    @abstractmethod
    def _acquire(self) -> TofFrame: ...

    @abstractmethod
    def _write_integration_time(self, register: int) -> None: ...

    @abstractmethod
    def _write_amplitude_threshold(self, threshold: int) -> None: ...

    @abstractmethod
    def _write_modulation_frequency(self, frequency: ModulationFrequency) -> None: ...

    @abstractmethod
    def _write_auto_exposure(self, min_time: int, max_time: int, percent_over_pos: int,
                             desired_pos: int) -> None: ...

    @abstractmethod
    def _write_mode(self, flags: AcquireMode) -> None: ...

    @abstractmethod
    def _write_timeout(self, milliseconds: int) -> None: ...

    @abstractmethod
    def _read_integration_time(self) -> int: ...

    @abstractmethod
    def _read_mode(self) -> int: ...


# --------------------------------------------------------------------------------------------
# rvs-libtof behaviour over the interface
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class GrabResult:
    """Averaged frame and how it was made.

    frame.distance / x / y / z: the mean over the valid samples of each pixel; undefined pixels
    (fewer than `min_valid` valid samples) have distance 0 and NaN x, y, z. frame.amplitude and
    frame.confidence: the mean over all frames. valid_count: valid samples per pixel (uint16).
    """

    frame: TofFrame
    valid_count: np.ndarray
    frames: int
    settled: bool
    settle_frames: int
    defined: np.ndarray = field(repr=False)   # bool: the pixel has a value


def wait_for_exposure(camera: Sr4000, max_frames: int = 10) -> tuple[bool, int]:
    """Acquire (and drop) frames until auto exposure stops moving the integration time.

    The camera changes the integration time only when it acquires, so frames are taken until two
    in a row leave it unchanged, at most `max_frames`. Returns (settled, frames used); with auto
    exposure off it returns (True, 0) at once.
    """
    if not camera.settings().auto_exposure:
        return True, 0
    previous = camera.integration_time()
    for used in range(1, max_frames + 1):
        camera.acquire()
        current = camera.integration_time()
        if current == previous:
            return True, used
        previous = current
    return False, max_frames


def grab(camera: Sr4000, frames: int = 1, min_confidence: int = 0, settle_frames: int = 10,
         min_valid: int = 1) -> GrabResult:
    """rvs-libtof's acquisition: wait for auto exposure (at most `settle_frames` frames), then average
    `frames` frames per pixel, dropping samples with no distance, saturated samples, samples with
    confidence below `min_confidence` (0..65535), and samples more than a quarter of the
    non-ambiguity range from the pixel's median (a reading that wrapped: averaging 4.98 m with
    0.02 m would give a point that is nowhere)."""
    if frames < 1 or min_valid < 1 or min_valid > frames:
        raise ValueError(f"need frames >= 1 and 1 <= min_valid <= frames; got frames={frames}, "
                         f"min_valid={min_valid}")
    if not 0 <= min_confidence <= CONFIDENCE_FULL:
        raise ValueError(f"min_confidence {min_confidence} outside 0..{CONFIDENCE_FULL}")
    settled, used = wait_for_exposure(camera, settle_frames)
    taken = []
    for _ in range(frames):
        frame = camera.acquire()
        if min_confidence > 0 and frame.confidence is None:
            raise Sr4000Error("min_confidence needs the confidence map: turn on confidence_map "
                              "(AM_CONF_MAP) or grab with min_confidence=0", device=camera.name)
        taken.append(frame)
    return _average(taken, min_confidence, min_valid, settled, used)


def _average(frames: list[TofFrame], min_confidence: int, min_valid: int, settled: bool,
             settle_frames: int) -> GrabResult:
    distance = np.stack([f.distance for f in frames]).astype(np.float64)
    valid = (distance > 0) & ~np.stack([f.saturated for f in frames])
    if min_confidence > 0:
        valid &= np.stack([f.confidence for f in frames]) >= min_confidence
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)          # all-NaN pixels: no valid sample
        median = np.nanmedian(np.where(valid, distance, np.nan), axis=0)
    valid &= np.abs(distance - median) <= CODE_FULL_SCALE / 4
    count = valid.sum(axis=0).astype(np.uint16)
    defined = count >= min_valid
    safe_count = np.maximum(count, 1)
    mean_code = np.where(defined, np.rint((distance * valid).sum(axis=0) / safe_count), 0).astype(np.uint16)
    xyz = np.stack([f.xyz() for f in frames]).astype(np.float64)
    mean_xyz = (xyz * valid[..., None]).sum(axis=0) / safe_count[..., None]
    mean_xyz = np.where(defined[..., None], mean_xyz, np.nan).astype(np.float32)
    confidence = (None if any(f.confidence is None for f in frames) else
                  np.rint(np.mean([f.confidence for f in frames], axis=0)).astype(np.uint16))
    last = frames[-1]
    averaged = TofFrame(distance=mean_code,
                        amplitude=np.rint(np.mean([f.amplitude for f in frames], axis=0)).astype(np.uint16),
                        confidence=confidence, x=mean_xyz[..., 0], y=mean_xyz[..., 1], z=mean_xyz[..., 2],
                        timestamp=float(np.mean([f.timestamp for f in frames])),
                        modulation_frequency=last.modulation_frequency,
                        integration_time=last.integration_time, sequence=last.sequence)
    return GrabResult(frame=averaged, valid_count=count, frames=len(frames), settled=settled,
                      settle_frames=settle_frames, defined=defined)


# --------------------------------------------------------------------------------------------
# False-colour previews
# --------------------------------------------------------------------------------------------

# rvs-libtof's ramp: dark blue, blue, green, yellow, red, dark red, evenly spread over [low, high].
COLOUR_RAMP = np.array([[0, 0, 128], [0, 0, 255], [0, 255, 0], [255, 255, 0], [255, 0, 0], [128, 0, 0]],
                       dtype=np.float64)
UNDEFINED_RGB = (0, 0, 0)
AMPLITUDE_PREVIEW_MAX = 0x8000


def false_colour(values: np.ndarray, low: float, high: float,
                 undefined: np.ndarray | None = None) -> np.ndarray:
    """RGB uint8 (..., 3): values <= low dark blue, >= high dark red, evenly through blue, green,
    yellow and red in between; NaN and `undefined` pixels black."""
    if not high > low:
        raise ValueError(f"colour range needs high > low, got {low}..{high}")
    values = np.asarray(values, dtype=np.float64)
    position = np.clip((values - low) / (high - low), 0.0, 1.0) * (len(COLOUR_RAMP) - 1)
    position = np.nan_to_num(position, nan=0.0)
    stops = np.arange(len(COLOUR_RAMP))
    rgb = np.stack([np.interp(position, stops, COLOUR_RAMP[:, channel]) for channel in range(3)], axis=-1)
    rgb = np.rint(rgb).astype(np.uint8)
    blank = np.isnan(values) if undefined is None else (np.isnan(values) | undefined)
    rgb[blank] = UNDEFINED_RGB
    return rgb


def grey_scale(values: np.ndarray, low: float, high: float) -> np.ndarray:
    """uint8: low and below black, high and above white, linear between; NaN black."""
    if not high > low:
        raise ValueError(f"grey range needs high > low, got {low}..{high}")
    scaled = np.clip((np.asarray(values, np.float64) - low) / (high - low), 0.0, 1.0) * 255.0
    return np.rint(np.nan_to_num(scaled, nan=0.0)).astype(np.uint8)


def preview(frame: TofFrame, image: str = "distance", low: float | None = None,
            high: float | None = None) -> np.ndarray:
    """False-colour RGB of one of the frame's images, with these default ranges:
    distance   0 .. non-ambiguity range, metres; pixels with no measurement black
    amplitude  0 .. AMPLITUDE_PREVIEW_MAX (0x8000) counts; saturated pixels white
    confidence 0 .. 0xFFFF
    """
    if image == "distance":
        return false_colour(frame.distance_m(), 0.0 if low is None else low,
                            frame.non_ambiguity_range_m if high is None else high)
    if image == "amplitude":
        rgb = false_colour(frame.amplitude, 0.0 if low is None else low,
                           AMPLITUDE_PREVIEW_MAX if high is None else high)
        rgb[frame.saturated] = (255, 255, 255)
        return rgb
    if image == "confidence":
        if frame.confidence is None:
            raise ValueError("this frame has no confidence map (AM_CONF_MAP was off)")
        return false_colour(frame.confidence, 0.0 if low is None else low,
                            CONFIDENCE_FULL if high is None else high)
    raise ValueError(f"image must be distance, amplitude or confidence, not {image!r}")
