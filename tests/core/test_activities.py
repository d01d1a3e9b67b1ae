"""The activity core without a server: the device sharing rules (devices/sharing.py) and the frame
loop (activities.py) with a real simulation clock."""
from __future__ import annotations

import asyncio
import threading
import time
from types import SimpleNamespace

import pytest

from drivers.sim.clock import SimClock
from rvs_server.activities import Activities, Activity
from rvs_server.devices.sharing import DeviceSharing
from rvs_server.protocol import WrongMode


def test_a_job_holds_what_it_uses_until_it_drives_or_ends_and_an_activity_never_waits():
    sharing = DeviceSharing()
    sharing.job_uses("ptu")                       # outside the job's thread: nothing is held
    assert sharing.held() == set()
    with sharing.job_running():
        sharing.job_uses("ptu")
        sharing.job_uses("tof")
        with sharing.borrow("ptu", "tof") as busy:
            assert busy in ("ptu", "tof")         # refused at once, nothing borrowed
        sharing.release_job("ptu", "tof")         # the rover drives: the guard may look
        with sharing.borrow("ptu", "tof") as busy:
            assert busy is None
        sharing.job_uses("tof")
    assert sharing.held() == set()                # the job's end gives everything back
    with sharing.borrow("tof") as busy:
        assert busy is None


def test_a_job_waits_for_the_frame_in_progress_only():
    sharing = DeviceSharing()
    inside, release, took = threading.Event(), threading.Event(), []

    def activity():
        with sharing.borrow("tof") as busy:
            assert busy is None
            inside.set()
            release.wait(5)

    thread = threading.Thread(target=activity)
    thread.start()
    inside.wait(5)

    def job():
        with sharing.job_running():
            sharing.job_uses("tof")
            took.append(time.monotonic())

    worker = threading.Thread(target=job)
    worker.start()
    time.sleep(0.2)
    assert not took                               # the frame still has the camera
    released = time.monotonic()
    release.set()
    worker.join(5)
    thread.join(5)
    assert took and took[0] >= released


class Counting(Activity):
    kind = "hazard"

    def frame(self, seq: int) -> dict:
        if seq == 2:
            raise RuntimeError("the sensor hiccuped")
        return {"state": "clear"}

    def finish(self) -> dict:
        return {"frames": self.frames}


def test_the_loop_keeps_its_rate_turns_a_failing_frame_into_unknown_and_stops_on_request():
    events = []
    server = SimpleNamespace(clock=SimClock(10.0), publish_threadsafe=lambda topic, data: events.append((topic, data)))
    activities = Activities()
    activity = Counting(server, rate_hz=20.0)
    activities.start(activity, "hazard-start")
    with pytest.raises(WrongMode, match="already running"):
        activities.start(Counting(server, rate_hz=1.0), "hazard-start")
    assert activities.status() == {"hazard": "on", "track": "off"}
    time.sleep(0.3)                                # 3 simulated seconds: about 60 frames at 20 Hz
    summary = asyncio.run(activities.stop("hazard", "hazard-stop"))
    assert activities.status()["hazard"] == "off" and summary["frames"] == activity.frames
    assert 30 <= activity.frames <= 70, activity.frames
    assert events[1] == ("hazard", {"seq": 2, "state": "unknown", "reason": "RuntimeError: the sensor hiccuped"})
    assert all(data["state"] == "clear" for _, data in events[2:])
    with pytest.raises(WrongMode, match="no hazard activity is running"):
        asyncio.run(activities.stop("hazard", "hazard-stop"))
