"""Emulated camera: the simulated world seen through a hardware-triggered Allied Vision camera.

`EmulatedCamera` implements the `drivers.avt.Camera` interface. Connected to an emulated trigger
box, on a pulse after arm() it notes the instant, its true pose and the sun at that instant, renders
the world in a thread of its own and exposes the image with the sensor model (`drivers.avt_sensor`).
Like the real camera in hardware-trigger mode it never makes a frame by itself. A frame carries the
simulated time of its trigger pulse; rendering takes wall time, which never leaks into that
timestamp. `emulated_stereo_pair` builds a `drivers.avt_stereo.StereoCameras` of two of them on
one emulated trigger box.
"""
from __future__ import annotations

import threading
import zlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import numpy as np

from drivers.avt import PIKE_F210B_SENSOR, RESOLUTION_MODES, Camera, CameraSettings, Frame, intrinsics_per_mode
from drivers.avt_sensor import _SceneAtPulse, expose_image
from drivers.avt_stereo import StereoCameras
from drivers.sim.clock import SimClock
from drivers.sim.faults import FaultSwitch
from drivers.sim.world import World
from drivers.trigger import EmulatedTrigger
from toolbox.camera import Intrinsics

READOUT_S = 1.0 / 31.0                 # the PIKE F-210B's frame time at full resolution
EMULATED_RESET_S = 1.0                 # a reset re-enumerates the camera; it takes a moment
FRAME_WALL_LIMIT_S = 300.0             # how long a triggered frame may take to render (wall time)


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
    `intrinsics` maps each resolution mode to its Intrinsics (see intrinsics_per_mode). The
    camera connects itself to `trigger` (the cable); on a pulse after arm() it notes the instant,
    the pose and the sun at that instant, and renders in a thread of its own. `seed` makes the
    sensor noise repeatable (it is mixed with the camera's name and the frame number). `fault`
    (drivers/sim/faults.py) counts the frames asked of it; once tripped the camera ignores pulses.
    """

    trigger_mode = "hardware (emulated)"

    def __init__(self, name: str, world: World, pose: Pose, intrinsics: Mapping[str, Intrinsics],
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
        _ = world.surface.scene   # build the ray-casting scene now, not in two render threads at once
        trigger.connect(self._on_trigger)

    def intrinsics(self, mode: str | None = None) -> Intrinsics:
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
        pose = self.pose_at(at)    # first: it brings a walking astronaut to where it was at the pulse
        scene = _SceneAtPulse(pose, self.world.sun, self.intrinsics(settings.resolution), self.world.snapshot())
        exposure.triggered.set()
        threading.Thread(target=self._develop, args=(exposure, scene, settings, frame_number),
                         name=f"render {self.camera_id}", daemon=True).start()

    def _develop(self, exposure: _Exposure, scene: _SceneAtPulse, settings: CameraSettings,
                 frame_number: int) -> None:
        try:
            rng = np.random.default_rng([self._seed, zlib.crc32(self.camera_id.encode()), frame_number])
            image, exposure_us = expose_image(scene, settings, rng)
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


def emulated_stereo_pair(world: World, left_pose: Pose, right_pose: Pose, *, clock: SimClock,
                         trigger: EmulatedTrigger | None = None,
                         sensor: Intrinsics = PIKE_F210B_SENSOR, seed: int = 0,
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
               for camera_id, pose, mount in zip(ids, (left_pose, right_pose), ("camera-left", "camera-right"),
                                                 strict=True)]
    return StereoCameras(cameras, trigger, default_settings)
