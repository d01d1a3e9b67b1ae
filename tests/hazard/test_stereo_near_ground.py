"""The stereo guard's frames near the view's foot: ground nearer than the matcher's search reaches
is not made into ground metres too far and too low (false steps beside it)."""
import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

from drivers.sim.config import WorldConfig
from drivers.sim.rover import Rover
from drivers.sim.world import World
from toolbox.mapping import hazard as H
from toolbox.mapping.corridor import CorridorParams, corridor_view
from toolbox.mapping.stereo import SgbmConfig

BENCH = Path(__file__).resolve().parents[1] / "bench"


def measure_corridor():
    """tests/bench/measure_corridor.py, whose pair is the guard's chain without a server."""
    sys.path.insert(0, str(BENCH))    # it imports the hazard campaign beside it
    spec = importlib.util.spec_from_file_location("measure_corridor", BENCH / "measure_corridor.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module       # its dataclass looks itself up there
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def steep_look():
    """A pair looking 44 degrees down on rock-free ground: the image's foot sees the ground at about
    1 m ahead, a disparity of 64-66 in the low mode, just past a search of 0-63 (the guard's -35
    degrees meets it uphill: a crater's 11-degree side, seed 31 of the hazard campaign)."""
    world = World.build(WorldConfig(seed=7, size_m=(8.0, 8.0), rocks={"cover": 0.0}, craters={"count": 0}))
    rover = Rover(world, x=-2.0, y=0.0, heading=0.0)
    return world, rover, measure_corridor().stereo_pair(rover, -44.0, seed=3)


def ground_errors(steep_look, min_disparity: int) -> tuple[np.ndarray, np.ndarray]:
    world, _, pair = steep_look
    world_points = pair.points(SgbmConfig(min_disparity=min_disparity, num_disparities=64, block_size=5), 4.0)
    return world_points, world_points[:, 2] - world.height_at(world_points[:, 0], world_points[:, 1])


def test_a_search_that_starts_at_16_keeps_the_near_ground_on_the_ground(steep_look):
    world, rover, *_ = steep_look
    cramped, cramped_error = ground_errors(steep_look, 0)
    shifted, shifted_error = ground_errors(steep_look, 16)
    # Searched from 0, the near ground's matches are crammed below 64: points far below the ground.
    assert np.sum(cramped_error < -0.05) > 3 * np.sum(shifted_error < -0.05)
    # The shifted search reaches the nearest ground, and sees more of it.
    assert shifted[:, 0].min() < cramped[:, 0].min() - 0.05
    assert len(shifted) > 1.1 * len(cramped)

    params = CorridorParams(reach=3.0, hazard=H.HazardConfig(step_min_cells=5))
    pose = (rover.x, rover.y, rover.heading)
    false_step = corridor_view(cramped, pose, params).nearest       # what the guard stopped for
    assert false_step is not None and false_step.distance < 1.0
    assert corridor_view(shifted, pose, params).nearest is None
