"""The ZeroMQ transport for programs: a ROUTER for requests, a PUB for events.

A request is one frame of UTF-8 JSON, `{"id": "42", "command": "move-ptu", "args": {...}}` or
`{"id": "42", "line": "move-ptu --pan 30"}`; replies are JSON frames with the same id, any number
with status `progress` and exactly one `ok` or `error`. Use a DEALER socket: a REQ socket allows
one reply per request and so cannot receive progress. Events go out on the PUB socket as
`[topic, json]`. Both reach the same dispatcher as the text transport.
"""
from __future__ import annotations

import json
import logging
from collections.abc import Mapping
from typing import Any

import zmq
import zmq.asyncio

from ..dispatch import DispatchHost, Request, Session
from ..protocol import TAG_RE, BadRequest, RvsError, parse_line

log = logging.getLogger("rvs.zmq")

PROGRESS_CODE = 102  # like HTTP's "processing": the request is still running
# ZeroMQ never tells a ROUTER that a peer has gone, and every new DEALER socket is a new identity: the
# peers heard from most recently are remembered (session, request count), the oldest beyond this forgotten,
# so a client that reconnects all day does not make the server grow without bound.
MAX_PEERS = 4096


def _json(value: Any) -> Any:
    if isinstance(value, (tuple, set)):
        return list(value)
    if hasattr(value, "tolist"):
        return value.tolist()
    return str(value)


class ZmqSink:
    def __init__(self, transport: ZmqTransport, envelope: list[bytes], request_id: str | None):
        self.transport = transport
        self.envelope = envelope
        self.request_id = request_id

    def _send(self, body: dict[str, Any]) -> None:
        self.transport.send(self.envelope, {"id": self.request_id, **body})

    def progress(self, percent: float, message: str) -> None:
        self._send({"status": "progress", "code": PROGRESS_CODE, "reason": "progress", "message": message,
                    "data": {"percent": int(round(percent))}})

    def ok(self, data: Mapping[str, Any]) -> None:
        self._send({"status": "ok", "code": 200, "reason": "ok", "message": "", "data": dict(data)})

    def error(self, error: RvsError) -> None:
        self._send({"status": "error", "code": error.code, "reason": error.reason, "message": error.message,
                    "data": dict(error.data)})


class ZmqTransport:
    def __init__(self, server: DispatchHost):
        self.server = server
        self.context = zmq.asyncio.Context()
        self.router = self.context.socket(zmq.ROUTER)
        # Replies and events are sent from the event loop without awaiting: a synchronous view of
        # the same sockets makes a full queue an immediate, catchable error instead of a lost future.
        self._router_out: zmq.Socket[bytes] = zmq.Socket.shadow(self.router.underlying)
        self.pub: zmq.Socket[bytes] = zmq.Context.shadow(self.context.underlying).socket(zmq.PUB)
        for sock in (self.router, self.pub):
            sock.setsockopt(zmq.LINGER, 200)
        self.sessions: dict[bytes, Session] = {}
        self.counters: dict[bytes, int] = {}
        self.router_endpoint = ""
        self.pub_endpoint = ""

    def bind(self, host: str, port: int) -> None:
        """ROUTER on `port`, PUB on `port + 1`; port 0 picks free ports for both (tests)."""
        if port == 0:
            self.router.bind(f"tcp://{host}:*")
            self.pub.bind(f"tcp://{host}:*")
        else:
            self.router.bind(f"tcp://{host}:{port}")
            self.pub.bind(f"tcp://{host}:{port + 1}")
        self.router_endpoint = self.router.getsockopt_string(zmq.LAST_ENDPOINT)
        self.pub_endpoint = self.pub.getsockopt_string(zmq.LAST_ENDPOINT)

    async def serve(self) -> None:
        while True:
            try:
                frames = await self.router.recv_multipart()
            except (zmq.ContextTerminated, zmq.ZMQError):
                return
            if len(frames) < 2:
                continue
            self._request(frames[:-1], frames[-1])

    def _request(self, envelope: list[bytes], payload: bytes) -> None:
        identity = envelope[0]
        session = self.sessions.pop(identity, None)
        if session is None:
            session = Session(name=f"zmq {identity.hex()}")
        self.sessions[identity] = session  # a dict keeps insertion order: the most recent peer last
        while len(self.sessions) > MAX_PEERS:
            oldest = next(iter(self.sessions))
            del self.sessions[oldest]
            self.counters.pop(oldest, None)
        self.counters[identity] = self.counters.get(identity, 0) + 1
        request_id: str | None = None
        try:
            message = json.loads(payload.decode("utf-8"))
            if not isinstance(message, dict):
                raise BadRequest("a request is a JSON object with id and command or line")
            if "id" in message and message["id"] is not None:
                request_id = str(message["id"])
                if not TAG_RE.fullmatch(request_id):
                    raise BadRequest(f"id {request_id!r} is not 1 to 32 characters of [A-Za-z0-9_.-]")
            else:
                request_id = str(self.counters[identity])
            request = self._to_request(message, request_id)
        except UnicodeDecodeError:
            ZmqSink(self, envelope, request_id).error(BadRequest("request is not UTF-8", reason="bad-encoding"))
            return
        except json.JSONDecodeError as exc:
            ZmqSink(self, envelope, request_id).error(BadRequest(f"request is not JSON: {exc}"))
            return
        except RvsError as exc:
            ZmqSink(self, envelope, request_id).error(exc)
            return
        self.server.dispatcher.submit(request, session, ZmqSink(self, envelope, request_id))

    @staticmethod
    def _to_request(message: dict[str, Any], request_id: str) -> Request:
        if "line" in message:
            if not isinstance(message["line"], str):
                raise BadRequest("line must be a string")
            parsed = parse_line(message["line"])
            return Request(command=parsed.command, tokens=parsed.tokens, tag=request_id, line=parsed.text)
        command = message.get("command")
        if not isinstance(command, str) or not command:
            raise BadRequest("a request needs a command (string) or a line")
        args = message.get("args") or {}
        if not isinstance(args, dict):
            raise BadRequest("args must be a JSON object of option names to values")
        values = {str(k).replace("-", "_"): v for k, v in args.items()}
        text = " ".join([command] + [f"--{k}={v}" for k, v in args.items()])
        return Request(command=command.lower(), values=values, tag=request_id, line=text)

    def send(self, envelope: list[bytes], body: dict[str, Any]) -> None:
        frame = json.dumps(body, default=_json).encode("utf-8")
        try:
            self._router_out.send_multipart([*envelope, frame], flags=zmq.NOBLOCK)
        except zmq.ZMQError as exc:  # the peer is gone or its queue is full: the job goes on
            log.warning("zmq reply to %s dropped: %s", envelope[0].hex(), exc)

    def publish(self, topic: str, data: Mapping[str, Any]) -> None:
        try:
            self.pub.send_multipart([topic.encode(), json.dumps(dict(data), default=_json).encode()],
                                    flags=zmq.NOBLOCK)
        except zmq.ZMQError as exc:
            log.debug("event %s dropped: %s", topic, exc)

    def close(self) -> None:
        self.router.close(linger=200)
        self.pub.close(linger=200)
        self.context.term()
