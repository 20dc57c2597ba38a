"""Helpers of the API tests: a running app on a test database, keys, uploads, and the worker's
stages run in-process (parse → optimize → evaluate → store the version and finish the job in one
transaction), so that maps get versions without a worker process."""

from __future__ import annotations

import gzip
import hashlib
import json
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Any

import httpx2
from fastapi import FastAPI
from fastapi.testclient import TestClient
from sqlalchemy import func, select

from app.config import Settings
from app.domain.evaluation.table import Evaluation, evaluate_map
from app.domain.mapping.map_result import MapResult
from app.domain.mapping.params import SlamParams
from app.domain.mapping.slam import optimize_session
from app.domain.navigation.path_graph import build_path_graph, path_graph_to_json
from app.domain.upload.session import decode_json_bytes, parse_session
from app.main import create_app
from app.storage import keys, maps, queue, sessions
from app.storage.db import Database
from app.storage.orm import Base, Role

ADMIN_KEY = "test-admin-key-0123456789abcdef"
SESSIONS_DIR = Path(__file__).resolve().parents[2] / "data" / "sessions"
ONETAG = SESSIONS_DIR / "onetag.json"
OCCAM = SESSIONS_DIR / "occam_room.json"


def bearer(key: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {key}"}


ADMIN = bearer(ADMIN_KEY)
JSON = {"Content-Type": "application/json"}


@dataclass
class Api:
    """The test client of a running app, its database and settings."""

    app: FastAPI
    client: TestClient
    db: Database
    settings: Settings

    def create_key(
        self, role: Role = Role.DEVICE, *, name: str = "test", expires_at: datetime | None = None
    ) -> tuple[int, str]:
        """A new key straight in the database: (id, secret)."""
        with self.db.transaction() as db_session:
            info, secret = keys.create_key(db_session, name=name, role=role, expires_at=expires_at)
        return info.id, secret

    def device(self) -> dict[str, str]:
        """Headers with a new device key."""
        return bearer(self.create_key(Role.DEVICE)[1])

    def upload(
        self,
        body: bytes | Path,
        *,
        headers: dict[str, str] | None = None,
        auth: dict[str, str] | None = None,
        compress: bool = False,
        idempotency_key: str | None = None,
    ) -> httpx2.Response:
        data = body.read_bytes() if isinstance(body, Path) else body
        sent_headers = {**JSON, **(ADMIN if auth is None else auth)}
        if compress:
            data = gzip.compress(data)
            sent_headers["Content-Encoding"] = "gzip"
        if idempotency_key is not None:
            sent_headers["Idempotency-Key"] = idempotency_key
        sent_headers.update(headers or {})
        return self.client.post("/v1/sessions", content=data, headers=sent_headers)

    def uploaded(self, body: bytes | Path, **kwargs: Any) -> dict[str, Any]:
        """Upload, expect 202, return the body."""
        response = self.upload(body, **kwargs)
        assert response.status_code == 202, response.text
        result: dict[str, Any] = response.json()
        return result

    def count(self, table: type[Base]) -> int:
        with self.db.read() as db_session:
            return db_session.scalar(select(func.count()).select_from(table)) or 0


def onetag(**changes: Any) -> dict[str, Any]:
    """The onetag session's upload as a document, with top-level keys replaced by ``changes``."""
    document: dict[str, Any] = json.loads(ONETAG.read_bytes())
    document.update(changes)
    return document


@contextmanager
def running_api(database_url: str, **settings: Any) -> Iterator[Api]:
    """The app on ``database_url`` with its lifespan running."""
    config = Settings(**{"database_url": database_url, "admin_key": ADMIN_KEY, **settings})
    app = create_app(config)
    with TestClient(app) as client:
        yield Api(app=app, client=client, db=app.state.db, settings=config)


def session_variant(path: Path, **changes: Any) -> bytes:
    """The session in ``path`` with top-level keys changed (e.g. another map_id)."""
    document = json.loads(path.read_bytes())
    document.update(changes)
    return json.dumps(document).encode()


@dataclass(frozen=True)
class _Build:
    """What :func:`run_next_job` computes for an upload (the same on every database)."""

    path_length_m: float
    result: MapResult
    evaluation: Evaluation
    plot_png: bytes | None
    path_graph_json: bytes | None


#: :func:`run_next_job`'s builds by (upload's SHA-256, parameters, plot, path graph), in this
#: test process: a build is deterministic, and most tests build one of a few small sessions once
#: per database (and some a 20,000-pose walk), so the second is the first's (at most 16 kept).
_BUILDS: dict[tuple[str, str, bool, bool], _Build] = {}


def _build(raw: bytes, params: dict[str, Any], *, plot: bool, path_graph: bool) -> _Build:
    key = (hashlib.sha256(raw).hexdigest(), json.dumps(params, sort_keys=True), plot, path_graph)
    if key not in _BUILDS:
        parsed = parse_session(decode_json_bytes(raw))
        result = optimize_session(parsed, SlamParams().with_overrides(params))
        png = None
        if plot:
            from app.render.map_plot import render_map_png

            png = render_map_png(result, parsed)
        graph = path_graph_to_json(build_path_graph(result)) if path_graph else None
        if len(_BUILDS) >= 16:
            _BUILDS.clear()
        _BUILDS[key] = _Build(
            path_length_m=parsed.path_length_m(),
            result=result,
            evaluation=evaluate_map(parsed, result),
            plot_png=png,
            path_graph_json=None if graph is None else json.dumps(graph).encode(),
        )
    return _BUILDS[key]


def run_next_job(db: Database, *, plot: bool = False, path_graph: bool = False) -> int | None:
    """Do what a worker does with the next queued build job; returns its id (None if none).
    The version gets a plot and a path graph only when asked (they take time)."""
    lease = queue.claim(db, worker_id="test-worker", lease_s=60)
    if lease is None:
        return None
    assert lease.session_id is not None
    assert lease.map_id is not None
    with db.read() as db_session:
        raw = sessions.raw_upload(db_session, lease.session_id)
    build = _build(raw, dict(lease.params), plot=plot, path_graph=path_graph)
    with db.transaction() as db_session:
        maps.store_version(
            db_session,
            map_id=lease.map_id,
            job_id=lease.job_id,
            result=build.result,
            evaluation=build.evaluation,
            path_length_m=build.path_length_m,
            plot_png=build.plot_png,
            path_graph=None if build.path_graph_json is None else json.loads(build.path_graph_json),
        )
        queue.finish(db_session, lease, log_tail=lease.log_tail)
    return lease.job_id
