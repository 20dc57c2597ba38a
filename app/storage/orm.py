"""SQLAlchemy 2 models. Alembic migrations in ``migrations/`` create these tables (never
``create_all``); ``tests/migrations`` checks that the two agree.

Tables (singular, snake_case): ``api_key`` with its dashboard logins (``admin_login``),
``session`` with its ``session_upload`` (the raw upload, gzip-compressed, written once), ``map``,
``map_version`` with one ``map_tag`` row per tag, ``blob`` with its ``blob_chunk`` rows (a
version's bulk data, content-addressed), ``job`` (the queue) and ``worker`` (who is alive
and what it runs), ``localization``, ``sweep`` with one ``sweep_trial`` row per finished trial,
``session_image`` (the app's picture of a session's map), ``corridor_edit`` (an operator's
corrections of a map's corridor graph), ``job_stage`` (how long each stage of a job took), and
``isam_state`` with its ``isam_walk_state`` rows (what makes a building map's next version
incremental, issue 38).
"""

from __future__ import annotations

import enum
from datetime import UTC, datetime
from typing import Any, ClassVar

from sqlalchemy import (
    JSON,
    CheckConstraint,
    Dialect,
    Float,
    ForeignKey,
    Index,
    LargeBinary,
    MetaData,
    String,
    Text,
    UniqueConstraint,
    text,
)
from sqlalchemy.dialects.postgresql import JSONB
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column
from sqlalchemy.types import DateTime, TypeDecorator

NAMING_CONVENTION = {
    "ix": "ix_%(column_0_label)s",
    "uq": "uq_%(table_name)s_%(column_0_N_name)s",
    "ck": "ck_%(table_name)s_%(constraint_name)s",
    "fk": "fk_%(table_name)s_%(column_0_name)s_%(referred_table_name)s",
    "pk": "pk_%(table_name)s",
}


class UTCDateTime(TypeDecorator[datetime]):
    """A timezone-aware UTC datetime on every backend.

    PostgreSQL stores ``timestamptz``; SQLite has no time zones, so the value is stored as naive
    UTC (fixed-width text, which compares in time order) and given back its UTC zone on the way out.
    """

    impl = DateTime(timezone=True)
    cache_ok = True

    def process_bind_param(self, value: datetime | None, dialect: Dialect) -> datetime | None:
        if value is None:
            return None
        if value.tzinfo is None:
            raise ValueError(f"naive datetime {value!r}: use timezone-aware UTC datetimes")
        value = value.astimezone(UTC)
        return value.replace(tzinfo=None) if dialect.name == "sqlite" else value

    def process_result_value(
        self,
        value: datetime | None,
        dialect: Dialect,  # noqa: ARG002
    ) -> datetime | None:
        if value is None:
            return None
        return value.replace(tzinfo=UTC) if value.tzinfo is None else value.astimezone(UTC)


JSONValue = JSON().with_variant(JSONB(), "postgresql")


class Base(DeclarativeBase):
    metadata = MetaData(naming_convention=NAMING_CONVENTION)
    type_annotation_map: ClassVar[dict[Any, Any]] = {
        datetime: UTCDateTime(),
        dict[str, Any]: JSONValue,
    }


def utc_now() -> datetime:
    return datetime.now(UTC)


class Role(enum.StrEnum):
    """What an API key may do."""

    #: upload sessions and read maps (the phone app)
    DEVICE = "device"
    #: everything a device may, plus manage jobs, maps and keys
    ADMIN = "admin"


class JobState(enum.StrEnum):
    """A job's life: queued → running → succeeded | failed | canceled (retry: back to queued)."""

    #: waiting for a worker (possibly not before ``run_after``)
    QUEUED = "queued"
    #: claimed by a worker holding a lease
    RUNNING = "running"
    #: finished; its result is stored
    SUCCEEDED = "succeeded"
    #: failed for good (a permanent error, or ``max_attempts`` transient ones)
    FAILED = "failed"
    #: canceled before or while running
    CANCELED = "canceled"


