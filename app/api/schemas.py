"""Pydantic v2 models of the HTTP API, one family per resource (as the FastAPI template does):
``…Public`` is what a GET returns, ``…sPublic`` a page of them (``data``, ``count``, ``limit``,
``offset``), ``…Create``/``…Request`` what a client sends. Storage returns frozen dataclasses;
``from_domain`` converts at the edge. Every model carries an example, so that the OpenAPI document
shows one for every request and response.
"""

from __future__ import annotations

from datetime import UTC, datetime, timedelta
from typing import Any, Literal

from pydantic import AwareDatetime, BaseModel, ConfigDict, Field

from app.storage.keys import KeyInfo
from app.storage.maps import MapInfo, TagPose, VersionInfo
from app.storage.orm import JobState, Role
from app.storage.queue import JobInfo, WorkerInfo
from app.storage.sessions import SessionInfo, SessionStatistics, UploadResult

_AT = "2026-11-22T10:15:30Z"
_LATER = "2026-11-22T10:15:31.250000Z"
_SHA = "9f86d081884c7d659a2feaa0c55ad015a3bf4f1b2b0b822cd15d6c15b0f00a08"


def _examples(*examples: dict[str, Any]) -> ConfigDict:
    return ConfigDict(json_schema_extra={"examples": list(examples)})


# --------------------------------------------------------------------------- errors


class ErrorBody(BaseModel):
    """Every error response: what went wrong, a stable code, and the field at fault if any."""

    model_config = _examples(
        {
            "detail": "pose_data[3].pose: rotation not orthonormal",
            "code": "invalid_session",
            "field": "pose_data[3].pose",
        },
        {"detail": "map 42 not found", "code": "not_found", "field": None},
    )

    detail: str = Field(description="a sentence for a person")
    code: str = Field(description="stable, for programs: not_found, invalid_session, …")
    field: str | None = Field(
        default=None, description="where in the request: a JSON path, a parameter or a header"
    )


# --------------------------------------------------------------------------- sessions

_STATS_EXAMPLE: dict[str, Any] = {
    "pose_count": 621,
    "detection_count": 200,
    "tag_count": 8,
    "poi_count": 0,
    "duration_s": 62.1,
    "path_length_m": 41.7,
    "tag_ids": [0, 1, 2, 3, 4, 5, 6, 7],
    "warnings": [],
}


class SessionStatisticsPublic(BaseModel):
    """What a session holds, computed when it was uploaded."""

    model_config = _examples(_STATS_EXAMPLE)

    pose_count: int
    detection_count: int
    tag_count: int
    poi_count: int = Field(description="points of interest (location_data)")
    duration_s: float = Field(description="last pose timestamp minus the first, s")
    path_length_m: float = Field(description="distance walked along the raw odometry, m")
    tag_ids: list[int]
    warnings: list[str]

    @classmethod
    def from_domain(cls, stats: SessionStatistics) -> SessionStatisticsPublic:
        return cls(
            pose_count=stats.pose_count,
            detection_count=stats.detection_count,
            tag_count=stats.tag_count,
            poi_count=stats.poi_count,
            duration_s=stats.duration_s,
            path_length_m=stats.path_length_m,
            tag_ids=stats.tag_ids,
            warnings=stats.warnings,
        )


class SessionCreated(BaseModel):
    """The answer to an upload (202): where to follow the build of its map."""

    model_config = _examples(
        {
            "session_id": 17,
            "map_id": 12,
            "job_id": 31,
            "map_name": "occam_room",
            "job_url": "/v1/jobs/31",
            "map_url": "/v1/maps/12",
            "statistics": _STATS_EXAMPLE,
        }
    )

    session_id: int
    map_id: int
    job_id: int = Field(description="the build_map job; poll it at job_url")
    map_name: str = Field(description="the upload's map_id")
    job_url: str
    map_url: str
    statistics: SessionStatisticsPublic

    @classmethod
    def from_domain(cls, result: UploadResult) -> SessionCreated:
        return cls(
            session_id=result.session_id,
            map_id=result.map_id,
            job_id=result.job_id,
            map_name=result.map_name,
            job_url=f"/v1/jobs/{result.job_id}",
            map_url=f"/v1/maps/{result.map_id}",
            statistics=SessionStatisticsPublic.from_domain(result.statistics),
        )


