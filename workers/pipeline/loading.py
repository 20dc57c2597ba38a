"""The ``load`` stage of build_map: the job's parameters checked, and each session's stored
upload read back a piece at a time and parsed (:func:`load_session_upload`, the sweep's too).

A building map's build reads every walk of the map, and parsing them is what a build of a big
map spends most of its ``load`` stage on (0.12 s a walk of 1,200 poses; 3.5 s at 30 walks). A
stored upload never changes, so a worker process keeps the walks it parsed for the next build
of the same map (:data:`PARSED_SESSIONS`, by database, session id and the upload's SHA-256,
at most :data:`PARSED_SESSIONS_MAX_POSES` poses, least recently used out first); their arrays
are read-only, so that no stage can change what the next build reads.
"""

from __future__ import annotations

import dataclasses
import sys
import zlib
from collections import OrderedDict
from collections.abc import Iterable, Iterator
from typing import Any

import numpy as np

from app.domain.evaluation.ground_truth import parse_ground_truth_json
from app.domain.mapping.params import SlamParams
from app.domain.upload.json_stream import gunzipped
from app.domain.upload.session import Session, parse_session_stream, require_tags
from app.storage.db import Database
from app.storage.sessions import (
    AUTO_TUNE_TRIALS,
    GROUND_TRUTH,
    SESSION_IDS,
    STORED_PIECE_BYTES,
    SessionNotFound,
    raw_sha256s,
    raw_upload_gzip_pieces,
)

from .context import JobContext, PermanentJobError

#: Per worker process, the walks of building maps parsed lately, by (database, session id,
#: the upload's SHA-256), most recently used last (the module docstring).
PARSED_SESSIONS: OrderedDict[tuple[str, int, str], Session] = OrderedDict()
#: At most this many poses in :data:`PARSED_SESSIONS` (≈ 200 walks of 2 minutes; ~0.3 kB a pose
#: with its share of detections).
PARSED_SESSIONS_MAX_POSES = 250_000


def load(ctx: JobContext) -> None:
    """Check the parameters, read the session's raw upload and parse it."""
    lease = ctx.lease
    if lease.session_id is None or lease.map_id is None:
        raise PermanentJobError(f"a {lease.kind} job needs a session and a map")
    overrides = dict(lease.params)
    ctx.map_generation = lease.map_generation
    ctx.auto_tune_trials = _auto_tune_trials(overrides.pop(AUTO_TUNE_TRIALS, 0))
    ctx.session_ids = _session_ids(overrides.pop(SESSION_IDS, None), lease.session_id)
    if (ground_truth := overrides.pop(GROUND_TRUTH, None)) is not None:
        ctx.ground_truth = parse_ground_truth_json(ground_truth)  # checked by the API already
    ctx.params = SlamParams().with_overrides(overrides)
    if len(ctx.session_ids) > 1:
        if ctx.auto_tune_trials:
            raise PermanentJobError(f"{AUTO_TUNE_TRIALS} is for maps of one session")
        ctx.sessions.extend(load_walks(ctx, ctx.session_ids))
        return
    size_bytes, ctx.session = load_session_upload(ctx.db, lease.session_id)
    session = ctx.session
    require_tags(session)  # before any tuning: a walk with no tag makes no map
    ctx.log(
        f"load: {session.num_poses} poses, {len(session.detections)} detections of "
        f"{len(session.tag_ids)} tags, {size_bytes / 1e6:.2f} MB"
    )


def load_walks(ctx: JobContext, session_ids: list[int]) -> list[Session]:
    """The walks of a building map, each from this process's cache of parsed sessions when it
    holds that upload (:data:`PARSED_SESSIONS`), else read and parsed (and kept); a line each
    in the job's log."""
    db = ctx.db
    with db.read() as tx:
        digests = raw_sha256s(tx, session_ids)
    walks, kept = [], 0
    for session_id in session_ids:
        key = parsed_session_key(db, session_id, digests.get(session_id, ""))
        session = PARSED_SESSIONS.get(key)
        if session is not None:
            PARSED_SESSIONS.move_to_end(key)
            kept += 1
        else:
            size_bytes, session = load_session_upload(db, session_id)
            ctx.log(
                f"load: session {session_id}: {session.num_poses} poses, "
                f"{len(session.detections)} detections of {len(session.tag_ids)} tags, "
                f"{size_bytes / 1e6:.2f} MB"
            )
            if key[2]:
                PARSED_SESSIONS[key] = _read_only(session)
        walks.append(session)
    _bound_parsed_sessions()
    if kept:
        ctx.log(f"load: {kept} of {len(session_ids)} sessions as this worker parsed them before")
    return walks


def parsed_session_key(db: Database, session_id: int, digest: str) -> tuple[str, int, str]:
    """A stored upload's key in :data:`PARSED_SESSIONS`: its database, session id and SHA-256
    (``digest``, "" when the session is not stored: never kept)."""
    return (db.url.render_as_string(hide_password=True), session_id, digest)


def _read_only(session: Session) -> Session:
    """``session`` with every array it holds made read-only (in place: it was just parsed)."""
    for holder in (session, session.detections):
        for field in dataclasses.fields(holder):
            value = getattr(holder, field.name)
            if isinstance(value, np.ndarray):
                value.setflags(write=False)
    return session


def _bound_parsed_sessions() -> None:
    total = sum(s.num_poses for s in PARSED_SESSIONS.values())
    while PARSED_SESSIONS and total > PARSED_SESSIONS_MAX_POSES:
        _, oldest = PARSED_SESSIONS.popitem(last=False)
        total -= oldest.num_poses


def _session_ids(value: Any, session_id: int) -> list[int]:
    if value is None:
        return [session_id]
    if (
        not isinstance(value, list)
        or not value
        or not all(isinstance(v, int) and not isinstance(v, bool) for v in value)
        or len(set(value)) != len(value)
    ):
        raise PermanentJobError(
            f"{SESSION_IDS} must be a list of distinct session ids, got {value!r}"
        )
    return list(value)


def _auto_tune_trials(value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= 1000:
        raise PermanentJobError(f"{AUTO_TUNE_TRIALS} must be an integer 0–1000, got {value!r}")
    return value


def load_session_upload(db: Database, session_id: int) -> tuple[int, Session]:
    """A session's stored upload parsed as it is read from the database a piece at a time and
    inflated (``parse_session_stream``: never the whole JSON, nor its object graph, in memory);
    its size (bytes of JSON) and the parse. PermanentJobError if missing or corrupt."""
    inflated: list[int] = []
    try:
        with db.read() as tx:
            session = parse_session_stream(
                _counted(
                    gunzipped(
                        raw_upload_gzip_pieces(tx, session_id, STORED_PIECE_BYTES),
                        STORED_PIECE_BYTES,
                        complete=True,
                    ),
                    inflated,
                ),
                max_poses=sys.maxsize,  # accepted once, within the limit there was then
                source=f"stored upload of session {session_id}",
            )
    except SessionNotFound as err:
        raise PermanentJobError(f"the raw upload of session {session_id} is missing") from err
    except (EOFError, zlib.error) as err:
        raise PermanentJobError(
            f"the stored upload of session {session_id} is corrupt (not valid gzip: {err})"
        ) from err
    return sum(inflated), session


def _counted(pieces: Iterable[bytes], lengths: list[int]) -> Iterator[bytes]:
    """``pieces``, each one's length appended to ``lengths`` as it passes."""
    for piece in pieces:
        lengths.append(len(piece))
        yield piece
