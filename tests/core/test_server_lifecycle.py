"""Start-up and shutdown: nothing is answered before the server is ready, and `quit`, SIGINT or
SIGTERM at any moment (while starting, in a job, in break, asleep, with clients connected or half
connected) end it with exit status 0, no traceback, and the recovery sets intact."""
from __future__ import annotations

import json
import random
import shutil
import signal
import socket
import subprocess
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest
import zmq

from conftest import REPO, SERVER, SIM_SPEED, LineClient, ServerProcess, pairs, write_configs

START_MOMENTS = 50
EARLIEST_S = 0.2
SEED = 20261203


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def free_zmq_ports() -> int:
    """A port P with P and P + 1 free (ROUTER and PUB)."""
    while True:
        port = free_port()
        try:
            with socket.socket() as sock:
                sock.bind(("127.0.0.1", port + 1))
            return port
        except OSError:
            continue


def seed_recovery_set(data_dir: Path) -> bytes:
    """A stored recovery set from an earlier run: start-up and shutdown must leave it as it is."""
    recovery = data_dir / "recovery"
    recovery.mkdir(parents=True)
    text = json.dumps({"job": "7", "command": "move-ptu", "options": {"pan": 20.0, "tilt": 0.0},
                       "line": "move-ptu --pan 20", "state": {"target": [20.0, 0.0]}, "reason": "break",
                       "percent": 40.0, "devices": ["ptu"], "created": 1.0,
                       "updated": 1.0}).encode()  # older than any job of this test
    (recovery / "7.json").write_bytes(text)
    return text


def spawn(config_dir: Path, data_dir: Path, port: int = 0, zmq_port: int = 0) -> subprocess.Popen:
    return subprocess.Popen([*SERVER, "--config-dir", str(config_dir), "--data-dir", str(data_dir),
                             "--port", str(port), "--zmq-port", str(zmq_port), "--web-port", "0",
                             "--sim-speed", str(SIM_SPEED)],
                            cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, stdin=subprocess.DEVNULL)


def logs_of(data_dir: Path) -> str:
    return "".join(p.read_text(errors="replace") for p in sorted((data_dir / "logs").glob("*.log*")))


def connect_at_once(port: int, deadline_s: float = 60.0) -> LineClient:
    """Connect the instant the port opens, as a GNC computer booting with the rover does."""
    deadline = time.monotonic() + deadline_s
    while True:
        try:
            return LineClient("127.0.0.1", port, timeout=30)
        except (ConnectionRefusedError, ConnectionResetError):
            if time.monotonic() > deadline:
                raise
            time.sleep(0.002)


@pytest.fixture(scope="module")
def config_dir(tmp_path_factory) -> Path:
    return write_configs(tmp_path_factory.mktemp("lifecycle") / "configs")


def test_commands_sent_while_starting_are_answered_as_once_ready(config_dir, tmp_path):
    port, zmq_port = free_port(), free_zmq_ports()
    context = zmq.Context()
    dealer = context.socket(zmq.DEALER)
    dealer.setsockopt(zmq.LINGER, 0)
    dealer.connect(f"tcp://127.0.0.1:{zmq_port}")
    dealer.send(json.dumps({"id": "early", "line": "move-ptu --pan 3"}).encode())  # before the process exists
    proc = spawn(config_dir, tmp_path / "data", port, zmq_port)
    try:
        with connect_at_once(port) as client:
            assert client.greeting.split()[-1] in ("standby", "busy")  # busy: the ZeroMQ move below
            status = pairs(client.command("status"))
            assert status["mode"] in ("standby", "busy")
            assert all(status[f"dev.{name}"] == "ok" for name in ("ptu", "tof", "camera_left", "trigger"))
            assert dealer.poll(60_000), "the ZeroMQ request sent before start-up was never answered"
            early = json.loads(dealer.recv())
            assert early["id"] == "early" and early["status"] in ("progress", "ok"), early
            while early["status"] == "progress":
                assert dealer.poll(60_000)
                early = json.loads(dealer.recv())
            assert early["status"] == "ok" and float(early["data"]["pan"]) == pytest.approx(3.0, abs=0.05)
            assert "OK job=" in client.command("move-ptu --pan 5", timeout=60)
            assert "OK" in client.command("quit", timeout=60)
        assert proc.wait(timeout=60) == 0
    finally:
        dealer.close()
        context.term()
        if proc.poll() is None:
            proc.kill()
        proc.communicate()


def _stop_during_start_up(config_dir: Path, data_dir: Path, how: str, moment_s: float) -> dict:
    """As _stop_once; ports are chosen free before the spawn, so another program (tests run beside
    each other) may take one meanwhile: that run is repeated on new ports."""
    for _ in range(3):
        result = _stop_once(config_dir, data_dir, how, moment_s)
        if not (result["code"] == 2 and "Address already in use" in result["stderr"]):
            break
        shutil.rmtree(data_dir)
    return result


