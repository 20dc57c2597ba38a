"""Bulk data stored by content (SHA-256), written in small transactions of its own.

A map version's bulk data (its map document, plot and path graph: megabytes for a big session)
used to be written inside the one transaction that also ends the build job, which on SQLite held
the database's only write lock for seconds (issue 19, finding 4). Now the worker writes it first,
here, a chunk of at most :data:`CHUNK_BYTES` per transaction, and then makes the version visible
by one small fenced write that only refers to the blobs by their SHA-256
(``app.storage.maps.store_version``). A worker that stalls while writing its blobs holds no lock
between two chunks, so every other writer goes on.

    sha256 = put_blob(db, data)           # its own small transactions; found present: touched
    with db.transaction() as tx:
        require_blobs(tx, [sha256])       # BlobMissing unless each is complete
        ...                               # the row that refers to it
    read_blob(tx, sha256)                 # the bytes again

A blob is written as: its ``blob`` row (``complete`` false), each ``blob_chunk``, then
``complete`` with the last chunk. Writing the same content again reuses it (a retried build's
identical plot, say). Blobs nobody refers to (a failed attempt's, a deleted map's, a half-written
one) are removed by :func:`collect_orphan_blobs` once untouched for :data:`ORPHAN_GRACE_S`, which
is far longer than a worker takes between writing its blobs and referring to them.
"""

from __future__ import annotations

import hashlib
from datetime import datetime, timedelta
from typing import Any

from sqlalchemy import delete, exists, or_, select, update
from sqlalchemy.dialects import postgresql, sqlite
from sqlalchemy.orm import Session

from app.storage.db import Database
from app.storage.orm import Blob, BlobChunk, MapVersion, utc_now

#: Most bytes written in one transaction (one chunk row).
CHUNK_BYTES = 2**20
#: A blob nobody refers to is removed once untouched this long, s.
ORPHAN_GRACE_S = 3600.0
#: Orphan blobs removed per transaction.
COLLECT_BATCH = 20


class BlobMissing(LookupError):
    """Raised when a blob is not stored (or not completely)."""

    def __init__(self, sha256: str) -> None:
        super().__init__(f"blob {sha256} is not stored")
        self.sha256 = sha256


def blob_sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def put_blob(db: Database, data: bytes) -> str:
    """Store ``data`` in transactions of its own, one chunk each; its SHA-256. Content already
    stored completely is only touched (one small write)."""
    sha256 = blob_sha256(data)
    chunks = _chunks(data)
    with db.transaction() as db_session:
        if _begin(db_session, sha256, len(data), len(chunks)):
            return sha256
    for number, chunk in enumerate(chunks):
        write_blob_chunk(db, sha256, number, chunk, last=number == len(chunks) - 1)
    return sha256


def write_blob_chunk(db: Database, sha256: str, number: int, chunk: bytes, *, last: bool) -> None:
    """One chunk of a blob in its own transaction; the last one marks the blob complete."""
    with db.transaction() as db_session:
        _insert_chunk(db_session, sha256, number, chunk)
        if last:
            _mark_complete(db_session, sha256)


def put_blob_in(db_session: Session, data: bytes) -> str:
    """:func:`put_blob` in the caller's transaction (an import, a test): its SHA-256."""
    sha256 = blob_sha256(data)
    chunks = _chunks(data)
    if not _begin(db_session, sha256, len(data), len(chunks)):
        for number, chunk in enumerate(chunks):
            _insert_chunk(db_session, sha256, number, chunk)
        _mark_complete(db_session, sha256)
    return sha256


def require_blobs(db_session: Session, sha256s: list[str]) -> None:
    """Raise BlobMissing unless every one of ``sha256s`` is stored completely (in the
    transaction that will refer to them: its foreign keys then hold them)."""
    wanted = set(sha256s)
    present = set(
        db_session.scalars(select(Blob.sha256).where(Blob.sha256.in_(wanted), Blob.complete))
    )
    for sha256 in sorted(wanted - present):
        raise BlobMissing(sha256)


