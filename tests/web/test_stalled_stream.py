"""A browser that stops reading, in-process so the stall is certain: 20 MB of events are published at
it; publishing never waits, its queue drops and counts, and the server still shuts down at once."""
from __future__ import annotations

import asyncio
import socket
import time
from types import SimpleNamespace

from rvs_server.web import WebView


def test_a_stalled_stream_drops_instead_of_blocking_and_closes_promptly():
    async def run():
        view = WebView(SimpleNamespace(ready=True, token=None))  # only the event routes are used
        view.claim("127.0.0.1", 0)
        address = await view.start()
        loop = asyncio.get_running_loop()
        stalled = socket.socket()
        stalled.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        stalled.setblocking(False)
        await loop.sock_connect(stalled, address)
        await loop.sock_sendall(stalled, b"GET /events HTTP/1.1\r\nHost: rvs\r\n\r\n")  # never read again
        while not view.hub.clients:
            await asyncio.sleep(0.01)
        client = next(iter(view.hub.clients))
        worst = 0.0
        message = "x" * 1000
        for batch in range(200):
            started = time.perf_counter()
            for index in range(100):
                view.publish("log", {"message": message, "n": batch * 100 + index})
            worst = max(worst, time.perf_counter() - started)
            await asyncio.sleep(0)  # the writer task runs, and blocks on the full socket
        assert client.dropped_total > 10_000, "the stream never stalled: nothing was dropped"
        assert worst < 0.5, f"100 publishes took {worst * 1000:.1f} ms"
        started = time.monotonic()
        await view.close()
        assert time.monotonic() - started < 5.0
        stalled.close()
    asyncio.run(run())
