"""Commands from the web view and signing in with a cookie, against a real server on loopback.

A command sent by the page goes through the server's one dispatcher (the same grammar, checks and
replies as the text port); it must come from the page itself (a JSON body, no foreign Origin), and
with a token only after signing in: POST /login sets an HttpOnly, SameSite=Strict cookie, so the
token never appears in a URL.
"""
from __future__ import annotations

import http.client
import json
from urllib.parse import urlencode

import pytest
from web_client import EventStream, free_port, get, get_json

from conftest import ServerProcess, pairs, write_configs

TOKEN = "web-command-token-0123456"


def post(address: str, path: str, body: bytes, headers: dict[str, str]) -> tuple[int, dict[str, str], bytes]:
    host, port = address.rsplit(":", 1)
    conn = http.client.HTTPConnection(host, int(port), timeout=120)
    try:
        conn.request("POST", path, body=body, headers=headers)
        response = conn.getresponse()
        return response.status, {k.lower(): v for k, v in response.getheaders()}, response.read()
    finally:
        conn.close()


def command(address: str, line: str, headers: dict[str, str] | None = None) -> tuple[int, dict]:
    code, _, body = post(address, "/api/command", json.dumps({"line": line}).encode(),
                         {"Content-Type": "application/json", **(headers or {})})
    return code, json.loads(body)


@pytest.fixture(scope="module")
def web_server(tmp_path_factory) -> ServerProcess:
    root = tmp_path_factory.mktemp("webcmd")
    server = ServerProcess(data_dir=root / "data", config_dir=write_configs(root / "configs"),
                           extra_args=["--web-port", str(free_port())]).start()
    yield server
    server.stop()


def test_a_command_runs_through_the_dispatcher_and_answers_as_the_text_port(web_server):
    code, reply = command(web_server.web, "status")
    assert code == 200 and reply["ok"] and reply["reply"].startswith("web OK mode=standby")
    assert reply["data"]["mode"] == "standby"
    stream = EventStream(web_server.web)
    try:
        code, reply = command(web_server.web, "move-ptu --pan 12 --tilt -5")
        assert code == 200 and reply["ok"], reply
        job = reply["data"]["job"]                  # the reply came at the job's end, its progress by events
        stream.wait_for(lambda e: e["topic"] == "progress" and str(e["data"].get("job")) == str(job)
                        and int(e["data"]["percent"]) == 100)
    finally:
        stream.close()
    with web_server.connect() as client:            # the text port sees what the web command did
        status = pairs(client.command("status"))
    assert float(status["pan"]) == pytest.approx(12, abs=0.1) and float(status["tilt"]) == pytest.approx(-5, abs=0.1)


def test_a_bad_line_gets_the_text_ports_error_and_changes_nothing(web_server):
    _, before = get_json(web_server.web, "/api/status")
    code, reply = command(web_server.web, "move-ptu --pan 9999")
    assert code == 200 and not reply["ok"] and reply["code"] == 400
    assert reply["reply"].startswith("web ERR 400") and "pan" in reply["message"]
    code, reply = command(web_server.web, "no-such-command --x 1")
    assert reply["code"] == 404 or reply["code"] == 400, reply
    assert "no-such-command" in reply["message"]
    _, after = get_json(web_server.web, "/api/status")
    assert after["pan"] == before["pan"]


@pytest.mark.parametrize("body, headers, status, reason", [
    (b"line=status", {"Content-Type": "application/x-www-form-urlencoded"}, 415, "unsupported-media-type"),
    (b'{"line": "status"}', {"Content-Type": "text/plain"}, 415, "unsupported-media-type"),
    (b'{"line": "status"}', {"Content-Type": "application/json", "Origin": "http://evil.example"}, 403,
     "cross-origin"),
])
def test_a_command_from_another_site_is_refused(web_server, body, headers, status, reason):
    code, _, text = post(web_server.web, "/api/command", body, headers)
    assert code == status and json.loads(text)["error"] == reason


def test_a_malformed_body_is_a_bad_request(web_server):
    for body in (b"{not json", b'["status"]', b'{"line": 5}'):
        code, _, text = post(web_server.web, "/api/command", body, {"Content-Type": "application/json"})
        reply = json.loads(text)
        assert code == 200 and reply["code"] == 400 and not reply["ok"], (body, reply)
    long_line = "sleep " + "9" * 9000
    assert command(web_server.web, long_line)[1]["reason"] == "line-too-long"


def test_with_a_token_a_browser_signs_in_and_then_commands(server_factory, tmp_path):
    token_file = tmp_path / "token"
    token_file.write_text(TOKEN + "\n")
    token_file.chmod(0o600)
    server = server_factory(args=["--token-file", str(token_file), "--web-port", str(free_port())])
    code, headers, page = get(server.web, "/")                    # a browser gets the sign-in form
    assert code == 401 and b'action="/login"' in page and TOKEN.encode() not in page
    assert command(server.web, "status")[0] == 401                 # no command before signing in
    form = {"Content-Type": "application/x-www-form-urlencoded"}
    code, _, page = post(server.web, "/login", urlencode({"token": "wrong"}).encode(), form)
    assert code == 401 and b"not this server" in page
    code, _, _ = post(server.web, "/login", urlencode({"token": TOKEN}).encode(),
                      {**form, "Origin": "http://evil.example"})
    assert code == 403
    code, headers, _ = post(server.web, "/login", urlencode({"token": TOKEN}).encode(), form)
    assert code == 303 and headers["location"] == "/"
    cookie = headers["set-cookie"]
    assert cookie.startswith(f"rvs_token={TOKEN}") and "HttpOnly" in cookie and "SameSite=Strict" in cookie
    jar = {"Cookie": cookie.split(";", 1)[0]}
    assert get(server.web, "/", jar)[0] == 200
    assert get_json(server.web, "/api/status", jar)[1]["mode"] == "standby"
    code, reply = command(server.web, "sleep 0.1", jar)
    assert code == 200 and reply["ok"], reply
    assert get(server.web, "/api/status", {"Cookie": "rvs_token=guess"})[0] == 401
