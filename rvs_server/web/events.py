"""Server-Sent Events: the web view is the third consumer of `Server.publish`, beside the subscribed
text connections and the ZeroMQ PUB socket, so a browser sees exactly the events they see.

A browser that is slow, or stopped in a debugger, must never hold the server up. Each one gets a
bounded queue that `publish` fills without waiting; its own writer task empties it. A progress event
replaces the same job's progress still waiting in the queue (coalesced: only the newest percent
matters), except the job's `started` line, which marks where the job began and is always delivered.
When the queue is full any other event is dropped and counted; the client is told how many before
its next event, as `{"topic": "dropped", "data": {"count": N, "total": T}}`.
"""
from __future__ import annotations

import asyncio
import collections
import json
from collections.abc import Mapping
from typing import Any

QUEUE_LIMIT = 256          # events waiting for one browser
MAX_CLIENTS = 64           # event streams open at once; more are refused (503)
KEEPALIVE_S = 15.0         # a comment line this often, so a vanished browser is noticed


def _json(value: Any) -> Any:
    if isinstance(value, (tuple, set)):
        return list(value)
    if hasattr(value, "tolist"):
        return value.tolist()
    return str(value)


def encode(topic: str, data: Mapping[str, Any]) -> str:
    """One event as the JSON text the page receives."""
    return json.dumps({"topic": topic, "data": dict(data)}, default=_json, separators=(",", ":"))


class _Entry:
    __slots__ = ("key", "text")

    def __init__(self, key: Any, text: str):
        self.key, self.text = key, text


class ClientQueue:
    """One browser's events: bounded, never blocks the publisher, coalesces progress, counts drops."""

    def __init__(self, limit: int = QUEUE_LIMIT):
        self.limit = limit
        self.entries: collections.deque[_Entry] = collections.deque()
        self.by_key: dict[Any, _Entry] = {}
        self.ready = asyncio.Event()
        self.dropped = 0        # since last told
        self.dropped_total = 0
        self.coalesced = 0
        self.closed = False

    def put(self, topic: str, data: Mapping[str, Any], text: str) -> None:
        if self.closed:
            return
        key = ("progress", data.get("job")) if topic == "progress" else None
        if key is not None and key in self.by_key:
            self.by_key[key].text = text  # the newest percent replaces the one still waiting
            self.coalesced += 1
            return
        if len(self.entries) >= self.limit:
            self.dropped += 1
            self.dropped_total += 1
            return
        entry = _Entry(key, text)
        self.entries.append(entry)
        if key is not None and data.get("message") != "started":
            self.by_key[key] = entry
        self.ready.set()

    def take(self) -> list[str]:
        """Everything waiting, oldest first, with a `dropped` notice first when events were lost."""
        texts = []
        if self.dropped:
            texts.append(encode("dropped", {"count": self.dropped, "total": self.dropped_total}))
            self.dropped = 0
        while self.entries:
            entry = self.entries.popleft()
            if entry.key is not None and self.by_key.get(entry.key) is entry:
                del self.by_key[entry.key]
            texts.append(entry.text)
        self.ready.clear()
        return texts

    def close(self) -> None:
        self.closed = True
        self.ready.set()


class EventHub:
    """The web's end of Server.publish: fans each event out to the open event streams."""

    def __init__(self) -> None:
        self.clients: set[ClientQueue] = set()

    def publish(self, topic: str, data: Mapping[str, Any]) -> None:
        if not self.clients:
            return
        text = encode(topic, data)  # once, however many browsers
        for client in list(self.clients):
            client.put(topic, data, text)

    def open(self) -> ClientQueue | None:
        if len(self.clients) >= MAX_CLIENTS:
            return None
        client = ClientQueue()
        self.clients.add(client)
        return client

    def discard(self, client: ClientQueue) -> None:
        client.close()
        self.clients.discard(client)

    def close_all(self) -> None:
        for client in list(self.clients):
            self.discard(client)
