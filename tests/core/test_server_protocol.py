"""PROTOCOL.md line by line, against a real server process over real loopback sockets."""
from __future__ import annotations

import json
import time

import pytest
import zmq

from conftest import pairs

STEP = 185.1428 / 3600  # the D46 turns in steps of 0.0514 degrees


def near(data: dict, pan: float, tilt: float) -> bool:
    """The unit reports where it stands, which is the target rounded to its step."""
    return abs(float(data["pan"]) - pan) <= STEP and abs(float(data["tilt"]) - tilt) <= STEP

# -- text transport: framing --------------------------------------------------------------------
# The tests on `shared_server` read and refuse but never move the PTU, start a job or edit a file, so
# one server answers them all; the tests that count jobs or change state start their own.


def test_greeting_names_version_and_mode(shared_server):
    with shared_server.connect() as c:
        assert c.greeting.split() == ["RVS", "0.1.0", "standby"]


def test_untagged_lines_are_numbered_and_ignored_lines_are_not_counted(shared_server):
    with shared_server.connect() as c:
        c.send_raw(b"status\n\n   \n# a comment\n@mine version\r\nversion\r\n")
        first, second, third = c.read_line(), c.read_line(), c.read_line()
        assert first.startswith("1 OK mode=standby")
        assert second.startswith("mine OK version=")
        assert third.startswith("3 OK version=")  # the tagged line counted as the second


def test_telnet_negotiation_bytes_are_ignored(shared_server):
    with shared_server.connect() as c:
        c.send_raw(b"\xff\xfd\x03\xff\xfb\x18sta\xff\xfa\x18\x00vt100\xff\xf0tus\r\n")
        while b"\n" not in c.buffer:
            c.buffer += c.sock.recv(65536)
        # DO SGA and WILL TTYPE are refused (WONT SGA, DONT TTYPE) before the line's reply
        refusals, c.buffer = c.buffer[:6], c.buffer[6:]
        assert refusals == b"\xff\xfc\x03\xff\xfe\x18"
        assert c.read_line().startswith("1 OK mode=")


def test_a_line_that_fails_to_parse_keeps_its_tag(shared_server):
    with shared_server.connect() as c:
        c.send('@q7 move-ptu --pan "30')
        assert c.read_line().startswith("q7 ERR 400 bad-request cannot split")
        c.send("@bad#tag status")
        assert c.read_line().startswith("2 ERR 400 bad-request tag 'bad#tag'")


def test_line_too_long_is_refused_and_the_connection_stays_usable(shared_server):
    with shared_server.connect() as c:
        c.send_raw(b"@long status --x " + b"y" * 9000 + b"\nstatus\n")
        assert c.read_line().startswith("long ERR 400 line-too-long")
        assert c.read_line().startswith("2 OK mode=")
        # exactly 8192 bytes is allowed, and CRLF does not count against it
        c.send_raw(b"@edge status" + b" " * (8192 - 12) + b"\r\n")
        assert c.read_line().startswith("edge OK")


def test_bytes_that_are_not_utf8_are_refused(shared_server):
    with shared_server.connect() as c:
        c.send_raw(b"@enc status \xc3\x28\n# comment \xff is still a comment\nversion\n")
        assert c.read_line().startswith("enc ERR 400 bad-encoding")
        assert c.read_line().startswith("2 OK version=")


def test_values_with_spaces_are_quoted(shared_server):
    with shared_server.connect() as c:
        reply = c.command("help move-ptu")
        assert ' summary="' in reply
        assert pairs(reply)["command"] == "move-ptu"


# -- errors and their codes ---------------------------------------------------------------------


def test_unknown_command_suggests_the_closest(shared_server):
    with shared_server.connect() as c:
        assert "404 unknown-command no command 'statsu'; did you mean status?" in c.command("statsu")


def test_invalid_option_names_option_and_range(shared_server):
    with shared_server.connect() as c:
        reply = c.command("move-ptu --pan 400")
        assert "ERR 400 bad-request" in reply and "--pan" in reply and "-360..360" in reply
        reply = c.command("move-ptu --pan 170")
        assert "ERR 400 bad-request" in reply and "outside the unit's range" in reply and "-158.9" in reply
        assert "unknown option --pna; did you mean --pan?" in c.command("move-ptu --pna 3")


