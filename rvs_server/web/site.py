"""The web view's aiohttp application: its routes, and its start and stop inside the server's loop.

The port is claimed (bound, not listening) with the text port, before any device starts, so a taken
port stops start-up at once; it listens only once the server is ready, so nothing is answered from a
half-started server (connections are refused until then, as on the text port).
"""
from __future__ import annotations

import asyncio
import html
import json
import logging
import re
import socket
from collections.abc import Awaitable, Callable, Mapping
from pathlib import Path
from typing import Any
from urllib.parse import quote

from aiohttp import web

from rvs_server.dispatch import DispatchHost, Request, Session
from rvs_server.protocol import RvsError
from rvs_server.transports.tcp import claim_tcp_port

from .access import allowed
from .events import KEEPALIVE_S, EventHub, _json
from .products import MAX_LIMIT, BadName, newest_manifests, product_file

log = logging.getLogger("rvs.web")

STATIC = Path(__file__).resolve().parent / "static"
_STATIC_REF = re.compile(r'\b(src|href)="(/static/[^"?#]+)"')  # the page's own assets
DEFAULT_LIMIT = 20
STATUS_TIMEOUT_S = 10.0
SECURITY_HEADERS = {
    # The page loads nothing from any other host, and nothing served is guessed into another type.
    "Content-Security-Policy": "default-src 'self'; img-src 'self' data:; style-src 'self' 'unsafe-inline'",
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "no-referrer",
}


class _ReplyFuture:
    """A dispatcher sink whose final reply completes a future (progress is not kept)."""

    def __init__(self, future: asyncio.Future):
        self.future = future

    def progress(self, percent: float, message: str) -> None:
        pass

    def ok(self, data: Mapping[str, Any]) -> None:
        if not self.future.done():
            self.future.set_result(dict(data))

    def error(self, error: RvsError) -> None:
        if not self.future.done():
            self.future.set_exception(error)


def _error(status: int, reason: str, message: str, **headers: str) -> web.Response:
    return web.json_response({"error": reason, "message": message}, status=status, headers=headers or None)