_SESSION_EXAMPLE: dict[str, Any] = {
    "id": 17,
    "map_name": "occam_room",
    "created_at": _AT,
    "uploaded_by": "key:3",
    "idempotency_key": "3f1c2a9e-occam-1",
    "raw_sha256": _SHA,
    "raw_size_bytes": 912204,
    "stored_size_bytes": 251377,
    "statistics": _STATS_EXAMPLE,
    "map_id": 12,
    "job_ids": [31],
}


class SessionPublic(BaseModel):
    """A stored session: metadata, statistics, and the map and jobs made from it."""

    model_config = _examples(_SESSION_EXAMPLE)

    id: int
    map_name: str = Field(description="the upload's map_id")
    created_at: datetime
    uploaded_by: str = Field(description="key:<id> of the key that uploaded it, or env-admin")
    idempotency_key: str | None
    raw_sha256: str = Field(description="SHA-256 of the JSON bytes as uploaded (hex)")
    raw_size_bytes: int = Field(description="size of the JSON as uploaded, after any gunzip")
    stored_size_bytes: int = Field(description="size as stored (gzip)")
    statistics: SessionStatisticsPublic
    map_id: int | None = Field(description="the map built from it (null once deleted)")
    job_ids: list[int] = Field(description="its jobs, oldest first (the upload's build first)")

    @classmethod
    def from_domain(cls, info: SessionInfo) -> SessionPublic:
        return cls(
            id=info.id,
            map_name=info.map_name,
            created_at=info.created_at,
            uploaded_by=info.uploaded_by,
            idempotency_key=info.idempotency_key,
            raw_sha256=info.raw_sha256,
            raw_size_bytes=info.raw_size_bytes,
            stored_size_bytes=info.stored_size_bytes,
            statistics=SessionStatisticsPublic.from_domain(info.statistics),
            map_id=info.map_id,
            job_ids=info.job_ids,
        )


class SessionsPublic(BaseModel):
    """A page of sessions, newest first; ``count`` is how many there are in all."""

    model_config = _examples(
        {
            "data": [_SESSION_EXAMPLE],
            "count": 1,
            "limit": 50,
            "offset": 0,
        }
    )

    data: list[SessionPublic]
    count: int
    limit: int
    offset: int


# --------------------------------------------------------------------------- jobs


_JOB_EXAMPLE: dict[str, Any] = {
    "id": 31,
    "kind": "build_map",
    "state": "running",
    "progress": 0.6,
    "stage": "optimize",
    "attempts": 1,
    "max_attempts": 3,
    "error": None,
    "log_tail": "2026-11-22T10:15:30Z queued\n"
    "2026-11-22T10:15:30Z attempt 1 of 3 started by host-1:4242\n",
    "cancel_requested": False,
    "map_id": 12,
    "session_id": 17,
    "params": {},
    "worker": "host-1:4242",
    "created_at": _AT,
    "run_after": _AT,
    "started_at": _AT,
    "finished_at": None,
    "updated_at": _LATER,
    "duration_s": 1.25,
}


class JobPublic(BaseModel):
    """A job of the queue: its state, progress, attempts, error, timings and log tail."""

    model_config = _examples(_JOB_EXAMPLE)

    id: int
    kind: str = Field(description="build_map, …")
    state: JobState
    progress: float = Field(ge=0, le=1, description="0–1")
    stage: str | None = Field(description="the stage running now (parse, optimize, store, …)")
    attempts: int
    max_attempts: int
    error: str | None
    log_tail: str = Field(description="the last lines of the job's log, timestamped, UTC")
    cancel_requested: bool
    map_id: int | None
    session_id: int | None
    params: dict[str, Any] = Field(description="SLAM parameter overrides of this build")
    worker: str | None = Field(description="the worker holding the job's lease while it runs")
    created_at: datetime
    run_after: datetime = Field(description="not claimed before this (retry backoff)")
    started_at: datetime | None
    finished_at: datetime | None
    updated_at: datetime
    duration_s: float | None = Field(
        description="finished_at − started_at; while running, time since started_at"
    )

    @classmethod
    def from_domain(cls, job: JobInfo, *, now: datetime | None = None) -> JobPublic:
        if job.started_at is None:
            duration_s = None
        else:
            end = job.finished_at or (now or datetime.now(UTC))
            duration_s = max((end - job.started_at) / timedelta(seconds=1), 0.0)
        return cls(
            id=job.id,
            kind=job.kind,
            state=job.state,
            progress=job.progress,
            stage=job.stage,
            attempts=job.attempts,
            max_attempts=job.max_attempts,
            error=job.error,
            log_tail=job.log_tail,
            cancel_requested=job.cancel_requested,
            map_id=job.map_id,
            session_id=job.session_id,
            params=job.params,
            worker=job.lease_owner,
            created_at=job.created_at,
            run_after=job.run_after,
            started_at=job.started_at,
            finished_at=job.finished_at,
            updated_at=job.updated_at,
            duration_s=duration_s,
        )