#: SQLite reuses the largest rowid after a delete unless a table says AUTOINCREMENT; a phone that
#: kept "map 5" must never get another building's map 5. (PostgreSQL sequences never reuse.)
NEVER_REUSE_IDS = {"sqlite_autoincrement": True}

TERMINAL_STATES = frozenset({JobState.SUCCEEDED, JobState.FAILED, JobState.CANCELED})


def _in(column: str, values: list[str]) -> str:
    return f"{column} IN ({', '.join(repr(v) for v in values)})"


class ApiKey(Base):
    """An API key. Only a SHA-256 of its secret part is stored; ``prefix`` finds the row."""

    __tablename__ = "api_key"
    __table_args__ = (
        CheckConstraint(_in("role", [r.value for r in Role]), name="role"),
        NEVER_REUSE_IDS,
    )

    id: Mapped[int] = mapped_column(primary_key=True)
    name: Mapped[str] = mapped_column(String(100))
    role: Mapped[str] = mapped_column(String(16))
    prefix: Mapped[str] = mapped_column(String(16), unique=True)
    secret_sha256: Mapped[str] = mapped_column(String(64))
    created_at: Mapped[datetime] = mapped_column(default=utc_now)
    expires_at: Mapped[datetime | None]
    revoked_at: Mapped[datetime | None]
    last_used_at: Mapped[datetime | None]


class AdminLogin(Base):
    """A login to the admin dashboard (``app.admin.auth``), kept on the server so that logging
    out, revoking the key that opened it, or "end all dashboard sessions" ends it for good (a
    copied cookie is worth nothing once its row is gone). Only a SHA-256 of the login's token is
    stored; the cookie carries the token. ``key_id`` is null for ``INVISIBLE_MAP_ADMIN_KEY``."""

    __tablename__ = "admin_login"

    id: Mapped[int] = mapped_column(primary_key=True)
    token_sha256: Mapped[str] = mapped_column(String(64), unique=True)
    key_id: Mapped[int | None] = mapped_column(
        ForeignKey("api_key.id", ondelete="CASCADE"), index=True
    )
    subject: Mapped[str] = mapped_column(String(64))
    created_at: Mapped[datetime] = mapped_column(default=utc_now)
    expires_at: Mapped[datetime]


class SessionRow(Base):
    """A mapping session as uploaded, with statistics computed when it was parsed."""

    __tablename__ = "session"
    __table_args__ = (
        UniqueConstraint("uploaded_by", "idempotency_key"),
        # a key's uploads of the last minute (the upload rate limit, across API processes)
        Index("ix_session_uploaded_by_created_at", "uploaded_by", "created_at"),
        NEVER_REUSE_IDS,
    )

    id: Mapped[int] = mapped_column(primary_key=True)
    map_name: Mapped[str] = mapped_column(String(200))
    created_at: Mapped[datetime] = mapped_column(default=utc_now)
    uploaded_by: Mapped[str] = mapped_column(String(64))
    idempotency_key: Mapped[str | None] = mapped_column(String(200))
    raw_sha256: Mapped[str] = mapped_column(String(64))
    raw_size_bytes: Mapped[int]
    stored_size_bytes: Mapped[int]
    pose_count: Mapped[int]
    detection_count: Mapped[int]
    tag_count: Mapped[int]
    poi_count: Mapped[int]
    duration_s: Mapped[float] = mapped_column(Float)
    path_length_m: Mapped[float] = mapped_column(Float)
    tag_ids: Mapped[list[int]] = mapped_column(JSONValue)
    warnings: Mapped[list[str]] = mapped_column(JSONValue)


class SessionUpload(Base):
    """The raw upload, gzip-compressed, written once and never changed."""

    __tablename__ = "session_upload"

    session_id: Mapped[int] = mapped_column(
        ForeignKey("session.id", ondelete="CASCADE"), primary_key=True
    )
    raw_gzip: Mapped[bytes] = mapped_column(LargeBinary)


