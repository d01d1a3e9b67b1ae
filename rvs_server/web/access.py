"""Who may use the web port: the text port's rule (PROTOCOL.md, "Security").

With no token configured (which the server allows on loopback only) every request is served. With a
token, a request must carry it, as `Authorization: Bearer TOKEN` or, for a browser's EventSource and
links that cannot set a header, as a `?token=TOKEN` query. Compared in constant time, as `auth` does.
"""
from __future__ import annotations

import hmac

from aiohttp import web


def token_of(request: web.Request) -> str | None:
    header = request.headers.get("Authorization", "")
    scheme, _, value = header.partition(" ")
    if scheme.lower() == "bearer" and value.strip():
        return value.strip()
    return request.query.get("token") or None


def allowed(request: web.Request, token: str | None) -> bool:
    if token is None:
        return True
    given = token_of(request)
    return given is not None and hmac.compare_digest(given.encode(), token.encode())