def test_help_is_generated_from_the_config_class(shared_server):
    with shared_server.connect() as c:
        listed = pairs(c.command("help"))["commands"].split()
        for name in ("status", "help", "version", "check", "standby", "break", "continue", "abort", "reset",
                     "reinit", "sleep", "logbook", "quit", "auth", "subscribe", "move-ptu"):
            assert name in listed
        data = pairs(c.command("help move-ptu"))
        assert data["opt.speed"].startswith("float; > 0 and <= 300; default none")
        assert data["opt.relative"].startswith("flag; default 0")
        assert data["usage"] == "move-ptu [--pan PAN] [--tilt TILT] [--speed SPEED] [--relative]"


def test_check_validates_without_running(shared_server):
    with shared_server.connect() as c:
        assert c.command("check move-ptu --pan 30 --tilt -10").split()[1] == "OK"
        assert "ERR 400" in c.command("check move-ptu --pan 999")
        assert "ERR 404" in c.command("check nosuch")
        assert pairs(c.command("status"))["pan"] == "0.00"  # nothing moved


# -- jobs, modes, progress ----------------------------------------------------------------------


def test_a_job_reports_progress_and_ends_with_its_result(server):
    with server.connect() as c:
        c.send("@m move-ptu --pan 20 --tilt -5 --speed 40")
        reply, before = c.reply("m")
        assert reply.startswith("m OK job=1 pan=")
        assert near(pairs(reply), 20, -5)
        progress = [line for line in before if line.startswith("m PROGRESS")]
        assert len(progress) >= 3
        percents = [int(line.split()[2]) for line in progress]
        assert percents == sorted(percents) and percents[-1] == 100


def test_immediate_commands_are_answered_while_a_job_runs_and_other_jobs_are_busy(server):
    with server.connect() as mover, server.connect() as other:
        mover.send("@m move-ptu --pan 150 --speed 5")  # 30 s simulated
        mover.read_line()  # the first PROGRESS: the job is running
        status = pairs(other.command("status"))
        assert status["mode"] == "busy" and status["job"] == "1" and status["command"] == "move-ptu"
        assert "ERR 409 busy job 1 (move-ptu) is running" in other.command("move-ptu --pan 0")
        assert "ERR 409 busy" in other.command("sleep 1")
        assert "ERR 409 busy" in other.command("standby")
        assert other.command("version").split()[1] == "OK"
        assert other.command("check status").split()[1] == "OK"
        assert "ERR 409 busy" in other.command("check move-ptu --pan 1")
        assert pairs(other.command("break"))["recovery"] == "1"


def test_break_then_continue_completes_the_move(server):
    with server.connect() as c:
        c.send("@m move-ptu --pan -60 --tilt 10 --speed 3")  # 20 s simulated, 0.4 s wall
        c.read_line()
        time.sleep(0.15)
        brk = pairs(c.command("break"))
        reply, _ = c.reply("m")
        assert reply.startswith("m ERR 499 interrupted job 1 (move-ptu) interrupted by break") and "recovery=1" in reply
        assert brk == {"job": "1", "recovery": "1", "mode": "break"}
        status = pairs(c.command("status"))
        assert status["mode"] == "break" and status["recovery"] == "1"
        stopped_at = float(status["pan"])
        assert -60 < stopped_at < 0  # halted on the way
        time.sleep(0.3)
        assert float(pairs(c.command("status"))["pan"]) == pytest.approx(stopped_at, abs=0.1)  # and stays
        assert "ERR 409 wrong-mode mode is break" in c.command("move-ptu --pan 5")
        done = c.command("continue", timeout=60)
        assert done.split()[1] == "OK" and pairs(done)["job"] == "1" and near(pairs(done), -60, 10)
        status = pairs(c.command("status"))
        assert status["mode"] == "standby" and status["recovery"] == "0"
        assert "ERR 409 wrong-mode nothing to resume" in c.command("continue")


