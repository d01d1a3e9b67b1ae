"""Commands that act on the simulated world only (PROTOCOL.md "Simulated world"); with real devices
they are `409 wrong-mode`."""
from __future__ import annotations

from ..dispatch import Module

module = Module("simulation", summary="the simulated world: injected device faults")
