"""``/admin/jobs``: the queue's jobs, by state, in pages; a job's state, progress, stage,
attempts, error and log tail (live), with cancel and retry buttons.

Cancel and retry are the queue's own requests (``queue.request_cancel``, ``queue.retry``), each in
one transaction; one the job's state does not allow is a 409 page saying why.
"""

from __future__ import annotations

from typing import Annotated

from fastapi import Query, Request, Response

from app.admin.auth import CheckedFormDep, DashboardUserDep
from app.admin.paging import PAGE_SIZE, Page, PageNumber
from app.admin.routing import admin_router
from app.admin.templating import redirect, render
from app.storage import queue
from app.storage.orm import JobState
from app.web.deps import DbDep, ReadDbSessionDep, valid_id

router = admin_router()


@router.get("/jobs")
def job_list(
    request: Request,
    _user: DashboardUserDep,
    db_session: ReadDbSessionDep,
    state: Annotated[JobState | None, Query(description="only jobs in this state")] = None,
    page: PageNumber = 1,
) -> Response:
    jobs, total = queue.list_jobs(
        db_session, state=state, limit=PAGE_SIZE, offset=(page - 1) * PAGE_SIZE
    )
    return render(
        request,
        "jobs.html",
        section="jobs",
        title="Jobs",
        jobs=jobs,
        state=state,
        states=list(JobState),
        page=Page.of(
            number=page,
            size=PAGE_SIZE,
            total=total,
            url="/admin/jobs",
            query={"state": state.value if state else ""},
        ),
    )


@router.get("/jobs/{job_id}")
def job_detail(
    request: Request, _user: DashboardUserDep, db_session: ReadDbSessionDep, job_id: int
) -> Response:
    job = queue.get_job(db_session, valid_id(job_id, "job"))
    return render(request, "job.html", section="jobs", title=f"Job {job.id}", job=job)


@router.get("/live/jobs/{job_id}")
def job_live(
    request: Request, _user: DashboardUserDep, db_session: ReadDbSessionDep, job_id: int
) -> Response:
    job = queue.get_job(db_session, valid_id(job_id, "job"))
    return render(request, "_job_live.html", job=job)


@router.post("/jobs/{job_id}/cancel")
def cancel_job(request: Request, _form: CheckedFormDep, db: DbDep, job_id: int) -> Response:
    with db.transaction() as db_session:
        job = queue.request_cancel(db_session, valid_id(job_id, "job"))
    message = (
        f"Job {job.id} canceled."
        if job.state is JobState.CANCELED
        else f"Job {job.id} is asked to stop: its worker stops it at the next stage."
    )
    return redirect(request, f"/admin/jobs/{job.id}", flash=message)


@router.post("/jobs/{job_id}/retry")
def retry_job(request: Request, _form: CheckedFormDep, db: DbDep, job_id: int) -> Response:
    with db.transaction() as db_session:
        job = queue.retry(db_session, valid_id(job_id, "job"))
    return redirect(request, f"/admin/jobs/{job.id}", flash=f"Job {job.id} is queued again.")