class JobsPublic(BaseModel):
    """A page of jobs, newest first."""

    model_config = _examples({"data": [_JOB_EXAMPLE], "count": 1, "limit": 50, "offset": 0})

    data: list[JobPublic]
    count: int
    limit: int
    offset: int


class JobBrief(BaseModel):
    """A map's newest job, in brief (its progress is at ``/v1/jobs/{id}``)."""

    model_config = _examples({"id": 31, "kind": "build_map", "state": "succeeded"})

    id: int
    kind: str
    state: JobState

    @classmethod
    def from_domain(cls, job: JobInfo) -> JobBrief:
        return cls(id=job.id, kind=job.kind, state=job.state)


# --------------------------------------------------------------------------- maps

_TAG_EXAMPLE = {
    "tag_id": 3,
    "position_m": [1.52, 0.31, -4.07],
    "quat_xyzw": [0.0, 0.7071, 0.0, 0.7071],
    "detection_count": 24,
    "covariance": None,
}
_VERSION_EXAMPLE: dict[str, Any] = {
    "number": 1,
    "created_at": _LATER,
    "job_id": 31,
    "params": {"tag_position_var_m2": 0.0001, "huber_k": 1.345},
    "statistics": {"poses": 621, "tags": 8, "path_length_m": 41.7, "iterations": 3},
    "metrics": {"shift_pre": 0.0139, "shift_opt": 0.0115},
    "shift_metric": 0.0115,
    "tag_count": 8,
    "detections_used": 191,
    "detections_rejected": 9,
    "warnings": [],
    "content_sha256": _SHA,
}


class TagPosePublic(BaseModel):
    """A tag in a map version, map frame (y up)."""

    model_config = _examples(_TAG_EXAMPLE)

    tag_id: int
    position_m: list[float] = Field(description="[x, y, z], m")
    quat_xyzw: list[float] = Field(description="orientation, unit quaternion [x, y, z, w]")
    detection_count: int = Field(description="detections of it used in the optimization")
    covariance: list[float] | None = Field(
        description="6×6 marginal covariance, row-major, [rotation rad, translation m] in the "
        "tag frame; null if not computed"
    )

    @classmethod
    def from_domain(cls, tag: TagPose) -> TagPosePublic:
        return cls(
            tag_id=tag.tag_id,
            position_m=list(tag.position_m),
            quat_xyzw=list(tag.quat_xyzw),
            detection_count=tag.detection_count,
            covariance=tag.covariance,
        )


class VersionSummary(BaseModel):
    """One version of a map: how it was made and how good it is (without its tags)."""

    model_config = _examples(_VERSION_EXAMPLE)

    number: int = Field(description="1, 2, … per map; the newest is the map's current version")
    created_at: datetime
    job_id: int | None = Field(description="the job that built it")
    params: dict[str, Any] = Field(description="every SLAM parameter it used")
    statistics: dict[str, Any] = Field(description="poses, tags, path length, solver figures")
    metrics: dict[str, Any] = Field(
        description="shift metric of the pre-optimized (shift_pre) and optimized (shift_opt) map"
    )
    shift_metric: float | None = Field(description="the optimized map's shift metric")
    tag_count: int
    detections_used: int
    detections_rejected: int
    warnings: list[str]
    content_sha256: str = Field(description="SHA-256 of the stored map document")

    @classmethod
    def from_domain(cls, version: VersionInfo) -> VersionSummary:
        return cls(**_version_fields(version))


