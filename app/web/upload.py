"""Reading an upload's body safely: media type, size limits, and gzip without gzip bombs.

    raw = await read_body(request, max_upload_bytes=…)         # 415 / 413 before parsing
    upload = decode_body(raw, max_session_bytes=…)             # 400 bad gzip, 413 too large
    for chunk in upload.json_chunks(): …                       # the JSON, ≤ 1 MiB at a time

The body is read from the stream, never more than ``max_upload_bytes`` (a ``Content-Length`` over
the limit is refused before reading). ``Content-Encoding: gzip`` is inflated incrementally with
``zlib.decompressobj`` and stopped as soon as the output passes ``max_session_bytes``, so a bomb
costs at most the time to inflate it. A body that is gzip without saying so (a phone that gzipped
the file itself) is inflated the same way. The inflated JSON is never held whole: it is inflated
once to check and hash it, and again, a chunk at a time, for the parser (``json_chunks``).
"""

from __future__ import annotations

import gzip
import hashlib
import io
import zlib
from collections.abc import Iterable, Iterator
from dataclasses import dataclass

from fastapi import Request

from app.domain.json_values import GZIP_MAGIC
from app.storage.sessions import GZIP_LEVEL, StoredUpload
from app.web.errors import ApiError

JSON_MEDIA_TYPE = "application/json"
JPEG_MEDIA_TYPE = "image/jpeg"
GZIP_ENCODINGS = frozenset({"gzip", "x-gzip"})
IDENTITY_ENCODINGS = frozenset({"", "identity"})
#: zlib's window bits for the gzip container.
GZIP_WBITS = 16 + zlib.MAX_WBITS
#: Largest piece of inflated JSON handed on at once, bytes.
CHUNK_BYTES = 1 << 20
#: Piece of gzip given to the inflater at once, bytes (so that it never copies the whole body).
INPUT_PIECE_BYTES = 1 << 16


@dataclass(frozen=True, slots=True)
class RawBody:
    """The body as sent (a bytearray when read from a request: it is not copied into bytes),
    and whether it said ``Content-Encoding: gzip``."""

    data: bytes | bytearray
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
        declared = declared.strip()
        if not (declared.isascii() and declared.isdigit()):  # "²" is a digit to isdigit()
            raise ApiError(
                400, "bad_request", "Content-Length is not a number", field="Content-Length"
            )
        if len(declared) > 18 or int(declared) > max_upload_bytes:  # int() of no 5,000 digits
            raise _too_large(f"the body ({_bytes_shown(declared)}) is", max_upload_bytes)
    # one buffer, grown in place (no list of chunks joined into a second copy)
    data = bytearray()
    async for chunk in request.stream():
        if len(data) + len(chunk) > max_upload_bytes:
            raise _too_large("the body is", max_upload_bytes)
        data += chunk
    return RawBody(data=data, gzip=gzipped)


@dataclass(frozen=True, slots=True)
class DecodedUpload:
    """An upload whose body was checked (gzip valid, within the limits) and hashed, without
    keeping its JSON bytes: ``json_chunks()`` inflates them again a chunk at a time."""

    body: RawBody
    stored: StoredUpload
    max_session_bytes: int

    def json_chunks(self) -> Iterator[bytes]:
        """The JSON bytes, in chunks of at most :data:`CHUNK_BYTES`."""
        if is_gzip_body(self.body):
            return iter(InflatedChunks(self.body.data, max_bytes=self.max_session_bytes))
        view = memoryview(self.body.data)
        return (bytes(view[k : k + CHUNK_BYTES]) for k in range(0, len(view), CHUNK_BYTES))


def is_gzip_body(raw: RawBody) -> bool:
    """Whether the body is gzip: it says so, or it starts as gzip does (a phone that gzipped
    the file itself)."""
    return raw.gzip or raw.data[:2] == GZIP_MAGIC


