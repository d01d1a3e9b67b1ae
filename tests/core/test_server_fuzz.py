"""Property tests against the live server: whatever a client sends, no exception escapes, the
server stays up, and every command line gets exactly one final reply."""
from __future__ import annotations

import socket
import time

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from rvs_server.protocol import MAX_LINE_BYTES, is_ignored, parse_reply

from conftest import ServerProcess, write_configs


@pytest.fixture(scope="module")
def live(tmp_path_factory):
    base = tmp_path_factory.mktemp("fuzz")
    server = ServerProcess(data_dir=base / "data", config_dir=write_configs(base / "configs")).start()
    yield server
    assert server.proc.poll() is None, "the server died under fuzzing: " + server.stderr()[-2000:]
    server.stop()


def expected_replies(data: bytes) -> int:
    """How many command lines the protocol finds in `data` (which contains no telnet IAC byte)."""
    data = data.replace(b"\r\0", b"\r\n")  # telnet's CR NUL ends a line as CR LF does
    count = 0
    for raw in data.split(b"\n")[:-1]:
        raw = raw[:-1] if raw.endswith(b"\r") else raw
        if len(raw) > MAX_LINE_BYTES:
            count += 1
            continue
        try:
            text = raw.decode("utf-8")
        except UnicodeDecodeError:
            count += 0 if is_ignored(raw.decode("utf-8", "replace")) else 1
            continue
        count += 0 if is_ignored(text) else 1
    return count


def exchange(server: ServerProcess, data: bytes) -> list[str]:
    """Send `data` on a fresh connection, then a sentinel; return the lines before the sentinel's reply."""
    with socket.create_connection((server.host, server.port), timeout=30) as sock:
        sock.sendall(data + b"\n@zz-sentinel version\n")
        buffer = b""
        lines: list[str] = []
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            chunk = sock.recv(65536)
            if not chunk:
                break
            buffer += chunk
            while b"\r\n" in buffer:
                line, buffer = buffer.split(b"\r\n", 1)
                text = line.decode("utf-8")
                if text.startswith("zz-sentinel "):
                    return lines
                lines.append(text)
        raise AssertionError(f"no sentinel reply; got {lines[-5:]}")


def final_replies(lines: list[str]) -> list[str]:
    finals = []
    for line in lines[1:]:  # the first line is the greeting
        reply = parse_reply(line)  # every line the server sends follows one of the forms
        if reply.final:
            finals.append(line)
    return finals


no_iac = st.binary(max_size=400).map(lambda b: b.replace(b"\xff", b""))


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=no_iac)
def test_arbitrary_bytes_get_one_final_reply_per_command_line(live, data):
    lines = exchange(live, data)
    assert len(final_replies(lines)) == expected_replies(data + b"\n")


COMMANDS = ["status", "help", "version", "check", "check move-ptu", "check sleep", "standby", "subscribe",
            "abort", "continue", "break", "logbook", "auth", "help move-ptu", "move-ptu --pan 9999",
            "nosuch", "STATUS", "sleep 0"]
TOKENS = st.sampled_from(["--pan", "--tilt", "--speed", "--relative", "--no-relative", "--", "-1", "30",
                          "1e309", "nan", "inf", "'", '"', "\\", "--job", "7", "x=y", "--pan=", "@t",
                          "\u00e9\u4e2d", "\t", "0:1", "1,2", "--output", "../x", ".hidden"])


@st.composite
def command_lines(draw):
    tag = draw(st.sampled_from(["", "@t1 ", "@a.b-c_d ", "@" + "x" * 33 + " ", "@bad! ", "@ "]))
    head = draw(st.sampled_from(COMMANDS) | st.text(min_size=1, max_size=12).filter(lambda s: "\n" not in s))
    tail = draw(st.lists(TOKENS | st.text(max_size=8), max_size=6))
    return (tag + " ".join([head, *tail])).replace("\n", " ").replace("\r", " ")


@settings(max_examples=120, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(lines=st.lists(command_lines(), min_size=1, max_size=8))
def test_arbitrary_command_lines_get_exactly_one_final_reply_each(live, lines):
    data = "\n".join(lines).encode("utf-8", "surrogatepass").replace(b"\xff", b"")
    replies = exchange(live, data)
    finals = final_replies(replies)
    assert len(finals) == expected_replies(data + b"\n")
    # a well-formed @TAG comes back on its own reply
    for line in lines:
        if line.startswith("@t1 ") and not is_ignored(line):
            assert any(f.startswith("t1 ") for f in finals)


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.binary(max_size=300))
def test_arbitrary_bytes_with_telnet_sequences_never_hurt_the_server(live, data):
    with socket.create_connection((live.host, live.port), timeout=10) as sock:
        sock.sendall(data)
    with live.connect() as c:  # the server is still up and answers others
        assert c.command("version").split()[1] == "OK"
