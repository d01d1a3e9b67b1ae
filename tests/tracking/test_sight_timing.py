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
