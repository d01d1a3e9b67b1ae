"""Screenshots of the web view after hop, hop-plan and hop-map (not a test: about a minute; look at them).

A real server (the tests' 12 m world, the hopper's camera at 320x240 as in tests/hopping), the page in
Debian's chromium through Playwright; every request must go to the server.

    .venv/bin/python tests/web/shoot_hop_map.py [--out /tmp]
"""
from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path
from urllib.parse import urlsplit

HERE = Path(__file__).resolve().parent
sys.path[:0] = [str(HERE), str(HERE.parent)]
from web_client import free_port  # noqa: E402

from conftest import ServerProcess, write_configs  # noqa: E402

HOPPING = """sfm_threads = 1
[hopper.camera]
width = 320
height = 240
motion_blur = false
"""


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--out", type=Path, default=Path("/tmp"))
    args = parser.parse_args()
    from playwright.sync_api import expect, sync_playwright
    from test_browser import CHROMIUM

    with tempfile.TemporaryDirectory() as tmp, sync_playwright() as playwright:
        base = Path(tmp)
        server = ServerProcess(data_dir=base / "data",
                               config_dir=write_configs(base / "configs", {"hopping.toml": HOPPING}),
                               extra_args=["--web-port", str(free_port())]).start()
        browser = playwright.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox", "--disable-gpu"])
        try:
            page = browser.new_page(viewport={"width": 1400, "height": 950})
            requests: list[str] = []
            page.on("request", lambda r: requests.append(r.url))
            page.goto(f"http://{server.web}/")
            page.wait_for_selector("#link.up", timeout=15000)
            with server.connect(timeout=300) as client:
                for line in ("hop --speed 1.5 --elevation 60 --heading 0", "hop-plan", "hop-map"):
                    reply = client.command(line, timeout=300)
                    print(line, "->", reply, flush=True)
                    assert " OK " in reply, reply
                    if line == "hop-plan":
                        expect(page.locator("#products .product .name").first).to_have_text("hop-plan-001",
                                                                                              timeout=15000)
                        expect(page.locator("#job")).to_contain_text("(ended)", timeout=15000)
                        page.wait_for_timeout(1000)   # the pictures load
                        page.screenshot(path=str(args.out / "webview-hop-plan.png"), full_page=True)
            expect(page.locator("#products .product .name").first).to_have_text("hop-map-001", timeout=15000)
            page.wait_for_timeout(1500)   # the pictures load
            page.screenshot(path=str(args.out / "webview-hop-map.png"), full_page=True)
            page.locator("#map-panel").screenshot(path=str(args.out / "webview-hop-map-canvas.png"))
            others = [u for u in requests if not u.startswith("data:") and urlsplit(u).netloc != server.web]
            print("requests", len(requests), "to other hosts", others)
            print("map", page.locator("#map").get_attribute("data-map"), "|", page.text_content("#map-note"))
            print("screenshots in", args.out)
        finally:
            browser.close()
            server.stop()


if __name__ == "__main__":
    main()
