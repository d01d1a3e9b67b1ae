"""The RVS client library, for a GNC computer or any program that drives the vision server.

Three clients with one API (PROTOCOL.md, version 1):

    RvsClient(host, port, timeout)          blocking, text transport (TCP, what telnet speaks)
    ZmqClient(endpoint, timeout)            blocking, ZeroMQ DEALER to the server's ROUTER
    AsyncRvsClient(host, port, timeout)     asyncio, text transport

    with RvsClient("127.0.0.1", 7400) as rvs:
        rvs.call("move-ptu", pan=30, tilt=-20)          # -> Result, or raises RvsRequestError
        rvs.send("status").get_float("pan")             # a whole command line
        for item in rvs.stream("move-ptu --pan 0"):     # Progress items, then the final Result
            print(item.line)

Every request carries a tag made here (or the `@TAG` already in the line), and replies are matched
by tag, so several commands can be in flight (from several threads or tasks) and an event or
another command's reply arriving in between is never taken for ours. `* EVENT` lines go to the
`on_event` callback or queue. An `ERR` reply raises the RvsRequestError subclass of its reason.

Only `rvs_server.protocol` is imported from the server package, as DESIGN.md requires.
"""
from __future__ import annotations

import asyncio
import inspect
import itertools
import json
import logging
import queue
import re
import socket
import threading
import time
from collections.abc import AsyncIterator, Callable, Iterator
from dataclasses import dataclass, field
from typing import Any, Union

from rvs_server.protocol import (
    Reply,
    build_line,
    format_err,
    format_event,
    format_ok,
    format_progress,
    format_value,
    is_ignored,
    parse_reply,
    split_tag,
)

log = logging.getLogger("rvs.client")

DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 7400
DEFAULT_ZMQ = "tcp://127.0.0.1:7401"
# Longest silence tolerated while waiting for a request's next line; every PROGRESS restarts it,
# so a long job that reports progress never times out. 60 s covers `break` and `quit` (30 s each).
DEFAULT_TIMEOUT = 60.0

_RECOVERY_RE = re.compile(r"\brecovery=([A-Za-z0-9_.-]+)")


# ---------------------------------------------------------------------------------------------
# What a request yields


@dataclass(frozen=True)
class Result:
    """A final `TAG OK key=value ...` reply. Values are text, exactly as the server sent them."""

    tag: str
    data: dict[str, str] = field(default_factory=dict)
    line: str = ""  # the reply in its text form (made up from the JSON for ZeroMQ)

    ok = True

    def __getitem__(self, key: str) -> str:
        return self._value(key)

    def __contains__(self, key: object) -> bool:
        return key in self.data

    def get(self, key: str, default: str | None = None) -> str | None:
        return self.data.get(key, default)

    def get_float(self, key: str) -> float:
        value = self._value(key)
        try:
            return float(value)
        except ValueError:
            raise ValueError(f"{key}={value!r} in reply {self.tag} is not a number") from None

    def get_int(self, key: str) -> int:
        value = self._value(key)
        try:
            return int(value)
        except ValueError:
            raise ValueError(f"{key}={value!r} in reply {self.tag} is not an integer") from None

    def _value(self, key: str) -> str:
        try:
            return self.data[key]
        except KeyError:
            raise KeyError(f"reply {self.tag} has no {key!r}; it has: {', '.join(self.data) or 'nothing'}") from None


@dataclass(frozen=True)
class Progress:
    """A `TAG PROGRESS PERCENT MESSAGE` line of a running job."""

    tag: str
    percent: int
    message: str
    line: str = ""


@dataclass(frozen=True)
class Event:
    """A `* EVENT TOPIC key=value ...` line (text transport, after `subscribe`) or a PUB message."""

    topic: str
    data: dict[str, str]
    line: str = ""


Item = Progress | Result
EventTarget = Union[Callable[[Event], Any], "queue.Queue[Event]", "asyncio.Queue[Event]", None]


# ---------------------------------------------------------------------------------------------
# Errors


class RvsClientError(Exception):
    """Anything that went wrong talking to the server."""


class RvsConnectionError(RvsClientError, ConnectionError):
    """The connection could not be made, or it closed before the reply came."""


