"""The simulated world's ground truth, as the products record it beside what the sensors measured.

The one door from the server to the simulator's truth: a command never reads drivers.sim itself, so a
product's truth/ folder always says where it came from, and real devices simply have none
(`Devices.truth` is None).
"""
from __future__ import annotations

from typing import Any

import numpy as np

from drivers.sim.testbed import SimulatedTestbed


class GroundTruth:
    """What the simulated test bed knows that the sensors only estimate."""

    def __init__(self, testbed: SimulatedTestbed):
        self._testbed = testbed

    def state(self) -> dict[str, Any]:
        """Rover pose, PTU angles and sensor poses of this instant (world frame)."""
        return self._testbed.truth()

    @property
    def cell(self) -> float:
        """The world's own grid cell, metres: finer maps of the truth would only interpolate."""
        return self._testbed.world.grid.cell

    def height_map(self, cell: float, x_range: tuple[float, float], y_range: tuple[float, float]) -> np.ndarray:
        """True height at each cell centre of the grid, metres."""
        return self._testbed.world.height_map(cell, x_range, y_range)

    def obstacle_mask(self, step: float, cell: float, x_range: tuple[float, float],
                      y_range: tuple[float, float]) -> np.ndarray:
        """True where a rock stands more than `step` metres above the ground."""
        return self._testbed.world.obstacle_mask(step, cell, x_range, y_range)

    def person(self, sensor: str, half_fov_deg: tuple[float, float], max_range_m: float,
               at_s: float | None = None) -> dict[str, Any] | None:
        """The astronaut's true place at clock time `at_s` (default now) and the share of it `sensor`
        sees now (None: no astronaut)."""
        return self._testbed.person_truth(sensor, half_fov_deg, max_range_m, at_s)
