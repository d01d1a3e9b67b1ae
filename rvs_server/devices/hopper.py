"""The hopping rover: the body that `hop` launches, and what the simulator knows of its ground.

Two backends, named by hopping.toml's `backend` (the hopper's settings live with its commands):

    sim   the simulated hopper (drivers/sim/hopper.py) on the test bed's world, the one every
          emulated device shares: put at the configured start on first use and kept across hops; a
          new world puts a new one at the start (a new sequence of hops), and a changed hopper
          configuration (reinit) takes effect where the hopper stands
    real  refused (ERR 503) naming what is missing: there is no link to a hopper in this server

The hopper is no entry of `Devices.items`: it has no driver to open or reset, and as one it would add
a line to every `status` and `reset` reply. The simulator's config types the hopping settings name
(HopperConfig) and its "off the terrain" error are re-exported here, so no command module imports
drivers.sim.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

from drivers.sim.hopper import Hopper, HopperConfig, HopRecord
from drivers.sim.hopper_flight import OffTerrain

from ..protocol import DeviceError
from .truth import GroundTruth

if TYPE_CHECKING:
    from drivers.sim.testbed import SimulatedTestbed
    from drivers.sim.world import World

HopperBackend = Literal["sim", "real"]
REAL_LINK_MISSING = ("hopper: backend \"real\" (hopping.toml) has no link to a hopper in this server: commanding "
                     "the spring launch and downloading the frames, timestamps and IMU / sun-sensor readings is not "
                     "implemented; set backend = \"sim\" to hop on the simulated world")

__all__ = ["HopRecord", "Hopper", "HopperBackend", "HopperConfig", "HopperDevice", "HopperTruth", "OffTerrain",
           "REAL_LINK_MISSING"]


@dataclass
class _Body:
    """The simulated hopper and the world it stands on; outlives a reinit that keeps the world (take_over)."""

    world: World | None = None
    hopper: Hopper | None = None
    sequence: object | None = None   # a new token each time a hopper is put at the start


class HopperTruth(GroundTruth):
    """The simulated world's ground, as hop-plan's truth/ comparison reads it: the sensors' truth, and
    the exact height of one point (the map's heights start from the start's ground)."""

    def height_at(self, x: float, y: float) -> float:
        """The exact height of the true surface at (x, y), metres."""
        return float(self._testbed.world.height_at(x, y))


class HopperDevice:
    """The hopper as the hopping commands see it: its backend's driver, and the simulator's truth."""

    name = "hopper"

    def __init__(self, testbed: SimulatedTestbed):
        self.testbed = testbed
        self._body = _Body()

    def take_over(self, previous: HopperDevice) -> None:
        """reinit builds the devices anew: on the same test bed (the same world) the hopper stays where
        it landed; on a new one the next hop starts a new sequence at the start."""
        if previous.testbed is self.testbed:
            self._body = previous._body

    @staticmethod
    def check_backend(backend: HopperBackend) -> None:
        """ERR 503 naming what is missing, for a backend this server cannot drive."""
        if backend == "real":
            raise DeviceError(REAL_LINK_MISSING)

    @property
    def ready(self) -> bool:
        """The simulated world is built: require() will not wait for it."""
        return self.testbed.ready

    @property
    def sequence(self) -> object | None:
        """Which run of hops from the start the hopper is on: a new token when a new world put it back
        at the start (the state of the hops so far then belongs to the old world); None before."""
        return self._body.sequence

    def require(self, backend: HopperBackend, config: HopperConfig, start: tuple[float, float],
                start_heading_deg: float) -> Hopper:
        """The hopper to hop with (waiting for the simulated world to be built)."""
        self.check_backend(backend)
        self.testbed.wait_for_build()
        world, body = self.testbed.world, self._body
        if body.hopper is None or body.world is not world:
            body.world, body.sequence = world, object()
            body.hopper = Hopper(world, config, *start, math.radians(start_heading_deg))
        elif body.hopper.config != config:
            old = body.hopper
            body.hopper = Hopper(world, config, old.x, old.y, old.heading)
            body.hopper.hops = old.hops
        return body.hopper

    def truth(self) -> HopperTruth | None:
        """The simulated world's ground for the products' truth/, once built; None without one."""
        return HopperTruth(self.testbed) if self.testbed.ready else None