class MapRow(Base):
    """A map, in versions (the latest succeeded one is current). ``session_id`` is its first
    (reference) session; ``map_session`` lists all the sessions it is made of."""

    __tablename__ = "map"
    __table_args__ = (NEVER_REUSE_IDS,)

    id: Mapped[int] = mapped_column(primary_key=True)
    #: the upload's ``map_id``
    name: Mapped[str] = mapped_column(String(200))
    #: the name people see (an admin may change it); null: derived from ``name``
    display_name: Mapped[str | None] = mapped_column(String(200))
    session_id: Mapped[int] = mapped_column(
        ForeignKey("session.id", ondelete="CASCADE"), index=True
    )
    created_at: Mapped[datetime] = mapped_column(default=utc_now)
    #: bumped by every change of what the next version is to be built from (its sessions, a
    #: rebuild's parameters); a build stores its version only if this is still the generation
    #: it was queued for (``app.storage.maps.bump_generation``, docs/multi-session.md)
    generation: Mapped[int] = mapped_column(default=0, server_default=text("0"))
    #: grows by one with every corridor edit added or deleted (``corridor_edit``): what the
    #: API's per-process caches of edited graphs and documents are keyed by, and the lock that
    #: puts two operators' edits of one map one after the other
    corridor_edits_revision: Mapped[int] = mapped_column(default=0, server_default=text("0"))


class CorridorEditRow(Base):
    """An operator's correction of a map's corridor graph (issue 27,
    ``app.domain.navigation.corridor_edits``): kept per map, applied to every version of it.
    ``edit`` is the edit's JSON (``{"op": "quiet", "at": [x, y, z]}``, …); ``created_by`` who
    made it (``key:<id>`` or the server's admin key) and ``created_by_name`` that key's name."""

    __tablename__ = "corridor_edit"
    __table_args__ = (NEVER_REUSE_IDS,)

    id: Mapped[int] = mapped_column(primary_key=True)
    map_id: Mapped[int] = mapped_column(ForeignKey("map.id", ondelete="CASCADE"), index=True)
    edit: Mapped[dict[str, Any]]
    created_by: Mapped[str] = mapped_column(String(64))
    created_by_name: Mapped[str | None] = mapped_column(String(100))
    created_at: Mapped[datetime] = mapped_column(default=utc_now)


class SessionImage(Base):
    """The picture the app sends with a session (a JPEG), shown with the session's map."""

    __tablename__ = "session_image"

    session_id: Mapped[int] = mapped_column(
        ForeignKey("session.id", ondelete="CASCADE"), primary_key=True
    )
    jpeg: Mapped[bytes] = mapped_column(LargeBinary)
    sha256: Mapped[str] = mapped_column(String(64))
    size_bytes: Mapped[int]
    created_at: Mapped[datetime] = mapped_column(default=utc_now)
    updated_at: Mapped[datetime] = mapped_column(default=utc_now)


class MapSession(Base):
    """A session a map is made of (a building's map holds several; docs/multi-session.md). The
    order of ``id`` is the order they are optimized in: the first is the reference frame."""

    __tablename__ = "map_session"
    __table_args__ = (UniqueConstraint("map_id", "session_id"),)

    id: Mapped[int] = mapped_column(primary_key=True)
    map_id: Mapped[int] = mapped_column(ForeignKey("map.id", ondelete="CASCADE"), index=True)
    session_id: Mapped[int] = mapped_column(
        ForeignKey("session.id", ondelete="CASCADE"), index=True
    )
    added_at: Mapped[datetime] = mapped_column(default=utc_now)