def test_abort_drops_the_recovery_set(server):
    with server.connect() as c:
        c.send("@m move-ptu --pan 100 --speed 5")
        c.read_line()
        c.command("break")
        assert pairs(c.command("abort")) == {"job": "1", "command": "move-ptu", "mode": "standby", "recovery": "0"}
        assert "wrong-mode" in c.command("abort")


def test_a_damaged_recovery_set_is_named_and_the_others_stay_usable(server_factory, tmp_path):
    recovery = tmp_path / "data" / "recovery"
    recovery.mkdir(parents=True)
    (recovery / "7.json").write_text(json.dumps({
        "job": "7", "command": "move-ptu", "options": {"pan": 20.0, "tilt": 0.0}, "line": "move-ptu --pan 20",
        "state": None, "reason": "break", "percent": 0.0, "devices": ["ptu"], "created": 1.0, "updated": 1.0}))
    (recovery / "8.json").write_text('{"job": "8", "command": "move-pt')  # cut short by a disk error
    (recovery / "9.json").write_text('{"job": "9"}')  # edited by hand
    server = server_factory()
    with server.connect() as c:
        reply = c.command("continue")  # the newest set is damaged: say so rather than resume an older job
        assert "ERR 409 wrong-mode recovery set 9 (" in reply and "9.json) is unreadable: missing command" in reply
        assert "abort --job 9 drops it; continue --job ID resumes another (7)" in reply
        reply = c.command("continue --job 8")
        assert "recovery set 8 (" in reply and "is unreadable" in reply
        assert pairs(c.command("status"))["recovery"] == "3"  # nothing was dropped by asking
        assert abs(float(pairs(c.command("continue --job 7", timeout=60))["pan"]) - 20.0) < 0.06
        assert pairs(c.command("abort --job 8")) == {"job": "8", "command": "unknown", "mode": "standby",
                                                   "recovery": "1"}
        assert pairs(c.command("abort"))["job"] == "9"
        assert "nothing to resume (stored: none)" in c.command("continue")


def test_relative_move_is_resolved_once_so_continue_does_not_add_it_twice(server):
    with server.connect() as c:
        start = float(pairs(c.command("move-ptu --pan 10 --speed 50"))["pan"])
        c.send("@r move-ptu --pan 30 --relative --speed 2")
        c.read_line()
        c.command("break")
        assert float(pairs(c.command("continue", timeout=60))["pan"]) == pytest.approx(start + 30, abs=0.06)


def test_restart_then_continue(server_factory, tmp_path):
    first = server_factory()
    with first.connect() as c:
        c.send("@m move-ptu --pan 80 --tilt -20 --speed 5")
        c.read_line()
        assert "recovery=1" in c.command("quit", timeout=60)  # quit interrupts and keeps the set
    assert first.proc.wait(timeout=30) == 0
    second = server_factory(data_dir=first.data_dir)
    with second.connect() as c:
        status = pairs(c.command("status"))
        assert status["recovery"] == "1" and status["mode"] == "standby"
        done = pairs(c.command("continue", timeout=60))
        assert done["job"] == "1" and near(done, 80, -20)
        # job ids go on counting across restarts
        assert pairs(c.command("move-ptu --pan 0 --speed 50"))["job"] == "2"


def test_crash_then_continue(server_factory):
    first = server_factory()
    with first.connect() as c:
        c.send("@m move-ptu --pan -120 --speed 5")
        c.read_line()
        time.sleep(0.2)
    first.kill()  # a power cut: no break, no quit
    second = server_factory(data_dir=first.data_dir)
    with second.connect() as c:
        assert pairs(c.command("status"))["recovery"] == "1"
        assert near(pairs(c.command("continue --job 1", timeout=60)), -120, 0)


def test_a_client_that_disconnects_does_not_stop_its_job(server):
    c = server.connect()
    c.send("@m move-ptu --pan 45 --speed 30")
    c.read_line()
    c.close()
    with server.connect() as watcher:
        deadline = time.monotonic() + 30
        while pairs(watcher.command("status"))["mode"] == "busy" and time.monotonic() < deadline:
            time.sleep(0.05)
        status = pairs(watcher.command("status"))
        assert status["mode"] == "standby" and near(status, 45, 0) and status["recovery"] == "0"
    log = next((server.data_dir / "logs").glob("rvs-*.log")).read_text()
    assert "job 1 end (finished)" in log


