"""Benchmark: the `status` round trip while hop-plan runs, with the native worker (server.toml
native_worker = true, the default) and without it (false: COLMAP, the dense cloud and the gridding in
the job's thread, as before the worker), each beside the idle figure of the same server in the same run.

Per mode: a server on the 12 m world with the hopper's small camera (tests/hopping), one hop; then
--idle-s seconds of status round trips with nothing running, then hop-plan --plans times with the round
trips measured until each reply. One client sends `status` and waits for the reply, --interval-ms
apart, so a slow reply delays the next one and is counted once. Goal (issue 46): p99 during a job
within 2 times idle.

    .venv/bin/python tests/bench/bench_status_job.py [--plans 2] [--idle-s 10] [--interval-ms 20]
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "tests"))
from conftest import ServerProcess, write_configs  # noqa: E402

HOPPING = """sfm_threads = 1
[hopper.camera]
width = 320
height = 240
motion_blur = false
"""


def round_trips(server: ServerProcess, until: threading.Event, interval_s: float) -> list[float]:
    """Seconds of each status round trip until `until` is set."""
    times = []
    with server.connect(timeout=120) as client:
        while not until.is_set():
            started = time.perf_counter()
            reply = client.command("status", timeout=120)
            times.append(time.perf_counter() - started)
            assert " OK " in reply, reply
            time.sleep(interval_s)
    return times


def measure(worker: bool, plans: int, idle_s: float, interval_s: float) -> dict[str, list[float]]:
    root = Path(tempfile.mkdtemp(prefix=f"rvs-bench-status-{'worker' if worker else 'inproc'}-"))
    configs = write_configs(root / "configs", {"hopping.toml": HOPPING,
                                               "server.toml": f"native_worker = {str(worker).lower()}\n"})
    server = ServerProcess(data_dir=root / "data", config_dir=configs).start(timeout=300)
    try:
        with server.connect(timeout=300) as c:
            hop = c.command("hop --speed 1.5 --elevation 60 --heading 0", timeout=300)
            assert " OK " in hop, hop
        stop = threading.Event()
        timer = threading.Timer(idle_s, stop.set)
        timer.start()
        idle = round_trips(server, stop, interval_s)
        during: list[float] = []
        for _ in range(plans):
            done = threading.Event()
            results: list[list[float]] = []
            pinger = threading.Thread(target=lambda results=results, done=done: results.append(
                round_trips(server, done, interval_s)))
            with server.connect(timeout=600) as c:
                pinger.start()
                reply = c.command("hop-plan", timeout=600)
                done.set()
                pinger.join()
            assert " OK " in reply, reply
            during += results[0]
        return {"idle": idle, "during": during}
    finally:
        server.stop()


def percentiles(values: list[float]) -> tuple[float, float]:
    ms = np.asarray(values) * 1000.0
    return float(np.percentile(ms, 50)), float(np.percentile(ms, 99))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--plans", type=int, default=2, help="hop-plan jobs measured per mode")
    parser.add_argument("--idle-s", type=float, default=10.0)
    parser.add_argument("--interval-ms", type=float, default=20.0)
    args = parser.parse_args()
    rows = []
    for worker in (False, True):
        figures = measure(worker, args.plans, args.idle_s, args.interval_ms / 1000.0)
        idle50, idle99 = percentiles(figures["idle"])
        job50, job99 = percentiles(figures["during"])
        rows.append(("worker" if worker else "in the job's thread (before)", idle50, idle99, job50, job99,
                     len(figures["idle"]), len(figures["during"])))
    print(f"status round trip while hop-plan runs ({args.plans} plans per mode, one client, "
          f"{args.interval_ms:.0f} ms between requests)")
    print(f"{'native steps':32s} {'idle p50':>9s} {'idle p99':>9s} {'job p50':>9s} {'job p99':>9s} "
          f"{'p99 job/idle':>12s}  samples idle/job")
    for name, idle50, idle99, job50, job99, n_idle, n_job in rows:
        print(f"{name:32s} {idle50:8.2f}ms {idle99:8.2f}ms {job50:8.2f}ms {job99:8.2f}ms {job99 / idle99:12.2f}"
              f"  {n_idle}/{n_job}")
    print("goal: p99 during a job within 2 times idle")


if __name__ == "__main__":
    main()
