"""Benchmark: `status` round trip and throughput of the RVS server beside a bare asyncio echo server,
and of the same RVS server with web-view pages open beside without.

Both servers run as separate processes on the same loopback in the same run, so the ratios hold on a
shared, noisy machine where absolute figures do not. Also prints the server's peak memory idle and
after the load.

The pages (--pages, default 10) run in a process of their own, as browsers would: each holds an event
stream open on /events and polls /api/status and /api/products?limit=12 (the page asks for the status
every 5 s and on job events, for the products on product events; the default polls are tighter, 1 s
and 2 s, so the figure is a pessimistic page). With --job the server also runs a PTU job over and over
in both phases (progress events that reach every page). The measurement then alternates without and
with pages --repeats times on the one server, and prints the ratio with/without.

    .venv/bin/python tests/bench/bench_status.py [--rounds 2000] [--connections 50] [--per-connection 200]
        [--pages 10] [--status-every 1.0] [--products-every 2.0] [--repeats 2] [--job]
"""
from __future__ import annotations

import argparse
import asyncio
import multiprocessing
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

sys.path.insert(0, str(REPO / "tests" / "web"))
from web_client import free_port  # noqa: E402

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


# ------------------------------------------------------------------------------------- web pages
async def _pages(web: str, pages: int, status_every: float, products_every: float, stop, ready, out) -> None:
    import aiohttp
    host, port = web.rsplit(":", 1)
    counts = {"events": 0, "status": 0, "products": 0, "errors": 0}
    latencies: list[float] = []

    async def stream() -> None:
        reader, writer = await asyncio.open_connection(host, int(port))
        writer.write(f"GET /events HTTP/1.1\r\nHost: {web}\r\nAccept: text/event-stream\r\n\r\n".encode())
        status = await reader.readline()
        if b" 200 " not in status:
            counts["errors"] += 1
            return
        try:
            while line := await reader.readline():
                if line.startswith(b"data:"):
                    counts["events"] += 1
        finally:
            writer.close()

    async def poll(session, path: str, every: float, key: str, phase: float) -> None:
        await asyncio.sleep(phase)
        while True:
            start = time.perf_counter()
            try:
                async with session.get(f"http://{web}{path}") as response:
                    await response.read()
                    counts[key] += 1
                    if key == "status":
                        latencies.append((time.perf_counter() - start) * 1000)
                    if response.status != 200:
                        counts["errors"] += 1
            except aiohttp.ClientError:
                counts["errors"] += 1
            await asyncio.sleep(every)

    async with aiohttp.ClientSession(connector=aiohttp.TCPConnector(limit=0)) as session:
        tasks = [asyncio.create_task(stream()) for _ in range(pages)]
        for i in range(pages):   # spread over the period, as pages opened at different times would be
            tasks.append(asyncio.create_task(poll(session, "/api/status", status_every, "status",
                                                  status_every * i / pages)))
            tasks.append(asyncio.create_task(poll(session, "/api/products?limit=12", products_every, "products",
                                                  products_every * i / pages)))
        await asyncio.sleep(0.5)
        ready.set()
        while not stop.is_set():
            await asyncio.sleep(0.1)
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
    lat = np.array(latencies) if latencies else np.array([np.nan])
    out.put({**counts, "page_status_p50": float(np.percentile(lat, 50)),
             "page_status_p99": float(np.percentile(lat, 99))})


def _pages_process(*args) -> None:
    asyncio.run(_pages(*args))


class Pages:
    """N pages in a process of their own, from start() until stop()."""

    def __init__(self, web: str, args: argparse.Namespace):
        context = multiprocessing.get_context("spawn")
        self.stop_flag, self.ready, self.out = context.Event(), context.Event(), context.Queue()
        self.proc = context.Process(target=_pages_process, args=(web, args.pages, args.status_every,
                                    args.products_every, self.stop_flag, self.ready, self.out), daemon=True)

    def __enter__(self) -> Pages:
        self.proc.start()
        if not self.ready.wait(30):
            raise RuntimeError("the pages did not start")
        self.started = time.perf_counter()
        return self

    def __exit__(self, *exc) -> None:
        self.stop_flag.set()
        self.report = self.out.get(timeout=30)
        self.report["seconds"] = time.perf_counter() - self.started
        self.proc.join(10)


def ptu_job_loop(port: int, stop) -> None:
    """move-ptu back and forth until stopped: a job publishing progress events all along."""
    from conftest import LineClient
    with LineClient("127.0.0.1", port, timeout=120) as client:
        pan = 60
        while not stop.is_set():
            client.command(f"move-ptu --pan {pan} --tilt 0", timeout=120)
            pan = -pan


