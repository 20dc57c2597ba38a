"""Mapping sessions as uploaded: the statistics row and the raw upload (gzip, written once).

    with db.transaction() as s:
        created = create_session(s, parsed=session, upload=stored, uploaded_by="key:3",
                                 idempotency_key="walk-42", max_attempts=3)
    created.session_id, created.map_id, created.job_id, created.replayed

An upload becomes, in the caller's one transaction, a ``session`` row with its statistics, its
``session_upload`` (the JSON bytes exactly as received, gzip-compressed), a ``map`` and a queued
``build_map`` job. With an idempotency key, a second upload by the same uploader with the same key
returns the first upload's ids (``replayed=True``) and stores nothing; the same key with other
bytes raises :class:`IdempotencyConflict`. Two such uploads racing each other are settled by the
unique constraint on ``(uploaded_by, idempotency_key)``.

Exceptions::

    SessionNotFound        no session with that id
    IdempotencyConflict    the key was used before for a different upload (or its map is gone)
"""

from __future__ import annotations

import gzip
import hashlib
import sqlite3
import struct
import sys
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from datetime import datetime

from sqlalchemy import ColumnElement, LargeBinary, and_, func, insert, select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from app.domain.upload.json_stream import gunzipped
from app.domain.upload.session import Session as ParsedSession
from app.domain.upload.session import parse_session_stream
from app.storage import maps, queue
from app.storage.orm import Job, MapRow, MapSession, SessionRow, SessionUpload, utc_now
from app.storage.rows import info_from_row

#: The job kind that turns a session into a map version.
BUILD_MAP = maps.BUILD_MAP
#: A build_map job parameter: tune the noise variances by the shift metric first (trial count).
AUTO_TUNE_TRIALS = "auto_tune_trials"
#: A build_map job parameter: the sessions of a map of several, in order (absent: the job's one
#: ``session_id``). The job, and so the version it makes, records exactly which it used.
SESSION_IDS = "session_ids"
#: A build_map job parameter: ground truth of the map's tags (the JSON form sweeps take); the
#: version it makes carries the ground-truth metric and tag RMSE beside the shift metric.
GROUND_TRUTH = "ground_truth"
#: Longest ``map_id`` (the app's map name) a session may have, characters.
MAX_MAP_NAME_LENGTH = 200
#: Longest idempotency key, characters.
MAX_IDEMPOTENCY_KEY_LENGTH = 200
#: The largest id the ``session`` table's 32-bit INTEGER column holds: a larger number (or one
#: below 1) names no session and is not sent to the database, which would refuse it (the API's
#: rule for every id: ``app.web.deps.MAX_ID``).
MAX_SESSION_ID = 2**31 - 1
#: Compression level of stored uploads (6: zlib's default trade-off).
GZIP_LEVEL = 6


class SessionNotFound(LookupError):
    """Raised when no session has the given id."""

    def __init__(self, session_id: int) -> None:
        super().__init__(f"session {session_id} not found")
        self.session_id = session_id


class IdempotencyConflict(Exception):
    """Raised when an idempotency key cannot replay its first upload: the key was used for
    different bytes, or the map made from the first upload has been deleted since."""

    def __init__(self, idempotency_key: str, session_id: int, reason: str) -> None:
        super().__init__(
            f"Idempotency-Key {idempotency_key!r} was used for session {session_id}: {reason}"
        )
        self.idempotency_key = idempotency_key
        self.session_id = session_id
        self.reason = reason


