"""Small HTTP helpers: entity tags, content negotiation, ready answers.

etag = strong_etag("v3", content_sha256)          # '"v3-9f86d081…"'
if_none_match_hits(request_header, etag)          # → answer 304
accepts_gzip("gzip, deflate, br")                 # True
json_response(model)                              # a pydantic model, encoded without revalidation
document = ReadyDocument.of(content, media_type="application/json")   # made once, kept
document.response(if_none_match, accept_encoding) # 200 (gzip if accepted) or 304
raw_upload_response(db, session_id, accept_encoding)   # the upload, streamed in chunks
"""

from __future__ import annotations

import gzip
import hashlib
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Annotated

from fastapi import Header, Response
from fastapi.responses import StreamingResponse
from pydantic import BaseModel

from app.domain.upload.json_stream import gunzipped
from app.storage import sessions as stored_sessions
from app.storage.db import Database


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


def weighted_items(header: str) -> Iterator[tuple[str, float]]:
    """The items of a list header with q-values (``Accept``, ``Accept-Encoding``: RFC 9110
    §12.4.2), each as (item, q): q 1 when not given, 0 when not a number."""
    for item in header.split(","):
        value, *parameters = (part.strip() for part in item.split(";"))
        quality = 1.0
        for parameter in parameters:
            name, _, text = parameter.partition("=")
            if name.strip().lower() == "q":
                try:
                    quality = float(text)
                except ValueError:
                    quality = 0.0
        yield value, quality


def accepts_gzip(accept_encoding: str | None) -> bool:
    """Whether ``Accept-Encoding`` allows gzip (listed, or ``*``, with a q-value above 0)."""
    if not accept_encoding:
        return False
    return any(
        coding.lower() in {"gzip", "x-gzip", "*"} and quality > 0
        for coding, quality in weighted_items(accept_encoding)
    )


#: Bytes of the stored upload read from the database at once when it is downloaded.
RAW_CHUNK_BYTES = 1 << 20


def raw_upload_response(db: Database, session_id: int, accept_encoding: str | None) -> Response:
    """The raw upload of ``session_id`` as a JSON attachment, gzip-encoded if the client accepts
    it, streamed from the database :data:`RAW_CHUNK_BYTES` at a time (each read in a short
    read transaction of its own; the upload is written once and never changed), so that no
    download holds the whole file. Raises SessionNotFound (before anything is sent)."""
    with db.read() as db_session:
        size = stored_sessions.raw_upload_gzip_size(db_session, session_id)
    headers = {
        "Content-Disposition": f'attachment; filename="session-{session_id}.json"',
        "Vary": "Accept-Encoding",
    }
    stored = _stored_chunks(db, session_id, size)
    if accepts_gzip(accept_encoding):
        headers["Content-Encoding"] = "gzip"
        headers["Content-Length"] = str(size)
        return StreamingResponse(stored, media_type="application/json", headers=headers)
    return StreamingResponse(
        gunzipped(stored, RAW_CHUNK_BYTES), media_type="application/json", headers=headers
    )


def _stored_chunks(db: Database, session_id: int, size: int) -> Iterator[bytes]:
    for offset in range(0, size, RAW_CHUNK_BYTES):
        with db.read() as db_session:
            yield stored_sessions.raw_upload_gzip_slice(
                db_session, session_id, offset, RAW_CHUNK_BYTES
            )


#: The ``Accept-Encoding`` request header, as a route parameter (not in the API's schema).
AcceptEncoding = Annotated[str | None, Header(include_in_schema=False)]

JSON_MEDIA_TYPE = "application/json"
#: Documents smaller than this are sent as they are (gzip would save too little to pay).
GZIP_MIN_BYTES = 4096
#: gzip level of kept documents: made once, so the smaller file wins.
KEPT_GZIP_LEVEL = 6


def json_response(model: BaseModel, *, status_code: int = 200) -> Response:
    """``model`` as a JSON answer, encoded by pydantic-core once (in Rust; faster on a model than
    orjson of its ``model_dump``), without FastAPI validating the answer again (the model was
    validated when it was made)."""
    return Response(
        content=model.__pydantic_serializer__.to_json(model),
        status_code=status_code,
        media_type=JSON_MEDIA_TYPE,
    )


@dataclass(frozen=True, slots=True, kw_only=True)
class ReadyDocument:
    """An answer made once and kept: its bytes, its gzip (None when too small to be worth it),
    a strong ETag of its content and its media type."""

    content: bytes
    gzipped: bytes | None
    etag: str
    media_type: str

    @classmethod
    def of(
        cls,
        content: bytes,
        *,
        media_type: str,
        etag: str | None = None,
        gzipped: bytes | None = None,
    ) -> ReadyDocument:
        """``content`` with its ETag (``etag``, else a hash of the bytes) and gzip (``gzipped``
        if the caller has it already)."""
        if gzipped is None and len(content) > GZIP_MIN_BYTES:
            gzipped = gzip.compress(content, compresslevel=KEPT_GZIP_LEVEL, mtime=0)
        return cls(
            content=content,
            gzipped=gzipped,
            etag=etag or f'"{hashlib.sha256(content).hexdigest()[:32]}"',
            media_type=media_type,
        )

    @property
    def size_bytes(self) -> int:
        """What it counts against a cache's byte bound."""
        return len(self.content) + len(self.gzipped or b"")

    def response(
        self,
        if_none_match: str | None,
        accept_encoding: str | None,
        *,
        headers: dict[str, str] | None = None,
    ) -> Response:
        """304 if ``If-None-Match`` names it, else 200 with it (gzip-encoded if accepted)."""
        sent = {"ETag": self.etag, "Vary": "Accept-Encoding", **(headers or {})}
        if if_none_match_hits(if_none_match, self.etag):
            return Response(status_code=304, headers=sent)
        content = self.content
        if self.gzipped is not None and accepts_gzip(accept_encoding):
            content = self.gzipped
            sent["Content-Encoding"] = "gzip"
        return Response(content=content, media_type=self.media_type, headers=sent)