class RvsNoReply(RvsClientError, TimeoutError):
    """The server said nothing about a request for longer than the client's timeout."""


class RvsRequestError(RvsClientError):
    """The server answered `TAG ERR CODE REASON MESSAGE`."""

    def __init__(self, tag: str, code: int, reason: str, message: str, line: str = "",
                 data: dict[str, str] | None = None):
        super().__init__(f"{code} {reason}: {message}")
        self.tag = tag
        self.code = code
        self.reason = reason
        self.message = message
        self.line = line or format_err(tag, code, reason, message)
        self.data = dict(data or {})
        # The text transport only has the message; ZeroMQ also gives it in data.
        found = _RECOVERY_RE.search(message)
        self.recovery: str | None = self.data.get("recovery") or (found.group(1) if found else None)

    ok = False


class RvsBadRequest(RvsRequestError):
    """400: syntax, unknown option, missing or invalid value; also line-too-long, bad-encoding."""


class RvsUnauthorized(RvsRequestError):
    """401: the server requires a token and `auth` has not succeeded."""


class RvsUnknownCommand(RvsRequestError):
    """404: no such command (the message suggests the closest one)."""


class RvsBusy(RvsRequestError):
    """409 busy: another job is running."""


class RvsWrongMode(RvsRequestError):
    """409 wrong-mode: not allowed in the current mode."""


class RvsSleeping(RvsRequestError):
    """423: the server is in sleep mode."""


class RvsInterrupted(RvsRequestError):
    """499: the job was stopped by `break` or `quit`; `.recovery` names its recovery set."""


class RvsInternalError(RvsRequestError):
    """500: a bug in the server; the message says where the traceback is."""


class RvsDeviceError(RvsRequestError):
    """503: a device is missing, not responding or reported an error."""


class RvsTimeout(RvsRequestError):
    """504: a device or step took longer than its configured limit (a server-side timeout)."""


_ERRORS_BY_REASON: dict[str, type[RvsRequestError]] = {
    "bad-request": RvsBadRequest, "unauthorized": RvsUnauthorized, "unknown-command": RvsUnknownCommand,
    "busy": RvsBusy, "wrong-mode": RvsWrongMode, "sleeping": RvsSleeping, "interrupted": RvsInterrupted,
    "internal": RvsInternalError, "device": RvsDeviceError, "timeout": RvsTimeout,
}
# A reason this client does not know (line-too-long, a future one) still gets its code's class.
_ERRORS_BY_CODE: dict[int, type[RvsRequestError]] = {
    400: RvsBadRequest, 401: RvsUnauthorized, 404: RvsUnknownCommand, 423: RvsSleeping, 499: RvsInterrupted,
    500: RvsInternalError, 503: RvsDeviceError, 504: RvsTimeout,
}


def request_error(tag: str, code: int, reason: str, message: str, line: str = "",
                  data: dict[str, str] | None = None) -> RvsRequestError:
    """The exception for one ERR reply, chosen by its reason, else by its code."""
    cls = _ERRORS_BY_REASON.get(reason) or _ERRORS_BY_CODE.get(code, RvsRequestError)
    return cls(tag, code, reason, message, line, data)


# ---------------------------------------------------------------------------------------------
# Pure helpers shared by the clients


class _TagMaker:
    """Tags `c1`, `c2`, ... unique within one client (the server keys nothing else on them)."""

    def __init__(self) -> None:
        self._counter = itertools.count(1)
        self._lock = threading.Lock()

    def next(self) -> str:
        with self._lock:
            return f"c{next(self._counter)}"


def tagged_line(line: str, tags: _TagMaker) -> tuple[str, str]:
    """(tag, line to send): the line's own `@TAG` is kept, otherwise a fresh one is put in front."""
    if "\n" in line or "\r" in line:
        raise ValueError(f"one command per line: {line!r} contains a line break")
    if is_ignored(line):
        raise ValueError(f"{line!r} is blank or a comment: the server would not answer it")
    tag, _ = split_tag(line)
    if tag is not None:
        return tag, line.strip()
    tag = tags.next()
    return tag, f"@{tag} {line.strip()}"


