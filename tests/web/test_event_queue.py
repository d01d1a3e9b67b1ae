"""One browser's event queue: bounded, never blocking the publisher, progress coalesced, drops told."""
from __future__ import annotations

import asyncio
import json

from rvs_server.web.events import ClientQueue, EventHub, encode


def put(queue: ClientQueue, topic: str, **data) -> None:
    queue.put(topic, data, encode(topic, data))


def topics(texts: list[str]) -> list[tuple[str, dict]]:
    return [(e["topic"], e["data"]) for e in map(json.loads, texts)]


def test_progress_of_one_job_is_coalesced_to_the_newest():
    async def run():
        queue = ClientQueue(limit=4)
        put(queue, "mode", mode="busy")
        for percent in range(0, 101, 5):
            put(queue, "progress", job="7", percent=percent)
        put(queue, "progress", job="8", percent=1)
        got = topics(queue.take())
        assert got == [("mode", {"mode": "busy"}), ("progress", {"job": "7", "percent": 100}),
                       ("progress", {"job": "8", "percent": 1})]
        assert queue.dropped_total == 0 and queue.coalesced == 20
    asyncio.run(run())


def test_a_jobs_started_line_is_never_coalesced_away():
    """A slow page still sees where the job began: only the percents after it are merged."""
    async def run():
        queue = ClientQueue(limit=8)
        put(queue, "progress", job="9", percent=0, message="started")
        for percent in (40, 100):
            put(queue, "progress", job="9", percent=percent, message="")
        got = topics(queue.take())
        assert got == [("progress", {"job": "9", "percent": 0, "message": "started"}),
                       ("progress", {"job": "9", "percent": 100, "message": ""})]
        assert queue.coalesced == 1
    asyncio.run(run())


def test_a_full_queue_drops_counts_and_tells_the_client_first():
    async def run():
        queue = ClientQueue(limit=3)
        for index in range(10):
            put(queue, "log", message=str(index))
        got = topics(queue.take())
        assert got[0] == ("dropped", {"count": 7, "total": 7})
        assert [d["message"] for _, d in got[1:]] == ["0", "1", "2"]
        put(queue, "log", message="after")
        assert topics(queue.take()) == [("log", {"message": "after"})]  # told once
    asyncio.run(run())


def test_the_hub_encodes_once_and_never_waits_for_a_client():
    async def run():
        hub = EventHub()
        slow, fast = hub.open(), hub.open()
        for index in range(10_000):
            hub.publish("log", {"message": str(index)})
        assert len(fast.take()) == 257 and slow.dropped_total == 10_000 - 256
        hub.close_all()
        assert not hub.clients and slow.closed
    asyncio.run(run())
