"""Pydantic v2 models of the HTTP API, one family per resource (as the FastAPI template does):
``…Public`` is what a GET returns, ``…sPublic`` a page of them (``data``, ``count``, ``limit``,
``offset``), ``…Create``/``…Request`` what a client sends. Storage returns frozen dataclasses;
``from_domain`` converts at the edge. Every model carries an example, so that the OpenAPI document
shows one for every request and response.

One module per router: ``common`` (example values; the error body is ``app.web.errors.ErrorBody``),
``sessions``, ``jobs``, ``maps``, ``keys``, ``system``, ``navigation``, ``sweeps``.
"""

from __future__ import annotations

from app.api.schemas.jobs import JobBrief, JobPublic, JobsPublic
from app.api.schemas.keys import KeyCreate, KeyCreated, KeyPublic, KeysPublic
from app.api.schemas.maps import (
    AppMap,
    AppOdometryVertex,
    AppTagVertex,
    AppWaypointVertex,
    MapPublic,
    MapsPublic,
    MapSummary,
    Quaternion,
    RebuildAccepted,
    RebuildRequest,
    TagPosePublic,
    Vector3,
    VersionDetail,
    VersionPublic,
    VersionsPublic,
    VersionSummary,
)
from app.api.schemas.sessions import (
    SessionCreated,
    SessionPublic,
    SessionsPublic,
    SessionStatisticsPublic,
)
from app.api.schemas.system import Health, Info, Ready, WorkerPublic
from app.web.errors import ErrorBody

__all__ = [
    "AppMap",
    "AppOdometryVertex",
    "AppTagVertex",
    "AppWaypointVertex",
    "ErrorBody",
    "Health",
    "Info",
    "JobBrief",
    "JobPublic",
    "JobsPublic",
    "KeyCreate",
    "KeyCreated",
    "KeyPublic",
    "KeysPublic",
    "MapPublic",
    "MapSummary",
    "MapsPublic",
    "Quaternion",
    "Ready",
    "RebuildAccepted",
    "RebuildRequest",
    "SessionCreated",
    "SessionPublic",
    "SessionStatisticsPublic",
    "SessionsPublic",
    "TagPosePublic",
    "Vector3",
    "VersionDetail",
    "VersionPublic",
    "VersionSummary",
    "VersionsPublic",
    "WorkerPublic",
]