def item_from_reply(reply: Reply, line: str) -> Item | RvsRequestError:
    """A parsed PROGRESS, OK or ERR line as what the client hands out."""
    tag = reply.tag or ""
    if reply.kind == "progress":
        return Progress(tag, reply.percent or 0, reply.message, line)
    if reply.kind == "ok":
        return Result(tag, dict(reply.data), line)
    return request_error(tag, reply.code, reply.reason, reply.message, line, reply.data)


def reply_from_json(frame: bytes) -> Reply:
    """A ZeroMQ reply frame as the Reply its text line would parse to; values become text."""
    body = json.loads(frame.decode("utf-8"))
    if not isinstance(body, dict) or not isinstance(body.get("data") or {}, dict):
        raise ValueError("a reply frame is a JSON object whose data is an object")
    tag = str(body.get("id"))
    data = {str(k): format_value(v) for k, v in (body.get("data") or {}).items()}
    status = body.get("status")
    if status == "progress":
        return Reply(kind="progress", tag=tag, percent=int(float(data.get("percent", "0"))),
                     message=str(body.get("message", "")))
    if status == "ok":
        return Reply(kind="ok", tag=tag, data=data)
    if status == "error":
        return Reply(kind="err", tag=tag, data=data, code=int(body.get("code", 500)),
                     reason=str(body.get("reason", "internal")), message=str(body.get("message", "")))
    raise ValueError(f"reply frame with unknown status {status!r}: {body!r}")


def text_line_of(reply: Reply) -> str:
    """The text-transport line a reply stands for, so both transports print the same."""
    tag = reply.tag or ""
    if reply.kind == "progress":
        return format_progress(tag, reply.percent or 0, reply.message)
    if reply.kind == "ok":
        return format_ok(tag, reply.data)
    return format_err(tag, reply.code, reply.reason, reply.message)


def deliver_event(target: EventTarget, event: Event) -> None:
    """Hand an event to a callback or a queue; a failing callback must not kill the reader."""
    if target is None:
        return
    try:
        if hasattr(target, "put_nowait"):
            target.put_nowait(event)  # type: ignore[union-attr]
            return
        outcome = target(event)  # type: ignore[operator]
        if inspect.isawaitable(outcome):
            asyncio.ensure_future(outcome)
    except Exception:
        log.exception("event handler failed on %s", event.line)


def _event_of(reply: Reply, line: str) -> Event:
    return Event(reply.topic or "", dict(reply.data), line)


def _raise_if_error(item: Item | RvsRequestError) -> Item:
    if isinstance(item, RvsRequestError):
        raise item
    return item


# ---------------------------------------------------------------------------------------------
# Blocking clients


class _BlockingClient:
    """The API both blocking clients share; a transport supplies _post, _next and _forget."""

    timeout: float | None

    def send(self, line: str, timeout: float | None = None) -> Result:
        """Send one command line and wait for its final reply; an ERR raises."""
        result: Item | None = None
        for result in self.stream(line, timeout):  # noqa: B007  the loop keeps the last item: the final reply
            pass
        assert isinstance(result, Result)
        return result

    def call(self, command: str, *positionals: Any, **options: Any) -> Result:
        """`call("move-ptu", pan=30)`: option names with underscores become --dashed-names."""
        return self.send(build_line(command, positionals, options))

    def stream(self, line: str, timeout: float | None = None) -> Iterator[Item]:
        """Yield each Progress of a command, then its Result; an ERR raises after the progress."""
        wait = self.timeout if timeout is None else timeout
        tag, text = tagged_line(line, self._tags)
        self._post(tag, text)
        try:
            while True:
                item = _raise_if_error(self._next(tag, wait))
                yield item
                if isinstance(item, Result):
                    return
        finally:
            self._forget(tag)

    def auth(self, token: str) -> Result:
        return self.call("auth", token)

    def __enter__(self):
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    # transport hooks
    _tags: _TagMaker

    def _post(self, tag: str, line: str) -> None:
        raise NotImplementedError

    def _next(self, tag: str, timeout: float | None) -> Item | RvsRequestError:
        raise NotImplementedError

    def _forget(self, tag: str) -> None:
        raise NotImplementedError

    def close(self) -> None:
        raise NotImplementedError


