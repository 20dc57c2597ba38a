"""``/metrics``: the server's metrics in the Prometheus text format, for an admin key
(``app.observability.metrics``; docs/operations.md, "Metrics")."""

from __future__ import annotations

from fastapi import APIRouter, Request, Response
from prometheus_client import CONTENT_TYPE_LATEST

from app.observability.metrics import ApiMetrics
from app.web.deps import AdminPrincipal
from app.web.route_class import SessionEndingRoute

router = APIRouter(tags=["system"], route_class=SessionEndingRoute)


@router.get("/metrics", include_in_schema=False)
def metrics(request: Request, _admin: AdminPrincipal) -> Response:
    """Request latency, upload refusals, and the job queue as the database has it now (401
    without a key, 403 for a device key). A plain ``def``: the queue is read on a thread."""
    api_metrics: ApiMetrics = request.app.state.metrics
    return Response(api_metrics.exposition(), media_type=CONTENT_TYPE_LATEST)