class Job(Base):
    """A unit of work in the durable queue. Every state change is one committed transaction.

    ``lease_token`` grows by one at every claim; a worker's writes name the token they hold, so a
    worker whose lease expired (and whose job was requeued or claimed again) cannot write.
    """

    __tablename__ = "job"
    __table_args__ = (
        CheckConstraint(_in("state", [s.value for s in JobState]), name="state"),
        CheckConstraint("progress >= 0 AND progress <= 1", name="progress"),
        Index("ix_job_claim", "state", "run_after", "priority"),
        NEVER_REUSE_IDS,
    )

    id: Mapped[int] = mapped_column(primary_key=True)
    kind: Mapped[str] = mapped_column(String(32))
    state: Mapped[str] = mapped_column(String(16), default=JobState.QUEUED.value)
    map_id: Mapped[int | None] = mapped_column(ForeignKey("map.id", ondelete="CASCADE"), index=True)
    session_id: Mapped[int | None] = mapped_column(
        ForeignKey("session.id", ondelete="CASCADE"), index=True
    )
    params: Mapped[dict[str, Any]] = mapped_column(default=dict)
    priority: Mapped[int] = mapped_column(default=0)
    attempts: Mapped[int] = mapped_column(default=0)
    max_attempts: Mapped[int] = mapped_column(default=3)
    run_after: Mapped[datetime] = mapped_column(default=utc_now)
    lease_owner: Mapped[str | None] = mapped_column(String(100))
    lease_token: Mapped[int] = mapped_column(default=0)
    lease_expires_at: Mapped[datetime | None]
    cancel_requested: Mapped[bool] = mapped_column(default=False)
    #: the sweep whose trials a ``sweep_trials`` job runs (no foreign key: the map's cascade
    #: removes both)
    sweep_id: Mapped[int | None] = mapped_column(index=True)
    #: a ``build_map`` job: the map's generation it builds (``map.generation``); its version is
    #: stored only while that is still the map's. Null: queued before generations (as 0)
    map_generation: Mapped[int | None]
    progress: Mapped[float] = mapped_column(Float, default=0.0)
    stage: Mapped[str | None] = mapped_column(String(32))
    error: Mapped[str | None] = mapped_column(Text)
    log_tail: Mapped[str] = mapped_column(Text, default="")
    created_at: Mapped[datetime] = mapped_column(default=utc_now)
    started_at: Mapped[datetime | None]
    finished_at: Mapped[datetime | None]
    updated_at: Mapped[datetime] = mapped_column(default=utc_now)


class JobStageRun(Base):
    """One stage of one attempt at a job that ran to its end, and how long it took: what the
    ``/metrics`` stage durations are counted from (``app.storage.job_metrics``). The worker
    writes an attempt's stages when the attempt ends; they are deleted with their job."""

    __tablename__ = "job_stage"

    id: Mapped[int] = mapped_column(primary_key=True)
    job_id: Mapped[int] = mapped_column(ForeignKey("job.id", ondelete="CASCADE"), index=True)
    kind: Mapped[str] = mapped_column(String(32))
    stage: Mapped[str] = mapped_column(String(32))
    attempt: Mapped[int]
    duration_s: Mapped[float] = mapped_column(Float)
    finished_at: Mapped[datetime] = mapped_column(default=utc_now)


