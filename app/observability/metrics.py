"""``/metrics``: the API's own counters, and the job queue as the database has it.

    metrics = ApiMetrics(database=lambda: app.state.db, alive_within_s=15.0)
    app.add_middleware(RequestMetrics, metrics=metrics)   # latency by route, upload refusals
    body = metrics.exposition()                           # the Prometheus text format

Two kinds of series (docs/operations.md, "Metrics", lists each):

- *per request*, counted by the API process that answered it: request latency by route template
  and status class (:class:`RequestMetrics`), uploads refused by reason. ``serve`` with several
  API processes runs them in prometheus-client's multiprocess mode (``PROMETHEUS_MULTIPROC_DIR``,
  which ``serve`` sets for its API processes), so any of them answers a scrape with the sum over
  all of them, the dead ones' counts included; several ``serve`` (scale-out) are each a target.
- *from the database* at scrape time (:class:`QueueCollector`), the one truth that every API
  process and worker shares: queue depth, finished jobs, job and stage durations, failed builds,
  worker processes alive. Any API process answers them the same.

A route's *template* (``/v1/maps/{map_id}``) labels its requests, never the raw path, so ids do
not multiply the series; a request that matched no route is ``unmatched``.
"""

from __future__ import annotations

import json
import logging
import os
import re
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from datetime import datetime

from prometheus_client import CollectorRegistry, Counter, Histogram, generate_latest
from prometheus_client.core import (
    CounterMetricFamily,
    GaugeMetricFamily,
    HistogramMetricFamily,
    Metric,
)
from prometheus_client.multiprocess import MultiProcessCollector
from prometheus_client.registry import Collector
from starlette.routing import BaseRoute, Mount
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from app.observability.multiprocess import MULTIPROCESS_DIR_VARIABLE
from app.storage import job_metrics
from app.storage.db import Database
from app.storage.job_metrics import QUEUE_STATES, Distribution
from app.storage.orm import TERMINAL_STATES, utc_now
from app.storage.sessions import BUILD_MAP
from app.storage.sweeps import SWEEP_TRIALS

logger = logging.getLogger(__name__)

#: The label of a request that matched no route.
UNMATCHED = "unmatched"
#: Request latency buckets, s: a route answer in milliseconds, an upload of a long walk in tens of
#: seconds.
REQUEST_BUCKETS_S = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0)
#: Job duration buckets, s: a small walk's build in seconds, a tuned one's in tens of minutes.
JOB_BUCKETS_S = (1.0, 2.0, 5.0, 10.0, 30.0, 60.0, 120.0, 300.0, 600.0, 1800.0, 3600.0)
#: Stage duration buckets, s.
STAGE_BUCKETS_S = (0.05, 0.1, 0.25, 0.5, 1.0, 2.0, 5.0, 10.0, 30.0, 60.0, 300.0, 1800.0)
#: The job kinds whose queue and outcome series are there (at 0) before any such job exists.
JOB_KINDS = (BUILD_MAP, SWEEP_TRIALS)
#: The worker states whose series are there (at 0) with no worker in them.
WORKER_STATES = ("idle", "busy")
#: The uploads whose refusals (4xx) are counted, by (method, route template).
UPLOAD_ROUTES = {
    ("POST", "/v1/sessions"): "session",
    ("PUT", "/v1/sessions/{session_id}/image"): "image",
}
#: HTTP methods kept as labels; any other is ``other`` (a client chooses the method).
METHODS = frozenset({"GET", "HEAD", "POST", "PUT", "PATCH", "DELETE", "OPTIONS"})
#: The most bytes of a refusal's body read for its ``code`` (which follows ``detail``, up to
#: 2,000 characters, each up to 6 bytes as JSON).
REFUSAL_BODY_BYTES = 65536
_CODE = re.compile(r"[a-z][a-z0-9_]{0,63}")


def multiprocess_dir() -> str | None:
    """The folder of prometheus-client's multiprocess mode, when this process runs in it."""
    return os.environ.get(MULTIPROCESS_DIR_VARIABLE) or None