class VersionPublic(VersionSummary):
    """A map version with its tag poses."""

    model_config = _examples({**_VERSION_EXAMPLE, "tags": [_TAG_EXAMPLE]})

    tags: list[TagPosePublic]

    @classmethod
    def with_tags(cls, version: VersionInfo, tags: list[TagPose]) -> VersionPublic:
        return cls(
            **_version_fields(version), tags=[TagPosePublic.from_domain(tag) for tag in tags]
        )


_REJECTION_EXAMPLE = {
    "detection_index": 57,
    "tag_id": 5,
    "pose_index": 233,
    "reason": "reprojection",
    "value": 11.2,
    "limit": 8.0,
    "detail": "reprojection 11.2 px > 8 px",
}


class VersionDetail(VersionPublic):
    """A map version with its tag poses and the detections it left out, and why."""

    model_config = _examples(
        {**_VERSION_EXAMPLE, "tags": [_TAG_EXAMPLE], "rejections": [_REJECTION_EXAMPLE]}
    )

    rejections: list[dict[str, Any]] = Field(
        description="detections left out: reason (reprojection, view_angle, distance), value, limit"
    )

    @classmethod
    def with_details(cls, version: VersionInfo, tags: list[TagPose]) -> VersionDetail:
        return cls(
            **_version_fields(version),
            tags=[TagPosePublic.from_domain(tag) for tag in tags],
            rejections=version.rejections,
        )


def _version_fields(version: VersionInfo) -> dict[str, Any]:
    return {
        "number": version.number,
        "created_at": version.created_at,
        "job_id": version.job_id,
        "params": version.params,
        "statistics": version.statistics,
        "metrics": version.metrics,
        "shift_metric": version.metrics.get("shift_opt"),
        "tag_count": version.tag_count,
        "detections_used": version.detections_used,
        "detections_rejected": version.detections_rejected,
        "warnings": version.warnings,
        "content_sha256": version.content_sha256,
    }


class VersionsPublic(BaseModel):
    """All versions of a map, oldest first."""

    model_config = _examples({"data": [_VERSION_EXAMPLE], "count": 1})

    data: list[VersionSummary]
    count: int


_MAP_EXAMPLE: dict[str, Any] = {
    "id": 12,
    "name": "occam_room",
    "session_id": 17,
    "created_at": _AT,
    "version_count": 1,
    "latest_job": {"id": 31, "kind": "build_map", "state": "succeeded"},
}


class MapSummary(BaseModel):
    """A map in a list: its current version without tags (null until the first build)."""

    model_config = _examples({**_MAP_EXAMPLE, "current_version": _VERSION_EXAMPLE})

    id: int
    name: str = Field(description="the session's map_id")
    session_id: int
    created_at: datetime
    version_count: int
    current_version: VersionSummary | None

    @classmethod
    def from_domain(cls, info: MapInfo) -> MapSummary:
        return cls(
            id=info.id,
            name=info.name,
            session_id=info.session_id,
            created_at=info.created_at,
            version_count=info.version_count,
            current_version=VersionSummary.from_domain(info.current) if info.current else None,
        )


class MapPublic(BaseModel):
    """A map: its current version with tag poses (null until the first build succeeds) and its
    newest job (to tell "not built yet" from "build failed")."""

    model_config = _examples(
        {**_MAP_EXAMPLE, "current_version": {**_VERSION_EXAMPLE, "tags": [_TAG_EXAMPLE]}},
        {
            **_MAP_EXAMPLE,
            "version_count": 0,
            "current_version": None,
            "latest_job": {"id": 31, "kind": "build_map", "state": "queued"},
        },
    )

    id: int
    name: str = Field(description="the session's map_id")
    session_id: int
    created_at: datetime
    version_count: int
    current_version: VersionPublic | None
    latest_job: JobBrief | None

    @classmethod
    def from_domain(
        cls, info: MapInfo, *, tags: list[TagPose], latest_job: JobInfo | None
    ) -> MapPublic:
        return cls(
            id=info.id,
            name=info.name,
            session_id=info.session_id,
            created_at=info.created_at,
            version_count=info.version_count,
            current_version=VersionPublic.with_tags(info.current, tags) if info.current else None,
            latest_job=JobBrief.from_domain(latest_job) if latest_job else None,
        )


