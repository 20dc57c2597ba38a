"""``/admin``: the queue at a glance — depth and jobs by state, workers alive and what each runs,
the newest jobs with live progress, and the failures of the last day.

The live part is ``/admin/live/overview``, an HTML fragment the page's script fetches every
second or two and swaps in (announcing jobs that changed state to screen readers).
"""

from __future__ import annotations

from datetime import timedelta
from typing import Any

from fastapi import Request, Response
from sqlalchemy.orm import Session

from app.admin.auth import DashboardUserDep
from app.admin.routing import admin_router
from app.admin.templating import render
from app.config import Settings
from app.services.system import ALIVE_HEARTBEATS
from app.storage import queue
from app.storage.orm import JobState, utc_now
from app.web.deps import ReadDbSessionDep, SettingsDep

router = admin_router()

RECENT_JOBS = 15
RECENT_FAILURES = 10
FAILURE_WINDOW = timedelta(days=1)


def _overview(db_session: Session, settings: Settings) -> dict[str, Any]:
    counts = queue.count_by_state(db_session)
    recent, _ = queue.list_jobs(db_session, limit=RECENT_JOBS)
    failures, failure_count = queue.list_jobs(
        db_session,
        state=JobState.FAILED,
        finished_after=utc_now() - FAILURE_WINDOW,
        limit=RECENT_FAILURES,
    )
    return {
        "counts": counts,
        "queue_depth": counts.get(JobState.QUEUED.value, 0),
        "workers": queue.alive_workers(
            db_session, within_s=ALIVE_HEARTBEATS * settings.heartbeat_s
        ),
        "recent": recent,
        "failures": failures,
        "failure_count": failure_count,
    }


@router.get("")
def overview(
    request: Request, _user: DashboardUserDep, db_session: ReadDbSessionDep, settings: SettingsDep
) -> Response:
    return render(
        request,
        "overview.html",
        section="overview",
        title="Overview",
        **_overview(db_session, settings),
    )


@router.get("/live/overview")
def overview_live(
    request: Request, _user: DashboardUserDep, db_session: ReadDbSessionDep, settings: SettingsDep
) -> Response:
    return render(request, "_overview_live.html", **_overview(db_session, settings))