class ApiMetrics:
    """An app's metrics: its per-request series and its :class:`QueueCollector`.

    ``database`` gives the app's database (None before its lifespan started);
    ``alive_within_s``: a worker that reported within this long is alive.
    """

    def __init__(self, *, database: Callable[[], Database | None], alive_within_s: float) -> None:
        # a registry per app, not prometheus-client's global one: tests make many apps in one
        # process (in multiprocess mode the counts go to the folder's files all the same)
        self.registry = CollectorRegistry(auto_describe=True)
        self.request_duration = Histogram(
            "invisible_map_http_request_duration_seconds",
            "Time to answer a request, by method, route template and status class",
            ["method", "route", "status_class"],
            buckets=REQUEST_BUCKETS_S,
            registry=self.registry,
        )
        self.upload_refusals = Counter(
            "invisible_map_upload_refusals",
            "Uploads refused (4xx), by upload (session, image) and reason (the error's code)",
            ["upload", "reason"],
            registry=self.registry,
        )
        self.queue = QueueCollector(database=database, alive_within_s=alive_within_s)
        self.registry.register(self.queue)

    def observe(self, *, method: str, route: str, status: int, duration_s: float) -> None:
        method = method if method in METHODS else "other"
        self.request_duration.labels(method, route, f"{status // 100}xx").observe(duration_s)

    def refused(self, *, upload: str, reason: str) -> None:
        self.upload_refusals.labels(upload, reason).inc()

    def exposition(self) -> bytes:
        """Every series in the Prometheus text format (this process's, or in multiprocess mode
        all API processes' summed), and the database's as read now."""
        folder = multiprocess_dir()
        if folder is None:
            return generate_latest(self.registry)
        registry = CollectorRegistry()
        MultiProcessCollector(registry, path=folder)  # type: ignore[no-untyped-call]
        registry.register(self.queue)
        return generate_latest(registry)


def route_template(scope: Scope, templates: Mapping[int, str]) -> str:
    """The whole template of the route that answered (``/v1/maps/{map_id}``), or
    :data:`UNMATCHED`; ``templates``: :func:`route_templates` of the app's routes.

    ``scope["route"]`` is the route as its router declared it; FastAPI ≥ 0.16x keeps an included
    router's routes as they are (``/sessions``) and the prefixes it was included with apart, so
    the whole template comes from ``templates``. With an older FastAPI, which copies included
    routes with their prefix, the route's own path is the whole template."""
    route = scope.get("route")
    if route is None:
        return UNMATCHED
    template = templates.get(id(route))
    if template is not None:
        return template
    path = getattr(route, "path", None)
    if not isinstance(path, str):
        return UNMATCHED
    return f"{path}/{{path}}" if isinstance(route, Mount) else path


def route_templates(routes: Sequence[BaseRoute]) -> dict[int, str]:
    """Each route object's whole template, by ``id`` (none for a route included twice), read
    from :func:`fastapi.routing.iter_route_contexts`; empty with a FastAPI without it."""
    try:
        from fastapi.routing import iter_route_contexts
    except ImportError:  # FastAPI before included routers kept their routes apart
        return {}
    templates: dict[int, str] = {}
    twice: set[int] = set()
    for context in iter_route_contexts(routes):
        key, template = id(context.original_route), context.path_format
        if not isinstance(template, str) or templates.get(key, template) != template:
            twice.add(key)
        else:
            templates[key] = template
    return {key: template for key, template in templates.items() if key not in twice}


class RequestMetrics:
    """ASGI middleware: times every HTTP request into ``metrics`` by its route template and
    status class, and counts the refusals (4xx) of the upload routes by their error ``code``
    (``{"detail", "code", "field"}``: ``app.web.errors``). Add it outermost, so that what the
    other middleware does is timed too."""

    def __init__(self, app: ASGIApp, *, metrics: ApiMetrics) -> None:
        self.app = app
        self.metrics = metrics
        #: the app's route templates (:func:`route_templates`), once its routes are all there
        self._templates: dict[int, str] | None = None

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        started_s = time.perf_counter()
        if self._templates is None:  # at the first request: every router is included by then
            self._templates = route_templates(scope["app"].routes)
        templates = self._templates
        status: int | None = None
        upload: str | None = None
        body = bytearray()

        async def timed_send(message: Message) -> None:
            nonlocal status, upload
            if message["type"] == "http.response.start":
                status = int(message["status"])
                if 400 <= status < 500:
                    upload = UPLOAD_ROUTES.get((scope["method"], route_template(scope, templates)))
            elif message["type"] == "http.response.body" and upload is not None:
                body.extend(message.get("body", b"")[: max(REFUSAL_BODY_BYTES - len(body), 0)])
            await send(message)

        try:
            await self.app(scope, receive, timed_send)
        except BaseException:
            if status is None:
                status = 500  # what the server's error middleware answers
            raise
        finally:
            if status is not None:
                self.metrics.observe(
                    method=scope["method"],
                    route=route_template(scope, templates),
                    status=status,
                    duration_s=time.perf_counter() - started_s,
                )
                if upload is not None:
                    self.metrics.refused(upload=upload, reason=refusal_reason(status, bytes(body)))


def refusal_reason(status: int, body: bytes) -> str:
    """A refusal's reason: its error body's ``code`` (``payload_too_large``, ``rate_limited``,
    …), else ``http_<status>``."""
    try:
        code = json.loads(body).get("code")
    except (ValueError, AttributeError):
        code = None
    if isinstance(code, str) and _CODE.fullmatch(code):
        return code
    return f"http_{status}"


