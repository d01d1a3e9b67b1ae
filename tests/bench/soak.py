"""Soak under load: a real rvs-server for MINUTES under 20 clients on both transports and a job stream.

Not collected by pytest (tests/bench is not searched). Run it by hand:

    .venv/bin/python tests/bench/soak.py [--minutes 20] [--tcp 10] [--zmq 10] [--rate 20]

It starts a server on its own temporary data and configuration directories (a small world, the
simulation sped up as the tests do, the log rotated at `--log-max-mb` so that rotation is seen
working under load), then for the whole run:

- `--tcp` text clients and `--zmq` DEALER clients each keep up to `--window` requests in flight at
  about `--rate` requests per second: immediate commands (status, version, help, check, logbook,
  subscribe), bad lines (unknown commands, bad option values, over-long lines, bytes that are not
  UTF-8, malformed tags, bad JSON, blank lines and comments that must get no reply) and short jobs
  (move-ptu, sleep, a one-frame grab), which mostly get `409 busy`, as they should;
- one job stream keeps the job slot busy back to back, over both transports in turn: move-ptu,
  one-frame grab-tof, dem-update-tof, now and then a break + continue/abort cycle, reset and reinit;
- every client reconnects now and then (a new TCP connection, a new DEALER identity), after its
  replies are in, so that per-connection state that is never freed shows up as memory growth;
- a SUB socket and two subscribed text clients take the events.

Every request carries a unique tag or id (or, on purpose, none: then the server's per-connection
number is predicted and checked). Every final reply must arrive exactly once, on the connection
that sent the request, with an outcome its kind allows; none may be missing at the end. The
server's resident memory (VmRSS), threads and open files are sampled every `--sample` seconds.

Figures are compared with a reference measured in the same run, since the machine is shared and
noisy: the latency of immediate commands in the last minute against the first, the memory at the
end against the memory after the first minute of warm-up, job durations late against early.

Exit status 0 only if: no reply lost, duplicated, stray or of an outcome its request does not
allow (500 included); memory growth at most `--max-rss-growth` %; the log folder within its
rotation bound; `quit` answered OK and the server's exit status 0.

`--season` (issue 46: a server that lives through a season) makes the job stream a season's work
beside a running hazard-start: dem-update-tof, navigate, hop and hop-plan, route-follow of a route it
records first, over and over, with a real segmentation fault injected into the native worker every
third cycle (`sim-fault --device worker`: that job ends 500, `continue` finishes it) and a small
storage cap so the retention rule removes products. Its memory is read as each cycle's last job
ends, the same point of every cycle: the median of cycles 2-4 is the reference, the median of the
last three the end (a time window would catch whichever job's peak falls in it); threads and open
files must not grow past the end of the first cycle; the worker must have been restarted.
Figures go to tests/bench/results/soak.jsonl as JSON lines: one per minute while it runs (so a killed
soak leaves what it saw) and the verdict at the end:

    nohup .venv/bin/python tests/bench/soak.py --season --minutes 60 --tcp 3 --zmq 2 --rate 2 > soak.log &
"""
from __future__ import annotations

import argparse
import asyncio
import collections
import json
import os
import random
import re
import shutil
import statistics
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import zmq
import zmq.asyncio

REPO = Path(__file__).resolve().parents[2]
sys.path[:0] = [str(REPO), str(REPO / "tests")]
from conftest import SIM_SPEED, ServerProcess, write_configs  # noqa: E402

MAX_LINE = 8192
HOPPING = """sfm_threads = 1
[hopper.camera]
width = 320
height = 240
motion_blur = false
"""   # --season: the hopper's small camera, as tests/hopping, so a hop-plan takes seconds
IAC, WILL, SB, SE = 255, 251, 250, 240
TELNET_ANSWER = re.compile(rb"\xff[\xfb-\xfe].", re.DOTALL)   # IAC WILL/WONT/DO/DONT option
OK = "OK"


# ---------------------------------------------------------------------------------------------
# Book-keeping


@dataclass
class Pending:
    key: str            # the tag or id the reply must carry
    client: str
    transport: str      # tcp | zmq
    category: str       # immediate | check | bad | job | stream | control
    label: str          # a short name of what was sent, for the tables
    expect: frozenset   # outcomes allowed: "OK" or an error code as text ("400", "409", ...)
    sent: float         # perf_counter at send
    at: float           # seconds since the load began
    text: str           # what was sent (shortened), for the report of anything unexpected
    future: asyncio.Future | None = None
    progress: int = 0


@dataclass
class Stats:
    t0: float = 0.0
    sent: collections.Counter = field(default_factory=collections.Counter)          # per transport
    no_reply_sent: collections.Counter = field(default_factory=collections.Counter)  # blank, comment
    received: collections.Counter = field(default_factory=collections.Counter)      # final replies
    progress: collections.Counter = field(default_factory=collections.Counter)
    events: collections.Counter = field(default_factory=collections.Counter)
    duplicates: collections.Counter = field(default_factory=collections.Counter)
    strays: collections.Counter = field(default_factory=collections.Counter)
    null_ids: collections.Counter = field(default_factory=collections.Counter)
    garbled: collections.Counter = field(default_factory=collections.Counter)       # lines that are no reply
    lost_on_close: collections.Counter = field(default_factory=collections.Counter)
    unanswered: collections.Counter = field(default_factory=collections.Counter)
    unanswered_examples: list = field(default_factory=list)
    reconnects: collections.Counter = field(default_factory=collections.Counter)
    outcomes: collections.Counter = field(default_factory=collections.Counter)      # (category, outcome)
    labels: collections.Counter = field(default_factory=collections.Counter)        # (label, outcome)
    unexpected: list = field(default_factory=list)
    unexpected_count: int = 0
    latencies: list = field(default_factory=list)  # (at, transport, seconds) of immediate commands
    jobs: list = field(default_factory=list)       # (at, label, seconds) of the stream's OK jobs
    stream_cycles: collections.Counter = field(default_factory=collections.Counter)
    pending: dict = field(default_factory=dict)    # id(conn) -> conn, to count what is left at the end

    def now(self) -> float:
        return time.perf_counter() - self.t0

    def record(self, p: Pending, outcome: str, reason: str, line: str) -> None:
        self.received[p.transport] += 1
        self.outcomes[(p.category, outcome if outcome == OK else f"{outcome} {reason}")] += 1
        self.labels[(p.label, outcome if outcome == OK else f"{outcome} {reason}")] += 1
        if outcome not in p.expect:
            self.unexpected_count += 1
            if len(self.unexpected) < 12:
                self.unexpected.append(f"{p.transport} {p.client} sent {p.text!r} -> {line[:300]!r}")
        if p.category == "immediate" and outcome == OK:
            self.latencies.append((p.at, p.transport, time.perf_counter() - p.sent))


SEASON_LABELS = ("dem-update-tof", "dem-update-tof (crash)", "continue", "navigate", "hop", "hop-plan",
                 "route-follow", "drive", "hazard-start", "hazard-stop")