_CLOSED = object()  # put in a waiter's queue when the connection ends


class RvsClient(_BlockingClient):
    """Blocking client over the text transport. A reader thread sorts incoming lines by tag.

    `on_event` gets every `* EVENT` line as an Event (a callable, called in the reader thread, so
    keep it short, or anything with put_nowait such as queue.Queue). `server_version` and
    `server_mode` come from the server's `RVS <version> <mode>` greeting. With `token`, the
    connection authenticates at once.
    """

    def __init__(self, host: str = DEFAULT_HOST, port: int = DEFAULT_PORT, timeout: float | None = DEFAULT_TIMEOUT,
                 on_event: EventTarget = None, token: str | None = None):
        self.host, self.port, self.timeout = host, port, timeout
        self.on_event = on_event
        self._tags = _TagMaker()
        self._waiters: dict[str, queue.Queue] = {}
        self._waiters_lock = threading.Lock()
        self._send_lock = threading.Lock()
        self._buffer = b""
        self._closed = threading.Event()
        try:
            self._sock = socket.create_connection((host, port), timeout=timeout)
        except OSError as exc:
            raise RvsConnectionError(f"cannot connect to {host}:{port}: {exc}") from None
        greeting = self._read_greeting()
        self.server_version = greeting.data["version"]
        self.server_mode = greeting.data["mode"]
        self._sock.settimeout(None)  # the reader blocks; waiters time out on their queues
        self._reader = threading.Thread(target=self._read_loop, name=f"rvs-reader {host}:{port}", daemon=True)
        self._reader.start()
        _authenticate(self, token)

    @property
    def closed(self) -> bool:
        """True once the connection has ended (close(), or the server hung up, e.g. after quit)."""
        return self._closed.is_set()

    def close(self) -> None:
        self._closed.set()
        try:
            self._sock.shutdown(socket.SHUT_RDWR)  # wakes the reader thread from recv
        except OSError:
            pass
        self._reader.join(timeout=5)
        self._sock.close()

    # -- reading --------------------------------------------------------------------------------

    def _read_greeting(self) -> Reply:
        try:
            line = self._read_line()
        except (OSError, ConnectionError) as exc:
            self._sock.close()
            raise RvsConnectionError(f"no greeting from {self.host}:{self.port}: {exc}") from None
        reply = _parse_or_none(line)
        if reply is None or reply.kind != "greeting":
            self._sock.close()
            raise RvsConnectionError(f"{self.host}:{self.port} is not an RVS server: it said {line!r}")
        return reply

    def _read_line(self) -> str:
        while b"\n" not in self._buffer:
            chunk = self._sock.recv(65536)
            if not chunk:
                raise ConnectionError("the server closed the connection")
            self._buffer += chunk
        raw, self._buffer = self._buffer.split(b"\n", 1)
        return raw.decode("utf-8", "replace").rstrip("\r")

    def _read_loop(self) -> None:
        try:
            while True:
                self._route(self._read_line())
        except (OSError, ConnectionError):
            pass
        finally:
            self._closed.set()
            with self._waiters_lock:
                for waiter in self._waiters.values():
                    waiter.put(_CLOSED)

    def _route(self, line: str) -> None:
        reply = _parse_or_none(line)
        if reply is None or reply.kind == "greeting":
            log.warning("ignoring a line that is no reply: %r", line)
            return
        if reply.kind == "event":
            deliver_event(self.on_event, _event_of(reply, line))
            return
        with self._waiters_lock:
            waiter = self._waiters.get(reply.tag or "")
        if waiter is None:  # its requester gave up waiting, or it was never ours
            log.debug("reply for no pending request: %r", line)
            return
        waiter.put(item_from_reply(reply, line))

    # -- transport hooks ------------------------------------------------------------------------

    def _post(self, tag: str, line: str) -> None:
        with self._waiters_lock:
            if tag in self._waiters:
                raise ValueError(f"tag {tag!r} is already in flight on this connection")
            self._waiters[tag] = queue.Queue()
        if self._closed.is_set():
            self._forget(tag)
            raise RvsConnectionError(f"the connection to {self.host}:{self.port} is closed")
        try:
            with self._send_lock:
                self._sock.sendall(line.encode("utf-8") + b"\n")
        except OSError as exc:
            self._forget(tag)
            raise RvsConnectionError(f"cannot send to {self.host}:{self.port}: {exc}") from None

    def _next(self, tag: str, timeout: float | None) -> Item | RvsRequestError:
        with self._waiters_lock:
            waiter = self._waiters[tag]
        try:
            item = waiter.get(timeout=timeout)
        except queue.Empty:
            raise RvsNoReply(f"no reply to request {tag} within {timeout:g} s") from None
        if item is _CLOSED:
            raise RvsConnectionError(f"the connection to {self.host}:{self.port} closed before the reply to {tag}")
        return item

    def _forget(self, tag: str) -> None:
        with self._waiters_lock:
            self._waiters.pop(tag, None)


