"""Small HTTP helpers: entity tags and content negotiation.

etag = strong_etag("v3", content_sha256)          # '"v3-9f86d081…"'
if_none_match_hits(request_header, etag)          # → answer 304
accepts_gzip("gzip, deflate, br")                 # True
"""

from __future__ import annotations

import hashlib
from typing import Annotated

from fastapi import Header, Response
from sqlalchemy.orm import Session

from app.storage import sessions as stored_sessions


def strong_etag(*parts: object) -> str:
    """A strong entity tag (quoted) from the values the representation depends on."""
    digest = hashlib.sha256("\x1f".join(str(part) for part in parts).encode()).hexdigest()
    return f'"{digest[:32]}"'


#: The ``If-None-Match`` request header, as a route parameter.
IfNoneMatch = Annotated[
    str | None,
    Header(
        alias="If-None-Match",
        description="the ETag of the copy you hold: 304 if it is still current",
    ),
]


def if_none_match_hits(if_none_match: str | None, etag: str) -> bool:
    """Whether ``If-None-Match`` names ``etag`` (or is ``*``): the client's copy is current.
    Comparison is weak, as RFC 9110 §13.1.2 asks for this header."""
    if not if_none_match:
        return False
    for candidate in if_none_match.split(","):
        tag = candidate.strip()
        if tag == "*" or tag.removeprefix("W/") == etag:
            return True
    return False


def accepts_gzip(accept_encoding: str | None) -> bool:
    """Whether ``Accept-Encoding`` allows gzip (listed, or ``*``, with a q-value above 0)."""
    if not accept_encoding:
        return False
    for item in accept_encoding.split(","):
        coding, *parameters = (part.strip() for part in item.split(";"))
        if coding.lower() not in {"gzip", "x-gzip", "*"}:
            continue
        quality = 1.0
        for parameter in parameters:
            name, _, value = parameter.partition("=")
            if name.strip().lower() == "q":
                try:
                    quality = float(value)
                except ValueError:
                    quality = 0.0
        if quality > 0:
            return True
    return False


def raw_upload_response(
    db_session: Session, session_id: int, accept_encoding: str | None
) -> Response:
    """The raw upload of ``session_id`` as a JSON attachment, gzip-encoded if the client accepts
    it. Raises SessionNotFound."""
    headers = {
        "Content-Disposition": f'attachment; filename="session-{session_id}.json"',
        "Vary": "Accept-Encoding",
    }
    if accepts_gzip(accept_encoding):
        headers["Content-Encoding"] = "gzip"
        content = stored_sessions.raw_upload_gzip(db_session, session_id)
    else:
        content = stored_sessions.raw_upload(db_session, session_id)
    return Response(content=content, media_type="application/json", headers=headers)
