"""The ground under a walker: a local plane over where it walked, with no lag on a slope, the noise
averaged where it stands, and a walk turned back on itself reading the ground it has walked."""
import numpy as np
import pytest

from toolbox.tracking.ground import GroundTrail


def slope(x, y):
    return 0.2 + 0.10 * x - 0.04 * y      # a 10 % rise along x


def walk(trail, rng, start, end, speed=1.5, rate_hz=10.0, t0=0.0, noise=0.03):
    """Samples under a walker from start to end; the estimates at each new place, against the truth."""
    start, end = np.asarray(start, float), np.asarray(end, float)
    steps = int(np.linalg.norm(end - start) / speed * rate_hz)
    errors = []
    for i in range(1, steps + 1):
        x, y = start + (end - start) * i / steps
        trail.add(x, y, slope(x, y) + rng.normal(0.0, noise), t0 + i / rate_hz)
        errors.append(trail.height_at(x, y) - slope(x, y))
    return np.array(errors), t0 + steps / rate_hz


def test_on_a_slope_the_estimate_does_not_lag_behind_the_walker():
    rng = np.random.default_rng(1)
    trail = GroundTrail()
    errors, _ = walk(trail, rng, (4.0, -2.0), (8.0, 1.0))
    settled = errors[5:]
    assert abs(settled.mean()) < 0.01                   # a running average of 0.3 a frame read ~4 cm behind
    assert np.sqrt(np.mean(settled ** 2)) < 0.02        # and the samples' 3 cm noise is averaged down


def test_standing_still_it_is_the_mean_of_the_samples_there():
    rng = np.random.default_rng(2)
    trail = GroundTrail()
    zs = [0.5 + rng.normal(0.0, 0.03) for _ in range(20)]
    for i, z in enumerate(zs):
        trail.add(5.0, 1.0, z, i * 0.1)
    assert trail.height_at(5.0, 1.0) == pytest.approx(np.mean(zs), abs=1e-9)


def test_old_samples_are_forgotten_and_a_far_query_takes_the_nearest():
    trail = GroundTrail()
    trail.add(0.0, 0.0, 1.0, 0.0)
    trail.add(10.0, 0.0, 2.0, 10.0)                     # 10 s later: the first is past the memory
    assert len(trail) == 1
    assert trail.height_at(0.0, 0.0) == 2.0             # only the sample left, however far
    assert GroundTrail().height_at(0.0, 0.0) is None