class QueueCollector(Collector):
    """The job queue's series, read from the database at each scrape (``app.storage.job_metrics``:
    a few aggregate queries in one read transaction). If the database does not answer, only
    ``invisible_map_database_up 0`` is there (and a warning is logged)."""

    def __init__(self, *, database: Callable[[], Database | None], alive_within_s: float) -> None:
        self.database = database
        self.alive_within_s = alive_within_s

    def describe(self) -> Iterator[Metric]:
        return iter(())  # read at scrape time only (auto_describe would query the database)

    def collect(self) -> Iterator[Metric]:
        up = GaugeMetricFamily(
            "invisible_map_database_up",
            "Whether the database answered this scrape's queries (1) or not (0)",
        )
        db = self.database()
        try:
            if db is None:
                raise RuntimeError("the app's database is not open")
            metrics = self._read(db)
        except Exception as err:
            logger.warning("metrics: could not read the queue from the database: %s", err)
            up.add_metric([], 0)
            yield up
            return
        up.add_metric([], 1)
        yield up
        yield from metrics

    def _read(self, db: Database) -> list[Metric]:
        now = utc_now()
        with db.read() as db_session:
            depth = job_metrics.queue_depth(db_session)
            oldest = job_metrics.oldest_queued_at(db_session)
            finished = job_metrics.finished_jobs(db_session)
            durations = job_metrics.job_durations(db_session, JOB_BUCKETS_S)
            stages = job_metrics.stage_durations(db_session, STAGE_BUCKETS_S)
            workers = job_metrics.workers_alive(db_session, within_s=self.alive_within_s, now=now)
        kinds = sorted({*JOB_KINDS, *(kind for kind, _ in (*depth, *finished))})
        return [
            _gauge(
                "invisible_map_queue_jobs",
                "Jobs in the queue now, by kind and state (queued: waiting, some after a "
                "back-off; running: claimed by a worker)",
                ["kind", "state"],
                {(k, s.value): depth.get((k, s.value), 0) for k in kinds for s in QUEUE_STATES},
            ),
            _gauge(
                "invisible_map_queue_oldest_job_age_seconds",
                "How long the oldest queued job of each kind has waited (0: none queued)",
                ["kind"],
                {(k,): _age_s(oldest.get(k), now) for k in kinds},
            ),
            _counter(
                "invisible_map_jobs_finished",
                "Jobs that finished, by kind and final state (succeeded, failed, canceled)",
                ["kind", "state"],
                {
                    (k, s.value): finished.get((k, s.value), 0)
                    for k in kinds
                    for s in sorted(TERMINAL_STATES)
                },
            ),
            _histogram(
                "invisible_map_job_duration_seconds",
                "How long finished jobs ran (their last attempt, start to end), by kind and "
                "final state",
                ["kind", "state"],
                durations,
                JOB_BUCKETS_S,
            ),
            _histogram(
                "invisible_map_job_stage_duration_seconds",
                "How long each stage of a job took (stages that ran to their end), by kind "
                "and stage",
                ["kind", "stage"],
                stages,
                STAGE_BUCKETS_S,
            ),
            _counter(
                "invisible_map_builds_failed",
                "Map builds (build_map jobs) that failed for good",
                [],
                {(): finished.get((BUILD_MAP, "failed"), 0)},
            ),
            _gauge(
                "invisible_map_workers_alive",
                "Worker processes that reported within the last three heartbeats, by state",
                ["state"],
                {(state,): workers.get(state, 0) for state in sorted({*WORKER_STATES, *workers})},
            ),
        ]


def _gauge(
    name: str, documentation: str, labels: list[str], values: dict[tuple[str, ...], float]
) -> Metric:
    family = GaugeMetricFamily(name, documentation, labels=labels)
    for key, value in values.items():
        family.add_metric(list(key), value)
    return family


def _counter(
    name: str, documentation: str, labels: list[str], values: dict[tuple[str, ...], float]
) -> Metric:
    family = CounterMetricFamily(name, documentation, labels=labels)
    for key, value in values.items():
        family.add_metric(list(key), value)
    return family


def _histogram(
    name: str,
    documentation: str,
    labels: list[str],
    distributions: dict[tuple[str, str], Distribution],
    bounds_s: tuple[float, ...],
) -> Metric:
    family = HistogramMetricFamily(name, documentation, labels=labels)
    for key, distribution in sorted(distributions.items()):
        buckets = [
            (str(float(bound)), float(below))
            for bound, below in zip(bounds_s, distribution.below, strict=True)
        ]
        buckets.append(("+Inf", float(distribution.count)))
        family.add_metric(list(key), buckets, sum_value=distribution.sum_s)
    return family


def _age_s(since: datetime | None, now: datetime) -> float:
    return 0.0 if since is None else max((now - since).total_seconds(), 0.0)
