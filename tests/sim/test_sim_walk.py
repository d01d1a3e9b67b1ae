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


def test_both_cameras_of_a_pair_see_a_walker_where_it_was_at_the_pulse(monkeypatch):
    """The two renders of a triggered pair run one after the other in wall time, while a fast clock
    moves the walker on and other sensors (the TOF, truth records) bring it to their own now: each
    render must show the world of the pulse, or the pair's disparity measures the walk (a 1.5 cm
    step between them reads a person at 6 m some 0.7 m nearer)."""
    import threading

    import drivers.avt_sensor as avt_sensor
    from drivers.avt import CameraSettings
    from drivers.avt_emulator import emulated_stereo_pair
    from drivers.sim.clock import SimClock
    from drivers.sim.config import WorldConfig
    from drivers.sim.testbed import WALK_STEP_M, SimulatedTestbed

    clock = SimClock(50.0)          # 10 ms of rendering is half a second of walking
    bed = SimulatedTestbed(clock, WorldConfig(seed=3, size_m=(10.0, 10.0), cell_m=0.02))
    _ = bed.world
    bed.place_astronaut(4.0, -2.0, to=(4.0, 2.0), speed=1.5)
    rendered: list[tuple[float, float]] = []
    real_render = avt_sensor.render

    def recording_render(world, camera_to_world, camera, sun=None):
        astronaut = next(o for o in world.obstacles() if o["kind"] == "astronaut")
        rendered.append((astronaut["x"], astronaut["y"]))
        return real_render(world, camera_to_world, camera, sun=sun)

    monkeypatch.setattr(avt_sensor, "render", recording_render)
    pair = emulated_stereo_pair(bed.world, lambda t: bed.sensor_pose("left", t), lambda t: bed.sensor_pose("right", t),
                                clock=clock, default_settings=CameraSettings(resolution="low"), faults=bed.faults)
    pair.open()
    done = threading.Event()

    def another_sensor() -> None:       # as the TOF's frames and truth records do, at their own now
        while not done.is_set():
            bed.update_obstacles()

    mover = threading.Thread(target=another_sensor, daemon=True)
    mover.start()
    try:
        for _ in range(3):
            rendered.clear()
            pulse = pair.grab()["left"].trigger_time_s
            assert len(rendered) == 2
            (left_x, left_y), (right_x, right_y) = rendered
            assert (left_x, left_y) == (right_x, right_y)
            true_x, true_y, _ = bed.walk.where(pulse)
            assert math.hypot(left_x - true_x, left_y - true_y) <= WALK_STEP_M + 1e-6
    finally:
        done.set()
        mover.join()
        pair.close()
