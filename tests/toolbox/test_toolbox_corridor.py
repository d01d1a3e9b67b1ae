"""toolbox.mapping.corridor on synthetic SR4000-like frames: a camera 1.5 m up sees the ground 1 to
4.5 m ahead (176 x 144 rays, 1 cm range noise) over planes, undulating ground, a 25 degree ramp and
box rocks 0.15 m tall and 0.2 m wide, at known distances along the path."""
from __future__ import annotations

import math
import time

import numpy as np
import pytest

from toolbox.mapping import corridor as C
from toolbox.mapping import hazard as H

PARAMS = C.CorridorParams()
CELL = PARAMS.cell
HALF_L = PARAMS.body_length / 2
HALF_W = PARAMS.half_width

# The synthetic SR4000: 176 x 144 pixels, 45.6 x 38 degrees, 1.5 m above the ground under the rover,
# 0.1 m ahead of its centre, its optical axis 37.35 degrees down: the image spans 1.0 to 4.5 m ahead.
WIDTH, HEIGHT, FOCAL = 176, 144, 209.0
CAMERA_UP, CAMERA_AHEAD, DEPRESSION = 1.5, 0.1, math.radians(37.35)
ROCK_HEIGHT, ROCK_HALF = 0.15, 0.10


def flat(slope_deg: float = 0.0, azimuth: float = 0.0):
    grade = math.tan(math.radians(slope_deg))
    return lambda x, y: grade * (x * math.cos(azimuth) + y * math.sin(azimuth))


def undulating(slope_deg, azimuth, amplitude, wavelength, wave_azimuth, phase):
    base = flat(slope_deg, azimuth)
    k = 2 * math.pi / wavelength
    return lambda x, y: base(x, y) + amplitude * np.sin(
        k * (x * math.cos(wave_azimuth) + y * math.sin(wave_azimuth)) + phase)


def ramp(start: tuple[float, float], azimuth: float, slope_deg: float, length: float):
    """Level ground, then a ramp rising at slope_deg along azimuth from the line through `start`,
    `length` metres long, then a plateau."""
    grade = math.tan(math.radians(slope_deg))

    def height(x, y):
        along = (x - start[0]) * math.cos(azimuth) + (y - start[1]) * math.sin(azimuth)
        return grade * np.clip(along, 0.0, length)
    return height


def path_point(pose, u, v=0.0, direction=1):
    """World (x, y) of path-frame (u, v): u along the driving direction from the rover's centre."""
    x, y, heading = pose
    c, s = direction * math.cos(heading), direction * math.sin(heading)
    return x + u * c - v * s, y + u * s + v * c


def frame(terrain, pose, rocks=(), look=0.0, noise=0.01, seed=0):
    """World points (N, 3) of one synthetic SR4000 frame from a rover at pose (x, y, heading), the
    camera turned `look` radians from the heading; rocks: (x, y, yaw) of 0.15 m boxes, 0.2 m square."""
    rng = np.random.default_rng(seed)
    x, y, heading = pose
    yaw = heading + look
    ground = float(terrain(np.float64(x), np.float64(y)))
    origin = np.array([x + CAMERA_AHEAD * math.cos(yaw), y + CAMERA_AHEAD * math.sin(yaw), ground + CAMERA_UP])
    forward = np.array([math.cos(yaw) * math.cos(DEPRESSION), math.sin(yaw) * math.cos(DEPRESSION),
                        -math.sin(DEPRESSION)])
    right = np.array([math.sin(yaw), -math.cos(yaw), 0.0])
    down = np.cross(forward, right)
    cols, rows = np.meshgrid(np.arange(WIDTH) + 0.5 - WIDTH / 2, np.arange(HEIGHT) + 0.5 - HEIGHT / 2)
    rays = (cols.reshape(-1, 1) * right + rows.reshape(-1, 1) * down) / FOCAL + forward
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)

    # The terrain: bisection on the height above ground along each ray (no occlusion on these terrains).
    near, far = np.full(len(rays), 0.5), np.full(len(rays), 12.0)
    for _ in range(30):
        mid = (near + far) / 2
        p = origin + mid[:, None] * rays
        above = p[:, 2] > terrain(p[:, 0], p[:, 1])
        near, far = np.where(above, mid, near), np.where(above, far, mid)
    t = (near + far) / 2

    for rock_x, rock_y, rock_yaw in rocks:
        top = float(terrain(np.float64(rock_x), np.float64(rock_y))) + ROCK_HEIGHT
        ca, sa = math.cos(rock_yaw), math.sin(rock_yaw)
        rel = origin - np.array([rock_x, rock_y, 0.0])
        o = np.array([rel[0] * ca + rel[1] * sa, -rel[0] * sa + rel[1] * ca, rel[2]])
        d = np.stack([rays[:, 0] * ca + rays[:, 1] * sa, -rays[:, 0] * sa + rays[:, 1] * ca, rays[:, 2]], axis=1)
        low = np.array([-ROCK_HALF, -ROCK_HALF, top - 1.0])
        high = np.array([ROCK_HALF, ROCK_HALF, top])
        with np.errstate(divide="ignore", invalid="ignore"):
            t1, t2 = (low - o) / d, (high - o) / d
        enter = np.nanmax(np.minimum(t1, t2), axis=1)
        leave = np.nanmin(np.maximum(t1, t2), axis=1)
        hits = (enter <= leave) & (enter > 0)
        t = np.where(hits, np.minimum(t, enter), t)

    t = t + rng.normal(0.0, noise, len(t))
    return origin + t[:, None] * rays


