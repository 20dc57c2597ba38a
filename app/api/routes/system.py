"""``/healthz`` (the process is up), ``/readyz`` (the database answers and its schema is current;
both without a key, for load balancers and orchestrators) and ``/v1/info`` (any valid key)."""

from __future__ import annotations

from fastapi import APIRouter, Request, Response
from fastapi.concurrency import run_in_threadpool
from sqlalchemy.exc import SQLAlchemyError

from app.api.schemas.system import Health, Info, Ready, WorkerProcesses, WorkerPublic
from app.services.system import ALIVE_HEARTBEATS, WorkerPool, no_worker_alive, package_version
from app.storage import migrate, queue
from app.storage.db import Database
from app.storage.keys import Principal
from app.storage.orm import JobState
from app.web.deps import CurrentPrincipal, DbDep, SettingsDep
from app.web.errors import ApiError, error_responses
from app.web.http import json_response
from app.web.route_class import SessionEndingRoute

router = APIRouter(tags=["system"], route_class=SessionEndingRoute)


@router.get("/healthz", summary="Liveness", description="The process is up (no key needed).")
async def healthz() -> Health:
    return Health()


@router.get(
    "/readyz",
    summary="Readiness",
    description="200 when the database answers, its schema is at the newest migration and (when "
    "this server runs worker processes, `serve --workers N`) at least one of them is alive; 503 "
    "with the reason otherwise (no key needed).",
    responses=error_responses(503, examples={503: ("not_ready", "database schema is not "
                                                   "migrated: at None, the code needs 0001")}),
)  # fmt: skip
def readyz(request: Request, db: DbDep) -> Ready:
    try:
        db.ping()
        revision = migrate.current_revision(db)
    except SQLAlchemyError as err:
        raise ApiError(503, "not_ready", f"database unreachable ({type(err).__name__})") from err
    head: str | None = request.app.state.head_revision
    if revision != head:
        raise ApiError(
            503,
            "not_ready",
            f"database schema is not migrated: at {revision}, the code needs {head} "
            "(run: invisible-map migrate)",
        )
    no_worker = no_worker_alive(request.app.state.worker_pool)
    if no_worker is not None:
        raise ApiError(503, "no_worker", no_worker)
    return Ready(database=db.backend, schema_revision=revision)


@router.get(
    "/v1/info",
    summary="Server information",
    description="Version, database, queue depth, jobs by state, and the workers alive with "
    "what each is running (any valid key).",
    response_model=Info,
    responses=error_responses(401),
)
async def info(
    request: Request,
    principal: CurrentPrincipal,
    db: DbDep,
    settings: SettingsDep,
) -> Response:
    pool: WorkerPool | None = request.app.state.worker_pool
    answer = await run_in_threadpool(_info, db, settings.heartbeat_s, pool, principal)
    return json_response(answer)


def _info(db: Database, heartbeat_s: float, pool: WorkerPool | None, principal: Principal) -> Info:
    with db.read() as db_session:
        counts = queue.count_by_state(db_session)
        workers = queue.alive_workers(db_session, within_s=ALIVE_HEARTBEATS * heartbeat_s)
    no_worker = no_worker_alive(pool)
    return Info(
        version=package_version(),
        database=db.backend,
        queue_depth=counts.get(JobState.QUEUED.value, 0),
        jobs_by_state=counts,
        workers=[WorkerPublic.model_validate(worker) for worker in workers],
        worker_processes=None
        if pool is None
        else WorkerProcesses(configured=pool.configured, alive=pool.alive, restarts=pool.restarts),
        warnings=[] if no_worker is None else [no_worker],
        principal={"subject": principal.subject, "role": principal.role.value},
    )