def pages_comparison(rvs: ServerProcess, args: argparse.Namespace) -> list[str]:
    import threading
    stop = threading.Event()
    job = threading.Thread(target=ptu_job_loop, args=(rvs.port, stop), daemon=True) if args.job else None
    if job:
        job.start()
        time.sleep(2.0)
    bare_rtt, with_rtt, bare_rate, with_rate, reports = [], [], [], [], []
    try:
        for _ in range(args.repeats):
            rtt, rate = measure(rvs.port, args)
            bare_rtt.append(rtt), bare_rate.append(rate)
            with Pages(rvs.web, args) as pages:
                rtt, rate = measure(rvs.port, args)
                with_rtt.append(rtt), with_rate.append(rate)
            reports.append(pages.report)
    finally:
        stop.set()
        if job:
            job.join(150)
    bare, loaded = np.concatenate(bare_rtt), np.concatenate(with_rtt)
    lines: list[str] = []
    print = lines.append  # noqa: A001 (the figures are printed after the echo comparison)

    def row(name: str, ours: float, ref: float, unit: str) -> None:
        print(f"{name:<22} {args.pages} pages {ours:10.3f} {unit:<6} none {ref:10.3f} {unit:<6} "
              f"ratio {ours / ref:6.2f}")

    print(f"\nrvs with {args.pages} web pages open beside without ({args.repeats} alternations"
          f"{', a move-ptu job running throughout' if args.job else ', server idle'}): each page holds /events open "
          f"and polls /api/status every {args.status_every:g} s and /api/products every {args.products_every:g} s")
    row("round trip p50", np.percentile(loaded, 50), np.percentile(bare, 50), "ms")
    row("round trip p99", np.percentile(loaded, 99), np.percentile(bare, 99), "ms")
    row("commands per second", float(np.mean(with_rate)), float(np.mean(bare_rate)), "1/s")
    seconds = sum(r["seconds"] for r in reports)
    total = {k: sum(r[k] for r in reports) for k in ("events", "status", "products", "errors")}
    print(f"the pages over {seconds:.1f} s: {total['status'] / seconds:.1f} /api/status and "
          f"{total['products'] / seconds:.1f} /api/products per second, {total['events'] / seconds:.1f} events per "
          f"second received in all, {total['errors']} errors; their /api/status p50 "
          f"{np.mean([r['page_status_p50'] for r in reports]):.2f} ms, "
          f"p99 {np.max([r['page_status_p99'] for r in reports]):.2f} ms")
    return lines


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--rounds", type=int, default=2000)
    parser.add_argument("--connections", type=int, default=50)
    parser.add_argument("--per-connection", type=int, default=200)
    parser.add_argument("--pages", type=int, default=10, help="web pages open in the second phase (0: skip it)")
    parser.add_argument("--status-every", type=float, default=1.0, help="each page's /api/status period, s")
    parser.add_argument("--products-every", type=float, default=2.0, help="each page's /api/products period, s")
    parser.add_argument("--repeats", type=int, default=5, help="alternations without / with pages")
    parser.add_argument("--job", action="store_true", help="a move-ptu job runs in both phases (events to pages)")
    args = parser.parse_args()

    with tempfile.TemporaryDirectory() as tmp:
        base = Path(tmp)
        rvs = ServerProcess(data_dir=base / "data", config_dir=write_configs(base / "configs"),
                            extra_args=["--web-port", str(free_port())]).start()
        echo = subprocess.Popen([sys.executable, "-c", ECHO_SERVER], stdout=subprocess.PIPE)
        try:
            echo_port = int(echo.stdout.readline())
            time.sleep(5.0)  # the simulated world builds in the background at start-up: let it finish
            idle = peak_rss_mib(rvs.proc.pid)
            echo_rtt, echo_rate = measure(echo_port, args)
            rvs_rtt, rvs_rate = measure(rvs.port, args)
            loaded = peak_rss_mib(rvs.proc.pid)
            echo_mem = peak_rss_mib(echo.pid)
            if args.pages:
                page_lines = pages_comparison(rvs, args)
                with_pages = peak_rss_mib(rvs.proc.pid)
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
    if args.pages:
        print("\n".join(page_lines))
        print(f"rvs peak memory after the pages: {with_pages:.0f} MiB")


if __name__ == "__main__":
    main()
