"""The telnet-friendly text transport: one command per line, one final reply per command line.

Bytes arrive as they like; this layer drops telnet negotiation (IAC sequences), splits lines on LF
(ignoring a CR before it), refuses lines over 8192 bytes and bytes that are not UTF-8 without
losing the connection, assigns tag numbers, and hands each command to the dispatcher.
"""
from __future__ import annotations

import asyncio
import logging
import socket
from collections.abc import Mapping
from typing import Any

from ..dispatch import DispatchHost, Request, Session
from ..protocol import (
    LINE_END,
    MAX_LINE_BYTES,
    BadRequest,
    RvsError,
    format_err,
    format_error,
    format_event,
    format_ok,
    format_progress,
    is_ignored,
    parse_line,
    split_tag,
)

log = logging.getLogger("rvs.tcp")

IAC, SB, SE = 255, 250, 240
WILL, WONT, DO, DONT = 251, 252, 253, 254

# A client that stops reading (a telnet window stopped with Ctrl-S, a hung program) must not make the
# server keep what it cannot send without bound. Events to it are dropped once this much is unsent ...
EVENT_BUFFER_LIMIT = 1 << 20
# ... and its own commands are not read on while this much of their replies is unsent (backpressure;
# no reply is ever dropped). Its other lines wait in the socket until it reads again.
REPLY_BUFFER_LIMIT = 4 << 20


class TelnetFilter:
    """Removes telnet IAC sequences from a byte stream, across chunk boundaries.

    Two things a real telnet sends are more than noise. A request for an option (`IAC DO x`, `IAC WILL
    x`: `mode character`, or the full negotiation of `open HOST -PORT`) is refused (`IAC WONT x`,
    `IAC DONT x`, RFC 854), collected in `answers` for the caller to send: telnet then stays in line
    mode, echoing locally and ending lines with CR LF. And CR NUL, telnet's end of line in character
    mode (RFC 854), ends a line as LF does."""

    def __init__(self) -> None:
        self._state = "data"
        self._verb = 0  # WILL, WONT, DO or DONT, whose option byte comes next
        self._cr = False  # the last data byte was a CR
        self.answers = bytearray()  # refusals to send back

    def feed(self, data: bytes) -> bytes:
        if IAC not in data and self._state == "data" and b"\r\0" not in data and not (self._cr and data[:1] == b"\0"):
            if data:
                self._cr = data[-1] == 13
            return data
        out = bytearray()
        for byte in data:
            state = self._state
            if state == "data":
                if byte == IAC:
                    self._state = "iac"
                elif byte == 0 and self._cr:
                    out.append(10)  # CR NUL is CR LF
                else:
                    out.append(byte)
                self._cr = byte == 13
            elif state == "iac":
                if byte == IAC:  # an escaped 255 is data (and never valid UTF-8, so it will be refused)
                    out.append(IAC)
                    self._state = "data"
                elif byte in (WILL, WONT, DO, DONT):
                    self._state, self._verb = "option", byte
                elif byte == SB:
                    self._state = "sub"
                else:
                    self._state = "data"
            elif state == "option":
                if self._verb in (WILL, DO):  # refused; WONT and DONT are never answered, so no loop
                    self.answers += bytes((IAC, DONT if self._verb == WILL else WONT, byte))
                self._state = "data"
            elif state == "sub":
                if byte == IAC:
                    self._state = "sub-iac"
            elif state == "sub-iac":
                self._state = "data" if byte == SE else "sub"
        return bytes(out)


class LineSink:
    """Replies to one command line on one connection, framed with its tag."""

    def __init__(self, connection: TextConnection, tag: str):
        self.connection = connection
        self.tag = tag

    def progress(self, percent: float, message: str) -> None:
        self.connection.send_line(format_progress(self.tag, percent, message))

    def ok(self, data: Mapping[str, Any]) -> None:
        self.connection.send_line(format_ok(self.tag, data))

    def error(self, error: RvsError) -> None:
        self.connection.send_line(format_error(self.tag, error))


