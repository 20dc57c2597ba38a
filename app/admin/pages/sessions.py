"""``/admin/sessions``: mapping sessions, searchable by map name, in pages; a session's
statistics (poses, distance walked, detections per tag, duration), its raw upload, its jobs."""

from __future__ import annotations

from collections import Counter
from typing import Annotated

from fastapi import Header, Query, Request, Response
from sqlalchemy.orm import Session

from app.admin.auth import DashboardUserDep
from app.admin.paging import PAGE_SIZE, Page, PageNumber
from app.admin.routing import admin_router
from app.admin.templating import render
from app.services.uploads import stored_session
from app.services.version_cache import VersionCache
from app.storage import queue, sessions
from app.web.deps import DbDep, ReadDbSessionDep, valid_id
from app.web.http import raw_upload_response

router = admin_router()

Search = Annotated[str, Query(max_length=200, description="part of the map name")]


@router.get("/sessions")
def session_list(
    request: Request,
    _user: DashboardUserDep,
    db_session: ReadDbSessionDep,
    q: Search = "",
    page: PageNumber = 1,
) -> Response:
    query = q.strip()
    infos, total = sessions.list_sessions(
        db_session, limit=PAGE_SIZE, offset=(page - 1) * PAGE_SIZE, name_contains=query or None
    )
    return render(
        request,
        "sessions.html",
        section="sessions",
        title="Sessions",
        sessions=infos,
        q=query,
        page=Page.of(
            number=page, size=PAGE_SIZE, total=total, url="/admin/sessions", query={"q": query}
        ),
    )


def detections_per_tag(
    request: Request, db_session: Session, session_id: int
) -> list[tuple[int, int]]:
    """(tag id, detections) of a session's raw upload, by tag id (uploads never change, so the
    count is kept in the process's cache)."""

    def count() -> list[tuple[int, int]]:
        parsed = stored_session(db_session, session_id)
        counts = Counter(int(tag_id) for tag_id in parsed.detections.tag_id)
        return sorted(counts.items())

    cache: VersionCache = request.app.state.version_cache
    return cache.get(("admin_session_detections", session_id), count)


@router.get("/sessions/{session_id}")
def session_detail(
    request: Request, _user: DashboardUserDep, db_session: ReadDbSessionDep, session_id: int
) -> Response:
    info = sessions.get_session(db_session, valid_id(session_id, "session"))
    jobs, _ = queue.list_jobs(db_session, session_id=info.id, limit=100)
    return render(
        request,
        "session.html",
        section="sessions",
        title=f"Session {info.id}",
        info=info,
        jobs=jobs,
        detections=detections_per_tag(request, db_session, info.id),
    )


@router.get("/sessions/{session_id}/raw")
def session_raw(
    _user: DashboardUserDep,
    db: DbDep,
    session_id: int,
    accept_encoding: Annotated[str | None, Header()] = None,
) -> Response:
    return raw_upload_response(db, valid_id(session_id, "session"), accept_encoding)