@dataclass(frozen=True, slots=True, kw_only=True)
class SessionStatistics:
    """What a session holds, computed once when it was parsed."""

    pose_count: int
    detection_count: int
    tag_count: int
    poi_count: int
    duration_s: float
    path_length_m: float
    tag_ids: list[int]
    warnings: list[str]

    @classmethod
    def of(cls, parsed: ParsedSession) -> SessionStatistics:
        timestamps_s = parsed.timestamp_s
        return cls(
            pose_count=parsed.num_poses,
            detection_count=len(parsed.detections),
            tag_count=len(parsed.tag_ids),
            poi_count=len(parsed.pois),
            duration_s=float(timestamps_s[-1] - timestamps_s[0]) if timestamps_s.size else 0.0,
            path_length_m=parsed.path_length_m(),
            tag_ids=parsed.tag_ids,
            warnings=list(parsed.warnings),
        )

    @classmethod
    def from_row(cls, row: SessionRow) -> SessionStatistics:
        return info_from_row(cls, row)


@dataclass(frozen=True, slots=True, kw_only=True)
class StoredUpload:
    """The upload's bytes as they will be kept.

    json_gzip: the JSON document exactly as the client sent it (any Content-Encoding undone),
        gzip-compressed, one gzip member (what is stored).
    sha256: hex SHA-256 of the JSON bytes (not of the gzip).
    size_bytes: length of the JSON bytes.

    The JSON bytes themselves need not be held: the API inflates them a chunk at a time.
    """

    json_gzip: bytes | bytearray
    sha256: str
    size_bytes: int

    @classmethod
    def of(
        cls, json_bytes: bytes | bytearray, *, json_gzip: bytes | bytearray | None = None
    ) -> StoredUpload:
        """``json_gzip`` may be the client's own gzip of ``json_bytes`` (one member), else it is
        compressed here."""
        if json_gzip is None:
            json_gzip = gzip.compress(json_bytes, compresslevel=GZIP_LEVEL, mtime=0)
        return cls(
            json_gzip=json_gzip,
            sha256=hashlib.sha256(json_bytes).hexdigest(),
            size_bytes=len(json_bytes),
        )


@dataclass(frozen=True, slots=True, kw_only=True)
class SessionInfo:
    """A stored session: metadata, statistics, and the map and jobs made from it."""

    id: int
    map_name: str
    created_at: datetime
    uploaded_by: str
    idempotency_key: str | None
    raw_sha256: str
    raw_size_bytes: int
    stored_size_bytes: int
    statistics: SessionStatistics
    map_id: int | None
    job_ids: list[int]


@dataclass(frozen=True, slots=True, kw_only=True)
class UploadResult:
    """What an upload returns; ``replayed`` when an idempotency key returned an earlier one."""

    session_id: int
    map_id: int
    job_id: int
    map_name: str
    statistics: SessionStatistics
    replayed: bool
    #: maps (other than its own) whose current version has some of its tags: (map id, name,
    #: shared tag ids), most shared first. Nothing merges by itself; an admin may merge them.
    shares_tags_with: tuple[tuple[int, str, list[int]], ...] = ()


# --------------------------------------------------------------------------- writing


