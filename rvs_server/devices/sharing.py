"""Who may use a device right now: the one job, or a background activity between its uses.

A job and an activity (hazard detection, tracking) share the PTU and the sensors, and the rules live
here, once, instead of in every command:

- A job holds a device from the first time it asks for it (`Device.require` in the job's thread)
  until the job ends, or until the rover starts to drive: a rover in motion hands its sensors to
  the activities that guard it (RoverDevice calls `release_job`). A job that asks again takes the
  device back, waiting at most for the activity's frame in progress.
- An activity borrows devices for one frame, never waiting: while a job holds any of them the
  borrow is refused and the activity reports that frame as unknown. A job is never delayed by more
  than one frame and never fails because an activity runs.
- An activity that steers a device all along (tracking keeps the PTU on its target) claims it: a job
  that starts after the claim and asks for it is `409 busy` naming the activity (the dispatcher
  refuses a job that declares the device before it starts). A job already running when the claim
  was made keeps what it had: the activity's frames wait for it as unknown frames.
"""
from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager

from rvs_server.activities import COMMANDS
from rvs_server.protocol import Busy


class DeviceSharing:
    def __init__(self) -> None:
        self._changed = threading.Condition()
        self._held: set[str] = set()       # held by the job
        self._borrowed: set[str] = set()   # borrowed by an activity for its frame in progress
        self._job_thread = threading.local()
        self._jobs = 0                             # jobs begun so far
        self._claims: dict[str, tuple[str, int]] = {}   # device -> (activity, jobs begun before the claim)

    # -- the job's side --------------------------------------------------------------------------
    @contextmanager
    def job_running(self) -> Iterator[None]:
        """Marks the calling thread as the job's for the handler's run; everything it held is given
        back when it ends, however it ends."""
        with self._changed:
            self._jobs += 1
            self._job_thread.serial = self._jobs
        self._job_thread.active = True
        try:
            yield
        finally:
            self._job_thread.active = False
            self.release_job()

    def in_job(self) -> bool:
        return bool(getattr(self._job_thread, "active", False))

    def job_uses(self, name: str) -> None:
        """The job takes `name` (no-op outside the job's thread: status, help and reset's checks only
        read). Waits while an activity's frame has it borrowed."""
        if not self.in_job():
            return
        with self._changed:
            claim = self._claims.get(name)
            if claim is not None and self._job_thread.serial > claim[1] and name not in self._held:
                raise Busy(self.claim_sentence(name))
            self._changed.wait_for(lambda: name not in self._borrowed)
            self._held.add(name)

    def release_job(self, *names: str) -> None:
        """Give back what the job holds (the named devices, or all of them)."""
        with self._changed:
            if names:
                self._held.difference_update(names)
            else:
                self._held.clear()
            self._changed.notify_all()

    def held(self) -> set[str]:
        with self._changed:
            return set(self._held)

    # -- claims: a device an activity steers all along -----------------------------------------------
    def claim(self, name: str, activity: str) -> None:
        with self._changed:
            self._claims[name] = (activity, self._jobs)

    def unclaim(self, name: str, activity: str) -> None:
        with self._changed:
            if self._claims.get(name, ("",))[0] == activity:
                del self._claims[name]

    def claimed_by(self, name: str) -> str | None:
        with self._changed:
            claim = self._claims.get(name)
            return claim[0] if claim else None

    def claim_sentence(self, name: str) -> str:
        activity = self.claimed_by(name) or "an activity"
        stop = COMMANDS.get(activity, ("", f"{activity}-stop"))[1]
        return f"the {name} is steered by the {activity} activity; {stop} first"

    # -- an activity's side -----------------------------------------------------------------------
    @contextmanager
    def borrow(self, *names: str) -> Iterator[str | None]:
        """For one frame: yields None when every named device was free and is now the activity's,
        else the name of one the job holds (the frame is skipped: nothing is borrowed)."""
        with self._changed:
            busy = next((n for n in names if n in self._held or n in self._borrowed), None)
            if busy is None:
                self._borrowed.update(names)
        if busy is not None:
            yield busy
            return
        try:
            yield None
        finally:
            with self._changed:
                self._borrowed.difference_update(names)
                self._changed.notify_all()