def _parse_or_none(line: str) -> Reply | None:
    try:
        return parse_reply(line)
    except ValueError:
        return None


class ZmqClient(_BlockingClient):
    """Blocking client over ZeroMQ: a DEALER socket (a REQ socket could not take progress frames).

    Requests go out as `{"id": TAG, "line": LINE}`, so both transports run the very same line.
    ZeroMQ connects lazily and silently, so the constructor asks for `version` (answered in any
    mode, without auth) and raises RvsConnectionError when nothing answers within
    `connect_timeout`. Give `pub` (the server's PUB endpoint) and `on_event` to receive events
    while waiting for replies; `poll_events(seconds)` delivers them when no request is pending.
    """

    def __init__(self, endpoint: str = DEFAULT_ZMQ, timeout: float | None = DEFAULT_TIMEOUT, pub: str | None = None,
                 on_event: EventTarget = None, topics: tuple[str, ...] = ("",), token: str | None = None,
                 connect_timeout: float = 5.0):
        import zmq  # only programs that use ZeroMQ need pyzmq
        self._zmq = zmq
        self.endpoint, self.timeout, self.on_event = endpoint, timeout, on_event
        self._tags = _TagMaker()
        self._context = zmq.Context()
        self._socket = self._context.socket(zmq.DEALER)
        self._socket.setsockopt(zmq.LINGER, 0)  # pending requests die with the client
        self._socket.connect(endpoint)
        self._poller = zmq.Poller()
        self._poller.register(self._socket, zmq.POLLIN)
        self._events = None
        if pub:
            self._events = self._context.socket(zmq.SUB)
            self._events.setsockopt(zmq.LINGER, 0)
            for topic in topics:
                self._events.setsockopt_string(zmq.SUBSCRIBE, topic)
            self._events.connect(pub)
            self._poller.register(self._events, zmq.POLLIN)
        self._waiters: dict[str, queue.Queue] = {}
        self._lock = threading.RLock()  # a zmq socket must be used by one thread at a time
        self._closed = False
        self.server_mode = ""  # no greeting on ZeroMQ; `status` tells
        self.server_version = self._probe(connect_timeout)
        _authenticate(self, token)

    def _probe(self, seconds: float) -> str:
        try:
            return self.send("version", timeout=seconds)["version"]
        except RvsNoReply:
            self.close()
            raise RvsConnectionError(f"no RVS server answers at {self.endpoint} (waited {seconds:g} s)") from None

    @property
    def closed(self) -> bool:
        return self._closed

    def close(self) -> None:
        with self._lock:
            if self._closed:
                return
            self._closed = True
            self._socket.close(linger=0)
            if self._events is not None:
                self._events.close(linger=0)
            self._context.term()

    def poll_events(self, seconds: float) -> None:
        """Deliver the events that arrive within `seconds` (for a program with nothing pending)."""
        deadline = time.monotonic() + seconds
        while (left := deadline - time.monotonic()) > 0:
            self._pump(left)

    # -- transport hooks ------------------------------------------------------------------------

    def _post(self, tag: str, line: str) -> None:
        _, bare = split_tag(line)  # the id carries the tag
        frame = json.dumps({"id": tag, "line": bare.strip()}).encode("utf-8")
        with self._lock:
            if self._closed:
                raise RvsConnectionError(f"the client of {self.endpoint} is closed")
            if tag in self._waiters:
                raise ValueError(f"id {tag!r} is already in flight on this client")
            self._waiters[tag] = queue.Queue()
            self._socket.send(frame)

    def _next(self, tag: str, timeout: float | None) -> Item | RvsRequestError:
        waiter = self._waiters[tag]
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            try:
                return waiter.get_nowait()
            except queue.Empty:
                pass
            left = None if deadline is None else deadline - time.monotonic()
            if left is not None and left <= 0:
                raise RvsNoReply(f"no reply to request {tag} within {timeout:g} s from {self.endpoint}")
            # Short slices: another thread may be waiting too, and needs the socket in between.
            self._pump(0.1 if left is None else min(left, 0.1))

    def _forget(self, tag: str) -> None:
        with self._lock:
            self._waiters.pop(tag, None)

    def _pump(self, seconds: float) -> None:
        """Read what arrives within `seconds` and sort it: replies to their waiters, events out."""
        with self._lock:
            if self._closed:
                raise RvsConnectionError(f"the client of {self.endpoint} is closed")
            ready = dict(self._poller.poll(seconds * 1000))
            if self._socket in ready:
                self._drain_replies()
            if self._events is not None and self._events in ready:
                self._drain_events()

    def _drain_replies(self) -> None:
        zmq = self._zmq
        while True:
            try:
                frame = self._socket.recv(zmq.NOBLOCK)
            except zmq.Again:
                return
            try:
                reply = reply_from_json(frame)
            except (ValueError, UnicodeDecodeError) as exc:
                log.warning("ignoring a frame that is no reply (%s): %r", exc, frame[:200])
                continue
            waiter = self._waiters.get(reply.tag or "")
            if waiter is None:
                log.debug("reply for no pending request: %r", frame[:200])
                continue
            waiter.put(item_from_reply(reply, text_line_of(reply)))

    def _drain_events(self) -> None:
        zmq = self._zmq
        while True:
            try:
                parts = self._events.recv_multipart(zmq.NOBLOCK)  # type: ignore[union-attr]
            except zmq.Again:
                return
            if len(parts) != 2:
                continue
            topic = parts[0].decode("utf-8", "replace")
            try:
                data = {str(k): format_value(v) for k, v in json.loads(parts[1]).items()}
            except (ValueError, AttributeError):
                continue
            deliver_event(self.on_event, Event(topic, data, format_event(topic, data)))


