"""Moving a lab's recorded maps over from Firebase: every recording of an export uploaded once.

    export = read_firebase_export(directory)                    # app.domain.formats.firebase_export
    for entry in export.maps:
        outcome = import_recording(db, entry, max_attempts=3, max_session_bytes=…)
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

A recording the server cannot take (no file, not valid JSON, not a session, too large) is
``refused`` with the reason, as an upload would be told; the others are still imported.
"""

from __future__ import annotations

import enum
import hashlib
from dataclasses import dataclass

from app.domain.errors import SessionFormatError
from app.domain.formats.firebase_export import FirebaseMap
from app.domain.json_values import gunzip_if_compressed
from app.domain.upload.session import decode_json_bytes, parse_session
from app.storage import images, sessions
from app.storage.db import Database
from app.storage.sessions import (
    MAX_IDEMPOTENCY_KEY_LENGTH,
    MAX_MAP_NAME_LENGTH,
    IdempotencyConflict,
    StoredUpload,
)

#: ``uploaded_by`` of imported sessions: this prefix and the Firebase uid.
OWNER_PREFIX = "firebase:"
#: Length of the ``uploaded_by`` column.
MAX_OWNER_LENGTH = 64


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
    db: Database, entry: FirebaseMap, *, max_attempts: int, max_session_bytes: int
) -> ImportOutcome:
    """Upload one recording of the export (see the module docstring); never raises for a
    recording the server cannot take (it is ``refused``)."""

    def refused(reason: str) -> ImportOutcome:
        return ImportOutcome(key=entry.key, status=ImportStatus.REFUSED, reason=reason)

    if entry.problem is not None or entry.raw_path is None:
        return refused(entry.problem or "no session file")
    try:
        raw = entry.raw_path.read_bytes()
    except OSError as err:
        return refused(f"cannot read {entry.raw_path.name}: {err.strerror or err}")
    if len(raw) > max_session_bytes:
        return refused(f"the session ({len(raw)} bytes) is larger than {max_session_bytes} bytes")
    try:
        plain = gunzip_if_compressed(raw)
    except ValueError as err:
        return refused(f"{entry.raw_path.name} is not valid gzip: {err}")
    if len(plain) > max_session_bytes:
        return refused(f"the session ({len(plain)} bytes) is larger than {max_session_bytes} bytes")
    try:
        parsed = parse_session(decode_json_bytes(plain, source=entry.raw_path.name))
    except SessionFormatError as err:
        return refused(f"not a session the server takes: {err}")
    if len(parsed.map_id) > MAX_MAP_NAME_LENGTH:
        return refused(f"map_id is longer than {MAX_MAP_NAME_LENGTH} characters")
    upload = StoredUpload.of(plain)
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
    return ImportOutcome(
        key=entry.key,
        status=ImportStatus.TAKEN,
        session_id=result.session_id,
        map_id=result.map_id,
        picture=picture,
    )


def _picture(entry: FirebaseMap) -> tuple[bytes | None, str]:
    """The recording's JPEG (None if absent or unusable) and what became of it, for the summary."""
    if entry.image_path is None:
        return None, "no picture in the export"
    try:
        data = entry.image_path.read_bytes()
    except OSError as err:
        return None, f"picture unreadable: {err.strerror or err}"
    problem = images.jpeg_problem(data)
    if problem is not None:
        return None, f"picture skipped: {problem}"
    return data, "picture kept"
