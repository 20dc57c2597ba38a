"""The API's route class: a route's database transaction ends when the route function returns,
and a JSON body is read by orjson.

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
of ``app.web.deps`` use their own short transactions for the same reason.

A route with a body gets an :class:`OrjsonRequest`: FastAPI reads JSON bodies with
``Request.json()``, the standard library's parser, ~6× slower than orjson on a localization
update's 2 KB (34 vs 6 µs). It is also the door of every JSON body: a string anywhere in it (a
value or an object's key) that no database can hold as text is refused with a 422 naming its
path (:class:`UnstorableText`), before the route runs (issue 28, finding 1).
"""

from __future__ import annotations

import functools
import inspect
import json
from collections.abc import Callable, Coroutine
from typing import Any

import orjson
from fastapi import Request, Response
from fastapi.routing import APIRoute
from sqlalchemy.orm import Session
from starlette.exceptions import HTTPException

from app.domain.upload.fields import json_text_fault
from app.storage.db import end_transaction


class SessionEndingRoute(APIRoute):
    """An :class:`APIRoute` whose (synchronous) endpoint ends its sessions as it returns, and
    whose body, if it has one, is read as JSON by orjson (:class:`OrjsonRequest`)."""

    def __init__(self, path: str, endpoint: Callable[..., Any], **kwargs: Any) -> None:
        if not inspect.iscoroutinefunction(endpoint):
            endpoint = ending_sessions(endpoint)
        super().__init__(path, endpoint, **kwargs)

    def get_route_handler(self) -> Callable[[Request], Coroutine[Any, Any, Response]]:
        handler = super().get_route_handler()
        if self.body_field is None:
            return handler

        async def reading_json_with_orjson(request: Request) -> Response:
            return await handler(OrjsonRequest(request.scope, request.receive))

        return reading_json_with_orjson


class OrjsonRequest(Request):
    """A request whose JSON body orjson reads. A body orjson refuses (``NaN``, a number beyond
    float64's range, a lone surrogate, UTF-16, malformed JSON) goes to the standard library's
    parser as before, so it reads as it did, and every error is the one it was.

    One difference: an integer literal beyond 64 bits (below -2^63 or above 2^64 - 1) reads as
    the nearest float, not as an exact int. Every integer the API takes (ids, counts) must stay
    within 2^53, so such a number is refused either way, naming its field; the message shows the
    float."""

    async def json(self) -> Any:
        if not hasattr(self, "_json"):
            body = await self.body()
            try:
                document = orjson.loads(body)
                # In UTF-8 JSON a NUL or a lone surrogate can only be a \u escape (a raw NUL is
                # invalid JSON, a surrogate's bytes invalid UTF-8): without one, no walk.
                suspect = b"\\u" in body
            except orjson.JSONDecodeError:
                try:
                    document = json.loads(body)  # a lone surrogate, UTF-16, NaN, …: walked
                except UnicodeDecodeError as err:  # answered as any other malformed body
                    raise json.JSONDecodeError(f"not UTF-8 text ({err.reason})", "", 0) from err
                suspect = True
            fault = json_text_fault(document) if suspect else None
            if fault is not None:
                raise UnstorableText(*fault)
            self._json = document
        return self._json


class UnstorableText(HTTPException):
    """Raised (422) for a JSON body holding a string no database can hold as text (a NUL, a
    lone surrogate: :func:`app.domain.upload.fields.text_fault`); ``field`` is its path.

    An HTTPException, because FastAPI passes those on from reading a body (any other error
    there becomes a 400 without the field)."""

    def __init__(self, field: str, reason: str) -> None:
        super().__init__(422, f"{field}: {reason}" if field else reason)
        self.field = field or None


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
