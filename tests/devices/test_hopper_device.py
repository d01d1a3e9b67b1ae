"""The hopper device: the simulated hopper on the test bed's world (made at the start, kept across hops
and reinit, a new world a new one), the real backend refused naming what is missing, and the truth
hop-plan's truth/ comparison reads.

Small worlds (8 m, flat where the hopper flies) and physics-only hops: the file runs in seconds.
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from drivers.sim.clock import SimClock
from drivers.sim.config import WorldConfig
from rvs_server.devices import Devices, DevicesConfig, HopperConfig, HopperDevice
from rvs_server.devices.hopper import REAL_LINK_MISSING
from rvs_server.protocol import DeviceError

WORLD = WorldConfig(seed=4, size_m=(8.0, 8.0), craters={"count": 0})
CONFIG = HopperConfig(camera={"width": 64, "height": 48})
START, HEADING_DEG = (0.5, -0.5), 30.0


@pytest.fixture
def devices():
    made = Devices(DevicesConfig(), SimClock(), WORLD)
    yield made
    made.close_all()


def require(device: HopperDevice, config: HopperConfig = CONFIG):
    return device.require("sim", config, START, HEADING_DEG)


def test_the_real_backend_is_refused_naming_what_is_missing(devices):
    with pytest.raises(DeviceError) as info:
        devices.hopper.require("real", CONFIG, START, HEADING_DEG)
    assert str(info.value) == REAL_LINK_MISSING and "not implemented" in str(info.value)
    with pytest.raises(DeviceError):
        devices.hopper.check_backend("real")
    devices.hopper.check_backend("sim")
    assert devices.hopper.sequence is None   # nothing was made


def test_the_simulated_hopper_starts_at_the_start_and_is_kept_across_hops(devices):
    device = devices.hopper
    assert device.truth() is None and not device.ready   # no world built yet: no truth
    hopper = require(device)
    assert device.ready and hopper.world is devices.testbed.world
    assert (hopper.x, hopper.y, hopper.heading) == pytest.approx((*START, math.radians(HEADING_DEG)))
    sequence = device.sequence
    assert sequence is not None
    hopper.hop(1.2, 60.0, 0.0, render_frames=False)
    landed = (hopper.x, hopper.y, hopper.heading)
    assert require(device) is hopper and device.sequence is sequence and hopper.hops == 1
    # A changed configuration (reinit) takes effect where the hopper stands, its hop count kept.
    changed = HopperConfig(camera={"width": 80, "height": 60})
    again = require(device, changed)
    assert again is not hopper and again.config == changed and again.hops == 1
    assert (again.x, again.y, again.heading) == pytest.approx(landed)
    assert device.sequence is sequence


def test_reinit_keeps_the_hopper_on_the_same_world_and_a_new_world_starts_anew(devices):
    hopper = require(devices.hopper)
    hopper.hop(1.2, 60.0, 0.0, render_frames=False)
    sequence = devices.hopper.sequence
    same = Devices(DevicesConfig(), devices.clock, WORLD, testbed=devices.testbed)   # what reinit builds
    same.hopper.take_over(devices.hopper)
    assert require(same.hopper) is hopper and same.hopper.sequence is sequence
    other = Devices(DevicesConfig(), devices.clock, WorldConfig(seed=5, size_m=(8.0, 8.0), craters={"count": 0}))
    try:
        other.hopper.take_over(devices.hopper)
        fresh = require(other.hopper)
        assert fresh is not hopper and fresh.world is other.testbed.world and fresh.hops == 0
        assert (fresh.x, fresh.y) == pytest.approx(START)
        assert other.hopper.sequence is not sequence
    finally:
        other.close_all()


def test_the_truth_is_the_worlds_ground(devices):
    require(devices.hopper)
    world, truth = devices.testbed.world, devices.hopper.truth()
    assert truth is not None and truth.cell == world.grid.cell
    assert truth.height_at(*START) == float(world.height_at(*START))
    args = (0.08, 0.05, (-1.0, 1.0), (-0.5, 1.5))
    assert np.array_equal(truth.obstacle_mask(*args), world.obstacle_mask(*args))
