"""The stereo camera pair and its trigger box: Allied Vision cameras through vmbpy, the trigger on the
parallel port through ppdev, or both emulated over the simulated test bed."""
from __future__ import annotations

from typing import Literal

from pydantic import Field

from drivers.avt import MODE_BINNING, PIKE_F210B_SENSOR, ResolutionMode, mode_intrinsics
from drivers.errors import DeviceFault
from toolbox.camera import Intrinsics

from ..config import Settings
from .base import SensorDevice

Resolution = ResolutionMode   # the cameras' modes, for the capabilities' settings


def mode_binning(mode: str) -> int:
    """How many sensor pixels a side one pixel of a resolution mode bins."""
    return MODE_BINNING[mode]


def nominal_intrinsics(mode: str) -> Intrinsics:
    """The thesis camera's (Pike F-210B, 12 mm lens) pinhole model in a resolution mode, where no
    camera is at hand to say its own."""
    return mode_intrinsics(PIKE_F210B_SENSOR, mode)


class CamerasDeviceConfig(Settings):
    enabled: bool = True
    backend: Literal["sim", "vimba"] = Field("sim", description="sim: emulated cameras over the world")
    left_id: str = Field("", description="camera id used as left; empty: the first found")
    right_id: str = Field("", description="camera id used as right; empty: the second found")
    settings_file: str = Field("", description="camera settings file (saved by the driver); empty: defaults")
    resolution: Resolution = "medium"
    grab_timeout_s: float = Field(5.0, gt=0, le=120, description="wait for a triggered frame, wall seconds")
    trigger_backend: Literal["sim", "ppdev"] = "sim"
    trigger_port: str = Field("/dev/parport0", description="parallel port node, for trigger_backend ppdev")
    seed: int = Field(11, description="sensor noise seed of the emulated cameras")


SIM_GRAB_TIMEOUT_S = 30.0


class StereoDevice(SensorDevice):
    """Both cameras and the trigger box; status shows each."""

    name = "cameras"

    @property
    def grab_timeout_s(self) -> float:
        """Wall seconds a grab may take. Emulated cameras render their frames in this process, so
        on a loaded host they are late through no fault of a camera: they get at least 30 s."""
        timeout = self.config.grab_timeout_s
        return max(timeout, SIM_GRAB_TIMEOUT_S) if self.config.backend == "sim" else timeout

    def health_items(self) -> dict[str, str]:
        """Each camera and the trigger box as their own status says, so a fault names the part."""
        if self.driver is None or self.health == "off":
            return {"dev.camera_left": self.health, "dev.camera_right": self.health, "dev.trigger": self.health}
        status = self.driver.status()
        state = {"error": "fault", "closed": "off"}
        parts = {"dev.camera_left": state.get(status.left.state, "ok"),
                 "dev.camera_right": state.get(status.right.state, "ok"),
                 "dev.trigger": "fault" if status.trigger.last_error else ("ok" if status.trigger.is_open else "off")}
        if self.health == "fault" and "fault" not in parts.values():  # a fault no part can be blamed for
            return dict.fromkeys(parts, "fault")
        return parts

    def live_fault(self) -> str | None:
        if self.driver is None:
            return None
        status = self.driver.status()
        broken = [f"camera {s.role}: {s.last_error}" for s in (status.left, status.right) if s.state == "error"]
        if status.trigger.last_error:
            broken.append(f"{status.trigger.device}: {status.trigger.last_error}")
        return "; ".join(broken) or None

    def _make(self) -> None:
        from drivers.avt import CameraSettings
        from drivers.avt_emulator import emulated_stereo_pair
        from drivers.avt_vimba import vimba_stereo_pair
        from drivers.trigger import PpdevTrigger
        c = self.config
        settings = CameraSettings.load(c.settings_file) if c.settings_file else CameraSettings()
        settings = settings.with_changes(resolution=c.resolution)
        trigger = PpdevTrigger(c.trigger_port, clock=self.clock) if c.trigger_backend == "ppdev" else None
        if c.backend == "sim":
            testbed = self.testbed
            pair = emulated_stereo_pair(testbed.world, lambda t: testbed.sensor_pose("left", t),
                                        lambda t: testbed.sensor_pose("right", t), clock=self.clock,
                                        trigger=trigger, seed=c.seed, default_settings=settings,
                                        faults=testbed.faults)
        else:
            if trigger is None:
                from drivers.trigger import EmulatedTrigger
                trigger = EmulatedTrigger(self.clock)
            pair = vimba_stereo_pair(trigger, default_settings=settings)
        if c.left_id and c.right_id:
            pair.set_ids(c.left_id, c.right_id)
        pair.open()
        self.driver = pair
        self.health, self.last_error = "ok", ""

    def check(self) -> None:
        if not self.config.enabled:
            self.health = "off"
            return
        fault = self.live_fault()
        if fault:
            self._fault(DeviceFault(fault, "cameras"))
            return
        if self.health != "ok" and self.config.backend == "sim":
            self.health, self.last_error = "ok", ""

    def reset(self) -> None:
        """A test grab, then the cameras' own reset. The grab is the only way to learn that the
        trigger box works (it says nothing itself); the reset after it gives the cameras their
        defaults and frame numbers from 1 again, as a fresh start would."""
        if self.driver is None:
            self.close()
            self.open()
            return
        try:
            self.driver.grab("both", timeout_s=self.grab_timeout_s)
            self.driver.reset()
            self.health, self.last_error = "ok", ""
        except DeviceFault as exc:
            self._fault(exc)
