"""The tracking toolbox on synthetic clouds and measurements: a person's shape against a boulder's,
the centre from the legs, the constant-velocity filter's convergence, its gate and its coasting."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from toolbox.tracking.detect import candidates
from toolbox.tracking.kalman import Track, TrackParams
from toolbox.tracking.standing import Cluster, Plane, StandingParams


def box_surface(rng, centre, across, along, bottom, top, count):
    """Points on the near (x-facing: the sensor is at the origin, the body along +x) face and sides
    of an upright box: what a range sensor would see of it."""
    x0, y0 = centre
    side = rng.uniform(-across / 2, across / 2, count)
    z = rng.uniform(bottom, top, count)
    return np.column_stack([np.full(count, x0 - along / 2), y0 + side, z])


def ground(rng, around, half=2.5, step=0.05):
    g = np.arange(-half, half, step)
    gx, gy = np.meshgrid(g + around[0], g + around[1])
    return np.column_stack([gx.ravel(), gy.ravel(), rng.normal(0, 0.005, gx.size)])


def figure(rng, centre=(5.0, 0.0)):
    """A person facing the sensor: two legs apart, a torso with arms, a helmet."""
    x, y = centre
    parts = [box_surface(rng, (x, y + 0.1), 0.15, 0.2, 0.0, 0.86, 600),
             box_surface(rng, (x, y - 0.1), 0.15, 0.2, 0.0, 0.86, 600),
             box_surface(rng, (x, y), 0.50, 0.26, 0.83, 1.44, 1500),
             box_surface(rng, (x, y), 0.26, 0.28, 1.44, 1.80, 500)]
    return np.concatenate(parts)


def boulder(rng, centre=(5.0, 0.0), height=1.8, diameter=0.7):
    """A standing boulder: widest at its foot, narrowing to a rounded top."""
    z = rng.uniform(0, height, 5000)
    half = diameter / 2 * np.sqrt(np.clip(1 - (z / height) ** 4, 0, 1))
    side = rng.uniform(-1, 1, len(z)) * half
    return np.column_stack([centre[0] - diameter / 2 + 0.0 * z, centre[1] + side, z])


@pytest.fixture
def rng():
    return np.random.default_rng(7)


def test_a_suited_figure_is_a_person_and_a_boulder_of_its_height_is_not(rng):
    plane = Plane(0.0, 0.0, 0.0, 0.0, 0.0)
    person = candidates(np.concatenate([ground(rng, (5, 0)), figure(rng)]), np.zeros(2), plane)
    assert person and person[0].confidence > 0.9, [c.terms for c in person]
    assert 1.75 < person[0].shape.height < 1.85
    # the centre from the legs: where it stands, not the middle of its visible face
    assert math.dist(person[0].xy, (5.0, 0.0)) < 0.06, person[0].xy
    rock = candidates(np.concatenate([ground(rng, (5, 0)), boulder(rng)]), np.zeros(2), plane)
    assert rock and rock[0].confidence == 0.0 and rock[0].terms["legs_to_torso"] == 0.0, [c.terms for c in rock]
    pebble = candidates(np.concatenate([ground(rng, (5, 0)), boulder(rng, height=0.5, diameter=0.5)]),
                        np.zeros(2), plane)
    assert all(c.terms["height"] == 0.0 for c in pebble)          # too low to be anyone standing


def noisy_ground(rng, around, per_m2, half=3.0, step=0.04):
    """Ground seen by a stereo pair from the origin: each point's height off by a heavy-tailed error
    (Student t, 3 degrees of freedom) whose scale grows with the range squared."""
    g = np.arange(-half, half, step)
    gx, gy = np.meshgrid(g + around[0], g + around[1])
    scale = per_m2 * (gx ** 2 + gy ** 2)
    return np.column_stack([gx.ravel(), gy.ravel(), (scale * rng.standard_t(3, gx.shape)).ravel()])


def test_a_noisy_sensors_ground_is_its_median_and_its_strays_stand_for_nothing(rng):
    """A stereo pair's ground at 6.5 m spreads by +-0.2 m: the lowest point per cell sat 0.1-0.4 m low
    (a person 2.0 m tall, its legs widened by stray returns until it was no person at all). Told the
    noise, the ground under the person is within 3 cm and the person is found where it stands."""
    plane = Plane(0.0, 0.0, 0.0, 0.0, 0.0)
    cloud = np.concatenate([noisy_ground(rng, (6.5, 0.0), 0.0025), figure(rng, (6.5, 0.0))])
    naive = candidates(cloud, np.zeros(2), plane)
    told = candidates(cloud, np.zeros(2), plane, StandingParams(noise_per_m2=0.0025, min_cell_points=5))
    assert naive and naive[0].shape.ground_z < -0.05, naive[0].shape    # what the noise's tail did
    best = told[0]
    assert abs(best.shape.ground_z) < 0.03 and 1.75 < best.shape.height < 1.85, best.shape
    assert best.confidence > 0.9, best.terms
    assert math.dist(best.xy, (6.5, 0.0)) < 0.06, best.xy


def test_the_gate_answers_a_plain_bool():
    """The type checker found in_gate answering numpy's bool for a detection within min_gate_m (json
    refuses that one): a plain bool either way."""
    track = Track.start(np.array([1.0, 2.0]), np.eye(2) * 0.01, 0.0, TrackParams())
    for xy in ([1.0, 2.0], [1.0, 2.5], [1.0, 9.0]):
        answer = track.in_gate(np.array(xy), np.eye(2) * 0.01)
        assert type(answer) is bool
        assert json.loads(json.dumps({"in_gate": answer})) == {"in_gate": answer}


def test_the_filter_follows_a_walker_and_its_gate_keeps_a_boulder_out(rng):
    sigma = 0.03
    truth = lambda t: np.array([5.0, -2.0 + 0.8 * t])           # noqa: E731  (0.8 m/s along y)
    track = Track.start(truth(0) + rng.normal(0, sigma, 2), np.eye(2) * sigma ** 2, 0.0, TrackParams(q=0.5))
    for k in range(1, 41):
        t = k * 0.1
        track.predict(t)
        track.update(truth(t) + rng.normal(0, sigma, 2), np.eye(2) * sigma ** 2)
    assert np.linalg.norm(track.position - truth(4.0)) < 0.03
    assert track.velocity == pytest.approx([0.0, 0.8], abs=0.08)
    track.predict(4.1)
    assert not track.in_gate(truth(4.1) + [0.0, 1.2], np.eye(2) * sigma ** 2)    # a boulder 1.2 m on
    assert track.in_gate(truth(4.1) + [0.02, -0.02], np.eye(2) * sigma ** 2)
    # hidden: it coasts on its velocity, its gate growing, and is lost after max_coast_s
    for k in range(1, 30):
        track.predict(4.1 + k * 0.1)
    assert np.linalg.norm(track.position - truth(7.0)) < 0.3 and not track.lost
    track.predict(8.2)
    assert track.lost


def side_on_figure(rng, centre=(6.0, 0.0), widen=0.0):
    """A person walking along +y seen from the origin: the near leg hides the far one, its side 0.2 m
    across; `widen` adds what a stereo matcher smears beyond each edge of the legs."""
    x, y = centre
    parts = [box_surface(rng, (x - 0.1, y), 0.20 + 2 * widen, 0.15, 0.0, 0.86, 900),
             box_surface(rng, (x, y), 0.30, 0.50, 0.83, 1.44, 1500),
             box_surface(rng, (x, y), 0.28, 0.26, 1.44, 1.80, 500)]
    return np.concatenate(parts)


def test_a_walkers_heading_places_its_centre_where_widened_legs_would_read_it_as_facing(rng):
    from toolbox.tracking.person import centre_facing
    plane = Plane(0.0, 0.0, 0.0, 0.0, 0.0)
    sharp = candidates(np.concatenate([ground(rng, (6, 0)), side_on_figure(rng)]), np.zeros(2), plane)[0]
    assert math.dist(sharp.xy, (6.0, 0.0)) < 0.03, sharp.xy          # the width told it side-on
    smeared = candidates(np.concatenate([ground(rng, (6, 0)), side_on_figure(rng, widen=0.06)]), np.zeros(2),
                         plane)[0]
    assert smeared.xy[0] < 5.96, smeared.xy                           # 0.32 m wide: read as half turned, 5 cm short
    assert centre_facing(smeared.shape, np.array([0.0, 0.8])) == pytest.approx([6.0, 0.0], abs=0.03)
    # walking away, the legs side by side: their face lies half a leg's depth before the centre
    away = candidates(np.concatenate([ground(rng, (5, 0)), figure(rng)]), np.zeros(2), plane)[0]
    assert centre_facing(away.shape, np.array([1.2, 0.0])) == pytest.approx([5.0, 0.0], abs=0.03)


def test_a_low_rock_at_a_persons_feet_widens_its_legs_and_the_legs_above_the_knees_are_clear_of_it(rng):
    from toolbox.tracking.detect import above_the_feet
    from toolbox.tracking.person import PersonModel, Trapezoid
    stereo = PersonModel(legs_to_torso=Trapezoid(0.0, 0.0, 0.92, 1.02))
    plane = Plane(0.0, 0.0, 0.0, 0.0, 0.0)
    rock = box_surface(rng, (5.0, -0.3), 0.35, 0.35, 0.0, 0.35, 800)     # beside the right leg, 0.35 m tall
    cloud = np.concatenate([ground(rng, (5, 0)), figure(rng), rock])
    merged = candidates(cloud, np.zeros(2), plane, model=stereo)[0]
    assert merged.terms["legs_to_torso"] == 0.0 and merged.confidence == 0.0, merged.terms
    assert merged.xy[1] < -0.05, merged.xy                               # its middle pulled towards the rock
    clear = above_the_feet(merged, np.zeros(2), stereo)
    assert clear.confidence > 0.9, clear.terms
    assert math.dist(clear.xy, (5.0, 0.0)) < 0.06, clear.xy
    # a boulder of a person's height stays wide above its foot too: no person there either
    lone = candidates(np.concatenate([ground(rng, (5, 0)), boulder(rng)]), np.zeros(2), plane, model=stereo)[0]
    assert above_the_feet(lone, np.zeros(2), stereo).confidence == 0.0


def test_a_noisy_sensors_ground_tail_beside_the_feet_does_not_widen_the_legs(rng):
    """At 7 m a stereo ground point stands once 0.49 m up (4 sigma of 0.12 m); the tail of the ground's
    noise just above that, smeared beside the feet, joined the cluster and read the legs wider than the
    torso. The legs are measured from one sigma above where points start to stand."""
    from toolbox.tracking.detect import legs_floor
    from toolbox.tracking.person import PersonModel, Trapezoid
    stereo = PersonModel(legs_to_torso=Trapezoid(0.0, 0.0, 0.92, 1.02))
    params = StandingParams(noise_per_m2=0.0025, min_cell_points=5)
    smear = np.column_stack([rng.uniform(6.95, 7.05, 300), rng.uniform(-0.45, 0.45, 300), rng.uniform(0.50, 0.58, 300)])
    cloud = np.concatenate([noisy_ground(rng, (7.0, 0.0), 0.0025), figure(rng, (7.0, 0.0)), smear])
    best = candidates(cloud, np.zeros(2), Plane(0.0, 0.0, 0.0), params, stereo)[0]
    assert best.confidence > 0.9 and best.shape.legs_width < 0.4, (best.terms, best.shape)
    seen = Cluster(best.points, 0.0, True)
    assert legs_floor(seen, np.zeros(2), params) == pytest.approx(5 * 0.0025 * 6.9 ** 2, abs=0.02)
    assert legs_floor(seen, np.zeros(2), StandingParams()) == 0.0    # the SR4000's
