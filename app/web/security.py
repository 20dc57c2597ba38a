"""One security-header policy for every answer of the server: the API, its documentation pages
and the dashboard.

    app.add_middleware(SecurityHeaders)     # in create_app: every answer gets the headers
    page_csp(inline_scripts=[script])        # a page with an inline script (``/docs``)

Every answer carries :data:`COMMON_HEADERS` (no MIME sniffing, no framing, a same-origin
referrer) and a Content-Security-Policy: :data:`API_CSP` (nothing may load: a JSON or PNG answer
opened in a browser runs nothing) unless the route set its own — the dashboard's pages
:data:`PAGE_CSP`, ``/docs`` and ``/redoc`` :func:`page_csp` with their inline scripts' hashes.
No policy names another origin.
"""

from __future__ import annotations

import base64
import hashlib
from collections.abc import Iterable

from starlette.datastructures import MutableHeaders
from starlette.types import ASGIApp, Message, Receive, Scope, Send

COMMON_HEADERS = {
    "X-Content-Type-Options": "nosniff",
    "X-Frame-Options": "DENY",
    "Referrer-Policy": "same-origin",
    "Cross-Origin-Opener-Policy": "same-origin",
}
#: The policy of the server's own pages (the dashboard): everything from this origin only.
PAGE_CSP = (
    "default-src 'self'; script-src 'self'; style-src 'self' 'unsafe-inline'; "
    "img-src 'self' data:; font-src 'self'; connect-src 'self'; object-src 'none'; "
    "base-uri 'none'; form-action 'self'; frame-ancestors 'none'"
)
#: The policy of everything else (JSON, PNG, GeoJSON, …): nothing loads or runs.
API_CSP = "default-src 'none'; base-uri 'none'; form-action 'none'; frame-ancestors 'none'"


def page_csp(*, inline_scripts: Iterable[str] = (), workers: bool = False) -> str:
    """:data:`PAGE_CSP`, allowing also the given inline scripts (by their SHA-256) and, with
    ``workers``, web workers made from blobs (ReDoc's)."""
    hashes = "".join(
        f" 'sha256-{base64.b64encode(hashlib.sha256(script.encode()).digest()).decode()}'"
        for script in inline_scripts
    )
    policy = PAGE_CSP.replace("script-src 'self'", f"script-src 'self'{hashes}")
    return policy + ("; worker-src 'self' blob:" if workers else "")


class SecurityHeaders:
    """ASGI middleware: adds the headers above to every HTTP answer that lacks them."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return

        async def send_with_headers(message: Message) -> None:
            if message["type"] == "http.response.start":
                headers = MutableHeaders(scope=message)
                for name, value in COMMON_HEADERS.items():
                    headers.setdefault(name, value)
                headers.setdefault("Content-Security-Policy", API_CSP)
            await send(message)

        await self.app(scope, receive, send_with_headers)
