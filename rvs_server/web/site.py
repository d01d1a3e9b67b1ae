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
from rvs_server.protocol import BadRequest, RvsError, format_error, format_ok, parse_line
from rvs_server.transports.tcp import claim_tcp_port

from .access import allowed, login_cookie, same_origin, token_matches
from .events import KEEPALIVE_S, EventHub, _json
from .products import MAX_LIMIT, BadName, newest_manifests, product_file

log = logging.getLogger("rvs.web")

STATIC = Path(__file__).resolve().parent / "static"
_STATIC_REF = re.compile(r'\b(src|href)="(/static/[^"?#]+)"')  # the page's own assets
DEFAULT_LIMIT = 20
STATUS_TIMEOUT_S = 10.0
MAX_COMMAND_BYTES = 8192          # a command line's limit on the text port
LOGIN_FAILED_PAUSE_S = 0.5        # a wrong token waits: guessing by the thousand takes hours
SECURITY_HEADERS = {
    # The page loads nothing from any other host, and nothing served is guessed into another type.
    "Content-Security-Policy": "default-src 'self'; img-src 'self' data:; style-src 'self' 'unsafe-inline'",
    "X-Content-Type-Options": "nosniff",
    # No URL leaves for another host; and the page's own requests keep their Origin (a browser sends
    # "Origin: null" under no-referrer), which is how a command is known to come from this page.
    "Referrer-Policy": "same-origin",
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
        app.router.add_post("/api/command", self._command)
        app.router.add_post("/login", self._login)
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
        elif not allowed(request, self.server.token) and not (request.path == "/login" and request.method == "POST"):
            if request.path == "/" and request.method == "GET":   # a browser: the sign-in form
                response = _login_page(401, "")
            else:
                response = _error(401, "unauthorized", "this server requires a token: send Authorization: Bearer "
                                  "TOKEN, the rvs_token cookie that POST /login sets, or ?token=TOKEN",
                                  **{"WWW-Authenticate": "Bearer"})
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

    async def _command(self, request: web.Request) -> web.Response:
        """One command line through the one dispatcher, as an authenticated text client would send it:
        `{"line": "move-ptu --pan 10"}` in, `{"reply": "OK ...", "ok": true, "code": 200, "data": {...}}`
        out once the final reply is there (a job's progress goes to /events as for every client)."""
        if request.content_type != "application/json":
            return _error(415, "unsupported-media-type", f"a command is a JSON body {{\"line\": \"...\"}}, "
                          f"not {request.content_type or 'no content type'}")
        if not same_origin(request):
            return _error(403, "cross-origin", f"a command must come from this server's own page, not from "
                          f"{request.headers.get('Origin')}")
        body = await request.content.read(4 * MAX_COMMAND_BYTES)   # room for JSON's escapes
        future: asyncio.Future = asyncio.get_running_loop().create_future()
        try:
            if not request.content.at_eof():
                raise BadRequest(f"body over {4 * MAX_COMMAND_BYTES} bytes: a line is at most {MAX_COMMAND_BYTES}",
                                 reason="line-too-long")
            message = json.loads(body.decode("utf-8"))
            line = message.get("line") if isinstance(message, dict) else None
            if not isinstance(line, str):
                raise BadRequest('a command is a JSON object {"line": "COMMAND ..."}')
            if len(line.encode()) > MAX_COMMAND_BYTES:
                raise BadRequest(f"line of {len(line.encode())} bytes: at most {MAX_COMMAND_BYTES}",
                                 reason="line-too-long")
            parsed = parse_line(line)
        except (UnicodeDecodeError, json.JSONDecodeError) as exc:
            return _command_reply(BadRequest(f"body is not JSON: {exc}"))
        except RvsError as exc:
            return _command_reply(exc)
        session = Session(name=f"web {request.remote}", authenticated=True)  # allowed() passed
        self.server.dispatcher.submit(Request(command=parsed.command, tokens=parsed.tokens, tag="web",
                                              line=parsed.text), session, _ReplyFuture(future))
        try:
            return _command_reply(await future)   # a job's reply comes at its end; the job never waits on us
        except RvsError as exc:
            return _command_reply(exc)

    async def _login(self, request: web.Request) -> web.Response:
        """The sign-in form's POST: the right token sets the cookie and goes to the page."""
        token = self.server.token
        if token is None:
            return web.Response(status=303, headers={"Location": "/"})
        if not same_origin(request):
            return _error(403, "cross-origin", "sign in from this server's own page")
        form = await request.post()
        given = form.get("token")
        if not isinstance(given, str) or not token_matches(given.strip(), token):
            await asyncio.sleep(LOGIN_FAILED_PAUSE_S)
            return _login_page(401, "That is not this server's token.")
        response = web.Response(status=303, headers={"Location": "/", "Cache-Control": "no-store"})
        login_cookie(response, token)
        return response

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


def _command_reply(result: Mapping[str, Any] | RvsError) -> web.Response:
    """The final reply as the text port would write it, and its parts."""
    if isinstance(result, RvsError):
        body = {"reply": format_error("web", result), "ok": False, "code": result.code, "reason": result.reason,
                "message": result.message}
    else:
        body = {"reply": format_ok("web", result), "ok": True, "code": 200, "data": dict(result)}
    return web.json_response(body, dumps=_dumps, headers={"Cache-Control": "no-store"})


def _login_page(status: int, message: str) -> web.Response:
    page = (STATIC / "login.html").read_text()
    if message:
        page = page.replace("<!--message-->", f'<p class="error">{html.escape(message)}</p>')
    return web.Response(text=page, status=status, content_type="text/html",
                        headers={"Cache-Control": "no-store", "WWW-Authenticate": "Bearer"})


def _dumps(value: Any) -> str:
    return json.dumps(value, default=_json)
