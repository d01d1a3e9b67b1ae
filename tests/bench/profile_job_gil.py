"""Which code holds the interpreter in the server while a job runs: py-spy samples the server with
--gil (only the thread holding the GIL is recorded) during hop-plan, and the stacks are summed by
their innermost RVS frame and by their leaf.

A status reply waits for the interpreter while a job's thread holds it; bench_status_job.py measures
how long (p99), this says where. A C call that holds the interpreter for milliseconds in one piece (a
numpy operation on a large array, a pybind11 call that does not release it) cannot be preempted by any
switch interval: it has to move into the native worker or release the interpreter.

    .venv/bin/pip install py-spy        # not a dependency of RVS; ptrace must be allowed
    .venv/bin/python tests/bench/profile_job_gil.py [--plans 2] [--rate 250] [--top 25]
"""
from __future__ import annotations

import argparse
import collections
import shutil
import signal
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "tests"))
sys.path.insert(0, str(REPO / "tests" / "bench"))
from bench_status_job import HOPPING  # noqa: E402

from conftest import ServerProcess, write_configs  # noqa: E402


def record(plans: int, rate: int, out: Path) -> None:
    root = Path(tempfile.mkdtemp(prefix="rvs-profile-gil-"))
    configs = write_configs(root / "configs", {"hopping.toml": HOPPING})
    server = ServerProcess(data_dir=root / "data", config_dir=configs).start(timeout=300)
    try:
        with server.connect(timeout=300) as client:
            reply = client.command("hop --speed 1.5 --elevation 60 --heading 0", timeout=300)
            assert " OK " in reply, reply
            spy = subprocess.Popen([shutil.which("py-spy") or str(Path(sys.executable).parent / "py-spy"), "record",
                                    "--gil", "--nonblocking", "--format", "raw", "--rate", str(rate),
                                    "--pid", str(server.proc.pid), "--output", str(out)],
                                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            try:
                for _ in range(plans):
                    reply = client.command("hop-plan", timeout=600)
                    assert " OK " in reply, reply
            finally:
                spy.send_signal(signal.SIGINT)   # py-spy writes its file on an interrupt, not on SIGTERM
                spy.wait(timeout=60)
    finally:
        server.stop()


def summarise(path: Path, top: int) -> None:
    """py-spy's raw format: one line per distinct stack, frames joined by ';' outermost first, then the
    sample count."""
    by_leaf: collections.Counter[str] = collections.Counter()
    by_rvs: collections.Counter[str] = collections.Counter()
    by_thread: collections.Counter[str] = collections.Counter()
    total = 0
    for line in path.read_text().splitlines():
        stack, _, count = line.rpartition(" ")
        if not stack:
            continue
        n = int(count)
        frames = stack.split(";")
        total += n
        by_thread[frames[0]] += n
        by_leaf[frames[-1]] += n
        ours = [f for f in frames if any(part in f for part in ("rvs_server/", "toolbox/", "drivers/"))]
        by_rvs[ours[-1] if ours else "(no RVS frame)"] += n
    print(f"{total} samples with the GIL held")
    for title, counter in (("by thread", by_thread), ("by innermost RVS frame", by_rvs), ("by leaf", by_leaf)):
        print(f"\n{title}:")
        for name, n in counter.most_common(top):
            print(f"  {100 * n / max(total, 1):5.1f} %  {name}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--plans", type=int, default=2)
    parser.add_argument("--rate", type=int, default=250, help="samples per second")
    parser.add_argument("--top", type=int, default=25)
    parser.add_argument("--out", type=Path, default=Path(tempfile.gettempdir()) / "rvs-gil-stacks.txt")
    args = parser.parse_args()
    record(args.plans, args.rate, args.out)
    summarise(args.out, args.top)


if __name__ == "__main__":
    main()
