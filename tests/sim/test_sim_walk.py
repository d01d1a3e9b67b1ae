"""A scripted walk: along its corners and back, standing at each end, heading along its way."""
import math

import pytest

from drivers.sim.testbed import Walk


def test_a_walk_turns_at_its_corners_stands_at_its_ends_and_comes_back():
    walk = Walk(((0.0, 0.0), (2.0, 0.0), (2.0, 1.0)), speed=1.0, since=10.0, pause=1.5)
    assert walk.where(5.0) == (0.0, 0.0, 0.0)                      # before it set off: at the start
    assert walk.where(11.0) == pytest.approx((1.0, 0.0, 0.0))      # the first leg, heading east
    x, y, heading = walk.where(12.5)
    assert (x, y) == pytest.approx((2.0, 0.5)) and heading == pytest.approx(math.pi / 2)   # turned north
    for t in (13.0, 13.9, 14.4):                                    # 3 m walked at 13 s: it stands 1.5 s
        assert walk.where(t)[:2] == pytest.approx((2.0, 1.0))
    x, y, heading = walk.where(15.0)                                # on its way back: south
    assert (x, y) == pytest.approx((2.0, 0.5)) and heading == pytest.approx(-math.pi / 2)
    assert walk.where(17.5)[:2] == pytest.approx((0.0, 0.0))        # home, standing again
    assert walk.where(19.5)[:2] == pytest.approx((0.5, 0.0))        # and off once more: the cycle is 9 s
    assert walk.where(28.5)[:2] == pytest.approx((0.5, 0.0))