class MapsPublic(BaseModel):
    """A page of maps, newest first."""

    model_config = _examples(
        {
            "data": [{**_MAP_EXAMPLE, "current_version": _VERSION_EXAMPLE}],
            "count": 1,
            "limit": 50,
            "offset": 0,
        }
    )

    data: list[MapSummary]
    count: int
    limit: int
    offset: int


class RebuildRequest(BaseModel):
    """Optional body of a rebuild: SLAM parameters to change from the defaults."""

    model_config = ConfigDict(
        extra="forbid",
        json_schema_extra={
            "examples": [
                {"params": {"tag_position_var_m2": 1e-3, "huber_k": 0}},
                {"params": {"tag_sizes_m": {"301": 0.15}, "max_reprojection_px": "12"}},
                {"auto_tune_trials": 40},
            ]
        },
    )

    params: dict[str, Any] = Field(
        default_factory=dict,
        description="name → value of any SlamParams field (see the README's parameter table)",
    )
    auto_tune_trials: int = Field(
        default=0,
        ge=0,
        le=1000,
        description="first choose the noise variances by the shift metric with this many "
        "sampler trials (0: use the parameters as given)",
    )


class RebuildAccepted(BaseModel):
    """The answer to a rebuild (202): the new job, which adds a version when it succeeds."""

    model_config = _examples(
        {
            "job_id": 40,
            "map_id": 12,
            "session_id": 17,
            "params": {"tag_position_var_m2": 0.001},
            "job_url": "/v1/jobs/40",
        }
    )

    job_id: int
    map_id: int
    session_id: int
    params: dict[str, Any] = Field(description="the overrides, as the job will use them")
    job_url: str

    @classmethod
    def queued(cls, info: MapInfo, job_id: int, params: dict[str, Any]) -> RebuildAccepted:
        """The answer for the build job ``job_id`` queued for map ``info`` with ``params``."""
        return cls(
            job_id=job_id,
            map_id=info.id,
            session_id=info.session_id,
            params=params,
            job_url=f"/v1/jobs/{job_id}",
        )


class Vector3(BaseModel):
    x: float
    y: float
    z: float


class Quaternion(BaseModel):
    x: float
    y: float
    z: float
    w: float


_TRANSLATION = {"x": 1.52, "y": 0.31, "z": -4.07}
_ROTATION = {"x": 0.0, "y": 0.7071, "z": 0.0, "w": 0.7071}


class AppTagVertex(BaseModel):
    id: int
    translation: Vector3
    rotation: Quaternion


class AppOdometryVertex(BaseModel):
    poseId: int  # noqa: N815 (the app's name)
    translation: Vector3
    rotation: Quaternion
    adjChi2: float  # noqa: N815
    vizTags: float  # noqa: N815
    neighbors: list[int]


class AppWaypointVertex(BaseModel):
    id: str = Field(description="the point of interest's name")
    translation: Vector3
    rotation: Quaternion


class AppMap(BaseModel):
    """The iPhone app's map download format (DESIGN §7), map frame y up."""

    model_config = _examples(
        {
            "tag_vertices": [{"id": 3, "translation": _TRANSLATION, "rotation": _ROTATION}],
            "odometry_vertices": [
                {
                    "poseId": 0,
                    "translation": {"x": 0.0, "y": 0.0, "z": 0.0},
                    "rotation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0},
                    "adjChi2": 0.0003,
                    "vizTags": 0.0,
                    "neighbors": [1],
                }
            ],
            "waypoints_vertices": [
                {"id": "Room 101", "translation": _TRANSLATION, "rotation": _ROTATION}
            ],
        }
    )

    tag_vertices: list[AppTagVertex]
    odometry_vertices: list[AppOdometryVertex]
    waypoints_vertices: list[AppWaypointVertex]


# --------------------------------------------------------------------------- keys

_KEY_EXAMPLE: dict[str, Any] = {
    "id": 3,
    "name": "lab iPhone 12",
    "role": "device",
    "prefix": "a1b2c3d4",
    "created_at": _AT,
    "expires_at": None,
    "revoked_at": None,
    "last_used_at": _LATER,
}


