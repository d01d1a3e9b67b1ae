"""The devices the server drives, built from `configs/devices.toml`, with their health.

Each device is a thin wrapper around a driver from `drivers/`: it opens the real backend or the
emulator the config names, keeps its health (`ok`, `fault`, `off`) and last error for `status`,
and gives jobs the driver once the device is healthy. When any device runs on the simulator, one
SimulatedTestbed (world, rover, truth) is shared by all of them. The rover (`devices.rover`: pose
estimate, drive, forward camera) and the hopper (`devices.hopper`: the body `hop` launches) are
built on the same test bed.

The simulator's config types the capabilities' settings name (DriveError, Sun, ForwardCameraConfig,
HopperConfig) are re-exported here, so no capability imports drivers.sim.
"""
from __future__ import annotations

import math
from pathlib import Path

from drivers.sim.clock import SimClock
from drivers.sim.config import DriveError, Sun, WorldConfig
from drivers.sim.faults import FAULT_DEVICES  # noqa: F401  the devices a fault can be injected into (sim-fault)
from drivers.sim.testbed import SimulatedTestbed

from ..config import Settings
from .base import Device, Health
from .cameras import CamerasDeviceConfig, StereoDevice
from .hopper import Hopper, HopperBackend, HopperConfig, HopperDevice, HopperTruth, OffTerrain
from .ptu import PtuDevice, PtuDeviceConfig
from .rover import ForwardCameraConfig, RoverDevice
from .sharing import DeviceSharing
from .tof import TofDevice, TofDeviceConfig
from .truth import GroundTruth


class DevicesConfig(Settings):
    ptu: PtuDeviceConfig = PtuDeviceConfig()
    tof: TofDeviceConfig = TofDeviceConfig()
    cameras: CamerasDeviceConfig = CamerasDeviceConfig()


class Devices:
    """Every device by name, in the order they were configured."""

    def __init__(self, config: DevicesConfig, clock: SimClock, world_config: WorldConfig | None = None,
                 world_file: Path | None = None, testbed: SimulatedTestbed | None = None,
                 sharing: DeviceSharing | None = None):
        self.config = config
        self.clock = clock
        if testbed is None:
            world = world_config or WorldConfig()
            x, y, heading = world.rover_start
            testbed = SimulatedTestbed(clock, world_config, world_file, start_pose=(x, y, math.radians(heading)),
                                       drive_error=world.drive_error)
        self.testbed = testbed
        self.items: dict[str, Device] = {
            "ptu": PtuDevice(config.ptu, clock, self.testbed),
            "tof": TofDevice(config.tof, clock, self.testbed),
            "cameras": StereoDevice(config.cameras, clock, self.testbed),
        }
        # A job's and the activities' turns at the devices (sharing.py); reinit passes it on, since
        # the job that reinitialises holds devices and activities keep running.
        self.sharing = sharing or DeviceSharing()
        for device in self.items.values():
            device.sharing = self.sharing
        self.rover = RoverDevice(self.testbed, lambda: self.simulated, self.sharing)  # not an item: see rover.py
        self.hopper = HopperDevice(self.testbed)  # not an item: see devices/hopper.py

    def __getitem__(self, name: str) -> Device:
        return self.items[name]

    def __iter__(self):
        return iter(self.items.values())

    @property
    def ptu(self) -> PtuDevice:
        return self.items["ptu"]  # type: ignore[return-value]

    @property
    def tof(self) -> TofDevice:
        return self.items["tof"]  # type: ignore[return-value]

    @property
    def cameras(self) -> StereoDevice:
        return self.items["cameras"]  # type: ignore[return-value]

    @property
    def simulated(self) -> bool:
        """True when the sensors run on the simulator, so products can carry its truth."""
        c = self.config
        return any(d.enabled and d.backend == "sim" for d in (c.tof, c.cameras))

    @property
    def truth(self) -> GroundTruth | None:
        """The simulator's truth for the products, once its world is built; None with real sensors."""
        return GroundTruth(self.testbed) if self.simulated and self.testbed.ready else None

    def open_all(self) -> None:
        for device in self:
            device.open()

    def close_all(self) -> None:
        for device in self:
            device.close()
        self.testbed.close()

    def health(self) -> dict[str, str]:
        items: dict[str, str] = {}
        for device in self:
            items.update(device.health_items())
        return items


__all__ = ["Devices", "DevicesConfig", "Device", "DriveError", "ForwardCameraConfig", "Health", "Hopper",
           "HopperBackend", "HopperConfig", "HopperDevice", "HopperTruth", "OffTerrain", "PtuDevice", "RoverDevice",
           "StereoDevice", "Sun", "TofDevice"]
