"""Who may use the web port: the text port's rule (PROTOCOL.md, "Security").

With no token configured (which the server allows on loopback only) every request is served. With a
token, a request must carry it: as `Authorization: Bearer TOKEN` (scripts), as the `rvs_token`
cookie that `POST /login` sets (a browser: the token never appears in a URL), or as a `?token=TOKEN`
query (links and older pages). Compared in constant time, as `auth` does.

A command (`POST /api/command`) must also come from the page itself, not from another site the
operator's browser has open: its body must be JSON (a cross-site form cannot send that without a
CORS preflight, which this server never grants) and an `Origin`, when the browser sends one, must
name this server.
"""
from __future__ import annotations

import hmac
from urllib.parse import urlsplit

from aiohttp import web

COOKIE = "rvs_token"


def token_of(request: web.Request) -> str | None:
    header = request.headers.get("Authorization", "")
    scheme, _, value = header.partition(" ")
    if scheme.lower() == "bearer" and value.strip():
        return value.strip()
    return request.cookies.get(COOKIE) or request.query.get("token") or None


def token_matches(given: str | None, token: str) -> bool:
    return given is not None and hmac.compare_digest(given.encode(), token.encode())


def allowed(request: web.Request, token: str | None) -> bool:
    return token is None or token_matches(token_of(request), token)


def login_cookie(response: web.StreamResponse, token: str) -> None:
    """The browser keeps the token for this server only, out of scripts' reach, never sent cross-site."""
    response.set_cookie(COOKIE, token, httponly=True, samesite="Strict", path="/")


def same_origin(request: web.Request) -> bool:
    """No Origin (not a browser's cross-site request), or one naming this very host and port."""
    origin = request.headers.get("Origin")
    if origin is None:
        return True
    parts = urlsplit(origin)
    return parts.scheme in ("http", "https") and parts.netloc.lower() == request.host.lower()
