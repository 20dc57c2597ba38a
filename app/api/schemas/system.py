"""Schemas of the system router: health, readiness, info, workers."""

from __future__ import annotations

from datetime import datetime
from typing import Any, Literal

from pydantic import BaseModel, Field

from app.api.schemas.common import AT_EXAMPLE, LATER_EXAMPLE, examples


class Health(BaseModel):
    """The process is up."""

    model_config = examples({"status": "ok"})

    status: Literal["ok"] = "ok"


class Ready(BaseModel):
    """The database answers and its schema is at the newest migration."""

    model_config = examples(
        {"status": "ready", "database": "postgresql", "schema_revision": "0001_initial"}
    )

    status: Literal["ready"] = "ready"
    database: str = Field(description="sqlite or postgresql")
    schema_revision: str | None


_WORKER_EXAMPLE: dict[str, Any] = {
    "id": "host-1:4242",
    "hostname": "host-1",
    "pid": 4242,
    "state": "busy",
    "current_job_id": 31,
    "jobs_done": 12,
    "started_at": AT_EXAMPLE,
    "heartbeat_at": LATER_EXAMPLE,
}


class WorkerPublic(BaseModel):
    """A worker process that reported recently."""

    model_config = examples(_WORKER_EXAMPLE)

    id: str
    hostname: str
    pid: int
    state: str = Field(description="idle or busy (or what the worker reports)")
    current_job_id: int | None
    jobs_done: int
    started_at: datetime
    heartbeat_at: datetime


class WorkerProcesses(BaseModel):
    """The worker processes ``serve`` supervises (embedded mode): it restarts any that dies."""

    model_config = examples({"configured": 1, "alive": 1, "restarts": 0})

    configured: int = Field(description="how many it keeps (`--workers`)")
    alive: int = Field(description="how many are alive now")
    restarts: int = Field(description="how many were started in place of one that died")


class Info(BaseModel):
    """The server: its version, database, queue and workers."""

    model_config = examples(
        {
            "version": "0.1.0",
            "database": "postgresql",
            "queue_depth": 2,
            "jobs_by_state": {
                "queued": 2,
                "running": 1,
                "succeeded": 40,
                "failed": 0,
                "canceled": 1,
            },
            "workers": [_WORKER_EXAMPLE],
            "worker_processes": {"configured": 1, "alive": 1, "restarts": 0},
            "warnings": [],
            "principal": {"subject": "key:3", "role": "device"},
        }
    )

    version: str = Field(description="the invisible-map package version")
    database: str = Field(description="sqlite or postgresql")
    queue_depth: int = Field(description="jobs waiting (queued)")
    jobs_by_state: dict[str, int]
    workers: list[WorkerPublic] = Field(description="workers alive (heartbeat in 3 × heartbeat_s)")
    worker_processes: WorkerProcesses | None = Field(
        default=None,
        description="the worker processes this server supervises (`serve --workers N`); null "
        "when it supervises none (`--workers 0`: workers run elsewhere)",
    )
    warnings: list[str] = Field(
        default_factory=list,
        description="what keeps the server from doing its work now, e.g. that none of its "
        "worker processes is alive (uploads are then queued, no map is built)",
    )
    principal: dict[str, str] = Field(description="who the presented key stands for")
