"""Settings from the environment (pydantic-settings), checked once at start-up.

Variables (defaults in brackets): ``DATABASE_URL`` [a SQLite file in the data directory],
``INVISIBLE_MAP_DATA_DIR`` [./var], ``INVISIBLE_MAP_ADMIN_KEY`` [unset: accepted as an admin key
when set], ``INVISIBLE_MAP_WORKERS`` [1: worker processes ``serve`` starts],
``INVISIBLE_MAP_API_PROCESSES`` [unset: the machine's cores, at most 8: API processes ``serve``
runs; see ``api_processes``],
``INVISIBLE_MAP_API_THREADS`` [400: threads for the API's requests; see ``api_threads``],
``INVISIBLE_MAP_KEEP_ALIVE_S`` [75: how long ``serve`` keeps an idle connection open; see
``keep_alive_s``],
``INVISIBLE_MAP_MAX_UPLOAD_BYTES`` [32 MiB: the body as sent], ``INVISIBLE_MAP_MAX_SESSION_BYTES``
[256 MiB: the body after gunzip], ``INVISIBLE_MAP_MAX_REQUEST_BYTES`` [4 MiB: any other request's
body], ``INVISIBLE_MAP_MAX_POSES`` [100,000 poses per session], ``INVISIBLE_MAP_LEASE_S``
[30], ``INVISIBLE_MAP_HEARTBEAT_S`` [5], ``INVISIBLE_MAP_POLL_S`` [0.25: how often an idle
worker looks for work],
``INVISIBLE_MAP_MAX_ATTEMPTS`` [3], ``INVISIBLE_MAP_RETRY_BACKOFF_S`` [2: first retry delay,
doubling per attempt], ``INVISIBLE_MAP_SESSION_SECRET`` [unset: a random secret kept in the file
``admin-session-secret`` of the data directory (mode 0600), so that every API process sharing
that directory agrees; it signs the admin dashboard's login cookies],
``INVISIBLE_MAP_TRUSTED_PROXIES`` [empty: the proxies whose forwarded headers are believed],
``INVISIBLE_MAP_HEADER_TIMEOUT_S`` [10], ``INVISIBLE_MAP_BODY_TIMEOUT_S`` [30],
``INVISIBLE_MAP_MAX_CONNECTIONS_PER_ADDRESS`` [128] (``app.api.connection_guard``),
``INVISIBLE_MAP_JOB_TIME_BUDGET_S`` [3600: a job attempt running longer fails for good],
``INVISIBLE_MAP_UPLOADS_PER_MINUTE`` [30 per device key],
``INVISIBLE_MAP_DEVICE_MAX_AUTO_TUNE_TRIALS`` [20], ``INVISIBLE_MAP_DB_LOCK_TIMEOUT_S`` [5],
``INVISIBLE_MAP_DB_STATEMENT_TIMEOUT_S`` [120], ``INVISIBLE_MAP_DB_IDLE_IN_TRANSACTION_TIMEOUT_S``
[60] (PostgreSQL's limits on the API's and the workers' connections),
``INVISIBLE_MAP_KEY_CACHE_S`` [5: how long an API process trusts a key it checked; see
``key_cache_s``], ``INVISIBLE_MAP_MAP_CACHE_S`` [2: the same for a map's current version; see
``map_cache_s``], ``INVISIBLE_MAP_VERSION_CACHE_BYTES`` [256 MiB: documents kept per process],
``INVISIBLE_MAP_MAX_CORRIDOR_EDITS`` [5,000 corridor edits per map; see ``max_corridor_edits``],
``INVISIBLE_MAP_LOG_FORMAT`` [text; or json: one JSON object per log line].
"""

from __future__ import annotations

import os
from functools import lru_cache
from ipaddress import ip_network
from pathlib import Path
from typing import Literal

from pydantic import AliasChoices, Field, field_validator, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

SQLITE_FILE_NAME = "invisible-map.sqlite3"
MIN_ADMIN_KEY_LENGTH = 16
MIN_SESSION_SECRET_LENGTH = 32
#: The most API processes ``serve`` runs.
MAX_API_PROCESSES = 64
#: The most API processes ``serve`` runs by default, whatever the cores.
DEFAULT_API_PROCESSES_CAP = 8


def default_api_processes() -> int:
    """``serve``'s API processes when neither ``--api-processes`` nor
    ``INVISIBLE_MAP_API_PROCESSES`` says: one per core this process may run on (its CPU
    affinity, so a container's limit counts), at least 1 and at most
    :data:`DEFAULT_API_PROCESSES_CAP`."""
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        cores = os.cpu_count() or 1
    return max(1, min(cores, DEFAULT_API_PROCESSES_CAP))


