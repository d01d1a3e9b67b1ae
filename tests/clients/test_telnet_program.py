"""The text server through the real `telnet` program (issue 48, item 2).

Debian's telnet (setup.sh installs it) runs on a pseudo-terminal, typed at as a person would: the
greeting, `status`, a `move-ptu` job with its progress lines, bad lines, `quit`. And the option
negotiation telnet really sends: none when given a port (it only negotiates on its own port), so it
is asked for: `mode character` (IAC DO SGA, IAC DO ECHO; Enter then travels as CR NUL), `send ayt`,
`send ip`, and `open HOST -PORT`, which sends the whole negotiation it sends to a telnet port (DO and
WILL ENCRYPT, SGA, TTYPE, NAWS, TSPEED, LFLOW, LINEMODE, NEW-ENVIRON, STATUS). The server refuses every
option, so telnet stays in line mode and each typed line gets its one reply.
"""
from __future__ import annotations

import os
import pty
import re
import select
import shutil
import subprocess
import time

import pytest

TELNET = shutil.which("telnet")
pytestmark = pytest.mark.skipif(TELNET is None, reason="the telnet program is not installed (setup.sh installs "
                                                       "Debian's package `telnet`)")


class Telnet:
    """telnet on a pty: type keys, wait for text on its screen."""

    def __init__(self, *args: str):
        self.master, slave = pty.openpty()
        self.proc = subprocess.Popen([TELNET, *args], stdin=slave, stdout=slave, stderr=slave,
                                     start_new_session=True, env={**os.environ, "TERM": "dumb"})
        os.close(slave)
        self.screen = ""  # everything shown, CRs removed
        self.seen = 0  # how far expect() has matched

    def type(self, keys: str) -> None:
        os.write(self.master, keys.encode())

    def escape(self, command: str) -> None:
        """Ctrl-] and a command at the `telnet>` prompt; back to the connection after it."""
        self.type("\x1d")
        self.expect(r"telnet> ")
        self.type(command + "\r")
        time.sleep(0.5)  # telnet sets its terminal back for the connection; keys typed before that are lost

    def _read(self, timeout: float) -> bool:
        ready, _, _ = select.select([self.master], [], [], timeout)
        if not ready:
            return True
        try:
            chunk = os.read(self.master, 65536)
        except OSError:  # telnet exited and the pty closed
            return False
        if not chunk:
            return False
        self.screen += chunk.decode("utf-8", "replace").replace("\r", "")
        return True

    def expect(self, pattern: str, timeout: float = 20.0) -> re.Match:
        """The first match of `pattern` (multiline) after the last one matched."""
        regex = re.compile(pattern, re.M)
        deadline = time.monotonic() + timeout
        while True:
            match = regex.search(self.screen, self.seen)
            if match:
                self.seen = match.end()
                return match
            left = deadline - time.monotonic()
            if left <= 0 or not self._read(min(left, 0.2)) and not regex.search(self.screen, self.seen):
                raise AssertionError(f"telnet never showed {pattern!r}; screen after the last match:\n"
                                     f"{self.screen[self.seen:][-2000:]}")

    def lines_since(self, start: int) -> list[str]:
        return [line for line in self.screen[start:].split("\n") if line.strip()]

    def close(self) -> int | None:
        if self.proc.poll() is None:
            self.proc.kill()
        code = self.proc.wait(timeout=10)
        os.close(self.master)
        return code


@pytest.fixture
def telnet_to():
    sessions: list[Telnet] = []

    def start(*args: str) -> Telnet:
        sessions.append(Telnet(*args))
        return sessions[-1]

    yield start
    for session in sessions:
        session.close()


def test_a_session_in_telnet_from_greeting_to_quit(server, telnet_to):
    t = telnet_to(server.host, str(server.port))
    t.expect(r"^Connected to ")
    t.expect(r"^Escape character is '\^\]'\.$")
    t.expect(r"^RVS \d+\.\d+\.\d+ standby$")

    t.type("status\r")  # the tty turns Enter into LF; telnet sends the line with CR LF
    t.expect(r"^1 OK mode=standby .*\bjob=none\b.*\bdev\.ptu=ok\b")

    start = t.seen
    t.type("@m1 move-ptu --pan 30 --tilt -10\r")
    # the axes stop on the PTU's nearest position step (185.1428 arc seconds, 0.0514 deg)
    done = t.expect(r"^m1 OK job=\d+ pan=(29\.9\d|30\.0\d) tilt=-(9\.9\d|10\.0\d)$", timeout=60)
    progress = [line for line in t.lines_since(start) if line.startswith("m1 PROGRESS")]
    assert progress and progress[0].startswith("m1 PROGRESS 0 moving to pan 30.00 tilt -10.00"), progress
    assert all(re.match(r"^m1 PROGRESS \d+ ", line) for line in progress)
    assert t.screen.index(progress[-1]) < done.start()

    t.type("move-ptu --pan 9999\r")  # the third command line: tag 3
    t.expect(r"^3 ERR 400 bad-request .*pan")
    t.type("statsu\r")
    t.expect(r"^4 ERR 404 unknown-command .*status")
    t.type("@x move-ptu --pan \"30\r")
    t.expect(r"^x ERR 400 bad-request ")

    # Option negotiation: `mode character` asks the server to echo and suppress go-ahead. The server
    # refuses both, so telnet goes back to line mode, and what is typed still makes one line each.
    t.escape("mode character")
    t.type("version\r")
    t.expect(r"^6 OK .*version=")
    t.escape("send ayt")  # IAC AYT and IAC IP: no line, no reply, nothing counted
    t.escape("send ip")
    t.type("status\r")
    t.expect(r"^7 OK mode=standby .*pan=(29\.9\d|30\.0\d) tilt=-(9\.9\d|10\.0\d)")
    assert not re.search(r"^\S+ (OK|ERR)", t.screen[t.seen:], re.M)

    t.type("quit\r")
    t.expect(r"^8 OK")
    t.expect(r"^Connection closed by foreign host\.$")
    assert t.proc.wait(timeout=20) == 0
    assert server.proc.wait(timeout=60) == 0  # the server stopped gracefully


def test_telnets_full_negotiation_is_refused_and_lines_still_work(server, telnet_to):
    """`open HOST -PORT` makes telnet negotiate as on its own port 23; the server's refusals leave it in
    line mode, local echo on, so the session reads exactly as without negotiation."""
    t = telnet_to()
    t.expect(r"^telnet> ")
    t.type(f"open {server.host} -{server.port}\r")
    t.expect(r"^RVS \d+\.\d+\.\d+ standby$")
    t.type("@s status\r")
    t.expect(r"^@s status$")  # telnet still echoes locally: it did not hand echo to the server
    t.expect(r"^s OK mode=standby ")
    t.type("# a comment gets no reply\r")
    t.type("\r")
    t.type("version\r")
    t.expect(r"^2 OK .*version=")  # the tagged status was line 1; the comment and the blank line are not counted
    with server.connect() as other:  # another client sees nothing of it
        assert other.command("status").split()[1] == "OK"