class MapVersion(Base):
    """One optimization of a map's session: the result, its parameters, statistics and metrics."""

    __tablename__ = "map_version"
    __table_args__ = (UniqueConstraint("map_id", "number"), NEVER_REUSE_IDS)

    id: Mapped[int] = mapped_column(primary_key=True)
    map_id: Mapped[int] = mapped_column(ForeignKey("map.id", ondelete="CASCADE"), index=True)
    number: Mapped[int]
    job_id: Mapped[int | None] = mapped_column(
        ForeignKey("job.id", ondelete="SET NULL"), unique=True
    )
    created_at: Mapped[datetime] = mapped_column(default=utc_now)
    params: Mapped[dict[str, Any]]
    statistics: Mapped[dict[str, Any]]
    metrics: Mapped[dict[str, Any]]
    shift_metric: Mapped[float | None] = mapped_column(Float)
    tag_count: Mapped[int]
    detections_used: Mapped[int]
    detections_rejected: Mapped[int]
    rejections: Mapped[list[dict[str, Any]]] = mapped_column(JSONValue)
    warnings: Mapped[list[str]] = mapped_column(JSONValue)
    #: the map document, gzip, held in the row itself: versions stored before the ``blob``
    #: table (and restored from archives); null when ``map_json_sha256`` names its blob
    map_json_gzip: Mapped[bytes | None] = mapped_column(LargeBinary)
    plot_png: Mapped[bytes | None] = mapped_column(LargeBinary)
    content_sha256: Mapped[str] = mapped_column(String(64))
    #: ``app.domain.navigation.path_graph.path_graph_to_json``, gzip; null for versions built before
    #: it
    path_graph_gzip: Mapped[bytes | None] = mapped_column(LargeBinary)
    #: the blobs (``blob.sha256``) holding the map document (gzip), the plot and the path graph
    #: (gzip) of versions stored since the ``blob`` table: written before the small transaction
    #: that stores the row (``app.storage.blobs``); null where the row holds the bytes itself
    map_json_sha256: Mapped[str | None] = mapped_column(ForeignKey("blob.sha256"), index=True)
    plot_png_sha256: Mapped[str | None] = mapped_column(ForeignKey("blob.sha256"), index=True)
    path_graph_sha256: Mapped[str | None] = mapped_column(ForeignKey("blob.sha256"), index=True)
    #: what the worker derived from the version when it stored it (issue 19, finding 3): the
    #: app's map file (gzip), made by export ``app_map_export``
    #: (``app.domain.formats.derived_documents.APP_MAP_EXPORT``), and the dashboard's overview (gzip
    #: JSON); null for versions stored before (an import makes them): the API builds them
    app_map_sha256: Mapped[str | None] = mapped_column(ForeignKey("blob.sha256"), index=True)
    app_map_export: Mapped[int | None]
    overview_sha256: Mapped[str | None] = mapped_column(ForeignKey("blob.sha256"), index=True)
    #: the sessions it was optimized from, in order (the first is the reference frame); null for
    #: versions built before maps held several sessions (their map's ``session_id`` alone)
    session_ids: Mapped[list[int] | None] = mapped_column(JSONValue)
    #: the map's ``generation`` it was built for (it was the map's generation when it was
    #: stored); null for versions stored before generations
    generation: Mapped[int | None]


class IsamStateRow(Base):
    """What makes a building map's ISAM2 tree again (issue 38; ``app.domain.mapping.incremental
    .isam_state.IsamState.to_dict``), stored with the map version it was made for: the building's
    row here, one :class:`IsamWalkStateRow` per walk. Plain values and ``.npz`` bytes, never
    pickle. Derivable (a batch build makes it again), so backups skip it; deleted with its
    version (and so with its map)."""

    __tablename__ = "isam_state"

    map_version_id: Mapped[int] = mapped_column(
        ForeignKey("map_version.id", ondelete="CASCADE"), primary_key=True, autoincrement=False
    )
    map_id: Mapped[int] = mapped_column(ForeignKey("map.id", ondelete="CASCADE"), index=True)
    format: Mapped[str] = mapped_column(String(32))
    #: ``building_fingerprint`` of its walks and parameters (SHA-256, hex)
    fingerprint: Mapped[str] = mapped_column(String(64))
    params: Mapped[dict[str, Any]]
    walk_ids: Mapped[list[str]] = mapped_column(JSONValue)
    walk_fingerprints: Mapped[list[str]] = mapped_column(JSONValue)
    next_key: Mapped[int]
    #: ``.npz``: tag_ids (T,), map_T_tag (T, 3, 4) m
    arrays: Mapped[bytes] = mapped_column(LargeBinary)
    created_at: Mapped[datetime] = mapped_column(default=utc_now)


