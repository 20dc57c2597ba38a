"""Mapping sessions as uploaded: the statistics row and the raw upload (gzip, written once)."""

from __future__ import annotations

import gzip

from sqlalchemy.orm import Session

from app.storage.orm import SessionUpload


class SessionNotFound(LookupError):
    """Raised when no session has the given id."""

    def __init__(self, session_id: int) -> None:
        super().__init__(f"session {session_id} not found")
        self.session_id = session_id


def raw_upload(session: Session, session_id: int) -> bytes:
    """The upload exactly as the client sent it (after undoing any ``Content-Encoding``)."""
    row = session.get(SessionUpload, session_id)
    if row is None:
        raise SessionNotFound(session_id)
    return gzip.decompress(row.raw_gzip)
