"""The real SR4000 backend: ctypes over MESA Imaging's libmesasr.so.

The library is loaded when a camera is opened, not when this module is imported, so machines
without it (CI, the emulated test bed) never need it. Every function used has its argtypes and
restype declared from libMesaSR.h / definesSR.h; `library` points at another build (the tests use
a fake compiled from tests/drivers/fakes/fake_mesasr.c).

Axes: SR_CoordTrfFlt gives metres in MESA's camera frame, X to the left, Y up, Z forward along the
optical axis (MRPT's CSwissRanger3DCamera maps it so). We turn it into the OpenCV frame of
TofFrame: x = -X, y = -Y, z = Z, a half turn about the optical axis.
"""
from __future__ import annotations

import ctypes
import logging
import threading

import numpy as np

from drivers.sim.clock import SimClock
from drivers.sr4000 import (
    AcquireMode,
    ModulationFrequency,
    Sr4000,
    Sr4000Error,
    Sr4000LibraryMissing,
    Sr4000NotAnswering,
    Sr4000NotFound,
    Sr4000Settings,
    TofFrame,
    integration_time_ms,
)

log = logging.getLogger(__name__)

DEFAULT_LIBRARY = "libmesasr.so"
INSTALL_HINT = ("install MESA Imaging's libmesasr Debian package (libmesasr-dev-*.deb, from the "
                "SR4000 driver CD or MESA's support site), which puts libmesasr.so in /usr/lib, or "
                "give its path as `library` in the device configuration")

# ImgEntry::ImgType and ImgEntry::DataType values we read.
IT_DISTANCE, IT_AMPLITUDE, IT_CONF_MAP = 0, 1, 8
DT_USHORT = 3


class ImgEntry(ctypes.Structure):
    """definesSR.h `ImgEntry`: {enum imgType; enum dataType; void* data; ushort width, height}."""

    _fields_ = [("imgType", ctypes.c_int), ("dataType", ctypes.c_int), ("data", ctypes.c_void_p),
                ("width", ctypes.c_ushort), ("height", ctypes.c_ushort)]


_SRCAM = ctypes.c_void_p
_FLOAT_P = ctypes.POINTER(ctypes.c_float)
_U8 = ctypes.c_ubyte

# name: (restype, argtypes), from libMesaSR.h.
SIGNATURES: dict[str, tuple[object, list[object]]] = {
    "SR_OpenUSB": (ctypes.c_int, [ctypes.POINTER(_SRCAM), ctypes.c_uint]),
    "SR_OpenETH": (ctypes.c_int, [ctypes.POINTER(_SRCAM), ctypes.c_char_p]),
    "SR_Close": (ctypes.c_int, [_SRCAM]),
    "SR_Acquire": (ctypes.c_int, [_SRCAM]),
    "SR_GetImageList": (ctypes.c_int, [_SRCAM, ctypes.POINTER(ctypes.POINTER(ImgEntry))]),
    "SR_GetImage": (ctypes.c_void_p, [_SRCAM, _U8]),
    "SR_CoordTrfFlt": (ctypes.c_int, [_SRCAM, _FLOAT_P, _FLOAT_P, _FLOAT_P,
                                      ctypes.c_int, ctypes.c_int, ctypes.c_int]),
    "SR_SetIntegrationTime": (ctypes.c_int, [_SRCAM, _U8]),
    "SR_GetIntegrationTime": (_U8, [_SRCAM]),
    "SR_SetAmplitudeThreshold": (ctypes.c_int, [_SRCAM, ctypes.c_ushort]),
    "SR_GetAmplitudeThreshold": (ctypes.c_ushort, [_SRCAM]),
    "SR_SetModulationFrequency": (ctypes.c_int, [_SRCAM, ctypes.c_int]),
    "SR_GetModulationFrequency": (ctypes.c_int, [_SRCAM]),
    "SR_SetAutoExposure": (ctypes.c_int, [_SRCAM, _U8, _U8, _U8, _U8]),
    "SR_SetMode": (ctypes.c_int, [_SRCAM, ctypes.c_int]),
    "SR_GetMode": (ctypes.c_int, [_SRCAM]),
    "SR_SetTimeout": (None, [_SRCAM, ctypes.c_int]),
    "SR_ReadSerial": (ctypes.c_uint, [_SRCAM]),
    "SR_GetRows": (ctypes.c_uint, [_SRCAM]),
    "SR_GetCols": (ctypes.c_uint, [_SRCAM]),
    "SR_GetVersion": (ctypes.c_int, [ctypes.POINTER(ctypes.c_ushort)]),
    "SR_GetDeviceString": (ctypes.c_int, [_SRCAM, ctypes.c_char_p, ctypes.c_int]),
}

