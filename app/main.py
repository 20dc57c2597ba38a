"""The FastAPI application.

    uvicorn --factory app.main:create_app          # settings from the environment
    app = create_app(Settings(database_url=…))     # tests, the CLI

Nothing connects at import time: the lifespan creates the :class:`Database` from
``settings.resolved_database_url`` and keeps it on ``app.state.db``. CORS is not enabled (the API
is for the app and for admins' tools, not for pages on other origins). The admin dashboard's pages
are under ``/admin`` (``app.admin``); ``/metrics``, for an admin key, and the timing of every
request are ``app.observability``'s.
"""

from __future__ import annotations

from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import Depends, FastAPI

from app.admin.router import router as admin_router
from app.api.body_limit import BodyLimit
from app.api.docs_pages import install_docs
from app.api.query_text import refuse_unstorable_query
from app.api.routes import (
    corridor_edits,
    jobs,
    keys,
    localization,
    maps,
    metrics,
    navigation,
    sessions,
    sweeps,
    system,
)
from app.config import Settings, get_settings
from app.observability.metrics import ApiMetrics, RequestMetrics
from app.services.keys import PrincipalCache
from app.services.maps import MapPages, MapStates
from app.services.system import ALIVE_HEARTBEATS, WorkerPool, package_version
from app.services.version_cache import VersionCache
from app.storage.db import Database, ServerTimeouts
from app.storage.migrate import head_revision
from app.web.deps import KeyUsage, UploadRate, current_principal
from app.web.errors import install_error_handlers
from app.web.security import SecurityHeaders

DESCRIPTION = """\
The Invisible Map server: phones upload AprilTag mapping sessions, workers turn them into maps
with graph SLAM, and the app downloads the maps.

Every `/v1` endpoint needs `Authorization: Bearer <key>`. A *device* key uploads sessions, reads
its own sessions and their jobs, and reads every map; an *admin* key may do everything, including
managing jobs, maps and keys. Errors have one shape: `{"detail", "code", "field"}`.
"""

#: Uploads have their own limits (``max_upload_bytes``, ``max_session_bytes``: app.web.upload).
UPLOAD_PATH = "/v1/sessions"

OPENAPI_TAGS = [
    {"name": "sessions", "description": "Mapping sessions as the phone uploads them."},
    {"name": "jobs", "description": "The durable job queue: build progress, cancel, retry."},
    {"name": "maps", "description": "Maps, their versions, the app's download format, plots."},
    {"name": "sweeps", "description": "Hyperparameter sweeps over all workers (admin)."},
    {"name": "navigation", "description": "Points of interest, routes and the path graph."},
    {"name": "localization", "description": "Live localization of a navigating phone."},
    {"name": "keys", "description": "API keys (admin)."},
    {"name": "system", "description": "Health, readiness and server information."},
]


@asynccontextmanager
async def lifespan(app: FastAPI) -> AsyncIterator[None]:
    """Open the database for the app's life; close its pools at shutdown."""
    settings: Settings = app.state.settings
    database = Database(
        settings.resolved_database_url,
        timeouts=ServerTimeouts.of(settings),
        pool_share=settings.api_processes or 1,
    )
    app.state.db = database
    app.state.head_revision = head_revision()
    app.state.localizer_threads = localization.localizer_threads()  # bound to this loop
    try:
        yield
    finally:
        database.dispose()


def create_app(
    settings: Settings | None = None, *, worker_pool: WorkerPool | None = None
) -> FastAPI:
    """The API with its routes and error handlers; ``settings`` default to the environment's.
    ``worker_pool``: the worker processes this server supervises (``serve --workers N``), whose
    liveness ``/readyz`` and ``/v1/info`` report."""
    app = FastAPI(
        title="Invisible Map",
        version=package_version(),
        description=DESCRIPTION,
        openapi_tags=OPENAPI_TAGS,
        lifespan=lifespan,
        docs_url=None,  # served by install_docs, with no CDN
        redoc_url=None,
        dependencies=[Depends(refuse_unstorable_query)],  # 422 for a NUL in a query string
    )
    app.state.settings = settings or get_settings()
    app.state.key_usage = KeyUsage()
    app.state.upload_rate = UploadRate(app.state.settings.uploads_per_minute)
    # Per-process memory of the hot read path (docs/api.md, "Caching and consistency").
    app.state.principals = PrincipalCache(app.state.settings.key_cache_s)
    app.state.map_states = MapStates(app.state.settings.map_cache_s)
    app.state.map_pages = MapPages(app.state.settings.map_cache_s)
    app.state.version_cache = VersionCache(max_bytes=app.state.settings.version_cache_bytes)
    app.state.hot_localizer_states = localization.HotStates()
    app.state.worker_pool = worker_pool
    install_error_handlers(app)
    app.add_middleware(
        BodyLimit, max_bytes=app.state.settings.max_request_bytes, exempt_paths=[UPLOAD_PATH]
    )
    app.add_middleware(SecurityHeaders)  # every answer, errors included
    app.state.metrics = ApiMetrics(
        database=lambda: getattr(app.state, "db", None),
        alive_within_s=ALIVE_HEARTBEATS * app.state.settings.heartbeat_s,
    )
    app.add_middleware(RequestMetrics, metrics=app.state.metrics)  # outermost: timed whole
    app.include_router(system.router)
    app.include_router(metrics.router)  # /metrics: admin key (docs/operations.md, "Metrics")
    install_docs(app)  # /docs, /redoc: Swagger UI and ReDoc from the installed package
    authenticated = [Depends(current_principal)]  # every /v1 route: 401 without a valid key
    # A request is matched against the routers in this order, route by route: the phones'
    # hottest (routes, localization updates, maps) first. (No two routers' paths overlap.)
    for module in (navigation, localization, maps, corridor_edits, jobs, sessions, sweeps, keys):
        app.include_router(module.router, prefix="/v1", dependencies=authenticated)
    app.include_router(admin_router)  # /admin: the dashboard (cookie login; not in OpenAPI)
    return app


#: For ``uvicorn --factory app.main:app`` (the same factory; there is no app at import time).
app = create_app
