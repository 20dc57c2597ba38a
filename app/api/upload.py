"""Reading an upload's body safely: media type, size limits, and gzip without gzip bombs.

    raw = await read_body(request, max_upload_bytes=…)         # 415 / 413 before parsing
    upload = decode_body(raw, max_session_bytes=…)             # 400 bad gzip, 413 too large

The body is read from the stream, never more than ``max_upload_bytes`` (a ``Content-Length`` over
the limit is refused before reading). ``Content-Encoding: gzip`` is inflated incrementally with
``zlib.decompressobj`` and stopped as soon as the output passes ``max_session_bytes``, so a bomb
costs at most that much memory and the time to inflate it. A body that is gzip without saying so
(a phone that gzipped the file itself) is inflated the same way.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass

from fastapi import Request

from app.api.errors import ApiError
from app.domain.json_values import GZIP_MAGIC
from app.storage.sessions import StoredUpload

JSON_MEDIA_TYPE = "application/json"
JPEG_MEDIA_TYPE = "image/jpeg"
GZIP_ENCODINGS = frozenset({"gzip", "x-gzip"})
IDENTITY_ENCODINGS = frozenset({"", "identity"})
#: zlib's window bits for the gzip container.
GZIP_WBITS = 16 + zlib.MAX_WBITS


@dataclass(frozen=True, slots=True)
class RawBody:
    """The body as sent, and whether it said ``Content-Encoding: gzip``."""

    data: bytes
    gzip: bool


def check_media_type(content_type: str | None) -> None:
    """415 unless the body is declared ``application/json`` (charset, if any, UTF-8)."""
    if not content_type:
        raise ApiError(
            415,
            "unsupported_media_type",
            f"Content-Type is missing: send {JSON_MEDIA_TYPE}",
            field="Content-Type",
        )
    media_type, *parameters = (part.strip() for part in content_type.split(";"))
    if media_type.lower() != JSON_MEDIA_TYPE:
        raise ApiError(
            415,
            "unsupported_media_type",
            f"Content-Type must be {JSON_MEDIA_TYPE}, got {media_type or '(empty)'}",
            field="Content-Type",
        )
    for parameter in parameters:
        name, _, value = parameter.partition("=")
        charset = value.strip().strip('"').lower()
        if name.strip().lower() == "charset" and charset not in {"utf-8", "utf8"}:
            raise ApiError(
                415,
                "unsupported_media_type",
                f"JSON must be UTF-8, got charset={charset}",
                field="Content-Type",
            )


def is_gzip_encoding(content_encoding: str | None) -> bool:
    """Whether the body is gzip (True) or as is (False); 415 for any other coding."""
    coding = (content_encoding or "").strip().lower()
    if coding in GZIP_ENCODINGS:
        return True
    if coding in IDENTITY_ENCODINGS:
        return False
    raise ApiError(
        415,
        "unsupported_media_type",
        f"Content-Encoding {content_encoding!r} is not supported: send gzip or nothing",
        field="Content-Encoding",
    )


async def read_body(request: Request, *, max_upload_bytes: int) -> RawBody:
    """The request body, at most ``max_upload_bytes`` (413 beyond), checked for media type and
    encoding first (415)."""
    check_media_type(request.headers.get("content-type"))
    gzipped = is_gzip_encoding(request.headers.get("content-encoding"))
    declared = request.headers.get("content-length")
    if declared is not None:
        if not declared.strip().isdigit():
            raise ApiError(400, "bad_request", "Content-Length is not a number")
        if int(declared) > max_upload_bytes:
            raise _too_large(f"the body ({int(declared)} bytes) is", max_upload_bytes)
    chunks: list[bytes] = []
    size = 0
    async for chunk in request.stream():
        size += len(chunk)
        if size > max_upload_bytes:
            raise _too_large("the body is", max_upload_bytes)
        chunks.append(chunk)
    return RawBody(data=b"".join(chunks), gzip=gzipped)


def decode_body(raw: RawBody, *, max_session_bytes: int) -> StoredUpload:
    """The JSON bytes of the upload (gunzipped, at most ``max_session_bytes``) and their stored
    gzip form. A single-member gzip as sent is kept as is; anything else is compressed here."""
    if not (raw.gzip or raw.data[:2] == GZIP_MAGIC):
        if len(raw.data) > max_session_bytes:
            raise _too_large("the session is", max_session_bytes)
        return StoredUpload.of(raw.data)
    json_bytes, members = gunzip_limited(raw.data, max_bytes=max_session_bytes)
    if json_bytes[:2] == GZIP_MAGIC:
        raise ApiError(400, "invalid_gzip", "the body is gzip-compressed twice")
    return StoredUpload.of(json_bytes, json_gzip=raw.data if members == 1 else None)


def gunzip_limited(data: bytes, *, max_bytes: int) -> tuple[bytes, int]:
    """Inflate gzip ``data`` (one or more members) without ever holding more than ``max_bytes``
    + 1 bytes of output; returns the output and the number of members.
    Raises ApiError 413 past the limit and 400 for data that is not complete, valid gzip."""
    output = bytearray()
    members = 0
    rest = data
    while True:
        inflater = zlib.decompressobj(GZIP_WBITS)
        members += 1
        try:
            while rest and not inflater.eof:
                output += inflater.decompress(rest, max_bytes - len(output) + 1)
                if len(output) > max_bytes:
                    raise _too_large("the session after gunzip is", max_bytes)
                rest = inflater.unconsumed_tail
        except zlib.error as err:
            raise ApiError(400, "invalid_gzip", f"the body is not valid gzip: {err}") from err
        if not inflater.eof:
            raise ApiError(400, "invalid_gzip", "the body is not valid gzip: it ends too soon")
        rest = inflater.unused_data
        if not rest:
            return bytes(output), members


def _too_large(what: str, limit_bytes: int) -> ApiError:
    return ApiError(
        413, "payload_too_large", f"{what} larger than the limit of {limit_bytes} bytes"
    )


async def read_image_body(request: Request, *, max_bytes: int) -> bytes:
    """A picture's bytes: 415 unless declared ``image/jpeg``, 413 past ``max_bytes`` (a
    ``Content-Length`` over it is refused before reading)."""
    content_type = request.headers.get("content-type")
    media_type = (content_type or "").split(";")[0].strip().lower()
    if media_type != JPEG_MEDIA_TYPE:
        raise ApiError(
            415,
            "unsupported_media_type",
            f"Content-Type must be {JPEG_MEDIA_TYPE}, got {media_type or '(none)'}",
            field="Content-Type",
        )
    if is_gzip_encoding(request.headers.get("content-encoding")):
        raise ApiError(
            415,
            "unsupported_media_type",
            "send the JPEG as it is, without Content-Encoding (it is compressed already)",
            field="Content-Encoding",
        )
    declared = request.headers.get("content-length")
    if declared is not None and declared.strip().isdigit() and int(declared) > max_bytes:
        raise _too_large(f"the picture ({int(declared)} bytes) is", max_bytes)
    chunks: list[bytes] = []
    size = 0
    async for chunk in request.stream():
        size += len(chunk)
        if size > max_bytes:
            raise _too_large("the picture is", max_bytes)
        chunks.append(chunk)
    return b"".join(chunks)
