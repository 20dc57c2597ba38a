"""Inflating an upload a bounded chunk at a time (app/web/upload.py): the JSON is never held
whole, the gzip as sent is what is stored, and every fault is the same 400/413 as before."""

from __future__ import annotations

import gzip
import hashlib
import zlib

import pytest

from app.web.errors import ApiError
from app.web.upload import CHUNK_BYTES, InflatedChunks, RawBody, decode_body

JSON = b'{"map_id": "x", "pose_data": [' + b'{"id": 1, "pose": [0.5]},' * 200_000 + b"{}]}"


def test_chunks_are_bounded_and_join_to_the_json() -> None:
    packed = gzip.compress(JSON)
    chunks = list(InflatedChunks(packed, max_bytes=len(JSON)))
    assert max(len(chunk) for chunk in chunks) <= CHUNK_BYTES < len(JSON)
    assert b"".join(chunks) == JSON


def test_several_members_are_one_document_stored_as_one_member() -> None:
    packed = gzip.compress(JSON[:1000]) + gzip.compress(JSON[1000:])
    upload = decode_body(RawBody(packed, gzip=True), max_session_bytes=len(JSON))
    assert upload.stored.sha256 == hashlib.sha256(JSON).hexdigest()
    assert upload.stored.size_bytes == len(JSON)
    assert gzip.decompress(upload.stored.json_gzip) == JSON
    assert zlib.decompressobj(16 + zlib.MAX_WBITS).decompress(upload.stored.json_gzip) == JSON
    assert b"".join(upload.json_chunks()) == JSON


def test_one_member_is_stored_as_sent() -> None:
    packed = gzip.compress(JSON, compresslevel=1)
    upload = decode_body(RawBody(packed, gzip=True), max_session_bytes=len(JSON))
    assert upload.stored.json_gzip is packed
    assert b"".join(upload.json_chunks()) == JSON


def test_plain_json_is_compressed_for_storage() -> None:
    upload = decode_body(RawBody(JSON, gzip=False), max_session_bytes=len(JSON))
    assert gzip.decompress(upload.stored.json_gzip) == JSON
    assert b"".join(upload.json_chunks()) == JSON


@pytest.mark.parametrize(
    ("body", "status", "words"),
    [
        (gzip.compress(JSON)[:-9], 400, "ends too soon"),
        (gzip.compress(JSON) + b"junk", 400, "not valid gzip"),
        (gzip.compress(gzip.compress(JSON)), 400, "compressed twice"),
        (gzip.compress(JSON + b" " * 10), 413, "after gunzip"),
        (b"", 400, "ends too soon"),
    ],
    # not the bytes: a gzip header holds the time it was made, and xdist's processes must
    # collect the same ids
    ids=["truncated", "trailing-junk", "twice", "bomb", "empty"],
)
def test_bad_gzip_and_bombs_are_refused_before_parsing(
    body: bytes, status: int, words: str
) -> None:
    with pytest.raises(ApiError) as info:
        decode_body(RawBody(body, gzip=True), max_session_bytes=len(JSON) + 5)
    assert info.value.status_code == status
    assert words in info.value.detail


def test_a_bomb_is_refused_after_inflating_no_more_than_the_limit() -> None:
    """50 MiB of zeros in ~50 KiB: inflation stops one byte past the limit, not at 50 MiB."""
    bomb = gzip.compress(bytes(50 * 2**20), compresslevel=9)
    limit_bytes = 2**20
    chunk_sizes: list[int] = []

    def inflate_all() -> None:
        for chunk in InflatedChunks(bomb, max_bytes=limit_bytes):
            chunk_sizes.append(len(chunk))

    with pytest.raises(ApiError) as info:
        inflate_all()
    assert info.value.status_code == 413
    assert f"after gunzip is larger than the limit of {limit_bytes} bytes" in info.value.detail
    assert limit_bytes - CHUNK_BYTES < sum(chunk_sizes) <= limit_bytes
