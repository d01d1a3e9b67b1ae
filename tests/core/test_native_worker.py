"""The native worker (rvs_server/native.py) against a real server: a real SIGSEGV in a job's native
step ends the job with one ERR 500, the same server process answers during and after, `continue`
retries the step and writes the map an uninterrupted run writes; a worker killed while idle is
started again for the next job; a step past the worker's memory limit ends the same way; the fault
switch refuses what does not apply."""
from __future__ import annotations

import os
import signal
import subprocess
import time
from pathlib import Path

import numpy as np

from rvs_server.products.rasters import read_geotiff

from conftest import pairs

MAP = "dem-full-tof --pan -20:20"


def product(server, reply: str) -> Path:
    return server.data_dir / "products" / pairs(reply)["product"]


def worker_pid(server) -> int:
    """The server's native worker: its child started by multiprocessing's spawn (not its resource tracker)."""
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        children = subprocess.run(["pgrep", "-P", str(server.proc.pid)], capture_output=True, text=True).stdout.split()
        for child in children:
            try:
                cmdline = Path(f"/proc/{child}/cmdline").read_bytes().replace(b"\0", b" ").decode()
            except OSError:
                continue
            if "spawn_main" in cmdline:
                return int(child)
        time.sleep(0.2)
    raise AssertionError("the server has no worker process")


def assert_same_maps(a: Path, b: Path) -> None:
    for name in ("dem.tif", "hazard.tif", "slope.tif", "step.tif"):
        if (a / name).exists():
            assert np.array_equal(read_geotiff(a / name)[0], read_geotiff(b / name)[0], equal_nan=True), name


def test_a_segfault_in_a_native_step_ends_the_job_not_the_server_and_continue_gives_the_same_map(server_factory,
                                                                                                  tmp_path):
    reference_server = server_factory(data_dir=tmp_path / "reference")
    with reference_server.connect(timeout=120) as c:
        reference = c.command(MAP, timeout=300)
        assert " OK " in reference, reference

    server = server_factory(data_dir=tmp_path / "crashed")
    pid = server.proc.pid
    with server.connect(timeout=120) as c:
        assert pairs(c.command("sim-fault --device worker --kind segv"))["state"] == "armed"
        before = worker_pid(server)
        crashed = c.command(MAP, timeout=300)
        assert "ERR 500 internal worker died: signal 11 (SIGSEGV) during grid; recovery set kept" in crashed, crashed
        assert crashed.endswith("recovery=1"), crashed
        status = pairs(c.command("status"))
        assert status["mode"] == "break" and status["recovery"] == "1" and server.proc.pid == pid
        assert server.proc.poll() is None
        resumed = c.command("continue --job 1", timeout=300)
        assert " OK " in resumed, resumed
        assert worker_pid(server) != before                  # a new worker took the step
        assert_same_maps(product(reference_server, reference), product(server, resumed))
        assert pairs(c.command("status"))["mode"] == "standby"


def test_a_worker_killed_while_idle_or_past_its_memory_limit_is_started_again(server_factory):
    server = server_factory(configs={"server.toml": "worker_memory_mb = 3000\n"})
    with server.connect(timeout=120) as c:
        os.kill(worker_pid(server), signal.SIGKILL)          # idle: nobody is told, the next job just runs
        assert " OK " in c.command(MAP, timeout=300)

        assert pairs(c.command("sim-fault --device worker --kind memory --after 1"))["after"] == "1"
        hog = c.command(MAP, timeout=300)
        assert "ERR 500 internal worker died: memory limit 3000 MiB passed" in hog and "during hazard" in hog, hog
        assert " OK " in c.command("continue", timeout=300)

        assert pairs(c.command("sim-fault --device worker --kind abrt"))["kind"] == "abrt"
        aborted = c.command(MAP, timeout=300)
        assert "worker died: signal 6 (SIGABRT) during grid" in aborted, aborted
        assert " OK " in c.command("abort", timeout=60)
        assert " OK " in c.command(MAP, timeout=300)       # abort dropped the recovery set; a new worker runs

        for line, wanted in (("sim-fault --device worker --kind silent", "does not apply to --device worker"),
                             ("sim-fault --device ptu --kind segv", "does not apply to --device ptu"),
                             ("sim-fault --device worker --kind bogus", "--kind")):
            reply = c.command(line)
            assert "ERR 400 bad-request" in reply and wanted in reply, reply
        assert pairs(c.command("sim-fault --clear --device worker"))["cleared"] == "worker"


def test_with_the_worker_off_steps_run_in_the_server_and_its_faults_are_refused(server_factory, tmp_path):
    """server.toml native_worker = false: the behaviour before the worker (the benchmark's `before`),
    the same map, no child, and no fault that would end the server itself."""
    server = server_factory(data_dir=tmp_path / "in-process", configs={"server.toml": "native_worker = false\n"})
    with server.connect(timeout=120) as c:
        reply = c.command("sim-fault --device worker --kind segv")
        assert reply.split()[1:3] == ["ERR", "409"] and "native worker is off" in reply, reply
        mapped = c.command(MAP, timeout=300)
        assert " OK " in mapped, mapped
    children = subprocess.run(["pgrep", "-P", str(server.proc.pid)], capture_output=True, text=True).stdout.split()
    assert not any(b"spawn_main" in Path(f"/proc/{child}/cmdline").read_bytes() for child in children
                   if Path(f"/proc/{child}/cmdline").exists())

    reference = server_factory(data_dir=tmp_path / "worker", configs={"server.toml": "native_worker = true\n"})
    worker_pid(reference)
    with reference.connect(timeout=120) as c:
        assert_same_maps(product(server, mapped), product(reference, c.command(MAP, timeout=300)))
