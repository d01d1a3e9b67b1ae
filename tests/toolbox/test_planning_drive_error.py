"""The drive-error model behind navigate's cut: its spread against the simulated rover's own errors,
and the cut against a wall beside the path."""
import math

import numpy as np
import pytest

from drivers.sim.config import DriveError, WorldConfig
from drivers.sim.motion import dead_reckon, execute, turn_and_distance
from drivers.sim.rover import Rover
from drivers.sim.world import World
from toolbox.grid import GridSpec
from toolbox.planning.drive_error import cut_for_drive_error, drive_error_profile, footprint_outline

MODEL = DriveError()


def test_a_straight_leg_spreads_as_the_closed_form():
    profile = drive_error_profile(np.array([[0.0, 0.0], [2.0, 0.0]]), 0.0, MODEL, sample_m=0.1)
    length = profile.along_m[-1]
    turn = math.radians(MODEL.turn_noise_deg)          # no turn: only the absolute turn noise
    drift = math.radians(MODEL.heading_drift_deg_per_m) * length
    sideways = math.hypot(turn * length, MODEL.lateral_slip_per_m * length, drift * length / 2)
    along = MODEL.distance_scale * length
    assert profile.sigma_m[-1] == pytest.approx(max(sideways, along), rel=1e-9)
    assert np.all(np.diff(profile.sigma_m) > 0) and profile.sigma_m[0] == 0.0


def test_the_spread_matches_the_simulated_rovers_errors():
    """Monte Carlo with the simulator's own motion (drivers/sim/motion.py) on rock-free ground: the
    model's standard deviation at the end of a turning path is within 10 % of the measured one."""
    world = World.build(WorldConfig(seed=4, size_m=(10.0, 10.0), rocks={"cover": 0.0}, craters={"count": 0}))
    rover = Rover(world)
    path = np.array([[0.0, 0.0], [0.0, 2.0], [1.5, 3.5], [3.0, 3.5]])
    rng = np.random.default_rng(1)
    ends = []
    for _ in range(400):
        rover.place(0.0, 0.0, 0.0)
        believed = (0.0, 0.0, 0.0)
        for target in path[1:]:
            turn, distance = turn_and_distance(believed, target)
            execute(rover, turn, distance, MODEL, rng, step_height=1.0, sample_m=1.0)
            believed = dead_reckon(believed, turn, distance)
        ends.append(rover.pose)
    ends = np.array(ends)
    measured = math.sqrt(np.linalg.eigvalsh(np.cov(ends[:, :2].T))[-1])
    profile = drive_error_profile(path, 0.0, MODEL)
    assert profile.sigma_m[-1] == pytest.approx(measured, rel=0.10)
    assert math.sqrt(profile.covariance[-1, 2, 2]) == pytest.approx(np.std(ends[:, 2]), rel=0.10)
    predicted = profile.sigma_m[-1]
    # The first turn (90 degrees) dominates: without it the spread is much smaller.
    assert drive_error_profile(path, math.pi / 2, MODEL).sigma_m[-1] < 0.7 * predicted


def wall_beside_the_path(gap_m: float) -> tuple[GridSpec, np.ndarray]:
    """A 10 x 4 m map (5 cm cells, y = 0 on cell centres) with a hazard row at y = gap_m; the distance to it."""
    spec = GridSpec(origin_x=-1.025, origin_y=-2.025, cell=0.05, rows=81, cols=200)
    _, ys = spec.centres()
    distance = np.abs(ys - gap_m)[:, None] * np.ones((1, spec.cols))
    return spec, distance


FOOTPRINT = (0.55, 0.50)


def drive_length(cut) -> float:
    return float(np.linalg.norm(np.diff(cut.waypoints, axis=0), axis=1).sum())


def test_the_drive_ends_where_the_error_would_take_the_side_onto_the_wall():
    """Beside a wall the room is the gap less half the rover's width; the error of the side's points
    towards the wall is the centre's sideways error plus the heading error times each point's lever."""
    spec, distance = wall_beside_the_path(0.5)
    path = np.array([[0.0, 0.0], [8.0, 0.0]])
    profile = drive_error_profile(path, math.pi / 2, MODEL, sample_m=spec.cell)
    levers = np.linspace(-0.275, 0.275, 12)                  # the left side, rear to front
    towards_wall = np.stack([np.zeros_like(levers), np.ones_like(levers), levers], axis=1)
    sigma = np.sqrt(np.einsum("mi,nij,mj->nm", towards_wall, profile.covariance, towards_wall)).max(axis=1)
    expected = profile.along_m[np.argmax(2.0 * sigma > 0.5 - 0.25) - 1]
    cut, error = cut_for_drive_error(path, math.pi / 2, distance, spec, FOOTPRINT, MODEL, 2.0)
    assert not cut.complete and 1.0 < expected < 6.0
    assert drive_length(cut) == pytest.approx(expected, abs=spec.cell + 1e-9)
    assert error == pytest.approx(0.25, abs=0.02)
    # Facing along the path, the same wall leaves it longer; at 1 sigma longer still; 0 sigmas: no cut.
    facing, _ = cut_for_drive_error(path, 0.0, distance, spec, FOOTPRINT, MODEL, 2.0)
    assert drive_length(facing) > expected + 0.3
    one, _ = cut_for_drive_error(path, math.pi / 2, distance, spec, FOOTPRINT, MODEL, 1.0)
    assert drive_length(one) > expected + 0.3
    off, error = cut_for_drive_error(path, math.pi / 2, distance, spec, FOOTPRINT, MODEL, 0.0)
    assert off.complete and error == 0.0


