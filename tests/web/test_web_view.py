"""The web view against a real server on loopback: real HTTP, a real event stream, the text port beside.

One server for the module (a start costs seconds); the token case starts its own.
"""
from __future__ import annotations

import json
import os
import socket
import subprocess
import time

import pytest
from web_client import EventStream, free_port, get, get_json

from conftest import REPO, SERVER, ServerProcess, pairs, write_configs


@pytest.fixture(scope="module")
def web_server(tmp_path_factory) -> ServerProcess:
    root = tmp_path_factory.mktemp("web")
    server = ServerProcess(data_dir=root / "data", config_dir=write_configs(root / "configs"),
                           extra_args=["--web-port", str(free_port())]).start()
    yield server
    server.stop()


def test_status_is_the_status_reply_as_json(web_server):
    with web_server.connect() as client:
        text = pairs(client.command("status"))
    code, status = get_json(web_server.web, "/api/status")
    assert code == 200
    assert set(status) == set(text)  # the same reply, built by the same command
    assert status["mode"] == "standby" and status["dev.ptu"] == "ok" and status["version"] == text["version"]


def test_page_is_served_from_the_package_with_a_same_host_policy(web_server):
    code, headers, body = get(web_server.web, "/")
    assert code == 200 and b"<html" in body
    assert "default-src 'self'" in headers["Content-Security-Policy"]


def test_events_stream_progress_of_a_text_port_job(web_server):
    stream = EventStream(web_server.web)
    try:
        assert stream.status == 200
        with web_server.connect() as client:
            reply = client.command("move-ptu --pan 10 --tilt 0", timeout=60)
            assert " OK " in reply + " ", reply
            job = pairs(reply)["job"]
            seen = stream.wait_for(lambda e: e["topic"] == "progress" and e["data"].get("job") == job
                                   and int(e["data"]["percent"]) == 100)
            assert any(e["topic"] == "mode" and e["data"]["mode"] == "busy" for e in seen)
            progress = [e for e in seen if e["topic"] == "progress"]
            assert progress[0]["data"]["command"] == "move-ptu"
            client.command("move-ptu --pan 0 --tilt 0", timeout=60)
    finally:
        stream.close()


def _fake_product(root, name: str, age_s: float, files: dict[str, bytes]) -> None:
    folder = root / name
    folder.mkdir(parents=True)
    for relative, data in files.items():
        (folder / relative).parent.mkdir(parents=True, exist_ok=True)
        (folder / relative).write_bytes(data)
    manifest = folder / "product.json"
    manifest.write_text(json.dumps({"name": name, "command": "test", "status": "complete",
                                    "files": {k: "a test file" for k in files}}))
    when = time.time() - age_s
    os.utime(manifest, (when, when))


def test_products_newest_first_with_limit_and_their_files(web_server):
    root = web_server.data_dir / "products"
    _fake_product(root, "web-old", 100, {"a.txt": b"old"})
    _fake_product(root, "web-new", 10, {"a.txt": b"new", "cycle-1/map.png": b"\x89PNG"})
    code, body = get_json(web_server.web, "/api/products?limit=200")
    names = [m["name"] for m in body["products"]]
    assert code == 200 and names.index("web-new") < names.index("web-old")
    newest = get_json(web_server.web, "/api/products?limit=1")[1]["products"]
    assert len(newest) == 1
    assert get_json(web_server.web, "/api/products?limit=0")[0] == 400
    assert get_json(web_server.web, "/api/products?limit=x")[0] == 400

    code, headers, data = get(web_server.web, "/products/web-new/a.txt")
    assert (code, data) == (200, b"new")
    assert get(web_server.web, "/products/web-new/cycle-1/map.png")[0] == 200
    assert get(web_server.web, "/products/web-new/nothing.png")[0] == 404
    assert get(web_server.web, "/products/no-such-product/a.txt")[0] == 404


