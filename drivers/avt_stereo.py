"""The stereo pair: two cameras as left and right on one trigger box, grabbed synchronously.

`StereoCameras` works on any two `drivers.avt.Camera` backends (`drivers.avt_vimba.vimba_stereo_pair`,
`drivers.avt_emulator.emulated_stereo_pair` build one) and a `drivers.trigger.TriggerBox`: left and
right identities, settings applied to both, `grab()` arming the cameras before one trigger pulse,
and, when a grab fails, which of the cameras or the trigger box is at fault. `StereoStatus` is a
snapshot of the pair, readable from any thread while a grab runs.
"""
from __future__ import annotations

import threading
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

from drivers.avt import ROLES, Camera, CameraSettings, CameraStatus, CameraTimeout, Frame
from drivers.errors import DeviceFault
from drivers.trigger import TriggerBox, TriggerStatus


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

    def __enter__(self) -> StereoCameras:
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
