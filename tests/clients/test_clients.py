"""Tests of the clients: the gnc library, the mission runner and the `rvs` command line.

The pure parts (mission parsing and substitution, tag handling, reply mapping) are tested alone;
everything else runs against a real `rvs-server` process on loopback (sim speed 50), a fresh one
per test from the `server` fixture of conftest.py, stopped with `quit`.
"""
from __future__ import annotations

import asyncio
import json
import os
import pty
import queue
import select
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from clients import gnc, mission
from clients.gnc import (
    AsyncRvsClient,
    Event,
    Progress,
    Result,
    RvsBadRequest,
    RvsBusy,
    RvsClient,
    RvsConnectionError,
    RvsInterrupted,
    RvsRequestError,
    RvsUnknownCommand,
    ZmqClient,
)
from rvs_server.protocol import Reply

REPO = Path(__file__).resolve().parents[2]

RVS = [str(REPO / ".venv" / "bin" / "rvs")] if (REPO / ".venv" / "bin" / "rvs").exists() else \
    [sys.executable, "-m", "clients.cli"]
SURVEY = REPO / "clients" / "missions" / "ptu-survey.rvs"


# ---------------------------------------------------------------------------------------------
# Pure parts


def test_assignments_are_parsed_and_malformed_ones_named():
    assert mission.parse_assignments(["PAN=30", "TILT=-5", "EMPTY=", "X=a=b"]) == \
        {"PAN": "30", "TILT": "-5", "EMPTY": "", "X": "a=b"}
    with pytest.raises(mission.MissionError) as caught:
        mission.parse_assignments(["PAN", "1X=2"])
    assert len(caught.value.problems) == 2 and "'PAN'" in caught.value.problems[0]


def test_substitute_replaces_every_reference():
    assert mission.substitute("move-ptu --pan -${PAN} --tilt ${TILT}", {"PAN": "30", "TILT": "-5"}) == \
        "move-ptu --pan -30 --tilt -5"
    assert mission.substitute("status", {}) == "status"


@pytest.mark.parametrize("text, expected", [
    ("move-ptu --pan ${PAN}", "line 7: variable PAN is not set"),
    ("move-ptu --pan ${1PAN}", "line 7: bad variable name ${1PAN}"),
    ("move-ptu --pan ${PAN", "line 7: unterminated ${"),
])
def test_substitute_names_the_line_and_the_variable(text, expected):
    with pytest.raises(mission.MissionError) as caught:
        mission.substitute(text, {}, number=7)
    assert caught.value.problems[0].startswith(expected)


def test_parse_mission_skips_comments_and_keeps_line_numbers():
    text = "# a survey ${UNSET_IN_COMMENT}\n\nstatus\n  - move-ptu --pan ${P}\n\t# indented comment\n@t9 status\n"
    lines = mission.parse_mission(text, {"P": "10"})
    assert lines == [mission.MissionLine(3, "status", False),
                     mission.MissionLine(4, "move-ptu --pan 10", True),
                     mission.MissionLine(6, "@t9 status", False)]


def test_parse_mission_reports_every_problem_before_anything_runs():
    text = "status\nmove-ptu --pan ${A}\n-\nmove-ptu --tilt ${B} --pan ${A}\n"
    with pytest.raises(mission.MissionError) as caught:
        mission.parse_mission(text, {})
    assert caught.value.problems == [
        "line 2: variable A is not set (give --set A=VALUE)",
        "line 3: no command after '-'",
        "line 4: variable B is not set (give --set B=VALUE)",
        "line 4: variable A is not set (give --set A=VALUE)",
    ]


def test_unused_variables_and_check_lines():
    assert mission.unused_variables("move-ptu --pan ${PAN}", {"PAN": "1", "TILIT": "2"}) == ["TILIT"]
    assert mission.check_line("move-ptu --pan 3") == "check move-ptu --pan 3"
    assert mission.check_line("@m1 move-ptu --pan 3") == "@m1 check move-ptu --pan 3"


