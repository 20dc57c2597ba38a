"""Moving a lab's recorded maps over from Firebase: every recording of an export uploaded once.

    export = read_firebase_export(directory)                    # app.domain.formats.firebase_export
    for entry in export.maps:
        outcome = import_recording(db, entry, max_attempts=3, max_session_bytes=…, max_poses=…)
        outcome.status        # "taken", "already_there" or "refused"; outcome.reason

Each recording goes in as an upload would (``app.storage.sessions.create_session``: the session,
its raw bytes exactly as stored in Firebase, its map and its build job, in one transaction), with:

- its **owner** kept: ``uploaded_by`` is ``firebase:<uid>`` (a hash of the uid where it is too
  long for the column), so the sessions of one Firebase user stay together and no API key of this
  server owns them;
- an **idempotency key** from the uid and the map id, so running the import again takes nothing
  twice (``already_there``), and a recording whose file changed since is refused, not doubled;
- its **name** as typed in the app (``maps/<uid>/<mapId>/name``) as the map's display name, and
  its **picture** (``<mapId>.jpg``) when the export has a valid JPEG of it.

A recording the server cannot take is ``refused`` with the reason, as an upload would be told,
and the others are still imported: no file; a file that is no file of the export's own (a link
leading out of the folder, a FIFO or a device); a file, or its gzip, larger than the server's
limit on an upload (checked before it is read, read and inflated no further); not JSON, nested
too deeply, not a session; what an upload is refused for at the door (text no database holds in
its ``map_id`` or a point of interest's name, tag ids beyond the database's column, too many
poses); a typed name holding such text; anything else the database refuses of it. A picture that
cannot be taken is skipped, the recording imported without it.
"""

from __future__ import annotations

import enum
import hashlib
import itertools
import zlib
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

from sqlalchemy.exc import DBAPIError

from app.domain.errors import SessionFormatError
from app.domain.formats.firebase_export import (
    ExportFileRefused,
    FirebaseMap,
    export_file_chunks,
    read_export_file,
)
from app.domain.json_values import GZIP_MAGIC
from app.domain.upload.fields import text_fault
from app.services.uploads import parse_upload
from app.storage import images, sessions
from app.storage.db import Database, database_fault, first_line
from app.storage.sessions import (
    GZIP_LEVEL,
    MAX_IDEMPOTENCY_KEY_LENGTH,
    MAX_MAP_NAME_LENGTH,
    IdempotencyConflict,
    StoredUpload,
)

#: ``uploaded_by`` of imported sessions: this prefix and the Firebase uid.
OWNER_PREFIX = "firebase:"
#: Length of the ``uploaded_by`` column.
MAX_OWNER_LENGTH = 64
#: The most a gzip recording is inflated at a time, bytes.
INFLATE_CHUNK_BYTES = 2**20


class ImportStatus(enum.StrEnum):
    """What happened to one recording."""

    #: uploaded now: a new session, map and build job
    TAKEN = "taken"
    #: imported by an earlier run (the same bytes): nothing done
    ALREADY_THERE = "already_there"
    #: not imported; ``reason`` says why
    REFUSED = "refused"


@dataclass(frozen=True, slots=True, kw_only=True)
class ImportOutcome:
    """One recording's outcome; ``picture`` says what became of its picture."""

    key: str
    status: ImportStatus
    reason: str | None = None
    session_id: int | None = None
    map_id: int | None = None
    picture: str | None = None


def owner_of(uid: str) -> str:
    """``uploaded_by`` for the Firebase user ``uid``."""
    owner = f"{OWNER_PREFIX}{uid}"
    if len(owner) <= MAX_OWNER_LENGTH and owner.isascii() and owner.isprintable():
        return owner
    return f"{OWNER_PREFIX}sha256:{hashlib.sha256(uid.encode()).hexdigest()[:40]}"


def idempotency_key_of(entry: FirebaseMap) -> str:
    """The same key for the same recording on every run (visible ASCII, ≤ 200 characters)."""
    digest = hashlib.sha256(f"{entry.uid}\x1f{entry.map_id}".encode()).hexdigest()
    key = f"firebase-import:{digest}"
    assert len(key) <= MAX_IDEMPOTENCY_KEY_LENGTH
    return key