def create_session(
    db_session: Session,
    *,
    parsed: ParsedSession,
    upload: StoredUpload,
    uploaded_by: str,
    idempotency_key: str | None = None,
    max_attempts: int = 3,
    auto_tune_trials: int = 0,
    now: datetime | None = None,
    display_name: str | None = None,
) -> UploadResult:
    """Store a validated upload with its map and build job in the caller's transaction.
    ``display_name``: the map's name for people, when known apart from ``map_id`` (else it is
    derived from ``map_id`` when read).

    Raises :class:`IdempotencyConflict` when ``idempotency_key`` was used by ``uploaded_by`` for
    other bytes, and ValueError when ``parsed.map_id`` is longer than
    :data:`MAX_MAP_NAME_LENGTH`."""
    if len(parsed.map_id) > MAX_MAP_NAME_LENGTH:
        raise ValueError(f"map_id longer than {MAX_MAP_NAME_LENGTH} characters")
    sha256 = upload.sha256
    if idempotency_key is not None:
        earlier = find_by_idempotency_key(db_session, uploaded_by, idempotency_key)
        if earlier is not None:
            return replay_upload(db_session, earlier, sha256)
    now = now or utc_now()
    statistics = SessionStatistics.of(parsed)
    row = SessionRow(
        map_name=parsed.map_id,
        created_at=now,
        uploaded_by=uploaded_by,
        idempotency_key=idempotency_key,
        raw_sha256=sha256,
        raw_size_bytes=upload.size_bytes,
        stored_size_bytes=len(upload.json_gzip),
        pose_count=statistics.pose_count,
        detection_count=statistics.detection_count,
        tag_count=statistics.tag_count,
        poi_count=statistics.poi_count,
        duration_s=statistics.duration_s,
        path_length_m=statistics.path_length_m,
        tag_ids=statistics.tag_ids,
        warnings=statistics.warnings,
    )
    try:
        with db_session.begin_nested():
            db_session.add(row)
            db_session.flush()
    except IntegrityError:
        # A concurrent upload with the same key committed first (PostgreSQL waited for it).
        if idempotency_key is None:
            raise
        earlier = find_by_idempotency_key(db_session, uploaded_by, idempotency_key)
        if earlier is None:
            raise
        return replay_upload(db_session, earlier, sha256)
    _store_upload_gzip(db_session, row.id, upload.json_gzip)
    map_id = maps.create_map(
        db_session, name=parsed.map_id, session_id=row.id, display_name=display_name
    )
    job_id = queue.enqueue(
        db_session,
        kind=BUILD_MAP,
        map_id=map_id,
        session_id=row.id,
        params={AUTO_TUNE_TRIALS: auto_tune_trials} if auto_tune_trials else {},
        max_attempts=max_attempts,
        now=now,
    )
    return UploadResult(
        session_id=row.id,
        map_id=map_id,
        job_id=job_id,
        map_name=row.map_name,
        statistics=statistics,
        replayed=False,
        shares_tags_with=tuple(
            maps.maps_sharing_tags(db_session, statistics.tag_ids, exclude_map_id=map_id)
        ),
    )


def find_by_idempotency_key(db_session: Session, uploaded_by: str, key: str) -> int | None:
    """The id of the session ``uploaded_by`` uploaded with ``key``, if any."""
    return db_session.scalar(
        select(SessionRow.id).where(
            SessionRow.uploaded_by == uploaded_by, SessionRow.idempotency_key == key
        )
    )


def replay_upload(db_session: Session, session_id: int, sha256: str) -> UploadResult:
    """The result of the earlier upload ``session_id``, if its bytes hash to ``sha256``.
    Raises :class:`IdempotencyConflict` otherwise (or when its map was deleted)."""
    row = db_session.get(SessionRow, session_id)
    if row is None:
        raise SessionNotFound(session_id)
    key = row.idempotency_key or ""
    if row.raw_sha256 != sha256:
        raise IdempotencyConflict(
            key, row.id, "the body differs from that upload; use a new key for a new upload"
        )
    # the build queued for its own map: the first answer's job, while that map is there
    own_job_id = db_session.scalar(
        select(func.min(Job.id)).where(Job.session_id == row.id, Job.kind == BUILD_MAP)
    )
    map_id = db_session.scalar(select(func.min(MapRow.id)).where(MapRow.session_id == row.id))
    job_id = own_job_id
    if map_id is None:  # uploaded into a map (or its map merged into one): the map holding it
        map_id = db_session.scalar(
            select(func.min(MapSession.map_id)).where(MapSession.session_id == row.id)
        )
        if map_id is not None:
            job_id = _build_taking_in(db_session, map_id, row.id, own_job_id)
    if map_id is None or job_id is None:
        raise IdempotencyConflict(
            key, row.id, "its map has been deleted since; use a new key to upload again"
        )
    statistics = SessionStatistics.from_row(row)
    return UploadResult(
        session_id=row.id,
        map_id=map_id,
        job_id=job_id,
        map_name=row.map_name,
        statistics=statistics,
        replayed=True,
        shares_tags_with=tuple(
            maps.maps_sharing_tags(db_session, statistics.tag_ids, exclude_map_id=map_id)
        ),
    )