def test_tagged_line_keeps_a_tag_or_adds_one_and_refuses_what_gets_no_reply():
    tags = gnc._TagMaker()
    assert gnc.tagged_line("@mine status", tags) == ("mine", "@mine status")
    assert gnc.tagged_line("  status ", tags) == ("c1", "@c1 status")
    assert gnc.tagged_line("status", tags)[0] == "c2"
    for line in ("", "   ", "# comment", "status\nquit"):
        with pytest.raises(ValueError):
            gnc.tagged_line(line, tags)


def test_errors_map_by_reason_then_code_and_carry_the_recovery_set():
    error = gnc.item_from_reply(Reply(kind="err", tag="7", code=499, reason="interrupted",
                                      message="job 12 (move-ptu) interrupted by break at 40%; recovery=12"), "")
    assert isinstance(error, RvsInterrupted) and error.recovery == "12" and error.tag == "7"
    assert error.line == "7 ERR 499 interrupted job 12 (move-ptu) interrupted by break at 40%; recovery=12"
    too_long = gnc.request_error("3", 400, "line-too-long", "line of 9000 bytes")
    assert isinstance(too_long, RvsBadRequest) and too_long.recovery is None
    assert type(gnc.request_error("3", 418, "teapot", "?")) is RvsRequestError
    assert isinstance(gnc.request_error("3", 409, "busy", "job 1"), RvsBusy)


def test_zmq_frames_become_the_same_items_as_text_lines():
    ok = gnc.reply_from_json(json.dumps({"id": "c4", "status": "ok", "code": 200,
                                         "data": {"pan": "30.00", "recovery": 0, "ratio": 0.5}}).encode())
    result = gnc.item_from_reply(ok, gnc.text_line_of(ok))
    assert result == Result("c4", {"pan": "30.00", "recovery": "0", "ratio": "0.5"},
                            "c4 OK pan=30.00 recovery=0 ratio=0.5")
    progress = gnc.reply_from_json(b'{"id": "c4", "status": "progress", "code": 102, "message": "pan 3.00",'
                                   b' "data": {"percent": 12}}')
    assert gnc.item_from_reply(progress, gnc.text_line_of(progress)) == \
        Progress("c4", 12, "pan 3.00", "c4 PROGRESS 12 pan 3.00")
    error = gnc.reply_from_json(b'{"id": "c5", "status": "error", "code": 499, "reason": "interrupted",'
                                b' "message": "stopped", "data": {"recovery": "9"}}')
    assert gnc.item_from_reply(error, "").recovery == "9"


def test_result_reads_numbers_and_names_missing_keys():
    result = Result("1", {"pan": "30.50", "job": "4", "mode": "standby"})
    assert result.get_float("pan") == 30.5 and result.get_int("job") == 4 and result["mode"] == "standby"
    assert result.get("absent") is None and "pan" in result
    with pytest.raises(KeyError, match="has: pan, job, mode"):
        result.get_float("tilt")
    with pytest.raises(ValueError, match="mode='standby'"):
        result.get_int("mode")


class ScriptedClient:
    """A stand-in client: replies OK, except ERR for lines containing 'bad'."""

    def __init__(self):
        self.sent: list[str] = []

    def stream(self, line):
        self.sent.append(line)
        if "bad" in line:
            raise gnc.request_error("x", 400, "bad-request", f"{line} is bad")
        yield Progress("x", 50, "half", "x PROGRESS 50 half")
        yield Result("x", {}, "x OK")


def test_runner_logic_stops_at_first_error_unless_excused():
    lines = mission.parse_mission("status\n- bad one\nstatus\nbad two\nstatus\n", {})
    client, out = ScriptedClient(), []
    report = mission.run_mission(client, lines, out.append)
    assert client.sent == ["status", "bad one", "status", "bad two"]
    assert (report.sent, report.ok, report.excused, report.failures, report.stopped_at) == (4, 2, [2], [4], 4)
    assert report.exit_status == 1 and "x PROGRESS 50 half" in out
    assert mission.summary("m.rvs", report) == ("mission m.rvs: STOPPED at line 4; 4 lines of 5 sent, 2 OK, "
                                                "1 excused failure (line 2); 1 line not run")
    client = ScriptedClient()
    report = mission.check_mission(client, lines, [].append)
    assert client.sent == ["check status", "check bad one", "check status", "check bad two", "check status"]
    assert (report.failures, report.excused) == ([4], [2])


