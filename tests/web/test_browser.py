"""The page in a real headless browser: Debian's chromium driven by Playwright (pointed at the system
browser; `playwright install` downloads one and cannot work offline). ./setup.sh installs chromium;
without it, or without the playwright package, these tests are skipped with the reason.

A real server with a token: the page, opened as /?token=T, must pass the token on to every request
(a 401 anywhere fails the test), must make no request to any other host, and must show a text-port
job's progress and its events live.
"""
from __future__ import annotations

import os
import re
import shutil
from urllib.parse import urlsplit

import pytest
from web_client import free_port

from conftest import pairs

sync_api = pytest.importorskip("playwright.sync_api", reason="the playwright package is not installed "
                               "(pip install -e '.[test]')")
CHROMIUM = os.environ.get("RVS_CHROMIUM") or shutil.which("chromium") or shutil.which("chromium-browser")
pytestmark = pytest.mark.skipif(CHROMIUM is None, reason="no chromium on this machine: ./setup.sh installs "
                                "Debian's chromium package (apt-get install chromium)")

TOKEN = "browser-test-token-0123"
SCREENSHOT = os.environ.get("RVS_WEBVIEW_SCREENSHOT", "/tmp/webview.png")


@pytest.fixture
def browser():
    with sync_api.sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=CHROMIUM, args=[
            "--no-sandbox", "--disable-gpu", "--disable-background-networking", "--no-first-run"])
        yield browser
        browser.close()


class Watched:
    """What a page asked for, what was refused and its script errors, gathered as it runs."""

    def __init__(self, page):
        self.requests, self.refused, self.errors, self.responses = [], [], [], []
        page.on("request", lambda r: self.requests.append(r.url))
        page.on("response", self._response)
        page.on("pageerror", lambda e: self.errors.append(str(e)))

    def _response(self, r) -> None:
        self.responses.append((r.status, r.url, r.headers.get("content-type", "")))
        if r.status >= 400:
            self.refused.append(f"{r.status} {r.url}")

    def assert_only_the_server(self, host: str, token: str | None = TOKEN) -> None:
        """Every request went to the server (no other host), with the token; none refused, no script error."""
        urls = [u for u in self.requests if not u.startswith("data:")]
        assert urls and all(urlsplit(u).netloc == host for u in urls), urls
        if token:
            assert all(f"token={token}" in u for u in urls), urls
        assert not self.refused, self.refused
        assert not self.errors, self.errors


def start_with_token(server_factory, tmp_path, args: list[str] | None = None):
    token_file = tmp_path / "token"
    token_file.write_text(TOKEN + "\n")
    token_file.chmod(0o600)
    return server_factory(args=["--token-file", str(token_file), "--web-port", str(free_port()), *(args or [])])


def test_page_shows_a_text_port_job_live(server_factory, tmp_path, browser):
    server = start_with_token(server_factory, tmp_path)
    page = browser.new_page(viewport={"width": 1400, "height": 950})
    watched = Watched(page)

    page.goto(f"http://{server.web}/?token={TOKEN}")
    page.wait_for_selector("#link.up", timeout=15000)          # the event stream is open
    page.wait_for_selector("#devices td.h-ok", timeout=15000)   # /api/status answered
    assert page.text_content("#mode") == "standby"

    with server.connect() as client:
        client.command(f"auth {TOKEN}")
        reply = client.command("move-ptu --pan 10 --tilt 0", timeout=60)
    assert " OK " in reply + " ", reply
    job = pairs(reply)["job"]
    # Locator assertions, not wait_for_function: the page's policy forbids eval, also to the test.
    sync_api.expect(page.locator("#bar-text")).to_have_text("100 %", timeout=15000)
    assert page.text_content("#job").split()[0] == job and page.text_content("#command") == "move-ptu"
    page.wait_for_selector("#events li.t-progress", timeout=5000)
    lines = page.locator("#events li").all_text_contents()
    assert any("move-ptu" in line and "100%" in line for line in lines), lines[:10]
    assert lines.index(next(line for line in lines if "100%" in line)) < \
        lines.index(next(line for line in lines if "started" in line)), "newest first"
    # The status asked again after the job: the PTU's own reading, within its resolution of 10.
    sync_api.expect(page.locator("#pan")).to_have_text(re.compile(r"^(9\.9\d|10\.0\d)$"), timeout=15000)

    # The topic filter hides and shows lines.
    page.uncheck("#topic-progress")
    sync_api.expect(page.locator("#events li.t-progress")).to_have_count(0)   # redrawn on the next frame
    sync_api.expect(page.locator("#events li.t-mode")).not_to_have_count(0)
    page.check("#topic-progress")
    sync_api.expect(page.locator("#events li.t-progress")).not_to_have_count(0)

    page.screenshot(path=SCREENSHOT, full_page=True)
    watched.assert_only_the_server(server.web)


def test_an_operator_signs_in_and_commands_from_the_page(server_factory, tmp_path, browser):
    """The sign-in form sets the cookie (no token in any URL after it), and the command box drives the
    PTU through the dispatcher: the reply is shown, the progress bar reaches 100 %, a bad line gets its
    ERR and moves nothing."""
    server = start_with_token(server_factory, tmp_path)
    page = browser.new_page(viewport={"width": 1400, "height": 950})
    watched = Watched(page)
    page.goto(f"http://{server.web}/")
    page.fill("input[name=token]", "not-the-token")
    page.click("button[type=submit]")
    sync_api.expect(page.locator("p.error")).to_contain_text("not this server's token")
    page.fill("input[name=token]", TOKEN)
    page.click("button[type=submit]")
    page.wait_for_selector("#link.up", timeout=15000)
    page.wait_for_selector("#devices td.h-ok", timeout=15000)

    page.fill("#command-line", "move-ptu --pan -15 --tilt 5")
    page.press("#command-line", "Enter")
    sync_api.expect(page.locator("#command-replies li.ok")).to_contain_text("OK job=", timeout=60000)
    sync_api.expect(page.locator("#bar-text")).to_have_text("100 %", timeout=15000)
    sync_api.expect(page.locator("#pan")).to_have_text(re.compile(r"^-1[45]\.\d\d$"), timeout=15000)
    page.fill("#command-line", "move-ptu --pan 500")
    page.press("#command-line", "Enter")
    sync_api.expect(page.locator("#command-replies li.err")).to_contain_text("ERR 400", timeout=15000)
    page.press("#command-line", "ArrowUp")                 # the history, as in a shell
    assert page.input_value("#command-line") == "move-ptu --pan 500"
    page.screenshot(path=str(tmp_path / "webview-command.png"), full_page=True)

    urls = [u for u in watched.requests if not u.startswith("data:")]
    assert not any("token=" in u for u in urls), urls      # the cookie carried it
    assert all(urlsplit(u).netloc == server.web for u in urls), urls
    assert [r for r in watched.refused if "/login" not in r and not r.endswith(f"{server.web}/")] == []
    assert not watched.errors, watched.errors