class TextConnection(asyncio.Protocol):
    def __init__(self, server: DispatchHost):
        self.server = server
        self.transport: asyncio.Transport | None = None
        self.telnet = TelnetFilter()
        self.buffer = bytearray()
        self.discarding: bytes | None = None  # the start of an over-long line being thrown away
        self.count = 0
        self.session: Session | None = None
        self.events_dropped = 0  # since the client last kept up

    # -- asyncio.Protocol ----------------------------------------------------------------------

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.transport = transport
        transport.set_write_buffer_limits(high=REPLY_BUFFER_LIMIT)
        peer = transport.get_extra_info("peername")
        name = f"tcp {peer[0]}:{peer[1]}" if isinstance(peer, tuple) else "tcp"
        self.session = Session(name=name, send_event=self.send_event, close=self.close)
        self.server.sessions.add(self.session)
        log.info("%s connected", name)
        self.send_line(f"RVS {self.server.version} {self.server.dispatcher.mode}")

    def connection_lost(self, exc: Exception | None) -> None:
        if self.session is not None:
            self.server.sessions.discard(self.session)
            log.info("%s disconnected", self.session.name)
        self.transport = None

    def pause_writing(self) -> None:
        """Replies pile up unsent: read no more of this client's commands until they are sent."""
        if self.transport is not None and not self.transport.is_closing():
            self.transport.pause_reading()

    def resume_writing(self) -> None:
        if self.transport is not None and not self.transport.is_closing():
            self.transport.resume_reading()

    def data_received(self, data: bytes) -> None:
        self.buffer += self.telnet.feed(data)
        if self.telnet.answers:
            if self.transport is not None and not self.transport.is_closing():
                self.transport.write(bytes(self.telnet.answers))
            self.telnet.answers.clear()
        while True:
            end = self.buffer.find(b"\n")
            if end < 0:
                break
            raw = bytes(self.buffer[:end])
            del self.buffer[:end + 1]
            self._line(raw)
        if len(self.buffer) > MAX_LINE_BYTES + 1:  # +1: room for the CR of a CRLF
            if self.discarding is None:
                self.discarding = bytes(self.buffer[:64])
            self.buffer.clear()

    # -- lines ----------------------------------------------------------------------------------

    def _line(self, raw: bytes) -> None:
        if raw.endswith(b"\r"):
            raw = raw[:-1]
        if self.discarding is not None:
            head, self.discarding = self.discarding, None
            self._refuse(head, "line-too-long", f"line longer than {MAX_LINE_BYTES} bytes, discarded")
            return
        if len(raw) > MAX_LINE_BYTES:
            self._refuse(raw[:64], "line-too-long", f"line of {len(raw)} bytes is longer than {MAX_LINE_BYTES}")
            return
        try:
            text = raw.decode("utf-8")
        except UnicodeDecodeError as exc:
            if is_ignored(raw.decode("utf-8", "replace")):  # a comment stays a comment
                return
            self._refuse(raw, "bad-encoding", f"bytes are not UTF-8 (byte {exc.start}: {raw[exc.start]:#04x})")
            return
        if is_ignored(text):
            return
        self.count += 1
        tag, _ = split_tag(text)
        tag = tag or str(self.count)
        try:
            parsed = parse_line(text)
        except RvsError as exc:
            self.send_line(format_error(tag, exc))
            return
        assert self.session is not None   # connection_made comes first
        self.server.dispatcher.submit(Request.from_line(parsed), self.session, LineSink(self, tag))

    def _refuse(self, head: bytes, reason: str, message: str) -> None:
        """A line that never reaches the parser still counts, and keeps a well-formed tag."""
        self.count += 1
        tag, _ = split_tag(head.decode("utf-8", "replace"))
        err = BadRequest(message, reason=reason)
        self.send_line(format_err(tag or str(self.count), err.code, err.reason, err.message))

    def send_line(self, line: str) -> None:
        if self.transport is not None and not self.transport.is_closing():
            self.transport.write((line + LINE_END).encode("utf-8"))

    def send_event(self, topic: str, data: Mapping[str, Any]) -> None:
        name = self.session.name if self.session else "tcp"
        if self.transport is not None and self.transport.get_write_buffer_size() > EVENT_BUFFER_LIMIT:
            if not self.events_dropped:
                log.warning("%s does not read what it is sent: its events are dropped until it does", name)
            self.events_dropped += 1
            return
        if self.events_dropped:
            log.warning("%s reads again: %d events were dropped", name, self.events_dropped)
            self.events_dropped = 0
        self.send_line(format_event(topic, data))

    def close(self) -> None:
        if self.transport is not None:
            self.transport.close()


def claim_tcp_port(host: str, port: int) -> socket.socket:
    """Bind the text port without listening: a taken port fails at once, before anything starts,
    and connections are refused (not answered) until `start_tcp` opens it."""
    infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    family, kind, proto, _, address = sorted(infos, key=lambda info: info[0] != socket.AF_INET)[0]
    sock = socket.socket(family, kind, proto)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(address)
        sock.setblocking(False)
    except OSError:
        sock.close()
        raise
    return sock


async def start_tcp(server: DispatchHost, sock: socket.socket) -> asyncio.Server:
    """Listen on a claimed socket (see claim_tcp_port): from now on clients are answered."""
    loop = asyncio.get_running_loop()
    return await loop.create_server(lambda: TextConnection(server), sock=sock)