# ---------------------------------------------------------------------------------------------
# Against a real server


@pytest.fixture(scope="module")
def server(shared_server):
    """One server for the module: every test here ends with the server in standby, nothing to resume,
    and asserts on the PTU only relative to where it stood or after moving it itself."""
    return shared_server


@pytest.fixture
def client(server):
    with RvsClient(server.host, server.port, timeout=20) as connection:
        yield connection


def ptu_angles(client: RvsClient) -> tuple[float, float]:
    status = client.call("status")
    return status.get_float("pan"), status.get_float("tilt")


def in_background(function, *args):
    """Run function in a thread; the returned list gets its result or its exception."""
    outcome: list = []

    def run():
        try:
            outcome.append(function(*args))
        except Exception as exc:  # handed to the test to assert on
            outcome.append(exc)
    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    return thread, outcome


def test_text_client_calls_streams_and_raises_typed_errors(client):
    assert client.server_mode in ("standby", "busy", "break", "sleep")
    status = client.call("status")
    assert status["mode"] == "standby" and status.tag.startswith("c")
    assert client.send("@own-tag version").tag == "own-tag"
    items = list(client.stream("move-ptu --pan 12 --tilt -4 --speed 10"))
    assert all(isinstance(item, Progress) for item in items[:-1]) and len(items) >= 2
    assert items[-1].get_float("pan") == pytest.approx(12, abs=0.1)
    assert ptu_angles(client) == pytest.approx((12, -4), abs=0.1)
    with pytest.raises(RvsUnknownCommand) as unknown:
        client.call("move-ptz", pan=1)
    assert unknown.value.code == 404 and "move-ptu" in unknown.value.message
    with pytest.raises(RvsBadRequest) as bad:
        client.call("move-ptu", pan=9999)
    assert bad.value.code == 400 and "pan" in bad.value.message
    with pytest.raises(RvsBadRequest) as too_long:
        client.send("status " + "x" * 9000)
    assert too_long.value.reason == "line-too-long"
    assert client.call("status")["mode"] == "standby"  # the connection is still in step


def test_replies_are_matched_by_tag_with_events_and_other_replies_between(server):
    events: queue.Queue[Event] = queue.Queue()
    with RvsClient(server.host, server.port, timeout=20, on_event=events) as client:
        assert "progress" in client.call("subscribe")["topics"]
        first_progress = threading.Event()
        seen: list = []

        def move():
            for item in client.stream("move-ptu --pan -25 --tilt 0 --speed 2"):
                seen.append(item)
                first_progress.set()
            return seen[-1]
        thread, outcome = in_background(move)
        assert first_progress.wait(10)
        # While the job runs, the same connection gets its own answers, in between the job's lines.
        assert client.call("status")["mode"] == "busy"
        with pytest.raises(RvsBusy):
            client.call("move-ptu", pan=1)
        thread.join(20)
        assert isinstance(outcome[0], Result) and outcome[0].get_float("pan") == pytest.approx(-25, abs=0.1)
        assert {item.tag for item in seen} == {seen[-1].tag}
        assert all(isinstance(item, Progress) for item in seen[:-1])
        topics = set()
        while not events.empty():
            topics.add(events.get_nowait().topic)
        assert "progress" in topics and "mode" in topics
        client.call("subscribe", "--off")


def test_break_gives_interrupted_with_the_recovery_set(client):
    started = threading.Event()

    def slow_move():
        for _ in client.stream("move-ptu --pan 30 --speed 2"):
            started.set()
    thread, outcome = in_background(slow_move)
    assert started.wait(10), outcome
    assert client.call("break")["mode"] == "break"
    thread.join(20)
    assert isinstance(outcome[0], RvsInterrupted), outcome
    assert outcome[0].code == 499 and outcome[0].recovery
    aborted = client.call("abort", job=outcome[0].recovery)
    assert aborted["mode"] == "standby"


