"""Recovery sets: what `continue` needs to resume a job (the command as validated, its last
checkpoint), stored as JSON files under `<data>/recovery/` from a job's first instant until it ends
normally. Its own module, below the host's interface and the jobs, so both can name it
(rvs_server/jobs.py uses it; rvs_server/host.py types the server's store with it).
"""
from __future__ import annotations

import json
import logging
import shutil
import time
from dataclasses import MISSING, dataclass, field, fields
from pathlib import Path
from typing import Any

from .files import write_json_atomic

log = logging.getLogger("rvs.jobs")


@dataclass
class RecoverySet:
    """What `continue` needs to resume a job: the command as validated, and its last checkpoint."""

    job: str
    command: str
    options: dict[str, Any]
    line: str
    state: dict[str, Any] | None = None
    created: float = field(default_factory=time.time)
    updated: float = field(default_factory=time.time)
    reason: str = "running"  # running (crashed if found at start-up) | break | quit | device | timeout
    percent: float = 0.0
    devices: list[str] = field(default_factory=list)

    def to_json(self) -> dict[str, Any]:
        return dict(self.__dict__)


class UnreadableRecoverySet(Exception):
    def __init__(self, job: str, path: Path, reason: str):
        super().__init__(f"recovery set {job} ({path}) is unreadable: {reason}")
        self.job = job


class RecoveryStore:
    """Recovery sets as JSON files under `<data>/recovery/`, written atomically."""

    def __init__(self, directory: Path):
        self.directory = directory
        self.directory.mkdir(parents=True, exist_ok=True)

    def _path(self, job: str) -> Path:
        return self.directory / f"{job}.json"

    def save(self, rset: RecoverySet) -> None:
        rset.updated = time.time()
        # A kill or a power cut must not leave a half-written set.
        write_json_atomic(self._path(rset.job), rset.to_json(), default=_jsonable)

    def read(self, job: str) -> RecoverySet | None:
        """The stored set of `job`, None if there is none; raises UnreadableRecoverySet naming the file
        when it is damaged (edited by hand, a disk error), so `continue` can say which."""
        path = self._path(job)
        try:
            with open(path) as handle:
                data = json.load(handle)
        except FileNotFoundError:
            return None
        except (OSError, ValueError) as exc:
            raise UnreadableRecoverySet(job, path, str(exc)) from None
        problem = _recovery_set_problem(data, job)
        if problem:
            raise UnreadableRecoverySet(job, path, problem)
        return RecoverySet(**data)

    def load(self, job: str) -> RecoverySet | None:
        """Like read, but a damaged set is logged and counts as none."""
        try:
            return self.read(job)
        except UnreadableRecoverySet as exc:
            log.error("%s", exc)
            return None

    def jobs(self) -> list[str]:
        """Every stored set's job id, readable or not, oldest update first (a damaged set by its file's
        time, which its last save set)."""
        def updated(path: Path) -> tuple[float, int]:
            rset = self.load(path.stem)
            try:
                when = rset.updated if rset else path.stat().st_mtime
            except FileNotFoundError:
                when = 0.0
            return when, _job_number(path.stem)
        return [p.stem for p in sorted(self.directory.glob("*.json"), key=updated)]

    def folder(self, job: str) -> Path:
        """A job's working folder: its workflow checkpoints live here, beside its recovery set."""
        return self.directory / job

    def delete(self, job: str) -> None:
        self._path(job).unlink(missing_ok=True)
        shutil.rmtree(self.folder(job), ignore_errors=True)

    def all(self) -> list[RecoverySet]:
        sets = [self.load(p.stem) for p in self.directory.glob("*.json")]
        return sorted((s for s in sets if s is not None), key=lambda s: (s.updated, _job_number(s.job)))

    def latest(self) -> RecoverySet | None:
        sets = self.all()
        return sets[-1] if sets else None

    def latest_job(self) -> str | None:
        """The job `continue` resumes by default, even if its set is damaged: resuming an older job
        instead would surprise whoever drives the rover."""
        jobs = self.jobs()
        return jobs[-1] if jobs else None

    def count(self) -> int:
        return sum(1 for _ in self.directory.glob("*.json"))


_RECOVERY_FIELDS = {f.name: f for f in fields(RecoverySet)}


def _recovery_set_problem(data: Any, job: str) -> str:
    """What makes stored JSON not a recovery set of `job`, or "" if nothing does."""
    if not isinstance(data, dict):
        return "not a JSON object"
    missing = [name for name, f in _RECOVERY_FIELDS.items()
               if name not in data and f.default is MISSING and f.default_factory is MISSING]
    if missing:
        return "missing " + ", ".join(missing)
    unknown = sorted(set(data) - set(_RECOVERY_FIELDS))
    if unknown:
        return "unknown fields " + ", ".join(unknown)
    if data["job"] != job:
        return f"it names job {data['job']!r}, not {job}"
    for name, kind in (("command", str), ("line", str), ("options", dict), ("devices", list)):
        if name in data and not isinstance(data[name], kind):
            return f"{name} is not a {kind.__name__}"
    return ""


def _job_number(job: str) -> int:
    return int(job) if job.isdigit() else -1


def _jsonable(value: Any) -> Any:
    if isinstance(value, (tuple, set)):
        return list(value)
    if isinstance(value, Path):
        return str(value)
    if hasattr(value, "tolist"):
        return value.tolist()
    raise TypeError(f"cannot store {type(value).__name__} in a recovery set")