@pytest.mark.parametrize("path", [
    "/products/..%2F..%2Fetc/passwd",
    "/products/web-x/..%2F..%2F..%2F..%2Fetc%2Fpasswd",
    "/products/web-x/%2Fetc%2Fpasswd",
    "/products/%2Fetc/passwd",
    "/products/web-x/.hidden",
    "/products/web-x/a/../../../../../etc/passwd",
    "/products/web-x/%2E%2E/%2E%2E/%2E%2E/etc/passwd",
    "/products/..%5C..%5Cetc/passwd",
])
def test_nothing_outside_a_product_can_be_read(web_server, path):
    code, _, body = get(web_server.web, path)
    assert code in (400, 404), (code, body[:200])
    assert b"root:" not in body


def test_a_symlink_out_of_the_data_directory_is_not_followed(web_server):
    root = web_server.data_dir / "products"
    _fake_product(root, "web-link", 5, {})
    (root / "web-link" / "passwd").symlink_to("/etc/passwd")
    (root / "web-outside").symlink_to("/etc")
    assert get(web_server.web, "/products/web-link/passwd")[0] == 404
    assert get(web_server.web, "/products/web-outside/passwd")[0] == 404


def test_a_stalled_event_stream_does_not_delay_the_text_port(web_server):
    """A browser that never reads: its socket buffers fill, its queue drops; status stays prompt."""
    host, port = web_server.web.rsplit(":", 1)
    stalled = socket.socket()
    stalled.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    stalled.connect((host, int(port)))
    stalled.sendall(b"GET /events HTTP/1.1\r\nHost: x\r\n\r\n")  # and never read again
    try:
        with web_server.connect() as jobs, web_server.connect() as probe:
            probe.command("subscribe progress log mode", timeout=10)
            worst = 0.0
            for pan in (5, -5, 5, -5, 0):
                jobs.send(f"@m{pan + 10} move-ptu --pan {pan} --tilt 0")
                started = time.monotonic()
                while True:
                    t0 = time.monotonic()
                    assert " OK " in probe.command("status", timeout=10)
                    worst = max(worst, time.monotonic() - t0)
                    if time.monotonic() - started > 0.3:
                        break
                reply, _ = jobs.reply(f"m{pan + 10}", timeout=60)
                assert " OK " in reply, reply
            assert worst < 1.0, f"status took {worst:.2f} s with a stalled event stream"
        assert get_json(web_server.web, "/api/status")[0] == 200  # the web port answers others too
    finally:
        stalled.close()


def test_a_taken_web_port_stops_start_up_cleanly(tmp_path):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        result = subprocess.run([*SERVER, "--config-dir", str(write_configs(tmp_path / "configs")),
                                 "--data-dir", str(tmp_path / "d"), "--port", "0", "--zmq-port", "0",
                                 "--web-port", str(taken.getsockname()[1])], cwd=REPO, capture_output=True,
                                text=True, timeout=60, stdin=subprocess.DEVNULL)
    assert result.returncode == 2 and "cannot listen" in result.stderr


def test_with_a_token_every_route_needs_it(server_factory, tmp_path):
    token_file = tmp_path / "token"
    token_file.write_text("s3cret-token-for-web\n")
    token_file.chmod(0o600)
    server = server_factory(args=["--token-file", str(token_file), "--web-port", str(free_port())])
    for path in ("/", "/api/status", "/api/products", "/products/x/y.png", "/events"):
        code, headers, _ = get(server.web, path)
        assert code == 401 and headers.get("WWW-Authenticate") == "Bearer", path
    assert get(server.web, "/api/status", {"Authorization": "Bearer wrong-token-xx"})[0] == 401
    assert get(server.web, "/api/status?token=wrong")[0] == 401
    code, status = get_json(server.web, "/api/status", {"Authorization": "Bearer s3cret-token-for-web"})
    assert code == 200 and status["mode"] == "standby"
    assert get(server.web, "/api/status?token=s3cret-token-for-web")[0] == 200
    stream = EventStream(server.web, "/events?token=s3cret-token-for-web")
    stream.close()
    assert stream.status == 200
