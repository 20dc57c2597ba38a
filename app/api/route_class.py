"""The API's route class: a route's database transaction ends when the route function returns.

    router = APIRouter(prefix="/maps", route_class=SessionEndingRoute)

Routes are plain ``def`` functions, so FastAPI runs each on a thread of anyio's pool (the
dependencies on others, and the validation of the answer on yet another). A request's
transaction (``ReadDbSessionDep``, ``WriteDbSessionDep``) would otherwise end only when its
dependency exits, after the answer has been validated: in between, the request holds a pooled
connection while it waits for a free thread. With more requests at once than threads plus
connections, every thread then waits for a connection and every connection for a thread, and the
API stands still until the pool's timeout (the load test of ``bench/load.py`` found this).

So a route function's sessions end as it returns: a write session commits, a read session rolls
back, and the connection goes back to the pool before the request waits for another thread. If
the function raises, nothing is committed (the dependency rolls back, as before). The validators
of ``app.api.deps`` use their own short transactions for the same reason.
"""

from __future__ import annotations

import functools
import inspect
from collections.abc import Callable
from typing import Any

from fastapi.routing import APIRoute
from sqlalchemy.orm import Session

from app.storage.db import end_transaction


class SessionEndingRoute(APIRoute):
    """An :class:`APIRoute` whose (synchronous) endpoint ends its sessions as it returns."""

    def __init__(self, path: str, endpoint: Callable[..., Any], **kwargs: Any) -> None:
        if not inspect.iscoroutinefunction(endpoint):
            endpoint = ending_sessions(endpoint)
        super().__init__(path, endpoint, **kwargs)


def ending_sessions(endpoint: Callable[..., Any]) -> Callable[..., Any]:
    """``endpoint``, which on returning ends the transaction of each session it was given."""

    @functools.wraps(endpoint)
    def ended(*args: Any, **kwargs: Any) -> Any:
        result = endpoint(*args, **kwargs)
        for value in kwargs.values():
            if isinstance(value, Session):
                end_transaction(value)
        return result

    return ended
