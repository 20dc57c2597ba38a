"""The server itself: its version, which workers count as alive.

What the API routers and the dashboard pages both do; errors are :mod:`app.services.errors`.
"""

from __future__ import annotations

from functools import lru_cache
from importlib.metadata import PackageNotFoundError, version


@lru_cache
def package_version() -> str:
    """The installed ``invisible-map`` version."""
    try:
        return version("invisible-map")
    except PackageNotFoundError:
        return "0+unknown"


#: A worker counts as alive if it reported within this many heartbeat periods.
ALIVE_HEARTBEATS = 3