def rock_nearest_distance(pose, rock, direction=1):
    """True distance from the leading edge to the rock's nearest corner along the path."""
    rx, ry, yaw = rock
    corners = np.array([[a, b] for a in (-ROCK_HALF, ROCK_HALF) for b in (-ROCK_HALF, ROCK_HALF)])
    xy = np.array([rx, ry]) + corners @ np.array([[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]).T
    c, s = direction * math.cos(pose[2]), direction * math.sin(pose[2])
    u = (xy[:, 0] - pose[0]) * c + (xy[:, 1] - pose[1]) * s
    return float(u.min()) - HALF_L


# ---------------------------------------------------------------------------------- one frame
@pytest.mark.parametrize("heading_deg, rock_yaw_deg, lateral", [(0.0, 0.0, 0.0), (37.0, 10.0, 0.1),
                                                                  (-121.0, 45.0, -0.2)])
def test_rock_in_path_is_found_at_its_distance(heading_deg, rock_yaw_deg, lateral):
    pose = (1.3, -0.7, math.radians(heading_deg))
    terrain = flat(3.0, 0.8)
    rock = (*path_point(pose, HALF_L + 1.9, lateral), math.radians(rock_yaw_deg))
    view = C.corridor_view(frame(terrain, pose, [rock]), pose, PARAMS)
    truth = rock_nearest_distance(pose, rock)
    assert view.nearest is not None
    assert abs(view.nearest.distance - truth) <= CELL
    assert view.nearest.cause & H.STEP
    assert math.hypot(view.nearest.x - rock[0], view.nearest.y - rock[1]) <= ROCK_HALF * math.sqrt(2) + CELL
    # The same ground without the rock is clear.
    assert C.corridor_view(frame(terrain, pose), pose, PARAMS).nearest is None


def test_rock_beside_the_corridor_is_mapped_but_not_hit():
    pose = (0.0, 0.0, math.radians(20.0))
    rock = (*path_point(pose, HALF_L + 2.0, -(HALF_W + 0.3 + ROCK_HALF)), 0.0)
    view = C.corridor_view(frame(flat(2.0), pose, [rock]), pose, PARAMS)
    assert view.nearest is None
    row, col, inside = view.spec.cell_of(rock[0], rock[1])
    assert inside and view.code[row, col] & H.STEP and H.is_hazard(view.code[row, col])
    assert not view.swept[H.is_hazard(view.code)].any()
    # Moved 0.3 m closer to the path it grazes the corridor and is hit.
    rock = (*path_point(pose, HALF_L + 2.0, -(HALF_W + ROCK_HALF - 0.03)), 0.0)
    assert C.corridor_view(frame(flat(2.0), pose, [rock]), pose, PARAMS).nearest is not None


def test_slope_patch_is_found_where_the_true_dem_says():
    pose = (0.5, 0.2, math.radians(37.0))
    foot = HALF_L + 2.0
    terrain = ramp(path_point(pose, foot), pose[2], 25.0, 1.2)
    view = C.corridor_view(frame(terrain, pose), pose, PARAMS)
    assert view.nearest is not None and view.nearest.cause & H.SLOPE
    # The truth: the same chain on the exact heights of every cell.
    xs, ys = view.spec.centres()
    exact = terrain(xs[None, :], ys[:, None])
    code = H.hazard_maps(exact, CELL, PARAMS.hazard).code
    rows, cols = np.nonzero(view.swept & H.is_hazard(code))
    _, distance = C.swept_cells(xs[None, :], ys[:, None], pose, 1, PARAMS.body_length, HALF_W, PARAMS.reach, CELL)
    truth = distance[rows, cols].min()
    assert abs(view.nearest.distance - truth) <= CELL
    # And the truth is past the ramp's foot, within the plane window.
    assert 2.0 - CELL <= truth <= 2.0 + PARAMS.hazard.plane_radius


def test_driving_backward_looks_behind():
    pose = (2.0, 1.0, math.radians(-65.0))
    rock = (*path_point(pose, HALF_L + 1.5, 0.05, direction=-1), 0.3)
    points = frame(flat(1.0, 2.0), pose, [rock], look=math.pi)   # the head turned round
    back = C.corridor_view(points, pose, PARAMS, direction=-1)
    assert back.nearest is not None
    assert abs(back.nearest.distance - rock_nearest_distance(pose, rock, direction=-1)) <= CELL
    ahead = C.corridor_view(points, pose, PARAMS, direction=1)
    assert ahead.nearest is None and ahead.seen == 0.0


@pytest.fixture(scope="module")
def clean_noisy_frames() -> list[tuple[np.ndarray, tuple[float, float, float]]]:
    """200 frames of clean undulating ground at random poses (the points and the pose): the same for
    every step_min_cells, and making them is most of the test's time, so they are made once."""
    rng = np.random.default_rng(7)
    frames = []
    for i in range(200):
        terrain = undulating(2.0, rng.uniform(0, 2 * math.pi), 0.15, 8.0, rng.uniform(0, 2 * math.pi),
                             rng.uniform(0, 2 * math.pi))
        pose = (rng.uniform(-3, 3), rng.uniform(-3, 3), rng.uniform(-math.pi, math.pi))
        frames.append((frame(terrain, pose, seed=i), pose))
    return frames


@pytest.mark.parametrize("step_min_cells", [5, 2])   # the HazardConfig default and configs/mapping.toml's TOF value
def test_no_false_hits_on_clean_noisy_ground(step_min_cells, clean_noisy_frames):
    params = C.CorridorParams(hazard=H.HazardConfig(step_min_cells=step_min_cells))
    hits, seen = [], []
    for i, (points, pose) in enumerate(clean_noisy_frames):
        view = C.corridor_view(points.copy(), pose, params)   # a copy: each case gets the frames untouched
        seen.append(view.seen)
        if view.nearest is not None:
            hits.append((i, view.nearest))
    assert hits == []
    # The ground was seen (not the footprint, nor the 0.8 m before the bumper below the view).
    assert min(seen) > 0.4 and np.mean(seen) > 0.6


def test_swept_cells_counts_squares_that_overlap():
    # Heading 0 at the origin: the corridor is x in [-L/2, L/2 + ahead], |y| <= HALF_W.
    pose = (0.0, 0.0, 0.0)
    x = np.array([0.0, 0.0, 0.0, 1.0, -HALF_L - 0.02, -HALF_L - 0.03, HALF_L + 1.0 + 0.02])
    y = np.array([HALF_W + 0.02, HALF_W + 0.03, -HALF_W - 0.02, 0.0, 0.0, 0.0, 0.0])
    inside, distance = C.swept_cells(x, y, pose, 1, PARAMS.body_length, HALF_W, 1.0, 0.05)
    assert inside.tolist() == [True, False, True, True, True, False, True]
    assert distance[3] == pytest.approx(1.0 - HALF_L)
    assert distance[0] == 0.0 and distance[6] == pytest.approx(1.0 + 0.02)
    # At 45 degrees a square reaches a corner's half diagonal (0.035 m) across the side.
    pose = (0.0, 0.0, math.pi / 4)
    side = np.array([-math.sin(math.pi / 4), math.cos(math.pi / 4)])
    centre = np.array([math.cos(math.pi / 4), math.sin(math.pi / 4)])
    probe = centre + side * np.array([[HALF_W + 0.034], [HALF_W + 0.036]])
    inside, _ = C.swept_cells(probe[:, 0], probe[:, 1], pose, 1, PARAMS.body_length, HALF_W, 2.0, 0.05)
    assert inside.tolist() == [True, False]
    # Past the front-left corner, the highest point of the rectangle at 45 degrees, a square is out
    # once its lower edge clears the corner, though both path-axis bands still reach it.
    corner = centre * (HALF_L + 2.0) + side * HALF_W
    probe = corner + np.array([[0.0, 0.024], [0.0, 0.026]])
    inside, _ = C.swept_cells(probe[:, 0], probe[:, 1], pose, 1, PARAMS.body_length, HALF_W, 2.0, 0.05)
    assert inside.tolist() == [True, False]
    # Behind the rover only when driving backward.
    inside, distance = C.swept_cells(np.array([-1.0]), np.array([0.0]), (0.0, 0.0, 0.0), -1,
                                     PARAMS.body_length, HALF_W, 1.0, 0.05)
    assert inside[0] and distance[0] == pytest.approx(1.0 - HALF_L)


def test_empty_frame_is_all_unknown():
    view = C.corridor_view(np.empty((0, 3)), (0.0, 0.0, 0.3), PARAMS)
    assert view.nearest is None and view.seen == 0.0
    assert (view.code == H.UNKNOWN).all() and view.swept.any()


def test_views_are_cell_aligned():
    for pose in [(0.013, -7.49, 0.4), (123.456, 78.9, -2.0)]:
        spec = C.corridor_view(frame(flat(), pose), pose, PARAMS).spec
        for origin in (spec.origin_x, spec.origin_y):
            assert abs(origin / CELL - round(origin / CELL)) < 1e-6


# ---------------------------------------------------------------------------------- memory
def test_memory_keeps_a_hazard_that_left_the_view_and_drops_it_when_seen_clear():
    terrain = flat(2.0, 1.0)
    start = (0.0, 0.0, math.radians(30.0))
    rock = (*path_point(start, HALF_L + 1.8), 0.0)
    memory = C.HazardMemory(PARAMS)
    first = C.corridor_view(frame(terrain, start, [rock]), start, PARAMS)
    assert first.nearest is not None
    memory.update(first)
    # 1.5 m on, the rock's nearest corner is 0.16 m ahead of the bumper: below the field of view.
    closer = (*path_point(start, 1.5), start[2])
    later = C.corridor_view(frame(terrain, closer, [rock], seed=1), closer, PARAMS)
    assert later.nearest is None
    memory.update(later)
    hit = memory.nearest(closer, 1, 1.0)
    assert hit is not None and hit.cause & H.STEP
    assert abs(hit.distance - rock_nearest_distance(closer, rock)) <= CELL
    assert memory.nearest(closer, 1, 0.05) is None             # not within 0.05 m
    assert memory.nearest(closer, -1, 1.0) is None             # not behind
    # Back at the start the rock is gone (someone carried it away): the ground is seen clear.
    memory.update(C.corridor_view(frame(terrain, start, seed=2), start, PARAMS))
    assert memory.nearest(closer, 1, 1.0) is None
    assert memory.nearest(start, 1, PARAMS.reach) is None


@pytest.mark.parametrize("heading_deg, slope_deg, lateral, rock_yaw", [(0.0, 0.0, 0.0, 0.0), (37.0, 3.0, 0.1, 0.3),
                                                                       (140.0, 4.0, -0.25, 1.0)])
def test_memory_tracks_a_rock_all_the_way_under_the_bumper(heading_deg, slope_deg, lateral, rock_yaw):
    # A frame every 0.1 m while driving at a rock: long after it dropped below the view (about 0.8 m
    # before the bumper) the memory reports it at its distance, down to 0 under the footprint.
    start = (0.0, 0.0, math.radians(heading_deg))
    terrain = flat(slope_deg, 1.0)
    rock = (*path_point(start, HALF_L + 2.5, lateral), rock_yaw)
    memory = C.HazardMemory(PARAMS)
    checked = 0
    for k in range(30):
        pose = (*path_point(start, 0.1 * k), start[2])
        memory.update(C.corridor_view(frame(terrain, pose, [rock], seed=k), pose, PARAMS))
        truth = rock_nearest_distance(pose, rock)
        if truth < 0.9:
            hit = memory.nearest(pose, 1, 1.0)
            assert hit is not None and abs(hit.distance - max(truth, 0.0)) <= CELL, (k, truth, hit)
            checked += 1
    assert checked >= 10


def test_memory_view_agrees_with_the_view():
    pose = (0.4, 0.4, math.radians(-37.0))
    rock = (*path_point(pose, HALF_L + 2.5, -0.1), 0.2)
    view = C.corridor_view(frame(flat(2.0), pose, [rock]), pose, PARAMS)
    memory = C.HazardMemory(PARAMS)
    memory.update(view)
    assert memory.nearest(pose, 1, PARAMS.reach) == view.nearest


def test_memory_recentres_keeping_state():
    terrain = flat()
    memory = C.HazardMemory(PARAMS, size=16.0)
    start = (0.0, 0.0, 0.0)
    rock = (HALF_L + 2.0, 0.0, 0.0)
    memory.update(C.corridor_view(frame(terrain, start, [rock]), start, PARAMS))
    placed = memory.spec
    for x in (3.0, 6.0, 9.0):                                  # the rock behind, out of view
        pose = (x, 0.0, 0.0)
        memory.update(C.corridor_view(frame(terrain, pose, seed=int(x)), pose, PARAMS))
    assert memory.spec != placed and memory.spec.x_range[0] > placed.x_range[0]
    back = (1.0, 0.0, 0.0)
    hit = memory.nearest(back, 1, 2.0)
    assert hit is not None and abs(hit.distance - rock_nearest_distance(back, rock)) <= CELL
    # Far enough on, the grid moves past the rock and forgets it.
    for x in (12.0, 15.0):
        pose = (x, 0.0, 0.0)
        memory.update(C.corridor_view(frame(terrain, pose, seed=int(x)), pose, PARAMS))
    assert memory.nearest(back, 1, 2.0) is None
    memory.clear()
    assert memory.spec is None and memory.nearest(back, 1, 2.0) is None


def test_memory_refuses_another_cell():
    view = C.corridor_view(np.empty((0, 3)), (0.0, 0.0, 0.0), C.CorridorParams(cell=0.1))
    with pytest.raises(ValueError):
        C.HazardMemory(PARAMS).update(view)


def test_timing_print():
    pose = (0.0, 0.0, math.radians(37.0))
    rock = (*path_point(pose, HALF_L + 2.0), 0.0)
    points = frame(flat(2.0), pose, [rock])
    C.corridor_view(points, pose, PARAMS)
    runs = 20
    start = time.perf_counter()
    for _ in range(runs):
        view = C.corridor_view(points, pose, PARAMS)
    per_view = (time.perf_counter() - start) / runs
    memory = C.HazardMemory(PARAMS)
    memory.update(view)
    start = time.perf_counter()
    for i in range(200):
        memory.nearest((0.05 * (i % 20), 0.0, pose[2]), 1, 1.0)
    per_nearest = (time.perf_counter() - start) / 200
    print(f"\ncorridor_view {per_view * 1e3:.2f} ms on {len(points)} points ({view.spec.rows}x{view.spec.cols} cells); "
          f"HazardMemory.nearest {per_nearest * 1e3:.3f} ms")


def test_swept_ground_of_a_turn_or_a_backward_drive_from_the_memory():
    """What the memory says of the ground a turn on the spot or a backward drive sweeps: unseen where
    no frame looked, clear where frames did, and the remembered rock that the turn's corners reach."""
    terrain = flat(1.0, 0.5)
    start = (0.0, 0.0, 0.0)
    memory = C.HazardMemory(PARAMS)
    assert memory.swept(start, math.radians(90), 0.0).unseen == 1.0     # nothing seen yet
    # Frames from 2.5 m behind to the start: the ground round the start was seen ahead of the rover.
    for i, back in enumerate(np.arange(2.5, -0.01, -0.25)):
        pose = (-back, 0.0, 0.0)
        memory.update(C.corridor_view(frame(terrain, pose, seed=i), pose, PARAMS))
    turn = memory.swept(start, math.radians(90), 0.0)
    assert turn.hit is None and turn.cells > 20 and turn.unseen < 0.5, turn
    backward = memory.swept(start, 0.0, -0.5)
    assert backward.hit is None and backward.unseen == 0.0, backward
    assert memory.swept(start, 0.0, 7.0).unseen > 0.2          # past the last frame's reach: not all seen
    # A rock beside the front corner, seen by a frame from behind: the turn reaches it, a drive past does not.
    rock = (0.25, 0.38, 0.0)
    pose = (-1.5, 0.0, 0.0)
    memory.update(C.corridor_view(frame(terrain, pose, [rock], seed=99), pose, PARAMS))
    hit = memory.swept(start, math.radians(-45), 0.0).hit
    # The nearest hazard cell: the box or its rim.
    assert hit is not None and hit.cause & H.STEP and math.hypot(hit.x - 0.25, hit.y - 0.38) < 0.2, hit
    assert memory.swept(start, 0.0, -0.5).hit is None