class IsamWalkStateRow(Base):
    """One walk of an :class:`IsamStateRow` (``IsamWalkState.to_dict``), ``position`` its place
    in the map's order."""

    __tablename__ = "isam_walk_state"

    map_version_id: Mapped[int] = mapped_column(
        ForeignKey("isam_state.map_version_id", ondelete="CASCADE"),
        primary_key=True,
        autoincrement=False,
    )
    position: Mapped[int] = mapped_column(primary_key=True, autoincrement=False)
    walk_id: Mapped[str] = mapped_column(String(100))
    fingerprint: Mapped[str] = mapped_column(String(64))
    depth_scale: Mapped[float] = mapped_column(Float)
    cost_alone: Mapped[float] = mapped_column(Float)
    key_offset: Mapped[int]
    #: ``.npz``: noise_scales (4,), map_T_world (3, 4), keyframes (K,), map_T_keyframe (K, 3, 4)
    arrays: Mapped[bytes] = mapped_column(LargeBinary)


class Blob(Base):
    """Bulk data stored by its SHA-256 (``app.storage.blobs``), in ``blob_chunk`` rows each
    written in a transaction of its own, so that no write transaction holds a large write.
    ``complete`` is set with the last chunk; ``touched_at`` is when it was last written or
    found present by a writer (blobs nobody refers to are collected a while after it)."""

    __tablename__ = "blob"

    sha256: Mapped[str] = mapped_column(String(64), primary_key=True)
    size_bytes: Mapped[int]
    chunk_count: Mapped[int]
    complete: Mapped[bool] = mapped_column(default=False)
    touched_at: Mapped[datetime] = mapped_column(default=utc_now, index=True)


class BlobChunk(Base):
    """A piece of a blob: ``number`` 0, 1, … in order, each at most ``blobs.CHUNK_BYTES``."""

    __tablename__ = "blob_chunk"

    sha256: Mapped[str] = mapped_column(
        ForeignKey("blob.sha256", ondelete="CASCADE"), primary_key=True
    )
    number: Mapped[int] = mapped_column(primary_key=True, autoincrement=False)
    data: Mapped[bytes] = mapped_column(LargeBinary)


class MapTag(Base):
    """A tag's optimized pose in one map version (so "which maps have tag 305?" is a query)."""

    __tablename__ = "map_tag"
    __table_args__ = (UniqueConstraint("map_version_id", "tag_id"),)

    id: Mapped[int] = mapped_column(primary_key=True)
    map_version_id: Mapped[int] = mapped_column(ForeignKey("map_version.id", ondelete="CASCADE"))
    tag_id: Mapped[int] = mapped_column(index=True)
    x_m: Mapped[float] = mapped_column(Float)
    y_m: Mapped[float] = mapped_column(Float)
    z_m: Mapped[float] = mapped_column(Float)
    qx: Mapped[float] = mapped_column(Float)
    qy: Mapped[float] = mapped_column(Float)
    qz: Mapped[float] = mapped_column(Float)
    qw: Mapped[float] = mapped_column(Float)
    detection_count: Mapped[int]
    #: 6×6 covariance, [rotation rad, translation m] in the tag frame, row-major; null if unknown
    covariance: Mapped[list[float] | None] = mapped_column(JSONValue)


class WorkerRow(Base):
    """A worker process, as it last reported itself."""

    __tablename__ = "worker"

    id: Mapped[str] = mapped_column(String(100), primary_key=True)
    hostname: Mapped[str] = mapped_column(String(255))
    pid: Mapped[int]
    started_at: Mapped[datetime] = mapped_column(default=utc_now)
    heartbeat_at: Mapped[datetime] = mapped_column(default=utc_now)
    current_job_id: Mapped[int | None]
    jobs_done: Mapped[int] = mapped_column(default=0)
    state: Mapped[str] = mapped_column(String(16), default="idle")