# ---------------------------------------------------------------------------------------------
# The asyncio client


def _authenticate(client: _BlockingClient, token: str | None) -> None:
    if token is None:
        return
    try:
        client.auth(token)
    except RvsClientError:
        client.close()
        raise


class AsyncRvsClient:
    """asyncio client over the text transport, the same calls as RvsClient but awaited.

        async with AsyncRvsClient(host, port) as rvs:
            await rvs.call("status")
            async for item in rvs.stream("move-ptu --pan 30"):
                ...

    `on_event` may be a callable (a coroutine function is scheduled as a task) or a queue.
    """

    def __init__(self, host: str = DEFAULT_HOST, port: int = DEFAULT_PORT, timeout: float | None = DEFAULT_TIMEOUT,
                 on_event: EventTarget = None, token: str | None = None):
        self.host, self.port, self.timeout = host, port, timeout
        self.on_event = on_event
        self.token = token
        self._tags = _TagMaker()
        self._waiters: dict[str, asyncio.Queue] = {}
        self._reader: asyncio.StreamReader | None = None
        self._writer: asyncio.StreamWriter | None = None
        self._reader_task: asyncio.Task | None = None
        self.server_version = ""
        self.server_mode = ""

    async def connect(self) -> AsyncRvsClient:
        try:
            self._reader, self._writer = await asyncio.wait_for(
                asyncio.open_connection(self.host, self.port, limit=1 << 20), self.timeout)
            line = await asyncio.wait_for(self._reader.readline(), self.timeout)
        except (TimeoutError, OSError) as exc:
            await self.close()
            raise RvsConnectionError(f"cannot connect to {self.host}:{self.port}: {exc!r}") from None
        text = line.decode("utf-8", "replace").rstrip("\r\n")
        greeting = _parse_or_none(text)
        if greeting is None or greeting.kind != "greeting":
            await self.close()
            raise RvsConnectionError(f"{self.host}:{self.port} is not an RVS server: it said {text!r}")
        self.server_version, self.server_mode = greeting.data["version"], greeting.data["mode"]
        self._reader_task = asyncio.create_task(self._read_loop())
        if self.token is not None:
            try:
                await self.auth(self.token)
            except RvsClientError:
                await self.close()
                raise
        return self

    @property
    def closed(self) -> bool:
        return self._reader_task is None or self._reader_task.done()

    async def close(self) -> None:
        if self._writer is not None:
            self._writer.close()
            try:
                await self._writer.wait_closed()
            except OSError:
                pass
        if self._reader_task is not None:
            self._reader_task.cancel()
            try:
                await self._reader_task
            except asyncio.CancelledError:
                pass

    async def __aenter__(self) -> AsyncRvsClient:
        return await self.connect()

    async def __aexit__(self, *exc: Any) -> None:
        await self.close()

    async def send(self, line: str, timeout: float | None = None) -> Result:
        result: Item | None = None
        async for result in self.stream(line, timeout):  # noqa: B007  the loop keeps the last item: the final reply
            pass
        assert isinstance(result, Result)
        return result

    async def call(self, command: str, *positionals: Any, **options: Any) -> Result:
        return await self.send(build_line(command, positionals, options))

    async def auth(self, token: str) -> Result:
        return await self.call("auth", token)

    async def stream(self, line: str, timeout: float | None = None) -> AsyncIterator[Item]:
        wait = self.timeout if timeout is None else timeout
        tag, text = tagged_line(line, self._tags)
        if self.closed or self._writer is None:
            raise RvsConnectionError(f"the connection to {self.host}:{self.port} is closed")
        if tag in self._waiters:
            raise ValueError(f"tag {tag!r} is already in flight on this connection")
        waiter: asyncio.Queue = asyncio.Queue()
        self._waiters[tag] = waiter
        try:
            self._writer.write(text.encode("utf-8") + b"\n")
            await self._writer.drain()
            while True:
                try:
                    item = await asyncio.wait_for(waiter.get(), wait)
                except TimeoutError:
                    raise RvsNoReply(f"no reply to request {tag} within {wait:g} s") from None
                if item is _CLOSED:
                    raise RvsConnectionError(
                        f"the connection to {self.host}:{self.port} closed before the reply to {tag}")
                item = _raise_if_error(item)
                yield item
                if isinstance(item, Result):
                    return
        except OSError as exc:
            raise RvsConnectionError(f"cannot send to {self.host}:{self.port}: {exc}") from None
        finally:
            self._waiters.pop(tag, None)

    async def _read_loop(self) -> None:
        assert self._reader is not None
        try:
            while True:
                raw = await self._reader.readline()
                if not raw.endswith(b"\n"):  # end of stream (a partial last line is no reply)
                    return
                self._route(raw.decode("utf-8", "replace").rstrip("\r\n"))
        except (OSError, ValueError):  # ValueError: a line over the stream limit
            return
        finally:
            for waiter in self._waiters.values():
                waiter.put_nowait(_CLOSED)

    def _route(self, line: str) -> None:
        reply = _parse_or_none(line)
        if reply is None or reply.kind == "greeting":
            log.warning("ignoring a line that is no reply: %r", line)
        elif reply.kind == "event":
            deliver_event(self.on_event, _event_of(reply, line))
        elif (waiter := self._waiters.get(reply.tag or "")) is not None:
            waiter.put_nowait(item_from_reply(reply, line))
        else:
            log.debug("reply for no pending request: %r", line)


__all__ = [
    "RvsClient", "ZmqClient", "AsyncRvsClient", "Result", "Progress", "Event",
    "RvsClientError", "RvsConnectionError", "RvsNoReply", "RvsRequestError", "RvsBadRequest", "RvsUnauthorized",
    "RvsUnknownCommand", "RvsBusy", "RvsWrongMode", "RvsSleeping", "RvsInterrupted", "RvsInternalError",
    "RvsDeviceError", "RvsTimeout", "request_error", "tagged_line", "reply_from_json",
]
