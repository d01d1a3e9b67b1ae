"""The SwissRanger SR4000 time-of-flight camera: libmesasr through ctypes, or the emulator over the
simulated test bed."""
from __future__ import annotations

from typing import Any, Literal

from pydantic import Field

from drivers.errors import DeviceFault

from ..config import Settings
from .base import SensorDevice


class TofDeviceConfig(Settings):
    enabled: bool = True
    backend: Literal["sim", "mesa"] = Field("sim", description="sim: the emulator over the world")
    usb_serial: int = Field(0, ge=0, description="USB serial number; 0 opens the first camera found")
    address: str = Field("", description="IP address for an Ethernet SR4000; empty: USB")
    library: str = Field("", description="path of libmesasr.so; empty: the system's")
    settings_file: str = Field("", description="SR4000 settings text file (with defaults); empty: defaults")
    seed: int = Field(5, description="noise seed of the emulated camera")


class TofDevice(SensorDevice):
    name = "tof"

    def _settings(self) -> Any:
        from drivers.sr4000 import Sr4000Settings
        path = self.config.settings_file
        return Sr4000Settings.load_or_default(path) if path else Sr4000Settings()

    def _make(self) -> None:
        c = self.config
        if c.backend == "sim":
            from drivers.sr4000_emulator import Sr4000Emulator
            testbed = self.testbed
            camera = Sr4000Emulator(testbed.world, lambda: testbed.sensor_pose("tof"), self.clock, seed=c.seed,
                                    settings=self._settings(), fault=testbed.faults["tof"])
        else:
            from drivers.sr4000_mesasr import MesaSr4000
            camera = MesaSr4000(usb_serial=c.usb_serial, address=c.address or None, library=c.library or None,
                                settings=self._settings(), clock=self.clock)
        camera.open()
        self.driver = camera
        self.health, self.last_error = "ok", ""

    def check(self) -> None:
        if not self.config.enabled:
            self.health = "off"
            return
        if self.driver is None:
            if self.config.backend == "sim":
                self.health, self.last_error = "ok", ""
            else:
                self.open()
            return
        status = self.driver.status()
        if getattr(status, "last_error", None):
            self._fault(DeviceFault(status.last_error, "tof"))
        else:
            self.health, self.last_error = "ok", ""

    # -- an activity's own settings -------------------------------------------------------------
    # Tracking frames want the camera otherwise than mapping (10 m range, a shorter exposure for the
    # frame rate). Switching there and back on every frame costs a frame's worth of register writes,
    # so an activity leaves its settings in force between its frames, and the device gives the job
    # its own back the moment a job takes the camera (require) or the activity ends (restore).
    _own_settings: Any = None

    def use_settings(self, wanted: Any) -> None:
        """An activity's settings, in force from now on until a job takes the camera (call it inside a
        borrow)."""
        camera = self.ready_driver()
        if self._own_settings is None:
            self._own_settings = camera.settings()
        camera.apply(wanted)

    def own_settings(self) -> Any:
        """The camera's own settings (those a job gets), whatever an activity left in force."""
        return self._own_settings if self._own_settings is not None else self.ready_driver().settings()

    def restore_settings(self) -> None:
        """The camera's own settings back, if an activity left its own in force."""
        own, self._own_settings = self._own_settings, None
        if own is not None and self.driver is not None:
            self.driver.apply(own)

    def require(self) -> Any:
        camera = super().require()
        if self._own_settings is not None:
            self.restore_settings()
        return camera

    def grab(self, frames: int = 1, min_confidence: int = 0, settle_frames: int = 10, camera: Any = None) -> Any:
        """Frames averaged per pixel once auto exposure settled (drivers.sr4000.grab's GrabResult);
        from `camera` when an activity borrowed it, else from the job's."""
        from drivers.sr4000 import grab
        return grab(camera or self.require(), frames=frames, min_confidence=min_confidence,
                    settle_frames=settle_frames)

    def live_fault(self) -> str | None:
        """A frame that failed in a job: the camera's own status keeps it until a frame succeeds."""
        return self.driver.status().last_error if self.driver is not None else None

    def reset(self) -> None:
        """Close and open again. An emulated camera is opened now when its world is built, so a
        camera that still does not answer is reported by the reset, not by the next job."""
        self.close()
        self.open()
        if self.health == "ok" and self.config.backend == "sim" and self.testbed.ready:
            try:
                self.require()
            except (DeviceFault, OSError, ValueError):
                pass  # require() recorded the fault