def _stop_once(config_dir: Path, data_dir: Path, how: str, moment_s: float) -> dict:
    """One start-up interrupted at `moment_s` after spawning: by a signal, or by `quit` on either
    transport sent then (the text port refuses until ready, so that client connects at once)."""
    kept = seed_recovery_set(data_dir)
    port, zmq_port = free_port(), free_zmq_ports()
    context = zmq.Context()
    dealer = context.socket(zmq.DEALER)
    dealer.setsockopt(zmq.LINGER, 0)
    dealer.connect(f"tcp://127.0.0.1:{zmq_port}")
    proc = spawn(config_dir, data_dir, port, zmq_port)
    reply = ""
    try:
        time.sleep(moment_s)
        if how in ("SIGTERM", "SIGINT"):
            proc.send_signal(getattr(signal, how))
        elif how == "quit-zmq":
            dealer.send(json.dumps({"id": "q", "line": "quit"}).encode())
            if dealer.poll(60_000):
                reply = json.loads(dealer.recv())["status"]
        else:
            with connect_at_once(port) as client:
                reply = client.command("quit", timeout=60).split()[1]
        code = proc.wait(timeout=90)
    finally:
        dealer.close()
        context.term()
        if proc.poll() is None:
            proc.kill()
        _, err = proc.communicate()
    return {"how": how, "moment": moment_s, "code": code, "reply": reply,
            "traceback": "Traceback" in err.decode(errors="replace") + logs_of(data_dir),
            "recovery": (data_dir / "recovery" / "7.json").read_bytes() == kept,
            "stderr": err.decode(errors="replace")[-1500:] if code != 0 else ""}


def test_quit_or_a_signal_at_any_moment_of_start_up_exits_0(config_dir, tmp_path):
    # How long start-up takes here, so the moments cover all of it (imports, configuration,
    # devices, the simulated world) and a little after.
    began = time.monotonic()
    first = ServerProcess(data_dir=tmp_path / "timing", config_dir=config_dir).start()
    ready_s = time.monotonic() - began
    assert first.stop() == 0
    rng = random.Random(SEED)
    # The interpreter's own start (30 ms idle, over 100 ms on a loaded machine) comes before any
    # code of ours can block a signal; a signal then gets the default action.
    moments = sorted(rng.uniform(EARLIEST_S, ready_s * 1.2) for _ in range(START_MOMENTS))
    ways = ["SIGTERM", "SIGINT", "quit-tcp", "quit-zmq"]
    runs = [(ways[i % len(ways)], moment) for i, moment in enumerate(moments)]
    with ThreadPoolExecutor(max_workers=3) as pool:
        results = list(pool.map(lambda item: _stop_during_start_up(
            config_dir, tmp_path / f"run{item[0]}", *item[1]), enumerate(runs)))
    bad = [r for r in results if r["code"] != 0 or r["traceback"] or not r["recovery"]
           or (r["how"].startswith("quit") and r["reply"] not in ("OK", "ok"))]
    print(f"start-up moments: {len(results)} over {EARLIEST_S}..{ready_s * 1.2:.2f} s (ready after {ready_s:.2f} s); "
          f"exit 0: {sum(r['code'] == 0 for r in results)}; failures: {bad}")
    assert len({round(r["moment"], 3) for r in results}) == START_MOMENTS
    assert not bad


# -- every state of a running server ----------------------------------------------------------


def _half_connected(server: ServerProcess) -> list[socket.socket]:
    """A client mid-line, and one that connected and never reads a byte."""
    partial = socket.create_connection((server.host, server.port))
    partial.sendall(b"stat")
    silent = socket.create_connection((server.host, server.port))
    return [partial, silent]


def _enter(state: str, client: LineClient, server: ServerProcess) -> None:
    if state == "job":
        client.send("@j move-ptu --pan 150 --speed 2")  # 75 simulated seconds, 15 s here
        assert pairs(client.command("status"))["mode"] == "busy"
    elif state == "break":
        client.send("@j move-ptu --pan 150 --speed 2")
        time.sleep(0.2)
        assert "OK" in client.command("break", timeout=60)
    elif state == "sleep":
        assert "OK" in client.command("sleep 3600")
    elif state == "idle":
        pass


@pytest.mark.parametrize("state", ["idle", "job", "break", "sleep"])
@pytest.mark.parametrize("how", ["quit", "SIGTERM", "SIGINT"])
def test_quit_and_signals_in_every_state_exit_0_and_keep_the_recovery_sets(server_factory, tmp_path, state, how):
    kept = seed_recovery_set(tmp_path / "data")
    server = server_factory(args=["--sim-speed", "5"])  # slow enough for the move to be under way
    others = _half_connected(server)
    client = server.connect()
    try:
        _enter(state, client, server)
        if how == "quit":
            assert " OK " in client.command("quit", timeout=60) + " "
        else:
            server.proc.send_signal(getattr(signal, how))
        assert server.proc.wait(timeout=90) == 0
    finally:
        client.close()
        for sock in others:
            sock.close()
    assert "Traceback" not in server.stderr() + logs_of(server.data_dir)
    recovery = server.data_dir / "recovery"
    assert (recovery / "7.json").read_bytes() == kept
    sets = {p.stem: json.loads(p.read_text()) for p in recovery.glob("*.json")}
    if state in ("job", "break"):  # the interrupted move is kept beside the older set
        (job,) = set(sets) - {"7"}
        assert sets[job]["command"] == "move-ptu" and sets[job]["reason"] == ("break" if state == "break" else "quit")
        assert sets[job]["state"] is not None
    else:
        assert set(sets) == {"7"}
