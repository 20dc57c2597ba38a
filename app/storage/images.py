"""The picture the app sends with a session (a JPEG), kept once per session and shown with its map.

    with db.transaction() as tx:
        stored = put_session_image(tx, session_id=7, jpeg=data)   # replaces; same bytes: no change
        stored.changed, stored.sha256
    image = map_image(tx, map_id=3)                               # None without a picture

Checking that the bytes are a JPEG of an accepted size is the caller's (the API's) job:
:func:`jpeg_problem` says what is wrong with them.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass

from sqlalchemy import select
from sqlalchemy.orm import Session

from app.storage.maps import MapNotFound
from app.storage.orm import MapRow, SessionImage, SessionRow, utc_now
from app.storage.sessions import SessionNotFound

#: Largest picture accepted, bytes (the app sends a JPEG of the last camera frame at quality 0:
#: tens of kB).
MAX_IMAGE_BYTES = 4 * 2**20
#: Start Of Image marker and the first byte of the next marker; End Of Image.
JPEG_START = b"\xff\xd8\xff"
JPEG_END = b"\xff\xd9"


@dataclass(frozen=True, slots=True, kw_only=True)
class StoredImage:
    """A session's picture: its SHA-256 and size; ``changed`` False when the same bytes were
    already stored (a repeated PUT)."""

    session_id: int
    sha256: str
    size_bytes: int
    changed: bool


@dataclass(frozen=True, slots=True, kw_only=True)
class MapImage:
    """A map's picture (the JPEG of its session)."""

    jpeg: bytes
    sha256: str


def jpeg_problem(data: bytes, *, max_bytes: int = MAX_IMAGE_BYTES) -> str | None:
    """Why ``data`` is not an acceptable picture, or None."""
    if not data:
        return "the body is empty: send the JPEG's bytes"
    if len(data) > max_bytes:
        return f"the picture ({len(data)} bytes) is larger than the limit of {max_bytes} bytes"
    if not data.startswith(JPEG_START):
        return "the body is not a JPEG (it does not start with the JPEG marker FF D8 FF)"
    if JPEG_END not in data[-64:]:
        return "the JPEG is cut short (no end-of-image marker FF D9)"
    return None


def put_session_image(session: Session, *, session_id: int, jpeg: bytes) -> StoredImage:
    """Store (or replace) the session's picture in the caller's transaction."""
    if session.get(SessionRow, session_id) is None:
        raise SessionNotFound(session_id)
    sha256 = hashlib.sha256(jpeg).hexdigest()
    row = session.get(SessionImage, session_id)
    if row is not None and row.sha256 == sha256:
        return StoredImage(
            session_id=session_id, sha256=sha256, size_bytes=len(jpeg), changed=False
        )
    now = utc_now()
    if row is None:
        session.add(
            SessionImage(
                session_id=session_id,
                jpeg=jpeg,
                sha256=sha256,
                size_bytes=len(jpeg),
                created_at=now,
                updated_at=now,
            )
        )
    else:
        row.jpeg, row.sha256, row.size_bytes, row.updated_at = jpeg, sha256, len(jpeg), now
    session.flush()
    return StoredImage(session_id=session_id, sha256=sha256, size_bytes=len(jpeg), changed=True)


def map_image(session: Session, map_id: int) -> MapImage | None:
    """The picture of the map's session; MapNotFound if there is no such map."""
    map_row = session.get(MapRow, map_id)
    if map_row is None:
        raise MapNotFound(map_id)
    row = session.execute(
        select(SessionImage.jpeg, SessionImage.sha256).where(
            SessionImage.session_id == map_row.session_id
        )
    ).first()
    return None if row is None else MapImage(jpeg=row.jpeg, sha256=row.sha256)
