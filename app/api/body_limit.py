"""A limit on the size of every request body but an upload's (which has its own, larger limits
and streaming checks in ``app.web.upload``): routes, localization updates, keys, sweeps and the
dashboard's forms are small, and a body of gigabytes must not be read into memory to find that
out.

    app.add_middleware(BodyLimit, max_bytes=4 * 2**20, exempt_paths=("/v1/sessions",))

A ``Content-Length`` over the limit is answered 413 before the body is read; a body without one
(chunked) is counted as it arrives and refused (413) once it passes the limit.
"""

from __future__ import annotations

from collections.abc import Sequence

from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from app.web.errors import error_response


class BodyLimit:
    """ASGI middleware: 413 ``payload_too_large`` for a request body over ``max_bytes``, on
    every path but ``exempt_paths`` (exact matches)."""

    def __init__(self, app: ASGIApp, *, max_bytes: int, exempt_paths: Sequence[str]) -> None:
        self.app = app
        self.max_bytes = max_bytes
        self.exempt_paths = frozenset(exempt_paths)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["path"] in self.exempt_paths:
            await self.app(scope, receive, send)
            return
        declared = _content_length(scope)
        if declared is not None and declared > self.max_bytes:
            response = error_response(413, "payload_too_large", self._detail(f"{declared} bytes"))
            await response(scope, receive, send)
            return
        received = 0

        async def counted() -> Message:
            nonlocal received
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > self.max_bytes:
                    raise StarletteHTTPException(413, self._detail("more"))
            return message

        await self.app(scope, counted, send)

    def _detail(self, size: str) -> str:
        return (
            f"the request body ({size}) is larger than the limit of {self.max_bytes} bytes "
            "for this endpoint"
        )


def _content_length(scope: Scope) -> int | None:
    for name, value in scope.get("headers", ()):
        if name == b"content-length":
            text = value.decode("latin-1").strip()
            # ASCII digits only ("²" is a digit to isdigit(), not to int()), and few enough
            # for int(); anything else is counted as the body streams in
            return int(text) if text.isascii() and text.isdigit() and len(text) <= 18 else None
    return None
