"""The stereo pair is one rigid rig at a trigger pulse, however the rover moves between its renders."""
import numpy as np

from drivers.sim.clock import SimClock
from drivers.sim.config import WorldConfig
from drivers.sim.testbed import SimulatedTestbed


def test_both_cameras_of_one_pulse_stand_on_the_rover_of_that_pulse():
    """A drive steps the rover 5 cm at a time in its own thread; at a simulation speed-up a step can
    fall between the left and the right render of one pulse. Both must see the rover where the first
    saw it (the right camera 5 cm off the left made the stereo guard's frames garbage), and the next
    pulse sees where it went."""
    bed = SimulatedTestbed(SimClock(50.0), WorldConfig(seed=3, size_m=(10.0, 10.0), cell_m=0.02))
    rover = bed.rover
    before = rover.sensor_to_world("left")
    rig = np.linalg.inv(rover.sensor_to_world("left")) @ rover.sensor_to_world("right")

    left = bed.sensor_pose("left", 12.0)
    bed.step_rover((0.05, 0.0, 0.02))                 # the drive's next sample, between the two renders
    right = bed.sensor_pose("right", 12.0)
    np.testing.assert_allclose(np.linalg.inv(left) @ right, rig, atol=1e-12)

    moved = bed.sensor_pose("left", 12.2)
    np.testing.assert_allclose(moved, rover.sensor_to_world("left"), atol=1e-12)
    np.testing.assert_allclose(left, before, atol=1e-12)
    assert np.linalg.norm(moved[:3, 3] - left[:3, 3]) > 0.01
