"""The PTU angles a tracking frame is placed with are those of its exposure, not of the grab's middle."""
from __future__ import annotations

import pytest

from rvs_server.tracking.sight import angles_at


def test_a_pair_exposed_at_the_start_of_its_grab_takes_the_angles_read_before_it():
    before, after = (10.0, -5.0, 100.0), (11.0, -4.0, 100.12)     # 8.3 deg/s over a 120 ms grab
    assert angles_at(before, after, 100.0) == pytest.approx((10.0, -5.0))
    assert angles_at(before, after, 100.03) == pytest.approx((10.25, -4.75))


def test_an_exposure_outside_the_readings_is_held_at_the_nearer_one_and_a_zero_span_takes_the_mean():
    before, after = (10.0, -5.0, 100.0), (11.0, -4.0, 100.12)
    assert angles_at(before, after, 99.0) == pytest.approx((10.0, -5.0))
    assert angles_at(before, after, 101.0) == pytest.approx((11.0, -4.0))
    assert angles_at((10.0, 0.0, 5.0), (12.0, 2.0, 5.0), 5.0) == pytest.approx((11.0, 1.0))


def test_a_hop_at_the_set_speed_is_over_before_the_reading_after_and_the_exposure_in_it_sees_it_so():
    # 2 degrees at 47 deg/s: 43 ms of a 62 ms grab; exposed 31 ms in, the unit stood 1.46 degrees on.
    before, after = (22.0, -0.4, 100.0), (24.0, -0.3, 100.062)
    pan, tilt = angles_at(before, after, 100.031, speed_deg_s=47.0)
    assert pan == pytest.approx(22.0 + 47.0 * 0.031)
    assert tilt == pytest.approx(-0.3)                     # 0.1 degree at 47 deg/s: there in 2 ms
    assert angles_at(before, after, 100.055, speed_deg_s=47.0) == pytest.approx((24.0, -0.3))


def test_an_axis_that_moved_farther_than_its_speed_allows_is_taken_on_the_straight_line():
    before, after = (10.0, 0.0, 100.0), (14.0, 0.0, 100.05)     # 80 deg/s, set to 20: not that speed
    assert angles_at(before, after, 100.025, speed_deg_s=20.0) == pytest.approx((12.0, 0.0))