RESULTS = REPO / "tests" / "bench" / "results" / "soak.jsonl"


def append_result(record: dict[str, Any], results: Path = RESULTS) -> None:
    results.parent.mkdir(parents=True, exist_ok=True)
    with open(results, "a", encoding="utf-8") as handle:
        handle.write(json.dumps(record) + "\n")
        handle.flush()
        os.fsync(handle.fileno())


def outcome_of(code: int | str | None) -> str:
    return OK if code in (200, "200", None) else str(code)


class Connection:
    """What TCP and ZeroMQ connections share: the pending table and exactly-once matching."""

    transport = ""

    def __init__(self, name: str, stats: Stats):
        self.name = name
        self.stats = stats
        self.pending: dict[str, Pending] = {}
        self.done: set[str] = set()
        self.count = 0           # the server's per-connection (per-peer) request number
        self.closing = False
        self.closed = asyncio.Event()
        stats.pending[id(self)] = self

    def expect(self, key: str, category: str, label: str, expect: set[str], text: str,
               want_future: bool = False) -> Pending:
        if key in self.pending or key in self.done:
            raise AssertionError(f"{self.name}: key {key} reused")
        p = Pending(key, self.name, self.transport, category, label, frozenset(expect), time.perf_counter(),
                    self.stats.now(), text[:120])
        if want_future:
            p.future = asyncio.get_running_loop().create_future()
        self.pending[key] = p
        self.stats.sent[self.transport] += 1
        return p

    def final(self, key: str | None, outcome: str, reason: str, line: str) -> None:
        p = self.pending.pop(key, None) if key is not None else None
        if p is None:
            if key in self.done:
                self.stats.duplicates[self.transport] += 1
            else:
                self.stats.strays[self.transport] += 1
            if len(self.stats.unexpected) < 12:
                kind = "duplicate" if key in self.done else "stray"
                self.stats.unexpected.append(f"{self.transport} {self.name}: {kind} reply {line[:200]!r}")
            return
        self.done.add(key)
        self.stats.record(p, outcome, reason, line)
        if p.future is not None and not p.future.done():
            p.future.set_result((outcome, reason, line))

    def progress_line(self, key: str | None) -> None:
        self.stats.progress[self.transport] += 1
        p = self.pending.get(key) if key is not None else None
        if p is None:
            self.stats.strays[self.transport] += 1
        else:
            p.progress += 1

    def lost(self) -> None:
        """The connection closed under us: whatever is pending will never come."""
        if self.pending and not self.closing:
            self.stats.lost_on_close[self.transport] += len(self.pending)
        for p in self.pending.values():
            if p.future is not None and not p.future.done():
                p.future.set_result(("lost", "connection closed", ""))

    def forget(self) -> None:
        """Closed by us: what is still pending now is unanswered for good."""
        for p in self.pending.values():
            self.stats.unanswered[p.transport] += 1
            if len(self.stats.unanswered_examples) < 10:
                self.stats.unanswered_examples.append(f"{p.transport} {p.client} {p.text!r} sent at {p.at:.1f} s")
        self.stats.pending.pop(id(self), None)

    async def drain(self, timeout: float) -> None:
        deadline = time.monotonic() + timeout
        while self.pending and time.monotonic() < deadline and not self.closed.is_set():
            await asyncio.sleep(0.02)


# ---------------------------------------------------------------------------------------------
# The text transport


TAG_OF_REPLY = re.compile(rb"^(\S+) (OK|ERR|PROGRESS)(?: |$)")


class TcpConnection(Connection):
    transport = "tcp"

    async def open(self, host: str, port: int) -> TcpConnection:
        self.reader, self.writer = await asyncio.open_connection(host, port, limit=1 << 20)
        greeting = await asyncio.wait_for(self.reader.readline(), 30)
        if not greeting.startswith(b"RVS "):
            raise AssertionError(f"{self.name}: greeting {greeting!r}")
        self.task = asyncio.ensure_future(self._read())
        return self

    async def _read(self) -> None:
        try:
            while True:
                raw = await self.reader.readline()
                if not raw:
                    break
                # The server refuses telnet options a line asked for (IAC DONT/WONT x, RFC 854): a telnet
                # client takes those bytes out of the stream, and so does this one.
                raw = TELNET_ANSWER.sub(b"", raw.rstrip(b"\r\n"))
                if raw.startswith(b"* EVENT "):
                    self.stats.events["tcp"] += 1
                    continue
                match = TAG_OF_REPLY.match(raw)
                if match is None:
                    self.stats.garbled["tcp"] += 1
                    continue
                key, word = match.group(1).decode(), match.group(2)
                if word == b"PROGRESS":
                    self.progress_line(key)
                    continue
                line = raw.decode("utf-8", "replace")
                if word == b"OK":
                    self.final(key, OK, "", line)
                else:
                    parts = line.split(" ", 4)
                    self.final(key, parts[2] if len(parts) > 2 else "?", parts[3] if len(parts) > 3 else "?", line)
        except (ConnectionError, asyncio.IncompleteReadError, ValueError):
            pass
        finally:
            self.lost()
            self.closed.set()

    async def send(self, data: bytes | list[bytes], key: str | None, category: str = "", label: str = "",
                   expect: set[str] = frozenset(), counted: bool = True, want_future: bool = False,
                   text: str | None = None) -> Pending | None:
        """Write one line (or one line in pieces). `key` None: the server numbers it (when counted)."""
        pieces = data if isinstance(data, list) else [data]
        p = None
        if counted:
            self.count += 1
            shown = text if text is not None else b"".join(pieces)[:120].decode("utf-8", "replace")
            p = self.expect(key or str(self.count), category, label, set(expect), shown, want_future)
        else:
            self.stats.no_reply_sent["tcp"] += 1
        for i, piece in enumerate(pieces):
            self.writer.write(piece)
            await self.writer.drain()
            if i + 1 < len(pieces):
                await asyncio.sleep(0.002)
        return p

    async def close(self) -> None:
        self.closing = True
        self.writer.close()
        try:
            await self.writer.wait_closed()
        except ConnectionError:
            pass
        self.forget()
        await asyncio.wait_for(self.closed.wait(), 10)


# ---------------------------------------------------------------------------------------------
# The ZeroMQ transport