class KeyCreate(BaseModel):
    """A new API key: a name for people, a role, and optionally when it stops working."""

    model_config = ConfigDict(
        extra="forbid",
        json_schema_extra={
            "examples": [
                {"name": "lab iPhone 12", "role": "device"},
                {"name": "ops laptop", "role": "admin", "expires_at": "2027-01-01T00:00:00Z"},
            ]
        },
    )

    name: str = Field(min_length=1, max_length=100)
    role: Role
    expires_at: AwareDatetime | None = Field(
        default=None, description="with a time zone, in the future"
    )


class KeyPublic(BaseModel):
    """An API key as listed: never its secret."""

    model_config = _examples(_KEY_EXAMPLE)

    id: int
    name: str
    role: Role
    prefix: str = Field(description="the public part of the key, im_<prefix>_…")
    created_at: datetime
    expires_at: datetime | None
    revoked_at: datetime | None
    last_used_at: datetime | None = Field(description="to within a minute")

    @classmethod
    def from_domain(cls, key: KeyInfo) -> KeyPublic:
        return cls(
            id=key.id,
            name=key.name,
            role=key.role,
            prefix=key.prefix,
            created_at=key.created_at,
            expires_at=key.expires_at,
            revoked_at=key.revoked_at,
            last_used_at=key.last_used_at,
        )


class KeyCreated(KeyPublic):
    """A new key with its secret: shown this once, never stored or shown again."""

    model_config = _examples(
        {**_KEY_EXAMPLE, "last_used_at": None, "key": "im_a1b2c3d4_Zq9…(32 characters)"}
    )

    key: str = Field(description="send as 'Authorization: Bearer <key>'")


class KeysPublic(BaseModel):
    """All API keys, oldest first."""

    model_config = _examples({"data": [_KEY_EXAMPLE], "count": 1})

    data: list[KeyPublic]
    count: int


# --------------------------------------------------------------------------- system


class Health(BaseModel):
    """The process is up."""

    model_config = _examples({"status": "ok"})

    status: Literal["ok"] = "ok"


class Ready(BaseModel):
    """The database answers and its schema is at the newest migration."""

    model_config = _examples(
        {"status": "ready", "database": "postgresql", "schema_revision": "0001_initial"}
    )

    status: Literal["ready"] = "ready"
    database: str = Field(description="sqlite or postgresql")
    schema_revision: str | None


_WORKER_EXAMPLE: dict[str, Any] = {
    "id": "host-1:4242",
    "hostname": "host-1",
    "pid": 4242,
    "state": "busy",
    "current_job_id": 31,
    "jobs_done": 12,
    "started_at": _AT,
    "heartbeat_at": _LATER,
}


class WorkerPublic(BaseModel):
    """A worker process that reported recently."""

    model_config = _examples(_WORKER_EXAMPLE)

    id: str
    hostname: str
    pid: int
    state: str = Field(description="idle or busy (or what the worker reports)")
    current_job_id: int | None
    jobs_done: int
    started_at: datetime
    heartbeat_at: datetime

    @classmethod
    def from_domain(cls, worker: WorkerInfo) -> WorkerPublic:
        return cls(
            id=worker.id,
            hostname=worker.hostname,
            pid=worker.pid,
            state=worker.state,
            current_job_id=worker.current_job_id,
            jobs_done=worker.jobs_done,
            started_at=worker.started_at,
            heartbeat_at=worker.heartbeat_at,
        )


class Info(BaseModel):
    """The server: its version, database, queue and workers."""

    model_config = _examples(
        {
            "version": "0.1.0",
            "database": "postgresql",
            "queue_depth": 2,
            "jobs_by_state": {
                "queued": 2,
                "running": 1,
                "succeeded": 40,
                "failed": 0,
                "canceled": 1,
            },
            "workers": [_WORKER_EXAMPLE],
            "principal": {"subject": "key:3", "role": "device"},
        }
    )

    version: str = Field(description="the invisible-map package version")
    database: str = Field(description="sqlite or postgresql")
    queue_depth: int = Field(description="jobs waiting (queued)")
    jobs_by_state: dict[str, int]
    workers: list[WorkerPublic] = Field(description="workers alive (heartbeat in 3 × heartbeat_s)")
    principal: dict[str, str] = Field(description="who the presented key stands for")