def _build_taking_in(
    db_session: Session, map_id: int, session_id: int, own_job_id: int | None
) -> int | None:
    """The build of map ``map_id`` that took session ``session_id`` in: what the upload into
    the map (or the merge of its own map into it) answered, so that a replay answers it again.

    That change queued the session's own build (``own_job_id``), canceled it with its map, and
    had the map's build under way in the same transaction: a new job (the first build of the
    map after ``own_job_id`` listing the session), or the map's queued one, which absorbed it
    (the last before ``own_job_id`` listing it; an older one cannot list it: absorbing cancels
    the other queued builds). Later builds list it too, so neither "the newest" nor "the
    first" would do. None if the map has no such build; then its newest build."""
    rows = db_session.execute(
        select(Job.id, Job.params)
        .where(Job.map_id == map_id, Job.kind == BUILD_MAP)
        .order_by(Job.id)
    ).all()
    job_ids: list[int] = [int(job_id) for job_id, _ in rows]
    listing = [int(job_id) for job_id, params in rows if session_id in params.get(SESSION_IDS, [])]
    if own_job_id is not None:
        absorbed = [job_id for job_id in listing if job_id < own_job_id]
        if absorbed:
            return absorbed[-1]
        listing = [job_id for job_id in listing if job_id > own_job_id]
    if listing:
        return listing[0]
    return job_ids[-1] if job_ids else None


# --------------------------------------------------------------------------- reading


def raw_sha256s(db_session: Session, session_ids: Sequence[int]) -> dict[int, str]:
    """The SHA-256 of each stored upload by session id (ids not stored left out): what a
    worker's cache of parsed sessions knows an upload by."""
    rows = db_session.execute(
        select(SessionRow.id, SessionRow.raw_sha256).where(SessionRow.id.in_(list(session_ids)))
    )
    return {int(session_id): str(sha) for session_id, sha in rows}


def get_session(db_session: Session, session_id: int) -> SessionInfo:
    """A stored session. Raises :class:`SessionNotFound`."""
    if not 1 <= session_id <= MAX_SESSION_ID:
        raise SessionNotFound(session_id)
    row = db_session.get(SessionRow, session_id)
    if row is None:
        raise SessionNotFound(session_id)
    return _infos(db_session, [row])[0]


def list_sessions(
    db_session: Session,
    *,
    limit: int = 50,
    offset: int = 0,
    uploaded_by: str | None = None,
    name_contains: str | None = None,
) -> tuple[list[SessionInfo], int]:
    """Sessions, newest first, and how many match in all; only ``uploaded_by``'s when given, and
    only those whose map name contains ``name_contains`` (case-insensitive) when given."""
    conditions: list[ColumnElement[bool]] = []
    if uploaded_by is not None:
        conditions.append(SessionRow.uploaded_by == uploaded_by)
    if name_contains:
        pattern = "%" + _escape_like(name_contains) + "%"
        conditions.append(SessionRow.map_name.ilike(pattern, escape="\\"))
    where = and_(*conditions) if conditions else and_(True)
    total = db_session.scalar(select(func.count()).select_from(SessionRow).where(where)) or 0
    rows = list(
        db_session.scalars(
            select(SessionRow)
            .where(where)
            .order_by(SessionRow.id.desc())
            .limit(limit)
            .offset(offset)
        )
    )
    return _infos(db_session, rows), total


def _escape_like(text: str) -> str:
    """``text`` matched literally by LIKE (its ``%``, ``_`` and ``\\`` escaped with ``\\``)."""
    return text.replace("\\", "\\\\").replace("%", "\\%").replace("_", "\\_")