def decode_body(raw: RawBody, *, max_session_bytes: int) -> DecodedUpload:
    """Check the upload's bytes (400 bad gzip, 413 too large), hash them and make their stored
    gzip form, inflating a chunk at a time. A single-member gzip as sent is kept as is; anything
    else is compressed here."""
    if not is_gzip_body(raw):
        if len(raw.data) > max_session_bytes:
            raise _too_large("the session is", max_session_bytes)
        return DecodedUpload(raw, StoredUpload.of(raw.data), max_session_bytes)
    chunks = InflatedChunks(raw.data, max_bytes=max_session_bytes)
    digest = hashlib.sha256()
    size_bytes = 0
    head = b""
    for chunk in chunks:
        if len(head) < 2:
            head += chunk[: 2 - len(head)]
        digest.update(chunk)
        size_bytes += len(chunk)
    if head == GZIP_MAGIC:
        raise ApiError(400, "invalid_gzip", "the body is gzip-compressed twice")
    json_gzip = (
        raw.data
        if chunks.members == 1
        else _gzip_of(InflatedChunks(raw.data, max_bytes=max_session_bytes))
    )
    stored = StoredUpload(json_gzip=json_gzip, sha256=digest.hexdigest(), size_bytes=size_bytes)
    return DecodedUpload(raw, stored, max_session_bytes)


def _gzip_of(chunks: Iterable[bytes]) -> bytes:
    """One gzip member of the concatenated ``chunks``, compressed a chunk at a time."""
    output = io.BytesIO()
    with gzip.GzipFile(fileobj=output, mode="wb", compresslevel=GZIP_LEVEL, mtime=0) as packed:
        for chunk in chunks:
            packed.write(chunk)
    return output.getvalue()


class InflatedChunks:
    """Inflate gzip ``data`` (one or more members) a chunk of at most :data:`CHUNK_BYTES` at a
    time, never past ``max_bytes`` of output in all; ``members`` counts the members read.
    Raises ApiError 413 past the limit and 400 for data that is not complete, valid gzip."""

    def __init__(self, data: bytes | bytearray, *, max_bytes: int) -> None:
        self._data = data
        self._max_bytes = max_bytes
        self.members = 0

    def __iter__(self) -> Iterator[bytes]:
        view = memoryview(self._data)
        offset = 0  # of the next input not given to an inflater
        output_bytes = 0
        while True:
            inflater = zlib.decompressobj(GZIP_WBITS)
            self.members += 1
            try:
                while not inflater.eof:
                    pending: bytes | memoryview
                    if inflater.unconsumed_tail:
                        pending = inflater.unconsumed_tail
                    elif offset < len(view):
                        pending = view[offset : offset + INPUT_PIECE_BYTES]
                        offset += len(pending)
                    else:
                        raise ApiError(
                            400, "invalid_gzip", "the body is not valid gzip: it ends too soon"
                        )
                    limit = min(CHUNK_BYTES, self._max_bytes - output_bytes + 1)
                    chunk = inflater.decompress(pending, limit)
                    output_bytes += len(chunk)
                    if output_bytes > self._max_bytes:
                        raise _too_large("the session after gunzip is", self._max_bytes)
                    if chunk:
                        yield chunk
            except zlib.error as err:
                raise ApiError(400, "invalid_gzip", f"the body is not valid gzip: {err}") from err
            offset -= len(inflater.unused_data)  # the next member starts there
            if offset >= len(view):
                return


def _bytes_shown(declared: str) -> str:
    """A declared Content-Length for a message: whole, or its number of digits if it is long."""
    return (
        f"{declared} bytes" if len(declared) <= 18 else f"a {len(declared)}-digit number of bytes"
    )


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
    declared = (declared or "").strip()
    if (
        declared.isascii()
        and declared.isdigit()
        and (len(declared) > 18 or int(declared) > max_bytes)
    ):
        raise _too_large(f"the picture ({_bytes_shown(declared)}) is", max_bytes)
    chunks: list[bytes] = []
    size = 0
    async for chunk in request.stream():
        size += len(chunk)
        if size > max_bytes:
            raise _too_large("the picture is", max_bytes)
        chunks.append(chunk)
    return b"".join(chunks)
