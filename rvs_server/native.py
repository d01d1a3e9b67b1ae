"""The native worker: a supervised child process that runs the heavy native steps of jobs.

A segmentation fault or an abort inside COLMAP, Open3D or OpenCV kills the process it happens in.
Run in the server, it takes the transports, the activities and every client with it; run here, it
takes only this process. A job calls `JobContext.native(step, func, *args)` (a workflow operation
`StepContext.native(func, *args)`): `func` is a module-level function (toolbox algorithms: arrays
in, arrays out), its arguments and result cross the pipe pickled. Devices stay in the server.

When the child dies by any signal, or passes its memory limit (RLIMIT_AS, server.toml
`worker_memory_mb`), the call raises `WorkerDied`: the job ends `500 internal worker died: signal 11
(SIGSEGV) during STEP; recovery set kept`, the child is started again at the next call, and
`continue` retries the step (workflow steps checkpoint, so the finished ones are not redone). A
break while a step runs in the child kills the child: the step stops at once, not at its end.

The child is started with `spawn`, not `fork`: the server has threads (the job's, the devices'
pollers), and a fork of a threaded process may hold a lock forever. `sim-fault --device worker
--kind segv|abrt|kill [--after N]` arms a real signal in the child at its N-th next step; `--kind
memory` makes that step allocate past the real limit.
"""
from __future__ import annotations

import importlib
import logging
import multiprocessing
import os
import pickle
import signal
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

log = logging.getLogger("rvs.native")

FAULT_KINDS = ("segv", "abrt", "kill", "memory")
POLL_S = 0.05


class WorkerDied(Exception):
    """The child died (a signal, or past its memory limit) while it ran `step`."""

    def __init__(self, step: str, cause: str):
        super().__init__(f"worker died: {cause} during {step}")
        self.step, self.cause = step, cause


@dataclass
class FaultSwitch:
    """A crash armed for the child's `after`-th next step (0: the next one)."""

    kind: str | None = None
    after: int = 0

    def arm(self, kind: str, after: int) -> None:
        if kind not in FAULT_KINDS:
            raise ValueError(f"kind {kind!r}: one of {', '.join(FAULT_KINDS)}")
        self.kind, self.after = kind, after

    def clear(self) -> None:
        self.kind, self.after = None, 0

    def take(self) -> str | None:
        """The fault for the step about to run, counting this step."""
        if self.kind is None:
            return None
        if self.after > 0:
            self.after -= 1
            return None
        kind, self.kind = self.kind, None
        return kind


def signal_name(number: int) -> str:
    try:
        return signal.Signals(number).name
    except ValueError:
        return f"signal {number}"