def test_zmq_client_gives_the_same_results(server, client):
    with ZmqClient(server.zmq, timeout=20) as zmq_client:
        assert zmq_client.call("status")["mode"] == "standby"
        assert zmq_client.send("@z1 version").tag == "z1"
        items = list(zmq_client.stream("move-ptu --pan 6 --tilt 3 --speed 10"))
        assert isinstance(items[-1], Result) and any(isinstance(item, Progress) for item in items)
        assert items[-1].line.startswith(f"{items[-1].tag} OK ")
        assert ptu_angles(client) == pytest.approx((6, 3), abs=0.1)
        with pytest.raises(RvsBadRequest) as bad:
            zmq_client.call("move-ptu", tilt=-999)
        with pytest.raises(RvsBadRequest) as bad_text:
            client.call("move-ptu", tilt=-999)
        assert bad.value.message == bad_text.value.message
        with pytest.raises(RvsUnknownCommand):
            zmq_client.send("statsu")


def test_async_client(server):
    async def session():
        events: asyncio.Queue = asyncio.Queue()
        async with AsyncRvsClient(server.host, server.port, timeout=20, on_event=events) as client:
            assert (await client.call("status"))["mode"] == "standby"
            await client.call("subscribe", "mode")
            items = [item async for item in client.stream("move-ptu --pan 3 --tilt 0 --speed 10")]
            status, version = await asyncio.gather(client.call("status"), client.call("version"))
            with pytest.raises(RvsBadRequest):
                await client.call("move-ptu", pan="east")
            return items, status, version, events
    items, status, version, events = asyncio.run(session())
    assert isinstance(items[-1], Result) and items[-1].get_float("pan") == pytest.approx(3, abs=0.1)
    assert status.get_float("pan") == pytest.approx(3, abs=0.1) and "protocol" in version
    assert events.qsize() >= 2  # busy, then standby


def test_closed_connection_and_refused_connection_raise_connection_errors(server):
    client = RvsClient(server.host, server.port, timeout=5)
    client.close()
    with pytest.raises(RvsConnectionError):
        client.call("status")
    with pytest.raises(RvsConnectionError):
        RvsClient("127.0.0.1", 1, timeout=5)


# -- the command line and the mission runner ---------------------------------------------------


