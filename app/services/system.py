"""The server itself: its version, which workers count as alive, the worker processes it
supervises.

What the API routers and the dashboard pages both do; errors are :mod:`app.services.errors`.
"""

from __future__ import annotations

from functools import lru_cache
from importlib.metadata import PackageNotFoundError, version
from typing import Protocol


@lru_cache
def package_version() -> str:
    """The installed ``invisible-map`` version."""
    try:
        return version("invisible-map")
    except PackageNotFoundError:
        return "0+unknown"


#: A worker counts as alive if it reported within this many heartbeat periods.
ALIVE_HEARTBEATS = 3


class WorkerPool(Protocol):
    """The worker processes this API process supervises (``serve --workers N``, embedded mode;
    ``workers.supervisor.WorkerSupervisor``). An API without one (``--workers 0``, scale-out)
    does not know the workers beyond their rows in the ``worker`` table."""

    @property
    def configured(self) -> int:
        """How many worker processes it keeps."""

    @property
    def alive(self) -> int:
        """How many are alive now."""

    @property
    def restarts(self) -> int:
        """How many were started in place of one that died."""


def no_worker_alive(pool: WorkerPool | None) -> str | None:
    """Why this server cannot build maps now (none of its worker processes is alive), or None
    (it has some alive, or supervises none)."""
    if pool is None or pool.configured == 0:
        return None
    if pool.alive > 0:
        return None
    return (
        f"no worker process is alive (0 of {pool.configured}; restarted {pool.restarts} "
        "time(s) so far): uploads are queued but no map is built until one is back"
    )