class ZmqConnection(Connection):
    transport = "zmq"

    def __init__(self, name: str, stats: Stats, context: zmq.asyncio.Context):
        super().__init__(name, stats)
        self.context = context
        self.null_waiting: collections.deque[str] = collections.deque()  # undecodable requests

    async def open(self, endpoint: str) -> ZmqConnection:
        self.sock = self.context.socket(zmq.DEALER)
        self.sock.setsockopt(zmq.LINGER, 0)
        self.sock.connect(endpoint)
        self.task = asyncio.ensure_future(self._read())
        return self

    async def _read(self) -> None:
        try:
            while True:
                frame = await self.sock.recv()
                try:
                    reply = json.loads(frame)
                    status, rid = reply["status"], reply.get("id")
                except (ValueError, KeyError, TypeError):
                    self.stats.garbled["zmq"] += 1
                    continue
                if rid is None:
                    self.stats.null_ids["zmq"] += 1
                    rid = self.null_waiting.popleft() if self.null_waiting else None
                if status == "progress":
                    self.progress_line(rid)
                    continue
                if rid in self.null_waiting:
                    self.null_waiting.remove(rid)
                text = f"{rid} {status} {reply.get('code')} {reply.get('reason')} {reply.get('message', '')}"
                if status == "ok":
                    self.final(rid, OK, "", text)
                elif status == "error":
                    self.final(rid, str(reply.get("code")), str(reply.get("reason")), text)
                else:
                    self.stats.garbled["zmq"] += 1
        except (zmq.ZMQError, asyncio.CancelledError):
            pass
        finally:
            self.lost()
            self.closed.set()

    async def send(self, frame: bytes, key: str | None, category: str, label: str, expect: set[str],
                   undecodable: bool = False, want_future: bool = False) -> Pending:
        self.count += 1
        key = key or str(self.count)
        p = self.expect(key, category, label, set(expect), frame[:120].decode("utf-8", "replace"), want_future)
        if undecodable:
            self.null_waiting.append(key)
        await self.sock.send(frame)
        return p

    async def close(self) -> None:
        self.closing = True
        self.forget()
        self.task.cancel()
        try:
            await self.task
        except asyncio.CancelledError:
            pass
        self.sock.close(linger=0)


def frame(**body: Any) -> bytes:
    return json.dumps(body).encode()


# ---------------------------------------------------------------------------------------------
# What the mixed clients send


IMM, CHECK, BAD, JOB, CONTROL = "immediate", "check", "bad", "job", "control"
JOB_OUTCOMES = {OK, "409", "423", "499"}  # 499: the stream's break caught this job instead (a rare race)


def tcp_request(rng: random.Random, tag: str, client: str) -> tuple[Any, ...]:
    """(data, tagged?, counted?, category, label, expect)."""
    t = f"@{tag} ".encode()
    choices: list[tuple[float, Any]] = [
        (20, lambda: (t + b"status\n", True, True, IMM, "status", {OK})),
        (5, lambda: (t + b"version\n", True, True, IMM, "version", {OK})),
        (3, lambda: (t + b"help\n", True, True, IMM, "help", {OK})),
        (3, lambda: (t + rng.choice([b"help move-ptu", b"help dem-update-tof", b"help grab-tof"]) + b"\n",
                     True, True, IMM, "help CMD", {OK})),
        (0.4, lambda: (t + b"logbook\n", True, True, IMM, "logbook", {OK})),
        (3, lambda: (b"  " + t + b"status  \r\n", True, True, IMM, "status CRLF", {OK})),
        (4, lambda: (b"status\n", False, True, IMM, "status untagged", {OK})),
        (2, lambda: ([t + b"sta", bytes([IAC, WILL, 1]) + b"tus\n"], True, True, IMM, "status IAC split", {OK})),
        (2, lambda: ([t + b"ver", b"sion\r", b"\n"], True, True, IMM, "version split", {OK})),
        (0.5, lambda: ((t + b"status").ljust(MAX_LINE, b" ") + b"\r\n", True, True, IMM, "status 8192 bytes",
                       {OK})),
        (3, lambda: (t + b"check move-ptu --pan 10\n", True, True, CHECK, "check move-ptu", {OK, "409", "423"})),
        (1, lambda: (t + b"check move-ptu --pan 1000\n", True, True, CHECK, "check bad", {"400"})),
        (3, lambda: (t + b"frobnicate --now\n", True, True, BAD, "unknown command", {"404"})),
        (2, lambda: (t + b"stauts\n", True, True, BAD, "misspelt command", {"404"})),
        (3, lambda: (t + b"move-ptu --pan 999\n", True, True, BAD, "value out of range", {"400"})),
        (2, lambda: (t + b"move-ptu --bogus 1\n", True, True, BAD, "unknown option", {"400"})),
        (2, lambda: (t + b"move-ptu --pan abc\n", True, True, BAD, "value not a number", {"400"})),
        (1, lambda: (t + b"move-ptu --pan 1 --pan 2\n", True, True, BAD, "option twice", {"400"})),
        (1, lambda: (t + b'status "unterminated\n', True, True, BAD, "open quote", {"400"})),
        (1, lambda: (t + b"grab-tof --output ../escape --frames 1\n", True, True, BAD, "name with path",
                     {"400", "409", "423"})),
        (1, lambda: (t.rstrip() + b"\n", True, True, BAD, "tag alone", {"400"})),
        (2, lambda: ((t + b"status ").ljust(MAX_LINE + 1, b"x") + b"\n", True, True, BAD, "8193 bytes", {"400"})),
        (1, lambda: (t + b"y" * 20000 + b"\n", True, True, BAD, "20000 bytes", {"400"})),
        (0.3, lambda: ([t + b"z" * 60000, b"z" * 60000 + b"\n"], True, True, BAD, "120000 bytes in 2", {"400"})),
        (1, lambda: (b"q" * 9000 + b"\n", False, True, BAD, "over-long untagged", {"400"})),
        (2, lambda: (t + b"\x80" + bytes(rng.randrange(0x80, 0xFF) for _ in range(rng.randrange(1, 40))) + b"\n",
                     True, True, BAD, "not UTF-8", {"400"})),
        (1, lambda: (b"\xc3\x28 status\n", False, True, BAD, "not UTF-8 untagged", {"400"})),
        (1, lambda: (t + bytes(rng.choice(b"\x01\x02\x07\x08\x0b\x0c\x1b\x7f") for _ in range(8)) + b"\n",
                     True, True, BAD, "control bytes", {"400", "404"})),
        (2, lambda: (b"@bad!tag status\n", False, True, BAD, "malformed tag", {"400"})),
        (1, lambda: (b"@" + b"a" * 33 + b" status\n", False, True, BAD, "tag of 33", {"400"})),
        (1.5, lambda: (rng.choice([b"\n", b"\r\n", b"   \t \n"]), False, False, BAD, "blank", set())),
        (1.5, lambda: (rng.choice([b"# a comment\n", b"  #status\n", b"#\xff\xfe not utf-8 comment\n"]), False,
                       False, BAD, "comment", set())),
        (3, lambda: (t + f"move-ptu --pan {rng.uniform(-40, 40):.1f} --speed 50\n".encode(), True, True, JOB,
                     "move-ptu", JOB_OUTCOMES)),
        (1, lambda: (t + b"move-ptu --relative --pan 1 --speed 50\n", True, True, JOB, "move-ptu relative",
                     JOB_OUTCOMES)),
        (1, lambda: (t + f"grab-tof --output mix-{client} --frames 1\n".encode(), True, True, JOB, "grab-tof",
                     JOB_OUTCOMES)),
        (0.7, lambda: (t + b"sleep 1\n", True, True, CONTROL, "sleep 1", {OK, "409", "423"})),
        (0.3, lambda: (t + b"standby\n", True, True, CONTROL, "standby", {OK, "409"})),
    ]
    return weighted(rng, choices)()


