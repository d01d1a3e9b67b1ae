"""world.toml rover_start: where the simulated rover stands when a server starts."""
from __future__ import annotations

import math

import pytest

from drivers.sim.clock import SimClock
from drivers.sim.config import DriveError, WorldConfig
from rvs_server.devices import Devices, DevicesConfig


def test_the_simulated_rover_starts_where_world_toml_says():
    devices = Devices(DevicesConfig(), SimClock(),
                      WorldConfig(seed=2, size_m=(8.0, 8.0), rover_start=(1.5, -2.0, 90.0)))
    try:
        x, y, heading = devices.testbed.start_pose
        assert (x, y) == (1.5, -2.0) and heading == pytest.approx(math.pi / 2)
        assert devices.testbed.rover.pose[:2] == pytest.approx((1.5, -2.0))
    finally:
        devices.testbed.close()


def test_world_toml_sets_the_drive_error():
    exact = WorldConfig(seed=2, size_m=(8.0, 8.0), drive_error=DriveError.none())
    devices = Devices(DevicesConfig(), SimClock(), exact)
    try:
        devices.testbed.drive(math.radians(30.0), 2.0)
        x, y, heading = devices.testbed.rover.pose
        assert (x, y) == pytest.approx((2.0 * math.cos(math.radians(30)), 2.0 * math.sin(math.radians(30))), abs=1e-6)
        assert heading == pytest.approx(math.radians(30.0))
    finally:
        devices.testbed.close()
    with pytest.raises(ValueError, match="turn_scale"):
        WorldConfig(drive_error={"turn_scale": -0.1})