def nth_latest_upload_at(
    db_session: Session, uploaded_by: str, *, n: int, since: datetime
) -> datetime | None:
    """When ``uploaded_by``'s ``n``-th latest session stored after ``since`` was stored (the
    latest is the 1st), or None if it stored fewer than ``n`` since then: the upload rate limit
    (``app.web.deps.UploadRate``), counted from the table so that it holds across API
    processes (index ``ix_session_uploaded_by_created_at``)."""
    return db_session.scalar(
        select(SessionRow.created_at)
        .where(SessionRow.uploaded_by == uploaded_by, SessionRow.created_at > since)
        .order_by(SessionRow.created_at.desc())
        .limit(1)
        .offset(n - 1)
    )


def uploader_of(db_session: Session, session_id: int) -> str | None:
    """Who uploaded ``session_id`` (None if there is no such session)."""
    return db_session.scalar(select(SessionRow.uploaded_by).where(SessionRow.id == session_id))


def raw_upload(db_session: Session, session_id: int) -> bytes:
    """The upload exactly as the client sent it (after undoing any ``Content-Encoding``)."""
    return gzip.decompress(raw_upload_gzip(db_session, session_id))


def raw_upload_gzip(db_session: Session, session_id: int) -> bytes:
    """The stored upload: one gzip member of the bytes :func:`raw_upload` returns."""
    row = db_session.get(SessionUpload, session_id)
    if row is None:
        raise SessionNotFound(session_id)
    return row.raw_gzip


#: Bytes of an upload written to SQLite at once.
UPLOAD_WRITE_CHUNK_BYTES = 1 << 20


def _store_upload_gzip(db_session: Session, session_id: int, data: bytes | bytearray) -> None:
    """Write the stored upload without another whole copy of it in this process. A BLOB bound
    whole is copied again: by SQLite twice (the binding, then the record: +32 MiB for a 16 MiB
    upload), by psycopg once (its parameter buffer). So on SQLite the row is made with a
    zero-filled BLOB of the right length and the bytes written into it a piece at a time
    (incremental blob I/O); on PostgreSQL the row is sent with ``COPY … FROM STDIN (FORMAT
    BINARY)``, the value a piece at a time. Both in the caller's transaction."""
    view = memoryview(data)
    pieces = (
        view[offset : offset + UPLOAD_WRITE_CHUNK_BYTES]
        for offset in range(0, len(view), UPLOAD_WRITE_CHUNK_BYTES)
    )
    dialect = db_session.get_bind().dialect
    connection = db_session.connection().connection.driver_connection
    if dialect.name == "sqlite":
        db_session.execute(
            insert(SessionUpload).values(session_id=session_id, raw_gzip=func.zeroblob(len(data)))
        )
        with connection.blobopen("session_upload", "raw_gzip", session_id) as blob:  # type: ignore[union-attr]
            for piece in pieces:
                blob.write(piece)
    elif dialect.name == "postgresql" and dialect.driver == "psycopg":
        copy_sql = "COPY session_upload (session_id, raw_gzip) FROM STDIN (FORMAT BINARY)"
        with connection.cursor() as cursor, cursor.copy(copy_sql) as copy:  # type: ignore[union-attr]
            # the binary COPY format: signature, flags, no header extension; one row of two
            # fields (int4 session_id, bytea raw_gzip), each length-prefixed; the end marker
            copy.write(b"PGCOPY\n\xff\r\n\x00" + struct.pack("!ii", 0, 0))
            copy.write(struct.pack("!hii", 2, 4, session_id) + struct.pack("!i", len(data)))
            for piece in pieces:
                copy.write(piece)
            copy.write(struct.pack("!h", -1))
    else:
        db_session.add(SessionUpload(session_id=session_id, raw_gzip=bytes(data)))


def raw_upload_gzip_size(db_session: Session, session_id: int) -> int:
    """Length of the stored upload (:func:`raw_upload_gzip`), bytes, without reading it."""
    size = db_session.scalar(
        select(func.length(SessionUpload.raw_gzip)).where(SessionUpload.session_id == session_id)
    )
    if size is None:
        raise SessionNotFound(session_id)
    return int(size)


