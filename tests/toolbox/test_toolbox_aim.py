"""toolbox.odometry.aim: where a look should point to find its keyframe's ground again, and the
ground-plane homography stereo odometry warps through after a manoeuvre."""
from __future__ import annotations

import math

import numpy as np
import pytest

from toolbox.camera import Intrinsics
from toolbox.geometry import SensorMount, apply, camera_to_rover, invert, rigid, rotation_z
from toolbox.odometry.aim import View, aim_at, choose_aim, matchable, seen_share
from toolbox.odometry.stereo import StereoKeyframe, apply_homography, ground_homography

MOUNT = SensorMount.from_offsets((0.10, 0.0, 1.40), (0.0, 0.0, 0.0))
VIEW = View(960, 540, 700.0, 700.0, 480.0, 270.0, 25.0)
PANS, TILTS = (-158.0, 158.0), (-46.0, 0.0)


def ground_ahead(distance: float = 4.0, spread: float = 1.2, n: int = 400) -> np.ndarray:
    """Points on the ground (z = 0, rover frame) round a spot `distance` ahead."""
    rng = np.random.default_rng(3)
    return np.column_stack([distance + rng.uniform(-spread, spread, n), rng.uniform(-spread, spread, n), np.zeros(n)])


def turned(points: np.ndarray, degrees: float, forward: float = 0.0) -> np.ndarray:
    """The same world points in the frame of a rover that turned `degrees` left, then drove `forward`."""
    motion = rigid(rotation_z(math.radians(degrees))) @ rigid(translation=(forward, 0.0, 0.0))
    return apply(invert(motion), points)


def test_the_view_along_the_heading_is_kept_while_it_sees_the_keyframe():
    points = ground_ahead()
    assert seen_share(points, camera_to_rover(MOUNT, 0.0, math.radians(-20.0)), VIEW) > 0.9
    aim = choose_aim(points, MOUNT, VIEW, -20.0, PANS, TILTS, enough=0.3)
    assert not aim.pointed and (aim.pan_deg, aim.tilt_deg) == (0.0, -20.0)


@pytest.mark.parametrize("turn", [90.0, -90.0])
def test_after_a_turn_in_place_the_head_points_back_against_the_turn(turn):
    points = turned(ground_ahead(), turn)
    aim = choose_aim(points, MOUNT, VIEW, -20.0, PANS, TILTS, enough=0.3)
    assert aim.pointed and aim.along_share == 0.0 and aim.share > 0.9
    # pan positive right: a left turn looks right; of the views that see it all, the nearest the heading
    assert 60.0 <= aim.pan_deg * np.sign(turn) <= 95.0


def test_aim_at_puts_a_point_on_the_heads_axis():
    pan, tilt = aim_at(np.array([0.10, -3.0, 1.40 - 3.0]), MOUNT)   # 3 m right of the mast, 3 m below it
    assert pan == pytest.approx(90.0) and tilt == pytest.approx(-45.0)


def test_matchable_keeps_points_seen_from_nearly_the_same_direction_and_distance():
    points = np.array([[10.0, 0.0, 0.0], [2.0, 0.0, 0.0], [2.0, 2.0, 0.0]])
    ok = matchable(points, np.zeros(3), np.array([0.0, 1.0, 0.0]), max_angle_deg=12.0, max_scale=1.4)
    assert ok.tolist() == [True, False, False]      # far: 6 deg; near: 27 deg; beside: nearer by 2x


def test_beyond_reach_nothing_is_pointed():
    points = turned(ground_ahead(distance=4.0), 180.0, forward=25.0)    # 29 m behind: past 25 m of range
    aim = choose_aim(points, MOUNT, VIEW, -20.0, PANS, TILTS, enough=0.3)
    assert not aim.pointed and aim.share == 0.0


def test_the_ground_homography_carries_a_ground_pixel_to_where_the_motion_sees_it():
    camera = Intrinsics(960, 540, 700.0, 700.0, 480.0, 270.0)
    key_to_rover = camera_to_rover(MOUNT, 0.0, math.radians(-20.0))
    ground = ground_ahead(n=200)
    points_key = apply(invert(key_to_rover), ground)
    key = StereoKeyframe(np.zeros((len(ground), 2), np.float32), np.zeros((len(ground), 32), np.uint8), points_key,
                         camera, np.zeros((540, 960), np.uint8))
    # the rover turned 45 deg left and drove 1.5 m, the head panned 50 deg right
    motion = rigid(rotation_z(math.radians(45.0))) @ rigid(translation=(1.5, 0.0, 0.0))
    new_to_rover = camera_to_rover(MOUNT, math.radians(50.0), math.radians(-20.0))
    key_from_new = invert(key_to_rover) @ invert(motion) @ new_to_rover
    homography = ground_homography(key, key_from_new)
    points_new = apply(invert(key_from_new), points_key)
    k = camera.matrix
    expected = (points_new @ k.T)[:, :2] / points_new[:, 2:3]
    got = apply_homography(homography, (points_key @ k.T)[:, :2] / points_key[:, 2:3])
    assert np.max(np.linalg.norm(got - expected, axis=1)) < 1e-6
