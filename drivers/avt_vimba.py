"""The real camera backend: current Allied Vision GigE / USB3 cameras through vmbpy (Vimba X).

`vmbpy` is the Python API of Vimba X (pip name `vmbpy`, the optional extra `vimba`). It is imported
when a camera is opened or listed, not when this module is imported, so machines without Vimba X
(CI, the emulated test bed) never need it; `import_vmbpy` names the missing package in a
CameraError.

- `discover_vimba_cameras`: the ids Vimba X finds (the first becomes left);
- `vimba_stereo_pair`: a `drivers.avt_stereo.StereoCameras` of them on a trigger box;
- `VimbaCamera`: one camera on the hardware trigger (FrameStart on Line1), the settings written to
  its GenICam features.

The thesis' PIKE F-210B cameras are IEEE 1394b FireWire cameras: Vimba X and vmbpy do NOT support
them (FireWire is not GenICam); they are reached through IIDC / libdc1394, which this backend does
not cover.
"""
from __future__ import annotations

import contextlib
import importlib
import queue
import threading
import time
from collections.abc import Sequence

import numpy as np

from drivers.avt import Camera, CameraError, CameraSettings, Frame, mode_window
from drivers.avt_stereo import StereoCameras
from drivers.sim.clock import SimClock
from drivers.trigger import TriggerBox

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