def zmq_request(rng: random.Random, rid: str, client: str) -> tuple[Any, ...]:
    """(frame, id given?, undecodable?, category, label, expect)."""
    choices: list[tuple[float, Any]] = [
        (20, lambda: (frame(id=rid, command="status"), True, False, IMM, "status", {OK})),
        (5, lambda: (frame(id=rid, line="version"), True, False, IMM, "version line", {OK})),
        (3, lambda: (frame(id=rid, command="help"), True, False, IMM, "help", {OK})),
        (3, lambda: (frame(id=rid, command="help", args={"command": rng.choice(["move-ptu", "grab-tof"])}),
                     True, False, IMM, "help CMD", {OK})),
        (0.4, lambda: (frame(id=rid, command="logbook"), True, False, IMM, "logbook", {OK})),
        (4, lambda: (frame(command="status"), False, False, IMM, "status without id", {OK})),
        (1, lambda: (frame(id=rid, command="STATUS"), True, False, IMM, "status upper case", {OK})),
        (3, lambda: (frame(id=rid, command="check", args={"line": "move-ptu --pan 10"}), True, False, CHECK,
                     "check move-ptu", {OK, "409", "423"})),
        (3, lambda: (frame(id=rid, command="frobnicate"), True, False, BAD, "unknown command", {"404"})),
        (3, lambda: (frame(id=rid, command="move-ptu", args={"pan": 999}), True, False, BAD, "value out of range",
                     {"400"})),
        (2, lambda: (frame(id=rid, command="move-ptu", args={"pan": "abc"}), True, False, BAD, "value not a number",
                     {"400"})),
        (2, lambda: (frame(id=rid, command="move-ptu", args={"bogus": 1}), True, False, BAD, "unknown option",
                     {"400"})),
        (1, lambda: (frame(id=rid, line="move-ptu --pan"), True, False, BAD, "value missing", {"400"})),
        (1, lambda: (frame(id=rid, line='status "open'), True, False, BAD, "open quote", {"400"})),
        (1, lambda: (frame(id=rid, line="status " + "x" * 9000), True, False, BAD, "over-long line", {"400"})),
        (1, lambda: (frame(id=rid, command="subscribe"), True, False, BAD, "subscribe on zmq", {"400"})),
        (1, lambda: (frame(id=rid), True, False, BAD, "no command", {"400"})),
        (1, lambda: (frame(id=rid, command="status", args=[1, 2]), True, False, BAD, "args not an object", {"400"})),
        (1, lambda: (frame(id=rid, line=17), True, False, BAD, "line not text", {"400"})),
        (1, lambda: (frame(id=f"{rid} bad!", command="status"), "bad", False, BAD, "malformed id", {"400"})),
        (2, lambda: (b"{not json " + rid.encode(), False, True, BAD, "not JSON", {"400"})),
        (1, lambda: (b"\xff\xfe" + bytes(rng.randrange(256) for _ in range(16)), False, True, BAD, "not UTF-8",
                     {"400"})),
        (1, lambda: (b"[1, 2, 3]", False, True, BAD, "JSON array", {"400"})),
        (1, lambda: (b"", False, True, BAD, "empty frame", {"400"})),
        (3, lambda: (frame(id=rid, command="move-ptu", args={"pan": round(rng.uniform(-40, 40), 1), "speed": 50}),
                     True, False, JOB, "move-ptu", JOB_OUTCOMES)),
        (1, lambda: (frame(id=rid, line="move-ptu --relative --pan -1 --speed 50"), True, False, JOB,
                     "move-ptu relative", JOB_OUTCOMES)),
        (1, lambda: (frame(id=rid, command="grab-tof", args={"output": f"mix-{client}", "frames": 1}), True, False,
                     JOB, "grab-tof", JOB_OUTCOMES)),
        (0.7, lambda: (frame(id=rid, command="sleep", args={"seconds": 1}), True, False, CONTROL, "sleep 1",
                       {OK, "409", "423"})),
    ]
    return weighted(rng, choices)()


def weighted(rng: random.Random, choices: list[tuple[float, Any]]) -> Any:
    total = sum(w for w, _ in choices)
    x = rng.uniform(0, total)
    for w, item in choices:
        x -= w
        if x <= 0:
            return item
    return choices[-1][1]


# ---------------------------------------------------------------------------------------------
# Clients


