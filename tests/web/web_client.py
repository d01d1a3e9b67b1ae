"""Plain HTTP for the web tests: raw requests (no URL clean-up, so traversal attempts reach the server
as written) and an event-stream reader in a thread."""
from __future__ import annotations

import http.client
import json
import queue
import socket
import threading
import time


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def get(address: str, path: str, headers: dict[str, str] | None = None, timeout: float = 10.0
        ) -> tuple[int, dict[str, str], bytes]:
    host, port = address.rsplit(":", 1)
    conn = http.client.HTTPConnection(host, int(port), timeout=timeout)
    try:
        conn.request("GET", path, headers=headers or {})
        response = conn.getresponse()
        return response.status, dict(response.getheaders()), response.read()
    finally:
        conn.close()


def get_json(address: str, path: str, headers: dict[str, str] | None = None) -> tuple[int, dict]:
    status, _, body = get(address, path, headers)
    return status, json.loads(body)


class EventStream:
    """GET /events, read in a thread; `events` gets each `data:` line's JSON object."""

    def __init__(self, address: str, path: str = "/events", headers: dict[str, str] | None = None):
        host, port = address.rsplit(":", 1)
        self.conn = http.client.HTTPConnection(host, int(port), timeout=30)
        self.conn.request("GET", path, headers=headers or {})
        self.response = self.conn.getresponse()
        self.status = self.response.status
        self.events: queue.Queue[dict] = queue.Queue()
        if self.status == 200:
            opening = b""
            while not opening.startswith(b": rvs events"):  # the stream is registered from here on
                opening = self.response.readline()
            self.thread = threading.Thread(target=self._read, daemon=True)
            self.thread.start()

    def _read(self) -> None:
        try:
            while True:
                line = self.response.readline()
                if not line:
                    return
                if line.startswith(b"data: "):
                    self.events.put(json.loads(line[6:]))
        except Exception:  # closed under the reader (close() from the test): the stream is over
            return

    def wait_for(self, predicate, timeout: float = 20.0) -> list[dict]:
        """Events until one satisfies `predicate` (included); raises TimeoutError."""
        seen: list[dict] = []
        deadline = time.monotonic() + timeout
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError(f"no matching event; saw {[e['topic'] for e in seen][-20:]}")
            try:
                event = self.events.get(timeout=left)
            except queue.Empty:
                continue
            seen.append(event)
            if predicate(event):
                return seen

    def close(self) -> None:
        try:
            self.conn.sock.shutdown(socket.SHUT_RDWR)
        except (OSError, AttributeError):
            pass
        self.conn.close()