def read_blob(db_session: Session, sha256: str) -> bytes:
    """A stored blob's bytes; BlobMissing if it is not (completely) stored."""
    header = db_session.get(Blob, sha256)
    if header is None or not header.complete:
        raise BlobMissing(sha256)
    chunks = db_session.scalars(
        select(BlobChunk.data).where(BlobChunk.sha256 == sha256).order_by(BlobChunk.number)
    )
    data = b"".join(bytes(chunk) for chunk in chunks)
    if len(data) != header.size_bytes:
        raise BlobMissing(sha256)
    return data


def collect_orphan_blobs(
    db: Database, *, grace_s: float = ORPHAN_GRACE_S, now: datetime | None = None
) -> int:
    """Remove the blobs no map version refers to that nobody has written or reused for
    ``grace_s`` (a failed attempt's, a deleted map's, a half-written one), a few per
    transaction; how many were removed."""
    cutoff = (now or utc_now()) - timedelta(seconds=grace_s)
    removed = 0
    while True:
        with db.transaction() as db_session:
            query = select(Blob.sha256).where(_orphan(cutoff)).limit(COLLECT_BATCH)
            if db_session.get_bind().dialect.name == "postgresql":
                query = query.with_for_update(skip_locked=True)
            batch = list(db_session.scalars(query))
            if not batch:
                return removed
            db_session.execute(delete(BlobChunk).where(BlobChunk.sha256.in_(batch)))
            db_session.execute(delete(Blob).where(Blob.sha256.in_(batch)))
            removed += len(batch)


def _orphan(cutoff: datetime) -> Any:
    referred = or_(
        MapVersion.map_json_sha256 == Blob.sha256,
        MapVersion.plot_png_sha256 == Blob.sha256,
        MapVersion.path_graph_sha256 == Blob.sha256,
        MapVersion.app_map_sha256 == Blob.sha256,
        MapVersion.overview_sha256 == Blob.sha256,
    )
    return (Blob.touched_at < cutoff) & ~exists().where(referred)


def _chunks(data: bytes) -> list[bytes]:
    return [data[start : start + CHUNK_BYTES] for start in range(0, len(data), CHUNK_BYTES)]


def _begin(db_session: Session, sha256: str, size_bytes: int, chunk_count: int) -> bool:
    """Write (or touch) the blob's row; True when it is complete already (nothing to write)."""
    values = {
        "sha256": sha256,
        "size_bytes": size_bytes,
        "chunk_count": chunk_count,
        "complete": chunk_count == 0,
        "touched_at": utc_now(),
    }
    statement = _insert(db_session, Blob).values(values)
    db_session.execute(
        statement.on_conflict_do_update(
            index_elements=[Blob.sha256], set_={"touched_at": values["touched_at"]}
        )
    )
    complete, chunks_before = db_session.execute(
        select(Blob.complete, Blob.chunk_count).where(Blob.sha256 == sha256)
    ).one()
    if not complete and chunks_before != chunk_count:  # half-written with other chunk sizes
        db_session.execute(delete(BlobChunk).where(BlobChunk.sha256 == sha256))
        db_session.execute(
            update(Blob).where(Blob.sha256 == sha256).values(chunk_count=chunk_count)
        )
    return bool(complete)


def _insert_chunk(db_session: Session, sha256: str, number: int, chunk: bytes) -> None:
    statement = _insert(db_session, BlobChunk).values(sha256=sha256, number=number, data=chunk)
    db_session.execute(statement.on_conflict_do_nothing())


def _mark_complete(db_session: Session, sha256: str) -> None:
    db_session.execute(
        update(Blob).where(Blob.sha256 == sha256).values(complete=True, touched_at=utc_now())
    )


def _insert(db_session: Session, model: type[Blob] | type[BlobChunk]) -> Any:
    """INSERT … ON CONFLICT of the session's dialect (two writers of one content race)."""
    if db_session.get_bind().dialect.name == "postgresql":
        return postgresql.insert(model)
    return sqlite.insert(model)