class WebView:
    """The web port of one server: claim, start when the server is ready, publish events, close."""

    def __init__(self, server: DispatchHost):
        self.server = server
        self.hub = EventHub()
        self.runner: web.AppRunner | None = None
        self.address: tuple[str, int] | None = None
        self._sock: socket.socket | None = None

    # -- life -------------------------------------------------------------------------------------

    def claim(self, host: str, port: int) -> None:
        self._sock = claim_tcp_port(host, port)

    def release(self) -> None:
        """Start-up ended before start(): give the claimed port back."""
        if self._sock is not None and self.runner is None:
            self._sock.close()
            self._sock = None

    async def start(self) -> tuple[str, int]:
        assert self._sock is not None, "claim() first"
        app = web.Application(middlewares=[self._guard])
        app.router.add_get("/", self._index)
        app.router.add_get("/api/status", self._status)
        app.router.add_get("/api/products", self._products)
        app.router.add_get("/products/{name}/{path:.+}", self._product_file)
        app.router.add_get("/events", self._events)
        app.router.add_static("/static/", STATIC, follow_symlinks=False)
        self.runner = web.AppRunner(app, access_log=None, shutdown_timeout=1.0)  # tokens stay out of logs
        await self.runner.setup()
        await web.SockSite(self.runner, self._sock).start()
        host, port = self._sock.getsockname()[:2]
        self.address = (host, port)
        return self.address

    def publish(self, topic: str, data: Mapping[str, Any]) -> None:
        self.hub.publish(topic, data)

    async def close(self) -> None:
        self.hub.close_all()  # open event streams end now instead of holding the shutdown
        if self.runner is not None:
            await self.runner.cleanup()
        self.release()

    # -- every request ----------------------------------------------------------------------------

    @web.middleware
    async def _guard(self, request: web.Request,
                     handler: Callable[[web.Request], Awaitable[web.StreamResponse]]) -> web.StreamResponse:
        if not self.server.ready:
            response: web.StreamResponse = _error(503, "starting", "the server is not ready yet")
        elif not allowed(request, self.server.token):
            response = _error(401, "unauthorized", "this server requires a token: send Authorization: Bearer "
                              "TOKEN or ?token=TOKEN", **{"WWW-Authenticate": "Bearer"})
        else:
            try:
                response = await handler(request)
            except web.HTTPException as exc:
                response = _error(exc.status, exc.reason.lower().replace(" ", "-"), exc.text or exc.reason)
        if not response.prepared:
            response.headers.update(SECURITY_HEADERS)
        return response

    # -- routes -----------------------------------------------------------------------------------

    async def _index(self, request: web.Request) -> web.StreamResponse:
        """The page. Opened as /?token=T, its own scripts and styles are named with the token too: a
        browser cannot send a header for them, and every route needs the token."""
        page = (STATIC / "index.html").read_text()
        token = request.query.get("token")
        if token and self.server.token is not None:  # allowed() found it equal to the server's token
            query = html.escape("?token=" + quote(token, safe=""), quote=True)
            page = _STATIC_REF.sub(lambda m: f'{m.group(1)}="{m.group(2)}{query}"', page)
        return web.Response(text=page, content_type="text/html", headers={"Cache-Control": "no-store"})

    async def _status(self, request: web.Request) -> web.Response:
        """The `status` command through the one dispatcher, its reply's pairs as a JSON object."""
        future: asyncio.Future = asyncio.get_running_loop().create_future()
        session = Session(name=f"web {request.remote}", authenticated=True)  # allowed() passed
        self.server.dispatcher.submit(Request(command="status", tag="web", line="status"), session,
                                      _ReplyFuture(future))
        try:
            data = await asyncio.wait_for(future, STATUS_TIMEOUT_S)
        except RvsError as exc:
            return _error(exc.code if 400 <= exc.code < 600 else 500, exc.reason, exc.message)
        return web.json_response(data, dumps=_dumps, headers={"Cache-Control": "no-store"})

    async def _products(self, request: web.Request) -> web.Response:
        text = request.query.get("limit", str(DEFAULT_LIMIT))
        try:
            limit = int(text)
        except ValueError:
            limit = -1
        if not 1 <= limit <= MAX_LIMIT:
            return _error(400, "bad-request", f"limit {text!r}: an integer 1..{MAX_LIMIT}")
        manifests = await asyncio.to_thread(newest_manifests, self.server.products.root, limit)
        return web.json_response({"products": manifests}, dumps=_dumps, headers={"Cache-Control": "no-store"})

    async def _product_file(self, request: web.Request) -> web.StreamResponse:
        name, relative = request.match_info["name"], request.match_info["path"]
        try:
            path = await asyncio.to_thread(product_file, self.server.products.root, name, relative)
        except BadName as exc:
            return _error(400, "bad-request", str(exc))
        if path is None:
            return _error(404, "not-found", f"product {name} has no file {relative}")
        return web.FileResponse(path, headers={"Cache-Control": "no-cache"})

    async def _events(self, request: web.Request) -> web.StreamResponse:
        """Server-Sent Events: `data: {"topic": T, "data": {...}}` per event (see events.py)."""
        client = self.hub.open()
        if client is None:
            return _error(503, "too-many-streams", "too many event streams are open; close one")
        response = web.StreamResponse(headers={"Content-Type": "text/event-stream", "Cache-Control": "no-store",
                                               "X-Accel-Buffering": "no", **SECURITY_HEADERS})
        try:
            await response.prepare(request)
            await response.write(b"retry: 2000\n: rvs events\n\n")
            seq = 0
            while not client.closed:
                try:
                    await asyncio.wait_for(client.ready.wait(), KEEPALIVE_S)
                except TimeoutError:
                    await response.write(b": keepalive\n\n")
                    continue
                texts = client.take()
                if not texts:
                    continue
                chunk = []
                for text in texts:
                    seq += 1
                    chunk.append(f"id: {seq}\ndata: {text}\n\n")
                await response.write("".join(chunk).encode())  # waits for this browser only
        except (ConnectionResetError, ConnectionError):
            pass  # the browser went away
        finally:
            self.hub.discard(client)
        return response


def _dumps(value: Any) -> str:
    return json.dumps(value, default=_json)
