"""Load on loopback: 50 connections x 200 tagged `status` as fast as they go, while a `move-ptu` job
runs and a subscriber watches events. Every reply must arrive exactly once, on its own connection,
with its own tag. Prints the wall time and the latency percentiles (the figures are reported, not
asserted: timing belongs to tests/bench/)."""
from __future__ import annotations

import asyncio
import time

import numpy as np

CONNECTIONS = 50
PER_CONNECTION = 200


async def status_client(host: str, port: int, index: int, latencies: list[float]) -> dict[str, int]:
    reader, writer = await asyncio.open_connection(host, port)
    greeting = await reader.readline()
    assert greeting.startswith(b"RVS ")
    seen: dict[str, int] = {}
    for i in range(PER_CONNECTION):
        tag = f"c{index}-{i}"
        sent = time.perf_counter()
        writer.write(f"@{tag} status\n".encode())
        while True:
            line = (await reader.readline()).decode().rstrip("\r\n")
            assert line, "connection closed"
            reply_tag, word = line.split(" ", 2)[:2]
            assert word in ("OK", "ERR"), line
            seen[reply_tag] = seen.get(reply_tag, 0) + 1
            if reply_tag == tag:
                latencies.append(time.perf_counter() - sent)
                assert word == "OK", line
                break
    writer.close()
    await writer.wait_closed()
    return seen


async def job_client(host: str, port: int) -> tuple[str, list[str]]:
    reader, writer = await asyncio.open_connection(host, port)
    await reader.readline()
    writer.write(b"@sub subscribe\n@job move-ptu --pan 120 --tilt -30 --speed 25\n")
    lines = []
    while True:
        line = (await reader.readline()).decode().rstrip("\r\n")
        lines.append(line)
        if line.startswith("job OK") or line.startswith("job ERR"):
            break
    # the mode event that follows the job's end
    while not any(x == "* EVENT mode mode=standby" for x in lines):
        lines.append((await asyncio.wait_for(reader.readline(), 10)).decode().rstrip("\r\n"))
    writer.close()
    return line, lines


async def load(host: str, port: int) -> tuple[float, list[float], list[dict[str, int]], tuple[str, list[str]]]:
    latencies: list[float] = []
    start = time.perf_counter()
    job = asyncio.ensure_future(job_client(host, port))
    await asyncio.sleep(0.05)
    results = await asyncio.gather(*(status_client(host, port, i, latencies) for i in range(CONNECTIONS)))
    elapsed = time.perf_counter() - start
    return elapsed, latencies, results, await job


def test_fifty_connections_with_a_job_and_events(server):
    elapsed, latencies, results, (job_reply, job_lines) = asyncio.run(load(server.host, server.port))
    for index, seen in enumerate(results):
        assert seen == {f"c{index}-{i}": 1 for i in range(PER_CONNECTION)}  # exactly once, own tags only
    assert len(latencies) == CONNECTIONS * PER_CONNECTION
    assert job_reply.startswith("job OK job=1 pan=119.9") and " tilt=-29.9" in job_reply
    assert job_lines[0] == "sub OK topics=\"mode progress product hazard track log navigate guard\""
    assert "* EVENT mode mode=busy" in job_lines
    assert any(line.startswith("job PROGRESS") for line in job_lines)
    assert any(line.startswith("* EVENT progress job=1") for line in job_lines)
    ms = np.array(latencies) * 1000
    print(f"\nload: {CONNECTIONS}x{PER_CONNECTION} status in {elapsed:.2f} s "
          f"({len(ms) / elapsed:.0f} commands/s); latency ms p50 {np.percentile(ms, 50):.2f} "
          f"p90 {np.percentile(ms, 90):.2f} p99 {np.percentile(ms, 99):.2f} max {ms.max():.2f}")
