"""world.toml rover_start: where the simulated rover stands when a server starts."""
from __future__ import annotations

import math

import pytest

from drivers.sim.clock import SimClock
from drivers.sim.config import WorldConfig
from rvs_server.devices import Devices, DevicesConfig


def test_the_simulated_rover_starts_where_world_toml_says():
    devices = Devices(DevicesConfig(), SimClock(), WorldConfig(seed=2, size_m=(8.0, 8.0), rover_start=(1.5, -2.0, 90.0)))
    try:
        x, y, heading = devices.testbed.start_pose
        assert (x, y) == (1.5, -2.0) and heading == pytest.approx(math.pi / 2)
        assert devices.testbed.rover.pose[:2] == pytest.approx((1.5, -2.0))
    finally:
        devices.testbed.close()
