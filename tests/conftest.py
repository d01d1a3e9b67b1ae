"""Shared test fixtures: a real `rvs-server` process on loopback, and a line-level text client.

Tests talk to the server the way a GNC computer would: over real sockets, to a real process, with
the emulated devices speaking their real byte protocols. The simulation clock runs fast (`SIM_SPEED`)
so a PTU move that takes seconds on the test bed takes a fraction of one here.
"""
from __future__ import annotations

import os
import shutil
import socket
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
SERVER = [sys.executable, "-m", "rvs_server"]
SIM_SPEED = 50.0


@dataclass
class ServerProcess:
    """A running rvs-server and where to reach it."""

    data_dir: Path
    config_dir: Path
    proc: subprocess.Popen | None = None
    host: str = "127.0.0.1"
    port: int = 0
    zmq: str = ""
    pub: str = ""
    web: str = "off"
    stderr_path: Path | None = None
    extra_args: list[str] = field(default_factory=list)

    def start(self, timeout: float = 60.0) -> ServerProcess:
        self.stderr_path = self.data_dir.parent / f"server-{int(time.time() * 1000)}.stderr"
        # The web view is off unless a test asks for it (extra_args come last and win): its default
        # port is fixed, and servers started side by side must not fight over it.
        args = [*SERVER, "--port", "0", "--zmq-port", "0", "--web-port", "0", "--data-dir", str(self.data_dir),
                "--config-dir", str(self.config_dir), "--sim-speed", str(SIM_SPEED), *self.extra_args]
        with open(self.stderr_path, "wb") as err:
            self.proc = subprocess.Popen(args, cwd=REPO, stdout=subprocess.PIPE, stderr=err,
                                         stdin=subprocess.DEVNULL)
        deadline = time.monotonic() + timeout
        assert self.proc.stdout is not None
        while time.monotonic() < deadline:
            line = self.proc.stdout.readline().decode()
            if not line:
                raise RuntimeError(f"rvs-server exited ({self.proc.wait()}): {self.stderr()}")
            if line.startswith("rvs-server ready"):
                fields = dict(part.split("=", 1) for part in line.split()[2:])
                self.host, port = fields["tcp"].rsplit(":", 1)
                self.port, self.zmq, self.pub = int(port), fields["zmq"], fields["pub"]
                self.web = fields.get("web", "off")  # HOST:PORT of the web view, or off
                return self
        raise RuntimeError(f"rvs-server did not become ready: {self.stderr()}")

    def stderr(self) -> str:
        return self.stderr_path.read_text(errors="replace") if self.stderr_path and self.stderr_path.exists() else ""

    def connect(self, timeout: float = 20.0) -> LineClient:
        return LineClient(self.host, self.port, timeout)

    def stop(self) -> int | None:
        if self.proc is None:
            return None
        if self.proc.poll() is None:
            try:
                with self.connect(timeout=5) as client:
                    reply = client.command("quit", timeout=60)
                if reply.split()[1:2] != ["OK"]:  # refused (a server with --token-file): SIGTERM quits as cleanly
                    self.proc.terminate()
            except (OSError, AssertionError, TimeoutError):
                pass
            try:
                self.proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        code = self.proc.returncode
        if self.proc.stdout:
            self.proc.stdout.close()
        return code

    def kill(self) -> None:
        """A crash or power cut: no chance to clean up."""
        assert self.proc is not None
        self.proc.kill()
        self.proc.wait()
        if self.proc.stdout:
            self.proc.stdout.close()


