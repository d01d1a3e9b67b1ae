"""Benchmark: `status` round trip and throughput of the RVS server beside a bare asyncio echo server.

Both servers run as separate processes on the same loopback in the same run, so the ratios hold on a
shared, noisy machine where absolute figures do not. Also prints the server's peak memory idle and
after the load.

    .venv/bin/python tests/bench/bench_status.py [--rounds 2000] [--connections 50] [--per-connection 200]
"""
from __future__ import annotations

import argparse
import asyncio
import os
import subprocess
import sys
import tempfile
import textwrap
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "tests"))
from conftest import ServerProcess, write_configs  # noqa: E402

ECHO_SERVER = textwrap.dedent("""
    import asyncio, sys
    REPLY = b"1 OK mode=standby version=0.1.0 uptime=1.0 job=none command=none percent=0 recovery=0 "\\
            b"pan=0.00 tilt=0.00 dev.ptu=ok\\r\\n"
    async def handle(reader, writer):
        writer.write(b"RVS echo standby\\r\\n")
        while line := await reader.readline():
            writer.write(REPLY)
    async def main():
        server = await asyncio.start_server(handle, "127.0.0.1", 0)
        print(server.sockets[0].getsockname()[1], flush=True)
        await server.serve_forever()
    asyncio.run(main())
""")


def peak_rss_mib(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return float("nan")


async def round_trips(port: int, rounds: int) -> np.ndarray:
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    await reader.readline()
    times = np.empty(rounds)
    for i in range(rounds):
        start = time.perf_counter()
        writer.write(b"status\n")
        await reader.readline()
        times[i] = time.perf_counter() - start
    writer.close()
    return times * 1000


async def throughput(port: int, connections: int, per_connection: int) -> float:
    async def one() -> None:
        reader, writer = await asyncio.open_connection("127.0.0.1", port)
        await reader.readline()
        for _ in range(per_connection):
            writer.write(b"status\n")
            await reader.readline()
        writer.close()
    start = time.perf_counter()
    await asyncio.gather(*(one() for _ in range(connections)))
    return connections * per_connection / (time.perf_counter() - start)


def measure(port: int, args: argparse.Namespace) -> tuple[np.ndarray, float]:
    rtt = asyncio.run(round_trips(port, args.rounds))
    rate = asyncio.run(throughput(port, args.connections, args.per_connection))
    return rtt, rate


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--rounds", type=int, default=2000)
    parser.add_argument("--connections", type=int, default=50)
    parser.add_argument("--per-connection", type=int, default=200)
    args = parser.parse_args()

    with tempfile.TemporaryDirectory() as tmp:
        base = Path(tmp)
        rvs = ServerProcess(data_dir=base / "data", config_dir=write_configs(base / "configs")).start()
        echo = subprocess.Popen([sys.executable, "-c", ECHO_SERVER], stdout=subprocess.PIPE)
        try:
            echo_port = int(echo.stdout.readline())
            time.sleep(5.0)  # the simulated world builds in the background at start-up: let it finish
            idle = peak_rss_mib(rvs.proc.pid)
            echo_rtt, echo_rate = measure(echo_port, args)
            rvs_rtt, rvs_rate = measure(rvs.port, args)
            loaded = peak_rss_mib(rvs.proc.pid)
            echo_mem = peak_rss_mib(echo.pid)
        finally:
            echo.kill()
            rvs.stop()

    def row(name: str, ours: float, ref: float, unit: str) -> None:
        print(f"{name:<22} rvs {ours:10.3f} {unit:<6} echo {ref:10.3f} {unit:<6} ratio {ours / ref:6.2f}")

    print(f"status round trip on one connection ({args.rounds} rounds), "
          f"throughput with {args.connections} connections x {args.per_connection}")
    row("round trip p50", np.percentile(rvs_rtt, 50), np.percentile(echo_rtt, 50), "ms")
    row("round trip p99", np.percentile(rvs_rtt, 99), np.percentile(echo_rtt, 99), "ms")
    row("commands per second", rvs_rate, echo_rate, "1/s")
    print(f"rvs peak memory: idle {idle:.0f} MiB, after load {loaded:.0f} MiB (echo server {echo_mem:.0f} MiB); "
          f"cpu count {os.cpu_count()}")


if __name__ == "__main__":
    main()
