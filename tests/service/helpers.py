"""Helpers for database tests: realistic sessions, maps and jobs, and polling with a deadline."""

from __future__ import annotations

import gzip
import hashlib
import json
import time
from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any, TypeVar

from sqlalchemy import func, select, update

from app.domain.evaluation.simulate import SimulationConfig, simulate_session
from app.domain.upload.session import decode_json_bytes, parse_session
from app.storage import maps, queue
from app.storage.db import Database
from app.storage.orm import Job, MapVersion, SessionRow, SessionUpload

REPO_ROOT = Path(__file__).resolve().parents[2]
SESSIONS_DIR = REPO_ROOT / "data" / "sessions"

T = TypeVar("T")


@dataclass(frozen=True, slots=True)
class Inserted:
    """The rows :func:`insert_session` made."""

    session_id: int
    map_id: int
    job_id: int


def session_bytes(name: str) -> bytes:
    """A real session from ``data/sessions`` (``"onetag"``, ``"occam_room"``, …)."""
    return (SESSIONS_DIR / f"{name}.json").read_bytes()


@lru_cache(maxsize=4)
def simulated_bytes(num_poses: int, seed: int = 0) -> bytes:
    """A simulated upload of ``num_poses`` poses, JSON bytes (cached: large ones take seconds)."""
    sim = simulate_session(SimulationConfig(num_poses=num_poses, seed=seed))
    return json.dumps(sim.upload, separators=(",", ":")).encode()


def insert_session(
    db: Database,
    raw: bytes | Path,
    *,
    params: dict[str, Any] | None = None,
    max_attempts: int = 3,
    priority: int = 0,
) -> Inserted:
    """Insert a session row (with every statistic), its gzip upload, a map and a queued
    ``build_map`` job for it, in one transaction, as an upload through the API would."""
    if isinstance(raw, Path):
        raw = raw.read_bytes()
    session = parse_session(decode_json_bytes(raw))
    stored = gzip.compress(raw, compresslevel=1, mtime=0)
    with db.transaction() as tx:
        row = SessionRow(
            map_name=session.map_id,
            uploaded_by="test",
            idempotency_key=None,
            raw_sha256=hashlib.sha256(raw).hexdigest(),
            raw_size_bytes=len(raw),
            stored_size_bytes=len(stored),
            pose_count=session.num_poses,
            detection_count=len(session.detections),
            tag_count=len(session.tag_ids),
            poi_count=len(session.pois),
            duration_s=float(session.timestamp_s[-1] - session.timestamp_s[0]),
            path_length_m=session.path_length_m(),
            tag_ids=session.tag_ids,
            warnings=list(session.warnings),
        )
        tx.add(row)
        tx.flush()
        tx.add(SessionUpload(session_id=row.id, raw_gzip=stored))
        map_id = maps.create_map(tx, name=session.map_id, session_id=row.id)
        job_id = queue.enqueue(
            tx,
            kind="build_map",
            map_id=map_id,
            session_id=row.id,
            params=params,
            max_attempts=max_attempts,
            priority=priority,
        )
    return Inserted(session_id=row.id, map_id=map_id, job_id=job_id)


def replace_stored_upload(db: Database, session_id: int, raw_gzip: bytes) -> None:
    """Overwrite a session's stored (gzip) upload, e.g. with garbage."""
    with db.transaction() as tx:
        tx.execute(
            update(SessionUpload)
            .where(SessionUpload.session_id == session_id)
            .values(raw_gzip=raw_gzip)
        )


def get_job(db: Database, job_id: int) -> queue.JobInfo:
    with db.read() as tx:
        return queue.get_job(tx, job_id)


def version_count(db: Database, **where: Any) -> int:
    """How many map versions there are (``job_id=…``, ``map_id=…`` to narrow)."""
    query = select(func.count()).select_from(MapVersion)
    for name, value in where.items():
        query = query.where(getattr(MapVersion, name) == value)
    with db.read() as tx:
        return tx.scalar(query) or 0


def job_states(db: Database) -> dict[int, str]:
    with db.read() as tx:
        return dict(tx.execute(select(Job.id, Job.state)).all())


def wait_for(
    condition: Callable[[], T | bool | None], *, timeout_s: float, what: str, every_s: float = 0.05
) -> T | bool:
    """Poll ``condition`` until it returns something truthy; after ``timeout_s``, fail naming
    ``what``."""
    deadline_s = time.monotonic() + timeout_s
    while True:
        value = condition()
        if value:
            return value
        if time.monotonic() > deadline_s:
            raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")
        time.sleep(every_s)