def test_sleep_mode_refuses_operations_until_woken(server):
    with server.connect() as c:
        assert pairs(c.command("sleep 3600")) == {"mode": "sleep", "seconds": "3600"}
        assert "ERR 423 sleeping" in c.command("move-ptu --pan 3")
        assert pairs(c.command("status"))["mode"] == "sleep"
        assert pairs(c.command("standby"))["mode"] == "standby"
        assert c.command("move-ptu --pan 1 --speed 50").split()[1] == "OK"
        c.command("sleep 2")  # 2 simulated seconds pass by themselves
        time.sleep(2 / 50 + 0.3)
        assert pairs(c.command("status"))["mode"] == "standby"


def test_subscribe_delivers_event_lines(server):
    with server.connect() as listener, server.connect() as c:
        assert pairs(listener.command("subscribe mode progress")) == {"topics": "mode progress"}
        c.command("move-ptu --pan 5 --speed 50")
        deadline = time.monotonic() + 10
        seen: list[str] = []
        while not any("mode=standby" in e for e in seen) and time.monotonic() < deadline:
            seen.append(listener.read_line(timeout=10))
        assert "* EVENT mode mode=busy" in seen
        assert any(e.startswith("* EVENT progress job=1 command=move-ptu percent=") for e in seen)
        assert "* EVENT mode mode=standby" in seen
        assert "ERR 400" in listener.command("subscribe weather")


def test_logbook_copies_the_log(shared_server):
    with shared_server.connect() as c:
        path = pairs(c.command("logbook"))["path"]
        assert path.startswith(str(shared_server.data_dir / "shared"))
        assert "listening" in open(path).read()


def test_reset_and_reinit_bring_devices_back(server):
    with server.connect() as c:
        c.command("move-ptu --pan 30 --speed 50")
        assert pairs(c.command("reset", timeout=120))["dev.ptu"] == "ok"
        assert pairs(c.command("reinit", timeout=60))["dev.ptu"] == "ok"
        assert pairs(c.command("status"))["dev.ptu"] == "ok"


def test_reinit_with_a_broken_file_changes_nothing(server):
    with server.connect() as c:
        (server.config_dir / "ptu.toml").write_text("default_speed_deg_s = -4\n")
        reply = c.command("reinit")
        assert "ERR 400" in reply and "ptu.toml" in reply and "default_speed_deg_s" in reply
        assert c.command("move-ptu --pan 2").split()[1] == "OK"  # the old default speed still works


def test_device_fault_is_503_and_the_server_stays_up(server_factory):
    server = server_factory(configs={"devices.toml": "[ptu]\nenabled = false\n"})
    with server.connect() as c:
        assert pairs(c.command("status"))["dev.ptu"] == "off"
        assert "ERR 503 device ptu is off" in c.command("move-ptu --pan 3")
        assert c.command("status").split()[1] == "OK"


def test_move_timeout_is_504(server_factory):
    server = server_factory(configs={"ptu.toml": "move_timeout_s = 1.0\n"})
    with server.connect() as c:
        reply = c.command("move-ptu --pan 100 --speed 5")
        assert "ERR 504 timeout ptu: move to pan 100.00" in reply and "recovery=1" in reply


# -- security -----------------------------------------------------------------------------------


def test_token_required_until_auth(server_factory, tmp_path):
    token = tmp_path / "token"
    token.write_text("s3cret-token\n")
    token.chmod(0o600)
    server = server_factory(args=["--token-file", str(token)])
    with server.connect() as c:
        assert "ERR 401 unauthorized" in c.command("status")
        assert c.command("version").split()[1] == "OK"
        assert c.command("help").split()[1] == "OK"
        assert "ERR 401 unauthorized wrong token" in c.command("auth nope")
        assert pairs(c.command("auth s3cret-token")) == {"auth": "ok"}
        assert c.command("status").split()[1] == "OK"
    with server.connect() as other:  # authentication is per connection
        assert "ERR 401" in other.command("status")


