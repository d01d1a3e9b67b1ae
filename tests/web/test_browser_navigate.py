"""A short `navigate` watched in a real headless browser (Debian's chromium through Playwright, as in
test_browser.py): the page shows the job's progress while it runs, draws the live path on the map,
and after it the navigate product's pictures and its driven path (path.csv) over the newest map, with
the goal. Every request goes to the server, none to another host.

The page may not run the test's scripts (its policy forbids eval), so what the map drew is read from
the canvas's data attributes (the view sets them on each redraw: the points in canvas pixels) and
checked against the canvas's own pixels in a screenshot of it.

Screenshots of the page during and after the navigate go to RVS_WEBVIEW_SHOTS (default /tmp).
"""
from __future__ import annotations

import os
import re
from pathlib import Path
from urllib.parse import urlsplit

import cv2
import numpy as np
import pytest
from test_browser import CHROMIUM, TOKEN, Watched, browser, start_with_token, sync_api  # noqa: F401 (fixture)

from conftest import pairs

pytestmark = pytest.mark.skipif(CHROMIUM is None, reason="no chromium on this machine: ./setup.sh installs "
                                "Debian's chromium package (apt-get install chromium)")
SHOTS = Path(os.environ.get("RVS_WEBVIEW_SHOTS", "/tmp"))
GOAL = (2.0, 0.5)   # open ground in the tests' 12 m world: two short drives, about 10 s at the tests' sim speed


def canvas_points(text: str | None) -> list[tuple[int, int]]:
    return [tuple(int(v) for v in p.split(",")) for p in (text or "").split()]


def path_pixels_drawn(png: bytes, points: list[tuple[int, int]]) -> tuple[int, int]:
    """(segments whose midpoint has the path's white or yellow within 2 px, segments) in a canvas shot."""
    # OpenCV decodes it (a chosen dependency); BGR flipped to RGB.
    image = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)[:, :, ::-1]
    h, w = image.shape[:2]
    seen = 0
    segments = [(a, b) for a, b in zip(points[:-1], points[1:], strict=True)
                if abs(a[0] - b[0]) + abs(a[1] - b[1]) >= 6]
    for a, b in segments:
        mx, my = (a[0] + b[0]) // 2, (a[1] + b[1]) // 2
        near = [tuple(int(v) for v in image[y, x]) for x in range(mx - 2, mx + 3) for y in range(my - 2, my + 3)
                if 0 <= x < w and 0 <= y < h]
        white = any(min(p) > 225 for p in near)                                   # driven: #ffffff
        yellow = any(p[0] > 220 and p[1] > 180 and p[2] < 110 for p in near)     # planned: #ffd33d
        seen += white or yellow
    return seen, len(segments)


def test_page_follows_a_navigate(server_factory, tmp_path, browser):  # noqa: F811  the fixture imported above
    server = start_with_token(server_factory, tmp_path)
    page = browser.new_page(viewport={"width": 1400, "height": 950})   # device scale 1: canvas px = CSS px
    watched = Watched(page)
    page.goto(f"http://{server.web}/?token={TOKEN}")
    page.wait_for_selector("#link.up", timeout=15000)
    canvas = page.locator("#map")
    expect = sync_api.expect

    with server.connect() as client:
        client.command(f"auth {TOKEN}")
        client.send(f"@nav navigate --to {GOAL[0]},{GOAL[1]} --tolerance 0.3 --max-steps 2")
        # While it runs: the progress, and the leg it drives drawn live (planned target, goal, rover).
        expect(page.locator("#command")).to_have_text("navigate", timeout=30000)
        expect(canvas).to_have_attribute("data-source", re.compile(r"^live "), timeout=30000)
        expect(canvas).to_have_attribute("data-planned", re.compile(r"^[1-9]"), timeout=60000)
        page.screenshot(path=str(SHOTS / "webview-navigate-running.png"), full_page=True)
        expect(canvas).to_have_attribute("data-goal", f"{GOAL[0]:.2f},{GOAL[1]:.2f}")
        # The planned leg's event can reach the page before the job's next progress line: wait for it.
        expect(page.locator("#bar-text")).to_have_text(re.compile(r"^(?:[1-9]\d?|100) %$"), timeout=30000)
        # The leg's progress line is in the event list (the header's message moves on within a second).
        expect(page.locator("#events li.t-progress", has_text="driving to")).not_to_have_count(0)
        reply, _ = client.reply("nav", timeout=120)
    assert " OK " in reply, reply
    product = pairs(reply)["product"]

    # After it: 100 %, the product's pictures, its driven path over its newest map, the goal.
    expect(page.locator("#bar-text")).to_have_text("100 %", timeout=15000)
    expect(canvas).to_have_attribute("data-source", f"product {product}", timeout=15000)
    expect(canvas).to_have_attribute("data-map", re.compile(rf"^{re.escape(product)}/cycle-\d+/\w+\.png$"),
                                     timeout=15000)
    expect(canvas).to_have_attribute("data-goal", f"{GOAL[0]:.2f},{GOAL[1]:.2f}")
    x, y = (float(v) for v in canvas.get_attribute("data-pose").split(","))
    assert abs(x - float(pairs(reply)["x"])) < 0.01 and abs(y - float(pairs(reply)["y"])) < 0.01
    assert int(canvas.get_attribute("data-driven")) >= 2

    card = page.locator("#products .product", has=page.locator(".name", has_text=product))
    expect(card).to_have_count(1, timeout=15000)
    thumbs = card.locator(".thumbs img")
    expect(thumbs).not_to_have_count(0)
    sources = [thumbs.nth(i).get_attribute("src") for i in range(thumbs.count())]
    assert all(urlsplit(s).netloc == server.web and urlsplit(s).path.startswith(f"/products/{product}/")
               and s.endswith(f".png?token={TOKEN}") for s in sources), sources
    for img in thumbs.all():   # lazy images: show each, then it must have come back as a PNG
        img.scroll_into_view_if_needed()
    expect(thumbs.first).to_be_visible()
    page.wait_for_timeout(500)
    pictures = {url.split("?")[0] for status, url, kind in watched.responses
                if status == 200 and kind.startswith("image/png") and f"/products/{product}/" in url}
    assert len(pictures) >= min(len(sources), 3), (pictures, sources)

    # The path is on the canvas: its segments' midpoints have the path's colours in the canvas's pixels.
    page.locator("#map").scroll_into_view_if_needed()
    driven = canvas_points(canvas.get_attribute("data-driven-px"))
    assert len(driven) >= 2, driven
    seen, segments = path_pixels_drawn(canvas.screenshot(), driven)
    assert segments and seen == segments, (seen, segments, driven)

    page.mouse.wheel(0, -10000)   # back to the top: a full-page shot of a scrolled page cuts under the sticky header
    page.wait_for_timeout(300)
    page.screenshot(path=str(SHOTS / "webview-navigate-done.png"), full_page=True)
    watched.assert_only_the_server(server.web)