_loaded: dict[str, ctypes.CDLL] = {}
_load_lock = threading.Lock()


def load_library(path: str = DEFAULT_LIBRARY, device: str = "sr4000") -> ctypes.CDLL:
    """dlopen libmesasr once per path and declare every signature; precise faults if we cannot."""
    with _load_lock:
        if path in _loaded:
            return _loaded[path]
        try:
            library = ctypes.CDLL(path)
        except OSError as exc:
            raise Sr4000LibraryMissing(f"cannot load the MESA library {path!r} ({exc}); {INSTALL_HINT}",
                                       device=device) from exc
        for name, (restype, argtypes) in SIGNATURES.items():
            try:
                function = getattr(library, name)
            except AttributeError:
                raise Sr4000LibraryMissing(f"{path!r} has no {name}: not a libmesasr for the SR4000, "
                                           f"or too old; {INSTALL_HINT}", device=device) from None
            function.restype, function.argtypes = restype, argtypes
        _loaded[path] = library
        return library


class MesaSr4000(Sr4000):
    """An SR4000 on USB (by serial number, 0 = the first found) or Ethernet (by address).

    `clock` stamps frames (default: wall-clock seconds since construction).
    """

    def __init__(self, *, usb_serial: int = 0, address: str | None = None, library: str | None = None,
                 settings: Sr4000Settings | None = None, name: str = "sr4000",
                 clock: SimClock | None = None):
        super().__init__(name, settings)
        self.usb_serial, self.address = usb_serial, address
        self.library_path = library or DEFAULT_LIBRARY
        self.clock = clock or SimClock()
        self.device_string = ""
        self._lib: ctypes.CDLL | None = None
        self._cam = _SRCAM()
        self._sequence = 0

    # -- lifecycle -----------------------------------------------------------------------------
    def _open(self) -> None:
        self._lib = load_library(self.library_path, self.name)
        cam = _SRCAM()
        if self.address is not None:
            where, call = f"Ethernet address {self.address}", "SR_OpenETH"
            opened = self._lib.SR_OpenETH(ctypes.byref(cam), self.address.encode())
        else:
            where, call = f"USB (serial {self.usb_serial:#010x}; 0 = first found)", "SR_OpenUSB"
            opened = self._lib.SR_OpenUSB(ctypes.byref(cam), self.usb_serial)
        if opened <= 0 or not cam.value:
            raise Sr4000NotFound(f"no SR4000 answered on {where}", device=self.name, call=call,
                                 returned=opened)
        self._cam = cam
        self.rows, self.cols = int(self._lib.SR_GetRows(cam)), int(self._lib.SR_GetCols(cam))
        self.serial = int(self._lib.SR_ReadSerial(cam))
        self.version, self.device_string = self._read_version()
        log.info("%s: opened %s, serial %#010x, %s", self.name, self.device_string, self.serial, self.version)

    def _close(self) -> None:
        closed = self._lib.SR_Close(self._cam)
        self._cam = _SRCAM()
        if closed < 0:
            raise Sr4000Error("closing failed", device=self.name, call="SR_Close", returned=closed)

    def _read_version(self) -> tuple[str, str]:
        numbers = (ctypes.c_ushort * 4)()
        self._lib.SR_GetVersion(numbers)
        text = ctypes.create_string_buffer(256)
        self._lib.SR_GetDeviceString(self._cam, text, len(text))
        return "libmesasr " + ".".join(str(n) for n in numbers), text.value.decode(errors="replace")

    # -- acquisition ---------------------------------------------------------------------------
    def _acquire(self) -> TofFrame:
        started = self.clock.now()
        transferred = self._lib.SR_Acquire(self._cam)
        finished = self.clock.now()
        if transferred < 0:
            raise Sr4000NotAnswering(f"acquisition failed: stopped answering (no frame within "
                                     f"{self._settings.timeout_ms} ms, or the camera is gone)", device=self.name,
                                     call="SR_Acquire", returned=transferred)
        images = self._images()
        if IT_DISTANCE not in images or IT_AMPLITUDE not in images:
            raise Sr4000Error(f"image list lacks distance or amplitude (types {sorted(images)})",
                              device=self.name, call="SR_GetImageList")
        x, y, z = self._coordinates()
        self._sequence += 1
        return TofFrame(distance=images[IT_DISTANCE], amplitude=images[IT_AMPLITUDE],
                        confidence=images.get(IT_CONF_MAP), x=x, y=y, z=z,
                        timestamp=(started + finished) / 2,
                        modulation_frequency=self._settings.modulation_frequency,
                        integration_time=self._read_integration_time(), sequence=self._sequence)

    def _images(self) -> dict[int, np.ndarray]:
        """Copies of the uint16 images by ImgEntry type (the list's order is the library's)."""
        entries = ctypes.POINTER(ImgEntry)()
        count = self._lib.SR_GetImageList(self._cam, ctypes.byref(entries))
        if count <= 0:
            raise Sr4000Error("no images after acquisition", device=self.name, call="SR_GetImageList",
                              returned=count)
        images = {}
        for index in range(count):
            entry = entries[index]
            if entry.imgType not in (IT_DISTANCE, IT_AMPLITUDE, IT_CONF_MAP):
                continue
            if entry.dataType != DT_USHORT or (entry.height, entry.width) != (self.rows, self.cols):
                raise Sr4000Error(f"image {index} (type {entry.imgType}) is data type {entry.dataType}, "
                                  f"{entry.width}x{entry.height}; expected unsigned short "
                                  f"{self.cols}x{self.rows}", device=self.name, call="SR_GetImageList")
            pointer = self._lib.SR_GetImage(self._cam, index)
            if not pointer:
                raise Sr4000Error(f"no data for image {index}", device=self.name, call="SR_GetImage")
            data = ctypes.cast(pointer, ctypes.POINTER(ctypes.c_uint16))
            images[entry.imgType] = np.ctypeslib.as_array(data, shape=(self.rows, self.cols)).copy()
        return images

    def _coordinates(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """SR_CoordTrfFlt into one interleaved (rows, cols, 3) buffer (pitch 12 bytes), then MESA's
        axes to OpenCV's."""
        mesa_xyz = np.zeros((self.rows, self.cols, 3), dtype=np.float32)
        pitch = mesa_xyz.strides[1]
        base = mesa_xyz.ctypes.data
        pointers = [ctypes.cast(base + axis * mesa_xyz.itemsize, _FLOAT_P) for axis in range(3)]
        result = self._lib.SR_CoordTrfFlt(self._cam, *pointers, pitch, pitch, pitch)
        if result < 0:
            raise Sr4000Error("coordinate transform failed", device=self.name, call="SR_CoordTrfFlt",
                              returned=result)
        return -mesa_xyz[..., 0], -mesa_xyz[..., 1], mesa_xyz[..., 2].copy()

    # -- settings ------------------------------------------------------------------------------
    def _checked(self, call: str, result: int) -> None:
        if result < 0:
            raise Sr4000Error("the camera refused a setting", device=self.name, call=call, returned=result)

    def _write_integration_time(self, register: int) -> None:
        self._checked("SR_SetIntegrationTime", self._lib.SR_SetIntegrationTime(self._cam, register))
        log.debug("%s: integration time %d (%.1f ms)", self.name, register, integration_time_ms(register))

    def _write_amplitude_threshold(self, threshold: int) -> None:
        self._checked("SR_SetAmplitudeThreshold", self._lib.SR_SetAmplitudeThreshold(self._cam, threshold))

    def _write_modulation_frequency(self, frequency: ModulationFrequency) -> None:
        self._checked("SR_SetModulationFrequency",
                      self._lib.SR_SetModulationFrequency(self._cam, int(frequency)))

    def _write_auto_exposure(self, min_time: int, max_time: int, percent_over_pos: int,
                             desired_pos: int) -> None:
        self._checked("SR_SetAutoExposure", self._lib.SR_SetAutoExposure(
            self._cam, min_time, max_time, percent_over_pos, desired_pos))

    def _write_mode(self, flags: AcquireMode) -> None:
        self._checked("SR_SetMode", self._lib.SR_SetMode(self._cam, int(flags)))

    def _write_timeout(self, milliseconds: int) -> None:
        self._lib.SR_SetTimeout(self._cam, milliseconds)

    def _read_integration_time(self) -> int:
        return int(self._lib.SR_GetIntegrationTime(self._cam))

    def _read_mode(self) -> int:
        return int(self._lib.SR_GetMode(self._cam))

    def modulation_frequency(self) -> ModulationFrequency:
        """SR_GetModulationFrequency when open."""
        with self._lock:
            if not self.is_open:
                return self._settings.modulation_frequency
            value = int(self._lib.SR_GetModulationFrequency(self._cam))
            try:
                return ModulationFrequency(value)
            except ValueError:
                raise Sr4000Error(f"camera reports modulation {value}, not an SR4000 frequency",
                                  device=self.name, call="SR_GetModulationFrequency") from None

    def amplitude_threshold(self) -> int:
        """SR_GetAmplitudeThreshold when open."""
        with self._lock:
            if not self.is_open:
                return self._settings.amplitude_threshold
            return int(self._lib.SR_GetAmplitudeThreshold(self._cam))