class Localization(Base):
    """A live navigation session: a phone localizing itself in one map version.

    ``state`` is the localizer's JSON state (``app.domain.localize``); ``revision`` grows by one
    per update, and an update commits only if the revision it read is still current, so two API
    processes never interleave updates of one session.
    """

    __tablename__ = "localization"
    __table_args__ = (NEVER_REUSE_IDS,)

    id: Mapped[int] = mapped_column(primary_key=True)
    map_id: Mapped[int] = mapped_column(ForeignKey("map.id", ondelete="CASCADE"), index=True)
    map_version_id: Mapped[int] = mapped_column(ForeignKey("map_version.id", ondelete="CASCADE"))
    created_by: Mapped[str] = mapped_column(String(64))
    created_at: Mapped[datetime] = mapped_column(default=utc_now)
    updated_at: Mapped[datetime] = mapped_column(default=utc_now)
    revision: Mapped[int] = mapped_column(default=0)
    status: Mapped[str] = mapped_column(String(32))
    update_count: Mapped[int] = mapped_column(default=0)
    state: Mapped[dict[str, Any]]


class Sweep(Base):
    """A hyperparameter sweep of one map's session (``app.domain.evaluation.tuning``).

    Its trials run as ``sweep_trials`` jobs; ``trials_started`` counts the trials handed to jobs
    so far (all of a grid's at once; a sampler's a batch at a time). ``ground_truth`` is the
    ground-truth file form (``{"poses": [...]}``) or null; ``baseline`` the pre-optimized map's
    metrics. ``state`` is ``running`` until every trial is stored (``succeeded``) or a job of it
    failed or was canceled.
    """

    __tablename__ = "sweep"
    __table_args__ = (NEVER_REUSE_IDS,)

    id: Mapped[int] = mapped_column(primary_key=True)
    map_id: Mapped[int] = mapped_column(ForeignKey("map.id", ondelete="CASCADE"), index=True)
    session_id: Mapped[int] = mapped_column(ForeignKey("session.id", ondelete="CASCADE"))
    method: Mapped[str] = mapped_column(String(16))
    objective: Mapped[str] = mapped_column(String(16))
    space: Mapped[dict[str, Any]]
    base_params: Mapped[dict[str, Any]]
    trials_total: Mapped[int]
    trials_started: Mapped[int] = mapped_column(default=0)
    batch: Mapped[int]
    seed: Mapped[int] = mapped_column(default=0)
    ground_truth: Mapped[dict[str, Any] | None] = mapped_column(JSONValue)
    baseline: Mapped[dict[str, Any] | None] = mapped_column(JSONValue)
    state: Mapped[str] = mapped_column(String(16), default="running")
    #: which definition of the shift metric its trials were scored with
    #: (``app.domain.evaluation.metrics.SHIFT_METRIC_VERSION``); sweeps stored before the column are
    #: 1
    shift_metric_version: Mapped[int] = mapped_column(server_default=text("1"))
    #: the sessions of its map when it started, in order, when there were several (the trials
    #: are joint maps of them; ``apply`` rebuilds from them); null for a map of one session
    session_ids: Mapped[list[int] | None] = mapped_column(JSONValue)
    error: Mapped[str | None] = mapped_column(Text)
    applied_job_id: Mapped[int | None]
    created_at: Mapped[datetime] = mapped_column(default=utc_now)
    finished_at: Mapped[datetime | None]


class SweepTrial(Base):
    """One finished trial of a sweep; ``number`` is its place in the sweep (unique), so a trial
    stored twice (a job run again after its worker died) is refused by the database."""

    __tablename__ = "sweep_trial"
    __table_args__ = (UniqueConstraint("sweep_id", "number"),)

    id: Mapped[int] = mapped_column(primary_key=True)
    sweep_id: Mapped[int] = mapped_column(ForeignKey("sweep.id", ondelete="CASCADE"))
    number: Mapped[int]
    #: the swept parameters' values, name → value
    values: Mapped[dict[str, Any]]
    shift: Mapped[float | None] = mapped_column(Float)
    gt_metric: Mapped[float | None] = mapped_column(Float)
    tag_rmse_m: Mapped[float | None] = mapped_column(Float)
    iterations: Mapped[int]
    converged: Mapped[bool]
    duration_s: Mapped[float] = mapped_column(Float)
    error: Mapped[str | None] = mapped_column(Text)
    job_id: Mapped[int | None]
    created_at: Mapped[datetime] = mapped_column(default=utc_now)
