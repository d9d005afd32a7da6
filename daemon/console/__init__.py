"""The surgeon's web console: plain HTML, CSS and JavaScript shipped as package data and
served by the daemon at ``/`` (the page) and ``/console/`` (its script and style sheet).

No build step and no third-party code: the page talks to the same REST endpoints and
telemetry websocket as any client, with the token the operator types in (kept in the
tab's session storage), so every action it offers is audited and refused by the API
exactly as from curl. docs/console.md describes what it shows and does.
"""

from __future__ import annotations

from functools import cache
from pathlib import Path

__all__ = ["CONSOLE_DIR", "SECURITY_HEADERS", "index_html"]

#: The folder of the console's files (``index.html``, ``console.js``, ``console.css``).
CONSOLE_DIR = Path(__file__).resolve().parent

#: Sent with the page: its script and style come from the daemon only, images too (the
#: views are fetched and drawn on canvases; ``data:`` for the empty icon), connections to
#: the daemon only (``'self'`` covers ws:/wss: to the same host in current browsers);
#: never framed.
SECURITY_HEADERS = {
    "Content-Security-Policy": "default-src 'self'; img-src 'self' data:; "
                               "connect-src 'self'; frame-ancestors 'none'; "
                               "base-uri 'none'; form-action 'none'",
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "no-referrer",
}


@cache
def index_html() -> bytes:
    """The console page (read once)."""
    return (CONSOLE_DIR / "index.html").read_bytes()