def run_rvs(server, *args: str, stdin: str | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([*RVS, "--port", str(server.port), *args], input=stdin, capture_output=True,
                          text=True, timeout=60, cwd=REPO)


def test_cli_send_exit_status(server):
    done = run_rvs(server, "send", "status", "# no reply, skipped", "@v version")
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    assert lines[0].split()[1:3] == ["OK", "mode=standby"] and lines[1].startswith("v OK version=")
    done = run_rvs(server, "send", "statsu", "status")
    assert done.returncode == 1
    assert " ERR 404 unknown-command " in done.stdout.splitlines()[0] and " OK " in done.stdout.splitlines()[1]
    refused = subprocess.run([*RVS, "--port", "1", "send", "status"], capture_output=True, text=True, timeout=30)
    assert refused.returncode == 2 and "cannot connect" in refused.stderr


def test_cli_shell_from_a_pipe(server):
    done = run_rvs(server, "shell", stdin="# comment\nstatus\n\nmove-ptu --pan 2 --tilt 0\n")
    assert done.returncode == 0, done.stderr
    replies = done.stdout.splitlines()
    assert " OK " in replies[0] and "PROGRESS" in done.stdout and replies[-1].split()[1] == "OK"
    assert run_rvs(server, "shell", stdin="bogus\n").returncode == 1


def test_cli_interactive_shell_keeps_history(server, tmp_path):
    pid, terminal = pty.fork()
    if pid == 0:  # the child: rvs shell on a terminal, with its history in tmp_path
        try:
            os.environ["HOME"] = str(tmp_path)
            os.execv(RVS[0], [*RVS, "--port", str(server.port), "shell"])
        finally:
            os._exit(127)  # never go on running pytest in the child
    seen = read_terminal(terminal, until="rvs> ")
    assert "connected to RVS" in seen
    os.write(terminal, b"status\n")
    assert "OK mode=standby" in read_terminal(terminal, until="rvs> ")
    os.write(terminal, b"\x04")  # Ctrl-D
    read_terminal(terminal, until=None)
    _, status = os.waitpid(pid, 0)
    os.close(terminal)
    assert os.waitstatus_to_exitcode(status) == 0
    assert (tmp_path / ".rvs_history").read_text().splitlines()[-1] == "status"


def read_terminal(terminal: int, until: str | None, timeout: float = 15.0) -> str:
    """What the terminal shows until `until` appears after the start (None: until it closes)."""
    seen, deadline = "", time.monotonic() + timeout
    while time.monotonic() < deadline:
        ready, _, _ = select.select([terminal], [], [], 0.1)
        if ready:
            try:
                chunk = os.read(terminal, 4096)
            except OSError:  # the child closed the terminal
                return seen
            if not chunk:
                return seen
            seen += chunk.decode(errors="replace")
            if until is not None and seen.rstrip().endswith(until.rstrip()):
                return seen
    raise AssertionError(f"terminal did not show {until!r}; it showed {seen!r}")


def test_cli_zmq_transport(server):
    done = subprocess.run([*RVS, "--zmq", server.zmq, "send", "status"], capture_output=True, text=True,
                          timeout=60, cwd=REPO)
    assert done.returncode == 0 and "mode=standby" in done.stdout, done.stderr


def test_mission_run_success_with_an_excused_failure(server, client):
    done = run_rvs(server, "mission", "run", str(SURVEY), "--set", "PAN=20", "--set", "TILT=-10")
    assert done.returncode == 0, done.stdout + done.stderr
    out = done.stdout
    assert "line 11: move-ptu --pan -20 --tilt -10" in out
    assert "line 16: - move-ptu --pan 9999 --tilt 0" in out and "ERR 400 bad-request" in out
    assert "excused by '-'" in out
    assert out.splitlines()[-1] == ("mission ptu-survey.rvs: completed; 7 lines of 7 sent, 6 OK, "
                                    "1 excused failure (line 16)")
    assert ptu_angles(client) == pytest.approx((0, 0), abs=0.1)


def test_mission_stops_at_the_first_unexcused_error(server, client, tmp_path):
    path = tmp_path / "stop.rvs"
    path.write_text("status\nmove-ptu --pan 5000\nmove-ptu --pan 9 --tilt 0\n")
    done = run_rvs(server, "mission", "run", str(path))
    assert done.returncode == 1
    assert "line 2: failed (400 bad-request); mission stopped" in done.stdout
    assert "line 3:" not in done.stdout
    assert done.stdout.splitlines()[-1].startswith("mission stop.rvs: STOPPED at line 2; 2 lines of 3 sent, 1 OK")
    assert ptu_angles(client)[0] != pytest.approx(9, abs=0.1)


def test_mission_with_an_unset_variable_sends_nothing(server, client, tmp_path):
    before = ptu_angles(client)
    path = tmp_path / "unset.rvs"
    path.write_text("move-ptu --pan 17 --tilt 0\n# ${NOT_AN_ERROR}\nmove-ptu --pan ${PAN}\n")
    done = run_rvs(server, "mission", "run", str(path))
    assert done.returncode == 2 and done.stdout == ""
    assert "line 3: variable PAN is not set" in done.stderr
    assert ptu_angles(client) == before


def test_mission_check_moves_nothing_and_reports_every_problem(server, client, tmp_path):
    before = ptu_angles(client)
    done = run_rvs(server, "mission", "check", str(SURVEY), "--set", "PAN=30", "--set", "TILT=-10")
    assert done.returncode == 0, done.stdout + done.stderr
    assert done.stdout.splitlines()[-1].startswith("mission ptu-survey.rvs: well-formed; 7 lines of 7 checked")
    assert ptu_angles(client) == before
    path = tmp_path / "bad.rvs"
    path.write_text("status\nmove-ptu --pan 5000\nmove-ptu --tilt 0\nmove-ptu --pna 3\n")
    done = run_rvs(server, "mission", "check", str(path))
    assert done.returncode == 1
    assert "line 2: would fail (400 bad-request)" in done.stdout
    assert "line 3: would fail" not in done.stdout
    assert "line 4: would fail (400 bad-request)" in done.stdout
    assert "NOT well-formed: 2 problems (line 2, 4)" in done.stdout.splitlines()[-1]
    assert ptu_angles(client) == before
