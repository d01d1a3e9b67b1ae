"""The live web view (PROTOCOL.md, "Web view"): an aiohttp server in the server's own asyncio loop.

    access.py     the token rule, the same as the text port's
    events.py     Server-Sent Events: the web as the third consumer of Server.publish, per-client queues
    products.py   the newest manifests, and a product's file read safely
    site.py       the aiohttp application, its routes, start-up and shutdown
    static/       the page and everything it loads (served from the package, nothing from other hosts)
"""
from .site import WebView

__all__ = ["WebView"]