class Run:
    def __init__(self, args: argparse.Namespace, server: ServerProcess):
        self.args = args
        self.server = server
        self.stats = Stats()
        self.context = zmq.asyncio.Context()
        self.stop_at = 0.0
        self.stopping = False
        self.samples: list[tuple[float, float, int, int, float]] = []  # at, rss MiB, threads, fds, cpu s
        self.serial = 0
        self.first_cycle_end: float | None = None   # --season: when the first full cycle ended
        self.crashes = 0                            # --season: jobs the injected worker crash ended (500)
        self.cycle_rss: list[tuple[float, float]] = []  # --season: (at, rss MiB) as each cycle's last job ends
        self.minutes_written = 0
        self.started_at = time.strftime("%Y-%m-%dT%H:%M:%S")

    def tag(self, client: str) -> str:
        self.serial += 1
        return f"{client}-{self.serial}"

    async def open_tcp(self, name: str) -> TcpConnection:
        return await TcpConnection(name, self.stats).open(self.server.host, self.server.port)

    async def open_zmq(self, name: str) -> ZmqConnection:
        return await ZmqConnection(name, self.stats, self.context).open(self.server.zmq)

    def next_life(self, rng: random.Random) -> float:
        """How long a connection lives before its client reconnects."""
        return time.monotonic() + rng.expovariate(1 / self.args.reconnect_s)

    async def mixed_client(self, transport: str, index: int) -> None:
        rng = random.Random(1000 * index + (transport == "zmq"))
        name = f"{transport[0].upper()}{index:02d}"
        subscriber = transport == "tcp" and index < 2
        window = asyncio.Semaphore(self.args.window)
        while not self.stopping:
            conn = await (self.open_tcp(name) if transport == "tcp" else self.open_zmq(name))
            if subscriber:  # one takes every topic, one the job's own
                words = b"subscribe\n" if index == 0 else b"subscribe mode progress\n"
                tag = self.tag(name)
                await conn.send(f"@{tag} ".encode() + words, tag, IMM, "subscribe", {OK})
            end_of_life = self.next_life(rng)
            while not self.stopping and time.monotonic() < end_of_life and not conn.closed.is_set():
                await asyncio.sleep(rng.expovariate(self.args.rate))
                await window.acquire()
                if self.stopping:
                    window.release()
                    break
                tag = self.tag(name)
                if transport == "tcp":
                    data, tagged, counted, category, label, expect = tcp_request(rng, tag, name)
                    p = await conn.send(data, tag if tagged else None, category, label, expect, counted,
                                        want_future=counted)
                else:
                    data, given, undecodable, category, label, expect = zmq_request(rng, tag, name)
                    key = f"{tag} bad!" if given == "bad" else (tag if given else None)
                    p = await conn.send(data, key, category, label, expect, undecodable, want_future=True)
                if p is None:
                    window.release()
                else:
                    p.future.add_done_callback(lambda _f: window.release())
            await conn.drain(60)
            await conn.close()
            if not self.stopping:
                self.stats.reconnects[transport] += 1

    async def season_stream(self) -> None:
        """The season's job stream (--season): hazard detection runs beside every job; the cycle maps,
        navigates, hops and plans, follows a route; every third cycle a real crash in the native worker."""
        conn = await self.open_tcp("SS-tcp")
        anything = {OK, "400", "409", "423"}
        await self.stream_job(conn, "hazard-start", "hazard-start --rate 2", {OK})
        await self.stream_job(conn, "route-record", "route-record start --name soak", {OK})
        for _ in range(2):
            await self.stream_job(conn, "drive", "drive --forward 0.6", anything)
        await self.stream_job(conn, "route-record", "route-record stop", {OK, "400"})
        cycle = 0
        while not self.stopping:
            cycle += 1
            if cycle % 3 == 1:
                await self.stream_job(conn, "sim-fault", "sim-fault --device worker --kind segv", {OK})
                outcome, _, _ = await self.stream_job(conn, "dem-update-tof (crash)", "dem-update-tof --pan -20:20",
                                                      {OK, "500", "409", "423"})
                self.stats.stream_cycles[f"dem-update-tof with a worker crash: {outcome}"] += 1
                if outcome == "500":
                    self.crashes += 1
                    done, _, _ = await self.stream_job(conn, "continue", "continue", {OK, "400", "409"})
                    self.stats.stream_cycles[f"continue after the crash: {done}"] += 1
            else:
                await self.stream_job(conn, "dem-update-tof", "dem-update-tof --pan -20:20", {OK, "409", "423"})
            if self.stopping:
                break
            goal = "1.2,0.0" if cycle % 2 else "0.3,0.0"
            await self.stream_job(conn, "navigate", f"navigate --to {goal} --tolerance 0.4 --max-steps 3", anything)
            await self.stream_job(conn, "hop", f"hop --speed 1.0 --elevation 60 --heading {0 if cycle % 2 else 180}",
                                  anything)
            await self.stream_job(conn, "hop-plan", "hop-plan", anything)
            await self.stream_job(conn, "route-follow", f"route-follow --name soak{' --reverse' if cycle % 2 else ''}",
                                  anything)
            if self.first_cycle_end is None:
                self.first_cycle_end = self.stats.now()
            rss = resident_mib(self.server.proc.pid)
            if rss is not None:   # the same point of every cycle: no job's transient peak in the figure
                self.cycle_rss.append((self.stats.now(), rss))
            self.stats.stream_cycles["season cycles"] += 1
        await self.stream_job(conn, "hazard-stop", "hazard-stop", {OK, "409"})
        await conn.drain(60)
        await conn.close()

    async def job_stream(self) -> None:
        """One client keeps the job slot busy: a job, the next as soon as the reply is in."""
        if self.args.season:
            await self.season_stream()
            return
        rng = random.Random(7)
        conns = {"tcp": await self.open_tcp("JS-tcp"), "zmq": await self.open_zmq("JS-zmq")}
        n = 0
        while not self.stopping:
            n += 1
            transport = "tcp" if n % 2 else "zmq"
            conn = conns[transport]
            if n % 97 == 0:
                await self.break_cycle(conn, abort=(n // 97) % 2 == 0)
                continue
            if n % 211 == 0:
                label, line = "reset", "reset"
            elif n % 401 == 0:
                label, line = "reinit", "reinit"
            elif n % 7 == 0:
                label, line = "dem-update-tof", "dem-update-tof --pan -10:10 --tilt -30:-30"
            elif n % 3 == 0:
                label, line = "grab-tof", "grab-tof --output stream --frames 1"
            else:
                label, line = "move-ptu", f"move-ptu --pan {rng.uniform(-45, 45):.1f} --tilt {rng.uniform(-35, 0):.1f}"
            await self.stream_job(conn, label, line)
        for conn in conns.values():
            await conn.drain(60)
            await conn.close()

    async def stream_request(self, conn: Connection, label: str, line: str, expect: set[str]) -> Pending:
        tag = self.tag(conn.name)
        if isinstance(conn, TcpConnection):
            return await conn.send(f"@{tag} {line}\n".encode(), tag, "stream", label, expect, want_future=True)
        return await conn.send(frame(id=tag, line=line), tag, "stream", label, expect, want_future=True)

    async def stream_job(self, conn: Connection, label: str, line: str,
                         expect: set[str] | None = None) -> tuple[str, str, str]:
        """Send until the server takes it (busy and sleeping are other clients' doing): its final reply."""
        for _ in range(5000):
            start = time.perf_counter()
            p = await self.stream_request(conn, label, line, {OK, "409", "423"} | (expect or set()))
            outcome, reason, text = await p.future
            if outcome == OK:
                self.stats.jobs.append((self.stats.now(), label, time.perf_counter() - start))
            if outcome not in ("409", "423") or self.stopping:
                return outcome, reason, text
            self.stats.stream_cycles[f"{label} refused ({outcome} {reason}), sent again"] += 1
            if "mode is break" in text and label not in ("continue", "abort"):
                # our break caught another client's job (the rare race): end it, as an operator would
                a = await self.stream_request(conn, "abort", "abort", {OK, "409"})
                self.stats.stream_cycles[f"abort of another's job: {(await a.future)[0]}"] += 1
            await asyncio.sleep(0.005)
        return outcome, reason, text

    async def break_cycle(self, conn: Connection, abort: bool) -> None:
        """A longer job, interrupted by break once it reports progress, then continued or aborted."""
        label = "dem-update-tof (break)"
        while not self.stopping:
            p = await self.stream_request(conn, label, "dem-update-tof --pan -30:30 --tilt -30:-30",
                                          {OK, "409", "423", "499"})
            while p.progress == 0 and not p.future.done():
                await asyncio.sleep(0.002)
            if p.future.done() and p.future.result()[0] in ("409", "423"):
                self.stats.stream_cycles[f"{label} refused ({p.future.result()[0]}), sent again"] += 1
                await asyncio.sleep(0.005)
                continue
            b = await self.stream_request(conn, "break", "break", {OK, "409"})
            job_outcome = (await p.future)[0]
            break_outcome = (await b.future)[0]
            self.stats.stream_cycles[f"break: job {job_outcome}, break {break_outcome}"] += 1
            if job_outcome != "499":
                return
            what = "abort" if abort else "continue"
            outcome, reason, text = await self.stream_job(conn, what, what)
            self.stats.stream_cycles[f"{what} after break: {outcome} {reason}".strip()] += 1
            return

    async def events(self) -> None:
        sub = self.context.socket(zmq.SUB)
        sub.setsockopt(zmq.LINGER, 0)
        sub.setsockopt(zmq.SUBSCRIBE, b"")
        sub.connect(self.server.pub)
        try:
            while True:
                await sub.recv_multipart()
                self.stats.events["zmq pub"] += 1
        except (asyncio.CancelledError, zmq.ZMQError):
            pass
        finally:
            sub.close(linger=0)

    async def sampler(self) -> None:
        pid = self.server.proc.pid
        ticks = os.sysconf("SC_CLK_TCK")
        while True:
            try:
                status = Path(f"/proc/{pid}/status").read_text()
                rss = int(re.search(r"VmRSS:\s+(\d+)", status).group(1)) / 1024
                threads = int(re.search(r"Threads:\s+(\d+)", status).group(1))
                fds = len(os.listdir(f"/proc/{pid}/fd"))
                stat = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
                cpu = (int(stat[11]) + int(stat[12])) / ticks
            except (OSError, AttributeError):
                return
            self.samples.append((self.stats.now(), rss, threads, fds, cpu))
            if self.args.season and self.stats.now() >= 60 * (self.minutes_written + 1):
                self.minutes_written += 1
                self.write_minute(rss, threads, fds)
            await asyncio.sleep(self.args.sample)

    def write_minute(self, rss: float, threads: int, fds: int) -> None:
        """A line per minute in soak.jsonl: what a killed soak leaves behind."""
        record = {"soak": self.started_at, "minute": self.minutes_written, "rss_mib": round(rss, 1),
                  "cycle_end_rss_mib": round(self.cycle_rss[-1][1], 1) if self.cycle_rss else None,
                  "threads": threads, "open_files": fds, "cycles": self.stats.stream_cycles["season cycles"],
                  "crashes": self.crashes, "jobs": {f"{lb} {o}": n for (lb, o), n in self.stats.labels.items()
                                                    if lb in SEASON_LABELS}}
        append_result(record, self.args.results)

    async def run(self) -> None:
        self.stats.t0 = time.perf_counter()
        duration = self.args.minutes * 60
        sampler = asyncio.ensure_future(self.sampler())
        events = asyncio.ensure_future(self.events())
        clients = [asyncio.ensure_future(self.mixed_client("tcp", i)) for i in range(self.args.tcp)]
        clients += [asyncio.ensure_future(self.mixed_client("zmq", i)) for i in range(self.args.zmq)]
        clients.append(asyncio.ensure_future(self.job_stream()))
        ticker = asyncio.ensure_future(self.ticker(duration))
        done, _ = await asyncio.wait(clients, timeout=duration, return_when=asyncio.FIRST_EXCEPTION)
        for task in done:  # a client that died is a bug in this script: say so at once
            if task.exception() is not None:
                raise task.exception()
        self.stopping = True
        self.drain_started = self.stats.now()
        await asyncio.wait(clients, timeout=90)
        self.drain_s = self.stats.now() - self.drain_started
        ticker.cancel()
        await asyncio.sleep(self.args.sample)  # one more memory sample with the load gone
        sampler.cancel()
        events.cancel()
        for task in clients:
            if not task.done():
                task.cancel()
        await asyncio.gather(*clients, return_exceptions=True)

    async def ticker(self, duration: float) -> None:
        """A line a minute, so that a long run shows it is alive."""
        minute = 0
        while True:
            await asyncio.sleep(60)
            minute += 1
            rss = self.samples[-1][1] if self.samples else float("nan")
            sent, got = sum(self.stats.sent.values()), sum(self.stats.received.values())
            print(f"  minute {minute}/{duration / 60:g}: sent {sent} answered {got} jobs {len(self.stats.jobs)} "
                  f"rss {rss:.0f} MiB", flush=True)


# ---------------------------------------------------------------------------------------------
# Report


def percentiles(values: list[float]) -> list[float]:
    if not values:
        return [float("nan")] * 5
    a = np.asarray(values) * 1000
    return [len(a), *np.percentile(a, [50, 95, 99]), a.max()]


def dir_size(path: Path) -> tuple[int, int]:
    total = files = 0
    for item in path.rglob("*"):
        if item.is_file():
            total += item.stat().st_size
            files += 1
    return total, files


def resident_mib(pid: int) -> float | None:
    """The process's resident memory (VmRSS) in MiB, None once it is gone."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return None
    found = re.search(r"VmRSS:\s+(\d+)", status)
    return int(found.group(1)) / 1024 if found else None


def cycle_growth(cycle_rss: list[tuple[float, float]], span: int = 3) -> tuple[float, float, float]:
    """Memory growth over a season, measured where every cycle looks alike: as its last job ends.
    The reference is the median of cycles 2..span+1 (the first builds caches and pools), the end the
    median of the last `span`; a time window instead catches whichever job's peak happens to fall in it."""
    values = [rss for _, rss in cycle_rss]
    if len(values) < 2 * span + 1:
        return float("nan"), float("nan"), float("nan")
    start = statistics.median(values[1:1 + span])
    end = statistics.median(values[-span:])
    return start, end, 100 * (end / start - 1)


def window_median(samples: list[tuple], lo: float, hi: float) -> float:
    values = [s[1] for s in samples if lo <= s[0] < hi]
    return statistics.median(values) if values else float("nan")


def report(run: Run, quit_reply: str, exit_code: int | None, base: Path, config_dir: Path) -> int:
    args, stats = run.args, run.stats
    duration = args.minutes * 60
    failures: list[str] = []
    for conn in list(stats.pending.values()):  # still open at the end (the job stream's)
        conn.forget()
    left, left_examples = stats.unanswered, stats.unanswered_examples
    print()
    print(f"soak: {args.minutes:g} min, {args.tcp} TCP + {args.zmq} ZeroMQ clients at ~{args.rate:g} req/s each "
          f"(window {args.window}), a job stream, sim speed {SIM_SPEED:g}, {os.cpu_count()} CPUs")
    print()
    print(f"{'replies':<34}{'tcp':>12}{'zmq':>12}")
    rows = [("requests sent (a reply due)", stats.sent), ("final replies received", stats.received),
            ("unanswered at the end", left), ("lost with a connection", stats.lost_on_close),
            ("duplicated", stats.duplicates), ("stray (no such request)", stats.strays),
            ("reply id null (bad JSON)", stats.null_ids), ("lines that are no reply", stats.garbled),
            ("blank/comment lines (no reply)", stats.no_reply_sent), ("progress lines", stats.progress),
            ("events (text / PUB)", collections.Counter(tcp=stats.events["tcp"], zmq=stats.events["zmq pub"])),
            ("reconnections", stats.reconnects)]
    for name, counter in rows:
        print(f"{name:<34}{counter['tcp']:>12}{counter['zmq']:>12}")
    print(f"(the load stopped at {duration:.0f} s; the last replies were in {run.drain_s:.1f} s later)")

    print()
    print("outcomes by kind of request")
    by_category: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)
    for (category, outcome), n in stats.outcomes.items():
        by_category[category][outcome] += n
    for category in ("immediate", "check", "bad", "job", "control", "stream"):
        if category in by_category:
            counts = by_category[category]
            print(f"  {category:<10} {sum(counts.values()):>8}  " +
                  ", ".join(f"{o} {n}" for o, n in counts.most_common()))
    if stats.stream_cycles:
        print("job stream: " + "; ".join(f"{k} {v}" for k, v in sorted(stats.stream_cycles.items()) if v))

    print()
    first = [lat for at, _, lat in stats.latencies if at < 60]
    last = [lat for at, _, lat in stats.latencies if duration - 60 <= at < duration]
    print(f"immediate commands' latency (ms)  {'n':>8}{'p50':>9}{'p95':>9}{'p99':>9}{'max':>9}")
    for transport in ("tcp", "zmq", None):
        pick = (lambda tr, want=transport: tr == want) if transport else (lambda tr: True)
        a = percentiles([lat for at, tr, lat in stats.latencies if at < 60 and pick(tr)])
        b = percentiles([lat for at, tr, lat in stats.latencies if duration - 60 <= at < duration and pick(tr)])
        name = transport or "both"
        print(f"  {name:<5} first minute            {a[0]:>8.0f}" + "".join(f"{x:>9.2f}" for x in a[1:]))
        print(f"  {name:<5} last minute             {b[0]:>8.0f}" + "".join(f"{x:>9.2f}" for x in b[1:]))
        print(f"  {name:<5} ratio last/first        {'':>8}" +
              "".join(f"{y / x:>9.2f}" if x == x and x > 0 else f"{'-':>9}" for x, y in zip(a[1:], b[1:], strict=True)))
    if not first or not last:
        failures.append("no immediate command answered in the first or the last minute")

    print()
    print(f"job stream: durations (ms) of OK jobs   {'first min':>10}{'last min':>10}{'ratio':>8}{'count':>8}")
    for label in ("move-ptu", "grab-tof", "dem-update-tof", "reset", "reinit", *SEASON_LABELS[3:7]):
        a = [d for at, lb, d in stats.jobs if lb == label and at < 60]
        b = [d for at, lb, d in stats.jobs if lb == label and duration - 60 <= at < duration]
        n = sum(1 for _, lb, _ in stats.jobs if lb == label)
        if n:
            ma = statistics.median(a) * 1000 if a else float("nan")
            mb = statistics.median(b) * 1000 if b else float("nan")
            ratio = mb / ma if ma == ma and mb == mb else float('nan')
            print(f"  {label:<37}{ma:>10.1f}{mb:>10.1f}{ratio:>8.2f}{n:>8}")
    per_minute = collections.Counter(int(at // 60) for at, _, _ in stats.jobs if at < duration)
    print("  jobs per minute: " + " ".join(str(per_minute[m]) for m in range(int(np.ceil(duration / 60)))))

    print()
    samples = run.samples
    warm = args.warmup
    if args.season:   # the reference: the end of the first full cycle of the season's work
        if run.first_cycle_end is None:
            failures.append("the season's first cycle never ended")
        else:
            warm = run.first_cycle_end
    loaded = [s for s in samples if s[0] < duration]
    start_rss = window_median(samples, warm, warm + 30)
    end_rss = window_median(samples, duration - 30, duration)
    growth = 100 * (end_rss / start_rss - 1)
    print("server resident memory (VmRSS, MiB), threads, open files, CPU")
    print(f"  at {warm:.0f}-{warm + 30:.0f} s (median)   {start_rss:8.1f}")
    print(f"  last 30 s of load (median) {end_rss:8.1f}   growth {growth:+.2f} %")
    if args.season:   # the verdict's figure: as each cycle ends, early cycles against the last
        start_rss, end_rss, growth = cycle_growth(run.cycle_rss)
        print(f"  as a cycle ends: cycles 2-4 (median) {start_rss:.1f}, last 3 (median) {end_rss:.1f}, growth "
              f"{growth:+.2f} % (target <= {args.max_rss_growth:g} %) over {len(run.cycle_rss)} cycles")
        print("  per cycle end: " + " ".join(f"{rss:.0f}" for _, rss in run.cycle_rss))
    else:
        print(f"  target <= {args.max_rss_growth:g} %")
    if loaded:
        after = [s for s in loaded if s[0] >= warm]
        if len(after) >= 3:
            slope = np.polyfit([s[0] / 60 for s in after], [s[1] for s in after], 1)[0]
            print(f"  trend after warm-up {slope:+.2f} MiB/min; min {min(s[1] for s in after):.1f} "
                  f"max {max(s[1] for s in after):.1f}")
        line = "  per minute (last sample): "
        for m in range(1, int(np.ceil(duration / 60)) + 1):
            at_m = [s for s in loaded if s[0] < m * 60]
            if at_m:
                line += f"{at_m[-1][1]:.0f} "
        print(line)
        t_first = next((s for s in loaded if s[0] >= warm), loaded[0])
        t_last = loaded[-1]
        if args.season and (t_last[2] > t_first[2] + 2 or t_last[3] > t_first[3] + 4):
            failures.append(f"threads {t_first[2]} -> {t_last[2]} or open files {t_first[3]} -> {t_last[3]} grew "
                            "after the first cycle")
        print(f"  threads {t_first[2]} -> {t_last[2]}, open files {t_first[3]} -> {t_last[3]}, "
              f"server CPU {100 * (t_last[4] - loaded[0][4]) / max(1e-9, t_last[0] - loaded[0][0]):.0f} % of one core")
        if samples[-1][0] >= duration:
            print(f"  after the load stopped: {samples[-1][1]:.1f} MiB")
    if not growth == growth or growth > args.max_rss_growth:
        failures.append(f"resident memory grew {growth:+.2f} % (target <= {args.max_rss_growth:g} %)")

    data = base / "data"
    logs_size, logs_files = dir_size(data / "logs")
    data_size, data_files = dir_size(data)
    stderr_size = run.server.stderr_path.stat().st_size if run.server.stderr_path else 0
    bound = args.logs_kept * args.log_max_mb * 1e6 * 1.1 + 200_000
    print()
    print(f"log folder at the end: {logs_size / 1e6:.2f} MB in {logs_files} files (rotation at {args.log_max_mb:g} MB, "
          f"{args.logs_kept} kept: bound {bound / 1e6:.2f} MB); the server logged {stderr_size / 1e6:.2f} MB in all "
          f"(its stderr copy)")
    print(f"data folder at the end: {data_size / 1e6:.1f} MB in {data_files} files")
    if logs_size > bound or logs_files > args.logs_kept:
        failures.append(f"log folder {logs_size / 1e6:.2f} MB in {logs_files} files is over its rotation bound")
    text = run.server.stderr() if stderr_size < 500e6 else ""
    tracebacks = text.count("Traceback")
    levels = collections.Counter()
    for line in text.splitlines():
        match = re.match(r"\S+ \S+ (WARNING|ERROR|CRITICAL) (\S+): (.{0,60})", line)
        if match:
            levels[(match.group(1), match.group(2), re.sub(r"\d+", "N", match.group(3)))] += 1
    print(f"tracebacks in the server's log: {tracebacks}; warnings and errors: "
          f"{sum(levels.values())}" + "".join(f"\n  {n} x {lv} {src}: {msg}" for (lv, src, msg), n in
                                             levels.most_common(8)))
    shown: set[str] = set()
    for block in text.split("Traceback (most recent call last):")[1:]:  # each kind once, its innermost frames
        lines = [x for x in block.splitlines() if x.strip()]
        end = next((i for i, x in enumerate(lines) if not x.startswith(" ")), len(lines) - 1)
        if lines and lines[end] not in shown and len(shown) < 3:
            shown.add(lines[end])
            print("  traceback: " + "\n  ".join(lines[max(0, end - 6):end + 1]))
    print(f"quit: {quit_reply!r}; server exit status {exit_code}")
    removed = [line for line in text.splitlines() if "retention (" in line and " removed " in line]
    if args.season:
        print(f"season: {stats.stream_cycles['season cycles']} cycles, {run.crashes} jobs ended by an injected "
              f"worker crash; the retention rule removed products {len(removed)} times"
              + "".join(f"\n  {line[-160:]}" for line in removed[:3]))
        if run.crashes == 0:
            failures.append("no injected worker crash ended a job: the worker was never restarted")

    if sum(left.values()):
        failures.append(f"{sum(left.values())} requests unanswered: {left_examples[:5]}")
    if sum(stats.lost_on_close.values()):
        failures.append(f"{sum(stats.lost_on_close.values())} replies lost when a connection closed under us")
    if sum(stats.duplicates.values()) or sum(stats.strays.values()):
        failures.append(f"duplicated {dict(stats.duplicates)}, stray {dict(stats.strays)} replies")
    if sum(stats.garbled.values()):
        failures.append(f"{dict(stats.garbled)} lines or frames that are no reply")
    if stats.unexpected_count:
        failures.append(f"{stats.unexpected_count} replies of an outcome their request does not allow")
    if tracebacks:
        failures.append(f"{tracebacks} tracebacks in the server's log")
    if not quit_reply.split(" ")[1:2] == ["OK"]:
        failures.append(f"quit answered {quit_reply!r}")
    if exit_code != 0:
        failures.append(f"server exit status {exit_code}")
    if stats.unexpected:
        print()
        print("unexpected replies (first few):")
        for text in stats.unexpected:
            print("  " + text)
    print()
    if args.season:
        append_result({"soak": run.started_at, "minutes": args.minutes, "verdict": "FAIL" if failures else "PASS",
                       "failures": failures, "rss_growth_pct": round(growth, 2) if growth == growth else None,
                       "rss_reference_mib": round(start_rss, 1), "rss_end_mib": round(end_rss, 1),
                       "rss_measured": "as each cycle ends",
                       "cycles": stats.stream_cycles["season cycles"], "crashes": run.crashes,
                       "retention_removals": len(removed),
                       "replies": {"sent": sum(stats.sent.values()), "received": sum(stats.received.values()),
                                   "unanswered": sum(left.values()), "duplicated": sum(stats.duplicates.values())}},
                      args.results)
    if failures:
        print("FAIL")
        for text in failures:
            print("  - " + text)
        return 1
    print("PASS: every reply arrived exactly once; memory, log folder and shutdown within their targets")
    return 0


def server_toml(args: argparse.Namespace) -> str:
    text = (REPO / "configs" / "server.toml").read_text()
    text = re.sub(r"(?m)^log_file_max_mb\s*=.*$", f"log_file_max_mb = {args.log_max_mb}", text)
    text = re.sub(r"(?m)^log_files_kept\s*=.*$", f"log_files_kept = {args.logs_kept}", text)
    return text


def quit_server(server: ServerProcess) -> tuple[str, int | None]:
    reply = "no reply"
    try:
        with server.connect(timeout=10) as client:
            reply = client.command("quit", timeout=90)
    except (OSError, TimeoutError, ConnectionError) as exc:
        reply = f"no reply: {exc}"
    try:
        code = server.proc.wait(timeout=60)
    except Exception:
        server.proc.kill()
        code = server.proc.wait()
    if server.proc.stdout:
        server.proc.stdout.close()
    return reply, code


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--minutes", type=float, default=20.0)
    parser.add_argument("--tcp", type=int, default=10, help="text clients")
    parser.add_argument("--zmq", type=int, default=10, help="ZeroMQ DEALER clients")
    parser.add_argument("--rate", type=float, default=20.0, help="requests per second per client (mean)")
    parser.add_argument("--window", type=int, default=4, help="requests in flight per client, at most")
    parser.add_argument("--reconnect-s", type=float, default=90.0, help="mean life of a connection")
    parser.add_argument("--warmup", type=float, default=60.0, help="seconds before the memory reference")
    parser.add_argument("--sample", type=float, default=5.0, help="seconds between memory samples")
    parser.add_argument("--max-rss-growth", type=float, default=5.0, help="target, percent")
    parser.add_argument("--log-max-mb", type=float, default=0.1, help="server.toml log_file_max_mb for the run")
    parser.add_argument("--logs-kept", type=int, default=3, help="server.toml log_files_kept for the run")
    parser.add_argument("--results", type=Path, default=RESULTS, help="--season: the JSON-lines file its minutes "
                        "and verdict go to (a trial run: somewhere else)")
    parser.add_argument("--keep", action="store_true", help="keep the temporary directory and say where")
    parser.add_argument("--season", action="store_true", help="the season's job stream beside hazard-start, with "
                        "worker crashes and a storage cap (issue 46); figures to tests/bench/results/soak.jsonl")
    args = parser.parse_args()
    if args.minutes * 60 < args.warmup + 60:
        parser.error(f"--minutes must leave a minute after the {args.warmup:g} s warm-up")

    tmp = tempfile.mkdtemp(prefix="rvs-soak-")
    base = Path(tmp)
    status = 1
    try:
        extra = {"server.toml": server_toml(args)}
        if args.season:
            # a small cap, so the retention rule removes products during the soak
            extra["server.toml"] = re.sub(r"(?m)^storage\.max_gib\s*=.*$", "storage.max_gib = 0.05",
                                          extra["server.toml"])
            extra["hopping.toml"] = HOPPING
        config_dir = write_configs(base / "configs", extra)
        server = ServerProcess(data_dir=base / "data", config_dir=config_dir).start()
        print(f"rvs-server pid {server.proc.pid} ready on tcp {server.host}:{server.port}, zmq {server.zmq}; "
              f"running {args.minutes:g} min in {base}", flush=True)
        run = Run(args, server)
        try:
            asyncio.run(run.run())
        finally:
            quit_reply, code = quit_server(server)
            run.context.destroy(linger=0)
        status = report(run, quit_reply, code, base, config_dir)
        return status
    finally:
        if args.keep:
            print(f"kept {base}")
        elif status:  # a failure: keep the log and the server's stderr to look at, not the products
            shutil.rmtree(base / "data" / "products", ignore_errors=True)
            print(f"kept {base} (without data/products) to look at the failure")
        else:
            shutil.rmtree(base, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