# -- ZeroMQ -------------------------------------------------------------------------------------


def zmq_call(server, message: dict, timeout_ms: int = 30000) -> list[dict]:
    ctx = zmq.Context.instance()
    sock = ctx.socket(zmq.DEALER)
    sock.setsockopt(zmq.LINGER, 0)
    sock.connect(server.zmq)
    try:
        sock.send(json.dumps(message).encode())
        frames = []
        while True:
            if not sock.poll(timeout_ms):
                raise TimeoutError(f"no reply to {message}")
            frames.append(json.loads(sock.recv()))
            if frames[-1]["status"] in ("ok", "error"):
                return frames
    finally:
        sock.close()


def test_zmq_router_reaches_the_same_dispatcher(server):
    frames = zmq_call(server, {"id": "42", "command": "move-ptu", "args": {"pan": 30, "tilt": -20, "speed": 50}})
    final = frames[-1]
    assert {k: final[k] for k in ("id", "status", "code", "reason", "message")} == \
        {"id": "42", "status": "ok", "code": 200, "reason": "ok", "message": ""}
    assert final["data"]["job"] == "1" and near(final["data"], 30, -20)
    assert all(f["status"] == "progress" and f["code"] == 102 for f in frames[:-1]) and len(frames) > 2
    line = zmq_call(server, {"id": "43", "line": "status"})[-1]
    assert line["data"]["pan"] == final["data"]["pan"]
    err = zmq_call(server, {"id": "44", "command": "move-ptu", "args": {"pan": 999}})[-1]
    assert (err["status"], err["code"], err["reason"]) == ("error", 400, "bad-request") and "--pan" in err["message"]
    bad = zmq_call(server, {"id": "45", "command": "nosuch"})[-1]
    assert bad["code"] == 404
    with server.connect() as c:
        assert pairs(c.command("status"))["pan"] == final["data"]["pan"]  # one dispatcher, one state


def test_zmq_bad_json_gets_an_error_not_silence(shared_server):
    ctx = zmq.Context.instance()
    sock = ctx.socket(zmq.DEALER)
    sock.setsockopt(zmq.LINGER, 0)
    sock.connect(shared_server.zmq)
    sock.send(b"{not json")
    assert sock.poll(10000)
    reply = json.loads(sock.recv())
    assert reply["status"] == "error" and reply["code"] == 400
    sock.close()


def test_zmq_pub_carries_events(server):
    ctx = zmq.Context.instance()
    sub = ctx.socket(zmq.SUB)
    sub.setsockopt(zmq.LINGER, 0)
    sub.setsockopt(zmq.SUBSCRIBE, b"mode")
    sub.connect(server.pub)
    time.sleep(0.3)  # a SUB socket needs a moment to join
    zmq_call(server, {"id": "1", "command": "move-ptu", "args": {"pan": 3, "speed": 50}})
    topics = []
    while sub.poll(2000):
        topic, body = sub.recv_multipart()
        topics.append((topic.decode(), json.loads(body)))
        if topics[-1][1].get("mode") == "standby":
            break
    sub.close()
    assert ("mode", {"mode": "busy"}) in topics and ("mode", {"mode": "standby"}) in topics


def test_help_is_answered_while_reset_replaces_the_ptu_driver(server):
    """help move-ptu reads the unit's limits on the event loop while reset (in the job thread)
    closes and reopens the PTU: it says the unit is re-initialising, never ERR 500."""
    import threading
    errors: list[str] = []
    stop = threading.Event()

    def ask() -> None:
        with server.connect() as c:
            while not stop.is_set():
                reply = c.command("help move-ptu")
                if " OK " not in reply:
                    errors.append(reply)
    asker = threading.Thread(target=ask)
    asker.start()
    try:
        with server.connect() as c:
            for _ in range(15):
                assert " OK " in c.command("reset", timeout=60)
    finally:
        stop.set()
        asker.join()
    assert errors == []
