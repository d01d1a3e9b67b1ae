"""The one running job: its worker thread, progress, interruption at safe points, recovery sets.

A job handler is a plain function `handler(ctx: JobContext, cfg) -> dict` that runs in a worker
thread, so device I/O and heavy computation never block the transports. It reports progress with
`ctx.progress`, saves what it has finished with `ctx.checkpoint`, and calls `ctx.safe_point()` (or
`ctx.sleep`) where stopping is harmless; `break` makes the next safe point raise JobInterrupted.

Every job that can be resumed has a recovery set on disk from its first instant: the command, its
options and the last checkpoint. It is deleted when the job ends normally, so after `break`, `quit`,
a device fault or a crash the set is still there, and `continue` picks it up, even after a restart.
"""
from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from .files import write_text_atomic
from .host import Host, ModuleScope
from .recovery import RecoverySet, RecoveryStore

if TYPE_CHECKING:
    from drivers.sim.clock import SimClock

    from .devices import Devices

log = logging.getLogger("rvs.jobs")


class JobInterrupted(Exception):
    """Raised inside a job at a safe point after `break` or `quit`."""

    def __init__(self, reason: str = "break"):
        super().__init__(reason)
        self.reason = reason


class JobCounter:
    """Job ids are numbers that keep counting across restarts, so a recovery set's id is unique."""

    def __init__(self, path: Path):
        self.path = path
        self._lock = threading.Lock()

    def next(self) -> str:
        with self._lock:
            try:
                current = int(self.path.read_text().strip() or 0)
            except (OSError, ValueError):
                current = 0
            current += 1
            write_text_atomic(self.path, f"{current}\n")
            return str(current)


class Job:
    """The state of one running job, shared between the event loop and its worker thread."""

    def __init__(self, job_id: str, command: str, line: str):
        self.id = job_id
        self.command = command
        self.line = line
        self.percent = 0.0
        self.message = ""
        self.started = time.time()
        self.interrupt = threading.Event()
        self.interrupt_reason = "break"
        self.done = threading.Event()
        self.products: list[str] = []  # names of the product folders it writes (the retention rule keeps them)

    def request_interrupt(self, reason: str) -> None:
        self.interrupt_reason = reason
        self.interrupt.set()


class JobContext(ModuleScope):
    """What a job handler sees: its settings and state, progress, checkpoints, safe points, devices,
    clock, data directory. Built from named fields (dispatch.Dispatcher.start_job)."""

    def __init__(self, *, job: Job, server: Host, module: str | None = None,
                 recovery_set: RecoverySet | None = None, store: RecoveryStore | None = None,
                 resume: dict[str, Any] | None = None,
                 on_progress: Callable[[float, str], None] = lambda percent, message: None):
        self.job = job
        self.server = server
        self.module = module  # the name of the command's module: its settings and state
        self.resume = resume  # the last checkpoint when this run continues an interrupted job
        self._rset = recovery_set
        self._store = store
        self._on_progress = on_progress
        self.products: list[Any] = []  # folders this run writes; the runner closes unfinished ones
        self.log = logging.getLogger(f"rvs.job.{job.command}")

    @property
    def devices(self) -> Devices:
        return self.server.devices

    @property
    def clock(self) -> SimClock:
        return self.server.clock

    @property
    def data_dir(self) -> Path:
        return self.server.data_dir

    def progress(self, percent: float, message: str) -> None:
        self.job.percent = float(max(0.0, min(100.0, percent)))
        self.job.message = message
        self._on_progress(self.job.percent, message)

    def checkpoint(self, state: dict[str, Any]) -> None:
        """Persist what is finished; `continue` hands it back as `ctx.resume`."""
        if self._rset is None or self._store is None:
            return
        self._rset.state = state
        self._rset.percent = self.job.percent
        self._store.save(self._rset)

    def interrupted(self) -> bool:
        return self.job.interrupt.is_set()

    def safe_point(self) -> None:
        if self.job.interrupt.is_set():
            raise JobInterrupted(self.job.interrupt_reason)

    def native(self, step: str, func: Any, *args: Any, **kwargs: Any) -> Any:
        """func(*args, **kwargs) in the native worker (rvs_server/native.py): a crash there ends this
        job with WorkerDied, not the server; a break kills the step at once."""
        return self.server.native.call(step, func, args, kwargs, check=self.safe_point)

    def sleep(self, sim_seconds: float) -> None:
        """Wait in simulated time; a `break` ends the wait at once."""
        if self.clock.wait(self.job.interrupt, sim_seconds):
            raise JobInterrupted(self.job.interrupt_reason)

    def publish(self, topic: str, data: dict[str, Any]) -> None:
        self.server.publish_threadsafe(topic, data)

    # -- products -------------------------------------------------------------------------------

    def product(self, cfg: Any, name: str | None = None) -> Any:
        """The job's product folder: new (named by --output when the command has one), or the
        same folder again when this run continues an interrupted job."""
        arguments = cfg.model_dump(mode="json")
        products = self.server.products
        if self.resume and "product" in self.resume:
            product = products.reopen(self.resume["product"], self.job.command, arguments, job=self.job.id)
        else:
            product = products.create(self.job.command, name or arguments.get("output"), arguments,
                                      job=self.job.id)
            self.checkpoint({**(self.resume or {}), "product": product.name})
        self.products.append(product)
        self.job.products.append(product.name)
        return product

    def save_truth(self, product: Any) -> None:
        """With simulated devices, the simulator's truth of this instant goes to truth/."""
        truth = self.devices.truth
        if truth is not None:
            product.write_json("truth/state.json", truth.state(),
                               "simulator truth of the moment: rover pose, PTU angles, sensor poses (world frame)")

    def finish_product(self, product: Any) -> dict[str, Any]:
        """Write the manifest, announce the product, and give the reply's product keys."""
        product.finish()
        self.publish("product", {"name": product.name, "command": product.manifest["command"],
                                 "path": str(product.path)})
        return {"product": product.name, "path": str(product.path)}