def test_the_footprint_faces_along_the_leg():
    """0.4 m from a wall (the planner's clearance) the rover's side keeps 15 cm, where a disc round its
    corners (0.37 m) would keep 3: it drives on for metres. A rover 10 cm wider keeps 10 cm and stops
    sooner."""
    spec, distance = wall_beside_the_path(0.4)
    path = np.array([[0.0, 0.0], [8.0, 0.0]])
    along, _ = cut_for_drive_error(path, 0.0, distance, spec, FOOTPRINT, MODEL, 2.0)
    wider, _ = cut_for_drive_error(path, 0.0, distance, spec, (0.55, 0.60), MODEL, 2.0)
    assert drive_length(along) > 3.5
    assert drive_length(wider) < drive_length(along) - 0.3


def test_open_ground_is_not_cut_and_a_cut_keeps_the_waypoints_before_it():
    spec, distance = wall_beside_the_path(3.0)
    path = np.array([[0.0, 0.0], [2.0, 0.0], [2.0, 0.8], [4.0, 0.8]])
    whole, error = cut_for_drive_error(path, 0.0, distance, spec, FOOTPRINT, MODEL, 2.0)
    assert whole.complete and error == 0.0 and np.array_equal(whole.waypoints, path)
    spec, distance = wall_beside_the_path(1.2)        # the last leg runs 0.4 m from the wall
    cut, _ = cut_for_drive_error(path, 0.0, distance, spec, FOOTPRINT, MODEL, 2.0)
    assert not cut.complete
    assert np.array_equal(cut.waypoints[:3], path[:3]) and len(cut.waypoints) == 4
    assert cut.waypoints[-1][1] == pytest.approx(0.8) and 2.0 <= cut.waypoints[-1][0] < 4.0


def test_a_rover_pushed_close_to_a_hazard_may_drive_away_from_it():
    spec, distance = wall_beside_the_path(0.3)        # within its corners' reach of the wall
    away = np.array([[0.0, 0.0], [0.0, -1.2], [3.0, -1.2]])
    cut, _ = cut_for_drive_error(away, 0.0, distance, spec, FOOTPRINT, MODEL, 2.0)
    assert cut.complete
    towards = np.array([[0.0, 0.0], [0.0, 0.2], [3.0, 0.2]])   # closer still: it stops as its front meets the wall
    cut, _ = cut_for_drive_error(towards, 0.0, distance, spec, FOOTPRINT, MODEL, 2.0)
    assert not cut.complete and drive_length(cut) <= spec.cell + 1e-9


def test_a_drive_is_never_cut_shorter_than_asked():
    """However large the error, a drive keeps min_drive_m: unless it may go that far, a rover cut to
    nothing would look again from the same place and be cut again, for ever."""
    sloppy = DriveError(turn_noise_deg=60.0)
    spec, distance = wall_beside_the_path(0.4)
    path = np.array([[0.0, 0.0], [3.0, 0.0]])
    cut, _ = cut_for_drive_error(path, 0.0, distance, spec, FOOTPRINT, sloppy, 2.0)
    assert drive_length(cut) < 0.1
    cut, error = cut_for_drive_error(path, 0.0, distance, spec, FOOTPRINT, sloppy, 2.0, min_drive_m=0.2)
    assert 0.2 <= drive_length(cut) < 0.3 and error > 0.15


def test_the_outline_goes_round_the_footprint():
    outline = footprint_outline(0.55, 0.50, 0.05)
    assert np.abs(outline).max(axis=0) == pytest.approx([0.275, 0.25])
    gaps = np.linalg.norm(np.diff(np.vstack([outline, outline[:1]]), axis=0), axis=1)
    assert gaps.max() <= 0.05 + 1e-9 and len(outline) >= 2 * (0.55 + 0.50) / 0.05
    with pytest.raises(ValueError, match="footprint"):
        footprint_outline(0.0, 0.5, 0.05)
