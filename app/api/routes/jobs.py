"""``/v1/jobs``: the job queue as the API shows it.

``GET /v1/jobs/{id}`` is open to the device that uploaded the job's session (the phone polls the
build of its upload); listing, cancel and retry are admin-only. Cancel and retry are requests the
queue records in one transaction: a queued job is canceled at once, a running one gets
``cancel_requested`` and its worker stops at the next stage boundary; retry queues a failed or
canceled job again. Any other state is a 409 naming the job's state.
"""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query, Response
from sqlalchemy.orm import Session

from app.api.schemas.jobs import JobPublic, JobsPublic
from app.storage import queue
from app.storage.changes import MAP_CHANGES
from app.storage.orm import JobState
from app.storage.queue import JobInfo
from app.web.deps import (
    AdminPrincipal,
    CurrentPrincipal,
    JobDep,
    JobId,
    MapFilter,
    ReadDbSessionDep,
    WriteDbSessionDep,
    is_id,
    valid_id,
)
from app.web.errors import error_responses
from app.web.http import json_response
from app.web.route_class import SessionEndingRoute

router = APIRouter(prefix="/jobs", tags=["jobs"], route_class=SessionEndingRoute)

Limit = Annotated[int, Query(ge=1, le=200, description="page size")]
Offset = Annotated[int, Query(ge=0, le=2**31, description="items to skip")]


@router.get(
    "",
    summary="List jobs",
    description="Newest first, optionally only those in one state or of one map (admin).",
    responses=error_responses(401, 403, 422),
)
def list_jobs(
    _admin: AdminPrincipal,
    db_session: ReadDbSessionDep,
    state: Annotated[JobState | None, Query(description="only jobs in this state")] = None,
    map_id: MapFilter = None,
    limit: Limit = 50,
    offset: Offset = 0,
) -> JobsPublic:
    if map_id is not None and not is_id(map_id):  # no map has it
        jobs: list[JobInfo] = []
        total = 0
    else:
        jobs, total = queue.list_jobs(
            db_session, state=state, map_id=map_id, limit=limit, offset=offset
        )
    return JobsPublic(
        data=[JobPublic.from_domain(job) for job in jobs], count=total, limit=limit, offset=offset
    )


@router.get(
    "/{job_id}",  # noqa: FAST003 (job_id is read by JobDep)
    summary="Get a job",
    description="State (queued, running, succeeded, failed, canceled), progress 0–1, stage, "
    "attempts, error, timings and log tail. A device key may read the jobs of its own uploads.",
    response_model=JobPublic,
    responses=error_responses(401, 404, 422),
)
async def get_job(job: JobDep, principal: CurrentPrincipal) -> Response:
    return json_response(JobPublic.from_domain(job, full_error=principal.is_admin))


@router.post(
    "/{job_id}/cancel",
    summary="Cancel a job",
    description="A queued job is canceled now; a running job is asked to stop "
    "(cancel_requested, state still running until its worker stops at the next stage). 409 "
    "for a job that has finished (admin).",
    responses=error_responses(401, 403, 404, 409, 422),
)
def cancel_job(job_id: JobId, _admin: AdminPrincipal, db_session: WriteDbSessionDep) -> JobPublic:
    job = queue.request_cancel(db_session, valid_id(job_id, "job"))
    _note_map_change(db_session, job)
    return JobPublic.from_domain(job)


@router.post(
    "/{job_id}/retry",
    summary="Retry a job",
    description="Queue a failed or canceled job again, with a fresh count of attempts. 409 for "
    "a job in any other state (admin).",
    responses=error_responses(401, 403, 404, 409, 422),
)
def retry_job(job_id: JobId, _admin: AdminPrincipal, db_session: WriteDbSessionDep) -> JobPublic:
    job = queue.retry(db_session, valid_id(job_id, "job"))
    _note_map_change(db_session, job)
    return JobPublic.from_domain(job)


def _note_map_change(db_session: Session, job: JobInfo) -> None:
    """A map shows its newest job: this process's memory of it is dropped at the commit."""
    if job.map_id is not None:
        MAP_CHANGES.note(db_session, job.map_id)