def import_recording(
    db: Database, entry: FirebaseMap, *, max_attempts: int, max_session_bytes: int, max_poses: int
) -> ImportOutcome:
    """Upload one recording of the export (see the module docstring); never raises for a
    recording the server cannot take (it is ``refused`` with the reason): its file is read as
    :func:`~app.domain.formats.firebase_export.read_export_file` allows (no link leading out of
    the export, no FIFO, no file beyond ``max_session_bytes``, checked before it is read), it is
    inflated no further than ``max_session_bytes`` and parsed with the door rules of an upload
    (:func:`app.services.uploads.parse_upload`: at most ``max_poses`` poses, text by the one
    rule, ids the database holds), and its name must be text too. It is read, inflated and
    parsed a chunk at a time (:data:`~app.domain.formats.firebase_export.CHUNK_BYTES`), never
    held whole: what is kept is the gzip of it that is stored (:class:`_KeptUpload`). A value
    the database refuses all the same refuses the recording, not the import; only a fault of the
    database itself (unreachable, full: ``app.storage.db.database_fault``) is raised."""

    def refused(reason: str) -> ImportOutcome:
        return ImportOutcome(key=entry.key, status=ImportStatus.REFUSED, reason=reason)

    if entry.problem is not None or entry.raw_path is None:
        return refused(entry.problem or "no session file")
    name = entry.raw_path.name
    kept = _KeptUpload()
    try:
        chunks = export_file_chunks(
            entry.export_folder, entry.raw_path, max_bytes=max_session_bytes
        )
        plain = kept.of(_gunzipped(chunks, name, max_bytes=max_session_bytes))
        parsed = parse_upload(plain, max_poses=max_poses, source=name)
        for _ in plain:  # (the parser reads to the end: nothing is left)
            pass
    except ExportFileRefused as err:
        return refused(str(err))
    except SessionFormatError as err:
        return refused(f"not a session the server takes: {err}")
    if (reason := text_fault(entry.name)) is not None:
        return refused(f"its name (maps/<uid>/<mapId>/name) {reason}")
    upload = kept.stored()
    picture_bytes, picture = _picture(entry)
    try:
        with db.transaction() as db_session:
            result = sessions.create_session(
                db_session,
                parsed=parsed,
                upload=upload,
                uploaded_by=owner_of(entry.uid),
                idempotency_key=idempotency_key_of(entry),
                max_attempts=max_attempts,
                display_name=entry.name.strip()[:MAX_MAP_NAME_LENGTH] or None,
            )
            if result.replayed:
                return ImportOutcome(
                    key=entry.key,
                    status=ImportStatus.ALREADY_THERE,
                    session_id=result.session_id,
                    map_id=result.map_id,
                )
            if picture_bytes is not None:
                images.put_session_image(
                    db_session, session_id=result.session_id, jpeg=picture_bytes
                )
    except IdempotencyConflict as err:
        return refused(f"imported before from a different file ({err.reason})")
    except DBAPIError as err:
        if database_fault(err) is not None:
            raise
        return refused(f"the database refused it: {first_line(err)}")
    return ImportOutcome(
        key=entry.key,
        status=ImportStatus.TAKEN,
        session_id=result.session_id,
        map_id=result.map_id,
        picture=picture,
    )


def _gunzipped(chunks: Iterator[bytes], name: str, *, max_bytes: int) -> Iterator[bytes]:
    """``chunks``, inflated as they come if they are gzip (every member), at most
    :data:`INFLATE_CHUNK_BYTES` at a time and no further than ``max_bytes`` + 1 in all (the one
    byte more tells it inflates further); ExportFileRefused if it is corrupt or inflates
    further."""
    first = b""
    while len(first) < len(GZIP_MAGIC) and (chunk := next(chunks, None)) is not None:
        first += chunk
    if first[:2] != GZIP_MAGIC:
        if first:
            yield first
        yield from chunks
        return
    inflater, started, size = _gzip_member(), False, 0
    try:
        for chunk in itertools.chain([first], chunks):
            data = chunk
            while True:
                most = min(INFLATE_CHUNK_BYTES, max_bytes + 1 - size)  # one byte more tells
                piece = inflater.decompress(data, most)
                started = started or bool(data)
                size += len(piece)
                if size > max_bytes:
                    raise ExportFileRefused(f"{name} inflates to more than {max_bytes} bytes")
                if piece:
                    yield piece
                if inflater.eof:  # the next member, if any, starts in the unused data
                    data, inflater, started = inflater.unused_data, _gzip_member(), False
                    if not data:
                        break
                    continue
                data = inflater.unconsumed_tail
                if not data and len(piece) < most:  # (else output may be pending)
                    break
    except zlib.error as err:
        raise ExportFileRefused(f"{name} is not valid gzip: {err}") from None
    if started:
        raise ExportFileRefused(f"{name} is not valid gzip: cut short")


def _gzip_member() -> Any:
    return zlib.decompressobj(wbits=16 + zlib.MAX_WBITS)


class _KeptUpload:
    """The upload's bytes as they pass to the parser: their SHA-256 and size, and their gzip (what
    is stored), made a chunk at a time so that the plain bytes are never held whole."""

    def __init__(self) -> None:
        self._digest = hashlib.sha256()
        self._size = 0
        self._deflater = zlib.compressobj(GZIP_LEVEL, zlib.DEFLATED, 16 + zlib.MAX_WBITS)
        self._gzip = bytearray()

    def of(self, chunks: Iterator[bytes]) -> Iterator[bytes]:
        """``chunks``, kept as they pass."""
        for chunk in chunks:
            self._digest.update(chunk)
            self._size += len(chunk)
            self._gzip += self._deflater.compress(chunk)
            yield chunk

    def stored(self) -> StoredUpload:
        self._gzip += self._deflater.flush()
        return StoredUpload(
            json_gzip=self._gzip, sha256=self._digest.hexdigest(), size_bytes=self._size
        )


def _picture(entry: FirebaseMap) -> tuple[bytes | None, str]:
    """The recording's JPEG (None if absent or unusable) and what became of it, for the summary."""
    if entry.image_path is None:
        return None, "no picture in the export"
    try:
        data = read_export_file(
            entry.export_folder, entry.image_path, max_bytes=images.MAX_IMAGE_BYTES
        )
    except ExportFileRefused as err:
        return None, f"picture skipped: {err}"
    problem = images.jpeg_problem(data)
    if problem is not None:
        return None, f"picture skipped: {problem}"
    return data, "picture kept"