class Settings(BaseSettings):
    """Everything the API, the workers and the CLI read from the environment."""

    model_config = SettingsConfigDict(env_prefix="INVISIBLE_MAP_", extra="ignore")

    database_url: str = Field(
        default="",
        validation_alias=AliasChoices("DATABASE_URL", "INVISIBLE_MAP_DATABASE_URL"),
        description="SQLAlchemy URL; empty means a SQLite file in data_dir",
    )
    data_dir: Path = Path("var")
    admin_key: str | None = None
    workers: int = Field(default=1, ge=0, le=64)
    #: How much lower the CPU priority of worker processes is than the API's (``nice``
    #: increment, 0–19): on a machine they share, a phone's route or localization update is
    #: answered first and a map build takes what is left.
    worker_nice: int = Field(default=10, ge=0, le=19)
    #: API processes ``serve`` runs on its one listening socket (``serve --api-processes N``);
    #: None: :func:`default_api_processes`, what the machine's cores suggest.
    api_processes: int | None = Field(default=None, ge=1, le=MAX_API_PROCESSES)
    #: Threads for the API's ``def`` routes and dependencies (anyio's limiter; its default is
    #: 40): how many requests may be inside a route at once (the rest wait their turn). A
    #: request holds a database connection only while one of its threads runs
    #: (``app.web.route_class``), so no number of threads can starve the pool. Threads start only
    #: when needed, so a large number costs nothing until that many requests come at once.
    api_threads: int = Field(default=400, ge=1, le=4096)
    #: How long ``serve`` keeps an idle keep-alive connection open, in seconds (uvicorn's
    #: ``timeout_keep_alive``; its default is 5). A server that closes an idle connection races
    #: with a client sending its next request on it, and that request fails unanswered. So the
    #: server waits longer than its clients and proxies keep idle connections (httpx: 5 s;
    #: nginx's upstream keepalive and AWS load balancers: 60 s), and they are the ones that
    #: close them. Keep it above the idle timeout of any proxy in front of the API.
    keep_alive_s: int = Field(default=75, ge=1)
    #: ``serve``: a request's line and headers must arrive within this, s (0: no limit;
    #: ``app.api.connection_guard``).
    header_timeout_s: float = Field(default=10.0, ge=0)
    #: ``serve``: the longest pause in a request's body while it is read, s.
    body_timeout_s: float = Field(default=30.0, gt=0)
    #: ``serve``: connections one client address may hold open (0: no cap; the trusted proxies'
    #: addresses are exempt).
    max_connections_per_address: int = Field(default=128, ge=0)
    max_upload_bytes: int = Field(default=32 * 2**20, gt=0)
    max_session_bytes: int = Field(default=256 * 2**20, gt=0)
    #: the most poses an uploaded session may have (checked before it is parsed)
    max_poses: int = Field(default=100_000, gt=0)
    #: any other request's body (routes, localization updates, keys, sweeps, dashboard forms)
    max_request_bytes: int = Field(default=4 * 2**20, gt=0)
    lease_s: float = Field(default=30.0, gt=0)
    heartbeat_s: float = Field(default=5.0, gt=0)
    poll_s: float = Field(default=0.25, gt=0)
    max_attempts: int = Field(default=3, ge=1)
    retry_backoff_s: float = Field(default=2.0, ge=0)
    #: PostgreSQL: the longest an API request or a worker waits for a row lock, s.
    db_lock_timeout_s: float = Field(default=5.0, gt=0)
    #: PostgreSQL: the longest one statement runs, s.
    db_statement_timeout_s: float = Field(default=120.0, gt=0)
    #: PostgreSQL: a connection idle this long inside a transaction (its process stalled) is
    #: ended by the server, and the locks it held are released, s.
    db_idle_in_transaction_timeout_s: float = Field(default=60.0, gt=0)
    #: Uploads one device key may make per minute (per API process; 0: no limit): 429 with
    #: Retry-After beyond.
    uploads_per_minute: int = Field(default=30, ge=0)
    #: The most auto-tuning trials a device key may ask for with an upload (admins: 1000).
    device_max_auto_tune_trials: int = Field(default=20, ge=0, le=1000)
    #: A job attempt that runs longer than this fails for good, with the reason (0: no budget).
    job_time_budget_s: float = Field(default=3600.0, ge=0)
    #: Building maps made incremental (issue 38; ``INVISIBLE_MAP_INCREMENTAL_BUILDS``): a build
    #: that adds or takes out one walk of a map whose current version has a current ISAM2 state
    #: (``app.storage.isam_states``) makes that change in the state restored from the database
    #: (``incremental.changes``) and serves the engine's map, no batch solve, unless the batch
    #: build's later steps would change a walk there (a walk rescaled, a tag set apart, a walk
    #: down-weighted: ``incremental.served_map``), which the job's log then names. Off by default;
    #: every batch build of several walks stores its state either way.
    incremental_builds: bool = False
    #: With incremental builds on (``INVISIBLE_MAP_INCREMENTAL_CHECK``): run the batch build too
    #: and serve it, and log how far the engine's map is from it (the bounds: 1 cm tags, 5 cm
    #: poses), to check the engine on a lab's own walks before trusting it.
    incremental_check: bool = False
    #: How long an API process answers from its memory of a key it checked, s (0: every request
    #: reads the key). The bound on seeing a revocation made by another process (the CLI,
    #: another API process); a revocation in this process and a key's ``expires_at`` count at
    #: once (docs/api.md, "Caching and consistency").
    key_cache_s: float = Field(default=5.0, ge=0, le=3600)
    #: How long an API process answers from its memory of a map (its current version, newest
    #: job), s (0: every request reads it). The bound on seeing another process's change of a
    #: map whose newest job has finished; a map whose job is queued or running is read on every
    #: request, and this process's own changes count at once.
    map_cache_s: float = Field(default=2.0, ge=0, le=3600)
    #: The most bytes of documents made from map versions (app-map, GeoJSON, map documents)
    #: one API process keeps.
    version_cache_bytes: int = Field(default=256 * 2**20, ge=0)
    #: The most corridor edits one map may hold (a POST past it: 409 too_many_corridor_edits).
    #: 5,000: several per node of the largest graphs we build (~1,000 nodes), and what a new
    #: version, a deleted edit or another process applies again once in under 1 s of CPU
    #: (10,000: ~1.7 s; docs/navigation.md "Corridor edits", bench/corridor_edits.py --scale).
    max_corridor_edits: int = Field(default=5_000, ge=1, le=100_000)
    session_secret: str | None = Field(
        default=None,
        description="signs the admin dashboard's cookies; unset: a random secret in data_dir",
    )
    #: The proxies in front of ``serve`` whose ``X-Forwarded-For`` / ``X-Forwarded-Proto`` are
    #: believed: addresses or networks, comma-separated (``"127.0.0.1,10.0.0.0/8"``). Empty (the
    #: default): none; the client address is the TCP peer's, and forwarded headers are ignored
    #: (anyone could send them).
    trusted_proxies: str = ""
    #: How ``serve`` and ``worker`` write their log (``--log-format``): ``text``, one line per
    #: record as before, or ``json``, one JSON object per line (docs/operations.md, "Logs").
    log_format: Literal["text", "json"] = "text"

    @field_validator("database_url")
    @classmethod
    def _psycopg_driver(cls, url: str) -> str:
        """``postgres://`` and ``postgresql://`` mean psycopg 3 here (SQLAlchemy's default is 2)."""
        for prefix in ("postgres://", "postgresql://"):
            if url.startswith(prefix):
                return "postgresql+psycopg://" + url.removeprefix(prefix)
        return url

    @field_validator("trusted_proxies")
    @classmethod
    def _addresses(cls, proxies: str) -> str:
        entries = [entry.strip() for entry in proxies.split(",") if entry.strip()]
        for entry in entries:
            try:
                ip_network(entry, strict=False)
            except ValueError:
                raise ValueError(
                    f"INVISIBLE_MAP_TRUSTED_PROXIES: {entry!r} is no IP address or network"
                ) from None
        return ",".join(entries)

    @field_validator("admin_key")
    @classmethod
    def _long_enough(cls, key: str | None) -> str | None:
        if key is not None and len(key) < MIN_ADMIN_KEY_LENGTH:
            raise ValueError(
                f"INVISIBLE_MAP_ADMIN_KEY must be at least {MIN_ADMIN_KEY_LENGTH} characters"
            )
        return key or None

    @field_validator("session_secret")
    @classmethod
    def _secret_long_enough(cls, secret: str | None) -> str | None:
        if secret and len(secret) < MIN_SESSION_SECRET_LENGTH:
            raise ValueError(
                f"INVISIBLE_MAP_SESSION_SECRET must be at least {MIN_SESSION_SECRET_LENGTH} "
                "characters"
            )
        return secret or None

    @model_validator(mode="after")
    def _heartbeat_within_lease(self) -> Settings:
        if self.heartbeat_s >= self.lease_s:
            raise ValueError(
                f"INVISIBLE_MAP_HEARTBEAT_S ({self.heartbeat_s} s) must be shorter than "
                f"INVISIBLE_MAP_LEASE_S ({self.lease_s} s)"
            )
        return self

    @property
    def resolved_database_url(self) -> str:
        """``database_url``, or the embedded SQLite file in ``data_dir``."""
        if self.database_url:
            return self.database_url
        return f"sqlite:///{(self.data_dir / SQLITE_FILE_NAME).resolve()}"

    @property
    def is_sqlite(self) -> bool:
        return self.resolved_database_url.startswith("sqlite")


@lru_cache
def get_settings() -> Settings:
    """The process's settings (cached; tests build their own ``Settings``)."""
    return Settings()