class LineClient:
    """A raw text-protocol client: send bytes, read lines. Tests see exactly what telnet would."""

    def __init__(self, host: str, port: int, timeout: float = 20.0):
        self.sock = socket.create_connection((host, port), timeout=timeout)
        self.sock.settimeout(timeout)
        self.buffer = b""
        self.greeting = self.read_line()
        self.events: list[str] = []
        self.pending: list[str] = []  # replies read but not yet asked for

    def __enter__(self) -> LineClient:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        try:
            self.sock.close()
        except OSError:
            pass

    def send_raw(self, data: bytes) -> None:
        self.sock.sendall(data)

    def send(self, line: str) -> None:
        self.send_raw(line.encode() + b"\n")

    def read_line(self, timeout: float | None = None) -> str:
        if timeout is not None:
            self.sock.settimeout(timeout)
        while b"\n" not in self.buffer:
            chunk = self.sock.recv(65536)
            if not chunk:
                raise ConnectionError("server closed the connection")
            self.buffer += chunk
        line, self.buffer = self.buffer.split(b"\n", 1)
        return line.decode().rstrip("\r")

    def reply(self, tag: str, timeout: float = 30.0) -> tuple[str, list[str]]:
        """Read until the final reply for `tag`; returns it and the lines for that tag before it.

        Lines for other tags are kept, so a later reply() for their tag still finds them."""
        deadline = time.monotonic() + timeout
        index = 0
        while True:
            while index < len(self.pending):
                line = self.pending[index]
                head = line.split(" ", 2)
                if head[0] == tag and len(head) > 1 and head[1] in ("OK", "ERR"):
                    before = [x for x in self.pending[:index] if x.split(" ", 1)[0] == tag]
                    self.pending = [x for x in self.pending[:index] if x.split(" ", 1)[0] != tag] + \
                        self.pending[index + 1:]
                    return line, before
                index += 1
            left = deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError(f"no final reply for tag {tag}; got {self.pending[-5:]}")
            line = self.read_line(timeout=left)
            if line.startswith("* EVENT"):
                self.events.append(line)
                continue
            self.pending.append(line)

    def command(self, line: str, timeout: float = 30.0) -> str:
        """Send one tagged command and return its final reply line."""
        tag = f"t{time.monotonic_ns() % 10**9}"
        self.send(f"@{tag} {line}")
        reply, _ = self.reply(tag, timeout)
        return reply


# A 12 m scene builds in half a second; the 40 m default takes seconds and over a gigabyte.
SMALL_WORLD = """seed = 3
size_m = [12.0, 12.0]
[rocks]
cover = 0.07
[craters]
count = 1
diameter_range_m = [2.0, 3.0]
"""


# 20 m across without craters: the routes' and the hazard guard's scenes (the forward camera sees ground,
# not the world's edge, on every leg).
WIDE_WORLD = """seed = 3
size_m = [20.0, 20.0]
[rocks]
cover = 0.07
[craters]
count = 0
"""


def look_at(eye, target):
    """Camera-to-world pose (OpenCV axes) at `eye` looking at `target`, image rows level."""
    import numpy as np
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    forward = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = right, np.cross(forward, right), forward, eye
    return pose


def write_configs(config_dir: Path, extra: dict[str, str] | None = None) -> Path:
    """The repository's configs with a small world, optional files replaced, in a private directory."""
    shutil.copytree(REPO / "configs", config_dir, dirs_exist_ok=True)
    shutil.copytree(REPO / "workflows", config_dir.parent / "workflows", dirs_exist_ok=True)
    (config_dir / "world.toml").write_text(SMALL_WORLD)
    for name, text in (extra or {}).items():
        (config_dir / name).write_text(text)
    return config_dir


def pairs(reply: str) -> dict[str, str]:
    from rvs_server.protocol import parse_reply
    return parse_reply(reply).data


def one_product(root: Path, line: str, timeout: float = 300) -> tuple[ServerProcess, dict[str, str]]:
    """A server on fresh data and the repository's configs under `root` runs one command and is stopped:
    the server (its data_dir) and the reply's fields (a module fixture's stored product)."""
    server = ServerProcess(data_dir=root / "data", config_dir=write_configs(root / "configs")).start()
    try:
        with server.connect() as client:
            reply = client.command(line, timeout=timeout)
    finally:
        server.stop()
    assert " OK " in reply, reply
    return server, pairs(reply)


@pytest.fixture
def server_factory(tmp_path):
    """Start servers on demand; all are stopped at the end of the test."""
    started: list[ServerProcess] = []

    def make(data_dir: Path | None = None, configs: dict[str, str] | None = None,
             args: list[str] | None = None) -> ServerProcess:
        data = data_dir or tmp_path / "data"
        config_dir = tmp_path / "configs"
        if not config_dir.exists() or configs:
            write_configs(config_dir, configs)
        server = ServerProcess(data_dir=data, config_dir=config_dir, extra_args=list(args or []))
        started.append(server)
        return server.start()

    yield make
    for server in started:
        server.stop()


@pytest.fixture
def server(server_factory) -> ServerProcess:
    """One running server on fresh data and the repository's configs."""
    return server_factory()


@pytest.fixture(scope="module")
def shared_server(tmp_path_factory) -> ServerProcess:
    """One server on fresh data and the repository's configs, shared by a module's tests that leave it
    as they found it (standby, no recovery set, configs untouched): a server start costs seconds."""
    root = tmp_path_factory.mktemp("shared")
    server = ServerProcess(data_dir=root / "data", config_dir=write_configs(root / "configs")).start()
    yield server
    server.stop()


os.environ.setdefault("PYTHONUNBUFFERED", "1")
