"""The page and what it loads: every asset it names is served by RVS with the right type, and nothing
in the package points a browser at another host (the page must work offline, on the rover's LAN)."""
from __future__ import annotations

import re
from html.parser import HTMLParser
from pathlib import Path

import pytest
from web_client import free_port, get

from conftest import REPO, ServerProcess, write_configs

STATIC = REPO / "rvs_server" / "web" / "static"
TYPES = {".html": "text/html", ".css": "text/css", ".js": "javascript", ".png": "image/png", ".svg": "image/svg+xml"}


class _Assets(HTMLParser):
    def __init__(self) -> None:
        super().__init__()
        self.urls: list[str] = []
        self.inline_scripts = 0

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        values = dict(attrs)
        for name in ("src", "href"):
            if values.get(name):
                self.urls.append(values[name])
        if tag == "script" and not values.get("src"):
            self.inline_scripts += 1


def page_assets() -> _Assets:
    parser = _Assets()
    parser.feed((STATIC / "index.html").read_text())
    return parser


@pytest.fixture(scope="module")
def web_server(tmp_path_factory) -> ServerProcess:
    root = tmp_path_factory.mktemp("assets")
    server = ServerProcess(data_dir=root / "data", config_dir=write_configs(root / "configs"),
                           extra_args=["--web-port", str(free_port())]).start()
    yield server
    server.stop()


def test_the_page_and_every_asset_it_names_are_served_with_their_type(web_server):
    code, headers, body = get(web_server.web, "/")
    assert code == 200 and headers["Content-Type"].startswith("text/html")
    assets = page_assets()
    local = [u for u in assets.urls if not u.startswith("data:")]
    assert any(u.endswith(".js") for u in local) and any(u.endswith(".css") for u in local)
    assert assets.inline_scripts == 0  # the policy is default-src 'self': an inline script would not run
    for asset in local:
        assert asset.startswith("/static/") and not asset.startswith("//"), asset
        code, headers, body = get(web_server.web, asset)
        assert code == 200, asset
        assert TYPES[Path(asset).suffix] in headers["Content-Type"], (asset, headers["Content-Type"])
        assert body == (STATIC / asset[len("/static/"):]).read_bytes()


def test_no_static_file_names_another_host():
    files = [p for p in STATIC.rglob("*") if p.is_file()]
    assert {p.name for p in files} >= {"index.html", "view.js", "view.css"}
    for path in files:
        text = path.read_text(errors="replace")
        assert not re.search(r"https?://", text, re.I), f"{path.name} names an outside URL"
        assert not re.search(r"""(?:src|href|url)\s*[=(]\s*["']?//""", text, re.I), \
            f"{path.name}: protocol-relative URL"
        assert "@import" not in text and "@font-face" not in text, f"{path.name} loads a style or font"
