"""A version's derived documents made from what is stored
(``app.domain.formats.derived_documents``): for versions that arrive without them, such as those
restored from a backup (the archive does not carry them), so that the API serves them as stored
instead of building them per process.

    add_derived_documents(db_session, version_id)   # in the caller's transaction (an import)

The worker makes them from what it has in memory (``workers.pipeline.derived_documents``); this
reads the version's map document, path graph and session back, the same inputs the API would use.
"""

from __future__ import annotations

import gzip
import json

from sqlalchemy.orm import Session

from app.domain.formats.derived_documents import APP_MAP_EXPORT, packed_documents
from app.domain.formats.map_io import map_from_json
from app.domain.navigation.path_graph import path_graph_from_json
from app.domain.upload.session import Session as ParsedSession
from app.storage import blobs, maps, sessions
from app.storage.orm import MapRow, MapVersion


def add_derived_documents(db_session: Session, version_id: int) -> None:
    """Make version ``version_id``'s app-map and overview from its stored map document, path
    graph and (a map of one session) its session's upload, store them as blobs and refer the
    version to them, in the caller's transaction. A version without a map document is left as
    it is (the API says so when asked)."""
    row = db_session.get(MapVersion, version_id)
    if row is None:
        raise maps.MapNotFound(0, None)
    packed = maps.version_bytes(db_session, row.map_json_gzip, row.map_json_sha256)
    if packed is None:
        return
    stored = map_from_json(json.loads(gzip.decompress(packed)))
    del packed
    packed_graph = maps.version_bytes(db_session, row.path_graph_gzip, row.path_graph_sha256)
    graph = (
        None
        if packed_graph is None
        else path_graph_from_json(json.loads(gzip.decompress(packed_graph)))
    )
    contributions = list(row.statistics.get("sessions") or [])
    raw = None
    if len(contributions) < 2:
        map_row = db_session.get(MapRow, row.map_id)
        session_ids = list(row.session_ids or ([map_row.session_id] if map_row else []))
        raw = _stored_session(db_session, session_ids[0]) if session_ids else None
    app_map_gzip, overview_gzip = packed_documents(stored, raw, graph, sessions=contributions)
    row.app_map_sha256 = blobs.put_blob_in(db_session, app_map_gzip)
    row.app_map_export = APP_MAP_EXPORT
    row.overview_sha256 = blobs.put_blob_in(db_session, overview_gzip)
    db_session.flush()


def _stored_session(db_session: Session, session_id: int) -> ParsedSession | None:
    """The session's stored upload parsed as it is read a piece at a time; None without one."""
    try:
        return sessions.parsed_upload(db_session, session_id)
    except sessions.SessionNotFound:
        return None