#: Bytes of a stored upload read from the database, and inflated, at once.
STORED_PIECE_BYTES = 1 << 20


def raw_upload_gzip_pieces(
    db_session: Session, session_id: int, piece_bytes: int = STORED_PIECE_BYTES
) -> Iterator[bytes]:
    """The stored upload (:func:`raw_upload_gzip`) read ``piece_bytes`` at a time
    (:func:`raw_upload_gzip_slice`), never whole. Raises SessionNotFound at once."""
    size = raw_upload_gzip_size(db_session, session_id)
    return (
        raw_upload_gzip_slice(db_session, session_id, offset, piece_bytes)
        for offset in range(0, size, piece_bytes)
    )


def parsed_upload(db_session: Session, session_id: int) -> ParsedSession:
    """A stored session parsed again, read a piece at a time and parsed as it is inflated,
    never held whole. Raises SessionNotFound."""
    return parse_session_stream(
        gunzipped(raw_upload_gzip_pieces(db_session, session_id), STORED_PIECE_BYTES),
        max_poses=sys.maxsize,  # accepted once, within the limit there was then
        source=f"session {session_id}",
    )


def raw_upload_gzip_slice(db_session: Session, session_id: int, offset: int, size: int) -> bytes:
    """``size`` bytes of the stored upload from ``offset`` (fewer at its end), read without
    reading the rest: SQLite's incremental blob I/O (its ``substr`` would load the whole value),
    PostgreSQL's ``substr`` (which fetches only the TOAST chunks it needs)."""
    if db_session.get_bind().dialect.name == "sqlite":
        connection = db_session.connection().connection.driver_connection
        try:
            # session_upload.session_id is an INTEGER PRIMARY KEY: the row's rowid
            with connection.blobopen(  # type: ignore[union-attr]
                "session_upload", "raw_gzip", session_id, readonly=True
            ) as blob:
                blob.seek(offset)
                return bytes(blob.read(size))
        except sqlite3.OperationalError as err:  # no such row
            raise SessionNotFound(session_id) from err
    piece = db_session.scalar(
        select(func.substr(SessionUpload.raw_gzip, offset + 1, size, type_=LargeBinary)).where(
            SessionUpload.session_id == session_id
        )
    )
    if piece is None:
        raise SessionNotFound(session_id)
    return bytes(piece)


def _infos(db_session: Session, rows: list[SessionRow]) -> list[SessionInfo]:
    """Rows as :class:`SessionInfo`, with their maps and jobs looked up in two queries."""
    ids = [row.id for row in rows]
    map_of: dict[int, int] = {}
    jobs_of: dict[int, list[int]] = {session_id: [] for session_id in ids}
    if ids:
        for map_id, session_id in db_session.execute(
            select(MapRow.id, MapRow.session_id)
            .where(MapRow.session_id.in_(ids))
            .order_by(MapRow.id)
        ):
            map_of.setdefault(session_id, map_id)
        for job_id, job_session_id in db_session.execute(
            select(Job.id, Job.session_id).where(Job.session_id.in_(ids)).order_by(Job.id)
        ):
            if job_session_id is not None:
                jobs_of[job_session_id].append(job_id)
    return [
        SessionInfo(
            id=row.id,
            map_name=row.map_name,
            created_at=row.created_at,
            uploaded_by=row.uploaded_by,
            idempotency_key=row.idempotency_key,
            raw_sha256=row.raw_sha256,
            raw_size_bytes=row.raw_size_bytes,
            stored_size_bytes=row.stored_size_bytes,
            statistics=SessionStatistics.from_row(row),
            map_id=map_of.get(row.id),
            job_ids=jobs_of[row.id],
        )
        for row in rows
    ]
