"""Schemas of the jobs router."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta
from typing import Any

from pydantic import BaseModel, Field

from app.api.schemas.common import AT_EXAMPLE, LATER_EXAMPLE, examples
from app.services.jobs import public_job_error
from app.storage.orm import JobState
from app.storage.queue import JobInfo

JOB_EXAMPLE: dict[str, Any] = {
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
    "created_at": AT_EXAMPLE,
    "run_after": AT_EXAMPLE,
    "started_at": AT_EXAMPLE,
    "finished_at": None,
    "updated_at": LATER_EXAMPLE,
    "duration_s": 1.25,
}


class JobPublic(BaseModel):
    """A job of the queue: its state, progress, attempts, error, timings and log tail."""

    model_config = examples(JOB_EXAMPLE)

    id: int
    kind: str = Field(description="build_map, …")
    state: JobState
    progress: float = Field(ge=0, le=1, description="0–1")
    stage: str | None = Field(description="the stage running now (parse, optimize, store, …)")
    attempts: int
    max_attempts: int
    error: str | None = Field(
        description="why the last attempt failed; with a device key only what the upload or "
        "the parameters can change (anything else is an internal error, detailed to admins)"
    )
    log_tail: str = Field(description="the last lines of the job's log, timestamped, UTC")
    cancel_requested: bool
    map_id: int | None = Field(
        description="its map (null once the map was deleted: the job is kept)"
    )
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
    def from_domain(
        cls, job: JobInfo, *, now: datetime | None = None, full_error: bool = True
    ) -> JobPublic:
        """The job; ``full_error=False`` (a device's view) gives :func:`public_job_error`."""
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
            error=job.error if full_error else public_job_error(job.error),
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

    model_config = examples({"data": [JOB_EXAMPLE], "count": 1, "limit": 50, "offset": 0})

    data: list[JobPublic]
    count: int
    limit: int
    offset: int


class JobBrief(BaseModel):
    """A map's newest job, in brief (its progress is at ``/v1/jobs/{id}``)."""

    model_config = examples({"id": 31, "kind": "build_map", "state": "succeeded"})

    id: int
    kind: str
    state: JobState

    @classmethod
    def from_domain(cls, job: JobInfo) -> JobBrief:
        return cls(id=job.id, kind=job.kind, state=job.state)


# --------------------------------------------------------------------------- maps
