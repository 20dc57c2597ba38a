"""``/admin/sessions``: mapping sessions, searchable by map name, in pages; a session's
statistics (poses, distance walked, detections per tag, duration), its raw upload, its jobs."""

from __future__ import annotations

import re
from collections import Counter
from collections.abc import Iterable
from typing import Annotated

from fastapi import Header, Query, Request, Response
from sqlalchemy.orm import Session

from app.admin.auth import DashboardUserDep
from app.admin.paging import PAGE_SIZE, Page, PageNumber
from app.admin.routing import admin_router
from app.admin.templating import render
from app.services.uploads import stored_session
from app.services.version_cache import VersionCache
from app.storage import keys, queue, sessions
from app.web.deps import DbDep, ReadDbSessionDep, valid_id
from app.web.http import raw_upload_response

router = admin_router()

Search = Annotated[str, Query(max_length=200, description="part of the map name")]

#: How ``uploaded_by`` names an API key: its id.
_KEY_SUBJECT = re.compile(r"key:(\d+)")


def uploader_names(db_session: Session, subjects: Iterable[str]) -> dict[str, str]:
    """Who uploaded, for people: an API key by its name and id ("lab iPhone (key 3)", not
    "key:3"), the environment's admin key as such, any other owner (an import's) as stored."""
    names = {}
    for subject in set(subjects):
        match = _KEY_SUBJECT.fullmatch(subject)
        if subject == keys.ENVIRONMENT_ADMIN:
            names[subject] = "the admin key from INVISIBLE_MAP_ADMIN_KEY"
        elif match is None:
            names[subject] = subject
        else:
            key_id = int(match.group(1))
            try:
                name = keys.get_key(db_session, key_id).name
            except keys.KeyNotFound:
                name = ""
            names[subject] = f"{name} (key {key_id})" if name else f"key {key_id}"
    return names


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
        uploaders=uploader_names(db_session, (info.uploaded_by for info in infos)),
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
        uploader=uploader_names(db_session, [info.uploaded_by])[info.uploaded_by],
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