class NativeWorker:
    """The server's one native worker. `call` blocks the calling (job) thread; one call at a time."""

    def __init__(self, memory_limit_mb: int | None, in_process: bool = False):
        self.memory_limit_mb = memory_limit_mb
        self.in_process = in_process       # server.toml native_worker = false: no child, calls run here
        self.faults = FaultSwitch()
        self.restarts = 0
        self.steps = 0
        self._process: multiprocessing.process.BaseProcess | None = None
        self._conn = None
        self._lock = threading.Lock()
        self._context = multiprocessing.get_context("spawn")

    # -- life ----------------------------------------------------------------------------------
    @property
    def pid(self) -> int | None:
        process = self._process
        return process.pid if process is not None and process.is_alive() else None

    def start(self) -> None:
        """Start the child if it is not running (a spawn imports numpy, OpenCV and Open3D: ~1-2 s)."""
        if self.in_process or (self._process is not None and self._process.is_alive()):
            return
        parent, child = self._context.Pipe()
        process = self._context.Process(target=_child_main, args=(child, self.memory_limit_mb),
                                        name="rvs-native", daemon=True)
        process.start()
        child.close()
        self._process, self._conn = process, parent
        log.info("native worker started (pid %d, memory limit %s MiB)", process.pid, self.memory_limit_mb or "none")

    def stop(self) -> None:
        """Kill the child (idle or not); the next call starts a new one."""
        process, conn = self._process, self._conn
        self._process = self._conn = None
        if conn is not None:
            conn.close()
        if process is not None and process.is_alive():
            process.kill()
            process.join(5.0)

    # -- work ----------------------------------------------------------------------------------
    def call(self, step: str, func: Callable[..., Any], args: tuple = (), kwargs: dict | None = None,
             check: Callable[[], None] | None = None) -> Any:
        """func(*args, **kwargs) in the child. Raises WorkerDied when it dies; what `check` raises
        (a break: JobInterrupted) after killing the child; func's own exception otherwise."""
        if self.in_process:
            with self._lock:
                self.steps += 1
                return func(*args, **(kwargs or {}))
        with self._lock:
            if self._process is None or not self._process.is_alive():
                if self._process is not None:
                    self.restarts += 1
                self.start()
            self.steps += 1
            fault = self.faults.take()
            target = (func.__module__, func.__qualname__)
            try:
                self._conn.send(("call", step, target, args, kwargs or {}, fault))
            except (BrokenPipeError, OSError):
                return self._died(step)
            while True:
                if check is not None:
                    try:
                        check()
                    except BaseException:
                        self.stop()          # the step stops now; the next call starts a new child
                        raise
                try:
                    if not self._conn.poll(POLL_S):
                        if not self._process.is_alive():
                            return self._died(step)
                        continue
                    kind, payload = self._conn.recv()
                except (EOFError, OSError):
                    return self._died(step)
                if kind == "ok":
                    return payload
                if kind == "raised":
                    raise payload
                if kind == "memory":
                    self.stop()
                    raise WorkerDied(step, f"memory limit {self.memory_limit_mb} MiB passed ({payload})")

    def _died(self, step: str) -> Any:
        process = self._process
        if process is not None:
            process.join(5.0)
        code = process.exitcode if process is not None else None
        self.stop()
        cause = (f"signal {-code} ({signal_name(-code)})" if code is not None and code < 0
                 else f"exit status {code}")
        log.error("native worker died: %s during %s; it is started again at the next step", cause, step)
        raise WorkerDied(step, cause)


# -- the child ---------------------------------------------------------------------------------
def _child_main(conn, memory_limit_mb: int | None) -> None:
    """Run calls until the pipe closes. Faults are real signals: a Python exception would not test
    what a crash in native code does."""
    if memory_limit_mb:
        import resource
        limit = int(memory_limit_mb) * 1024 * 1024
        resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
    signal.signal(signal.SIGINT, signal.SIG_IGN)       # a ^C to the server is the server's to handle
    for library in ("numpy", "cv2", "open3d"):        # ready before the first step needs them
        importlib.import_module(library)
    while True:
        try:
            message = conn.recv()
        except (EOFError, OSError):
            return
        _, step, (module, qualname), args, kwargs, fault = message
        try:
            if fault is not None:
                _crash(fault, memory_limit_mb)
            func = importlib.import_module(module)
            for part in qualname.split("."):
                func = getattr(func, part)
            result = func(*args, **kwargs)
            reply = ("ok", result)
        except MemoryError as exc:
            reply = ("memory", f"{type(exc).__name__} {exc}".strip())
        except BaseException as exc:      # the job's to handle, as if it had run in the server
            reply = ("raised", _picklable(exc))
        try:
            conn.send(reply)
        except MemoryError:
            conn.send(("memory", "MemoryError while sending the result"))


def _crash(kind: str, memory_limit_mb: int | None = None) -> None:
    if kind == "memory":                  # past the real RLIMIT_AS: MemoryError, as a runaway step gets
        hog = bytearray((memory_limit_mb or 1 << 20) * 1024 * 1024)
        del hog
        return
    if kind == "segv":
        import ctypes
        ctypes.string_at(0)               # a real invalid read: SIGSEGV from the kernel
    signals = {"abrt": signal.SIGABRT, "kill": signal.SIGKILL}
    os.kill(os.getpid(), signals.get(kind, signal.SIGSEGV))
    time.sleep(10)


def _picklable(exc: BaseException) -> BaseException:
    try:
        pickle.loads(pickle.dumps(exc))
        return exc
    except Exception:
        return RuntimeError(f"{type(exc).__name__}: {exc}")
