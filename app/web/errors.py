"""One error body everywhere: ``{"detail": "…", "code": "invalid_session", "field": "…"}``.

Routes raise :class:`ApiError`, services a :class:`~app.services.errors.ServiceError`, and
storage and domain errors pass through (``app.services.errors.STATUS_OF_ERROR`` says what each
means); the handlers of :func:`install_error_handlers` turn each into that body and status. No
stack trace, SQL or internal message ever reaches a client: anything unexpected is a 500 with a
generic message (and a full log line on the server).

What becomes what::

    ApiError(status, code, detail, field)      as raised (401 also sends WWW-Authenticate: Bearer)
    ServiceError (NotFound, Conflict, …)       its class's status, its code, detail and field
    RequestValidationError                     422 validation_error, field = the parameter's path
                                               (a body that is no JSON: 400 invalid_json, and
                                               no body where one is needed: 422, field = body)
    UnstorableText (app.web.route_class)       422 validation_error, field = the JSON body's
                                               string that no database can hold (NUL, …)
    SessionFormatError                         422 invalid_session, field = the upload's JSON path
    ParameterError                             422 invalid_parameter
    MapNotFound, JobNotFound,
    SessionNotFound, KeyNotFound,
    LocalizationNotFound                       404 not_found
    InvalidTransition                          409 invalid_transition (names the job's state)
    IdempotencyConflict                        409 idempotency_conflict
    a database fault (app.storage.db)          503 database_unavailable, storage_full,
                                               storage_read_only or storage_unavailable, with
                                               Retry-After; nothing of the request was stored
    starlette HTTPException (404 route, 405)   its status, code from the status
    anything else                              500 internal_error
"""

from __future__ import annotations

import logging
import math
import re
from collections.abc import Sequence
from decimal import Decimal
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from pydantic import BaseModel, ConfigDict, Field
from sqlalchemy.exc import DBAPIError
from sqlalchemy.exc import TimeoutError as PoolTimeout
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.requests import ClientDisconnect

from app.domain.errors import SessionFormatError
from app.services.errors import STATUS_OF_ERROR, ServiceError
from app.storage.db import DatabaseFault, database_fault, first_line

logger = logging.getLogger(__name__)

#: The ``code`` of an error body for a bare status (404 route, 405 method, …).
CODE_OF_STATUS = {
    400: "bad_request",
    401: "unauthorized",
    403: "forbidden",
    404: "not_found",
    405: "method_not_allowed",
    406: "not_acceptable",
    409: "conflict",
    413: "payload_too_large",
    415: "unsupported_media_type",
    422: "validation_error",
    429: "rate_limited",
    500: "internal_error",
    503: "service_unavailable",
}

BEARER_CHALLENGE = 'Bearer realm="invisible-map"'


class ErrorBody(BaseModel):
    """Every error response: what went wrong, a stable code, and the field at fault if any."""

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "detail": "pose_data[3].pose: rotation not orthonormal",
                    "code": "invalid_session",
                    "field": "pose_data[3].pose",
                },
                {"detail": "map 42 not found", "code": "not_found", "field": None},
            ]
        }
    )

    detail: str = Field(description="a sentence for a person")
    code: str = Field(description="stable, for programs: not_found, invalid_session, …")
    field: str | None = Field(
        default=None, description="where in the request: a JSON path, a parameter or a header"
    )


class ApiError(ServiceError):
    """An error answer of the HTTP layer itself (a missing key, a body too large): like a
    :class:`ServiceError`, with its ``status_code`` given."""

    def __init__(
        self,
        status_code: int,
        code: str,
        detail: str,
        *,
        field: str | None = None,
        headers: dict[str, str] | None = None,
    ) -> None:
        super().__init__(code, detail, field=field, headers=headers)
        self.status_code = status_code


def unauthorized(detail: str, *, invalid_token: bool = False) -> ApiError:
    """401 with the ``WWW-Authenticate: Bearer`` challenge (RFC 6750)."""
    challenge = BEARER_CHALLENGE + (', error="invalid_token"' if invalid_token else "")
    return ApiError(401, "unauthorized", detail, headers={"WWW-Authenticate": challenge})


def not_found(what: str) -> ApiError:
    return ApiError(404, "not_found", f"{what} not found")


def error_response(
    status_code: int,
    code: str,
    detail: str,
    *,
    field: str | None = None,
    headers: dict[str, str] | None = None,
) -> JSONResponse:
    body = ErrorBody(
        detail=_shown(detail), code=code, field=None if field is None else _shown(field)
    )
    return JSONResponse(body.model_dump(), status_code=status_code, headers=headers)


#: A run of more digits than this in an error's text is a number shown compactly (``%.6g``):
#: 1e308 is not echoed as 309 digits. (2^64 and 2^70, 20 and 22 digits, are still shown whole.)
MAX_DIGITS_SHOWN = 30
_LONG_NUMBER = re.compile(rf"\d{{{MAX_DIGITS_SHOWN + 1},}}(?:\.\d+)?")
#: The longest error text (detail or field) an answer carries, characters; the rest is cut.
MAX_ERROR_TEXT = 2000


def _shown(text: str) -> str:
    """``text`` as an error answer shows it: long numbers compact, at most
    :data:`MAX_ERROR_TEXT` characters, and UTF-8 (:func:`_as_text`)."""
    text = _LONG_NUMBER.sub(_compact, text)
    if len(text) > MAX_ERROR_TEXT:
        text = text[: MAX_ERROR_TEXT - 1] + "…"
    return _as_text(text)


def _compact(match: re.Match[str]) -> str:
    value = float(match.group())
    return f"{value:.6g}" if math.isfinite(value) else f"{Decimal(match.group()):.6g}"


def _as_text(text: str) -> str:
    """``text`` with any lone surrogate (which a refused value may bring into a message) written
    as an escape, ``\\ud800``: an answer must be UTF-8, and a surrogate has no encoding."""
    if text.isascii():
        return text
    return text.encode("utf-8", "backslashreplace").decode("utf-8")


def install_error_handlers(app: FastAPI) -> None:
    """Register the handlers of every error the API can answer with."""

    def handle(status_code: int, code: str) -> Any:
        async def handler(_request: Request, exc: Exception) -> JSONResponse:
            return error_response(status_code, code, str(exc))

        return handler

    app.add_exception_handler(ServiceError, _service_error)
    app.add_exception_handler(RequestValidationError, validation_error_response)
    app.add_exception_handler(StarletteHTTPException, _http_exception)
    for types, status, code in STATUS_OF_ERROR:
        for error_type in types:
            app.add_exception_handler(error_type, handle(status, code))
    app.add_exception_handler(SessionFormatError, _session_format_error)
    app.add_exception_handler(DBAPIError, _database_fault)
    app.add_exception_handler(PoolTimeout, _database_fault)
    app.add_exception_handler(ClientDisconnect, _client_disconnected)
    app.add_exception_handler(Exception, _internal_error)


async def _service_error(_request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, ServiceError)
    return error_response(
        exc.status_code, exc.code, exc.detail, field=exc.field, headers=exc.headers
    )


async def _session_format_error(_request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, SessionFormatError)
    return error_response(422, "invalid_session", str(exc), field=exc.field or None)


async def _http_exception(_request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, StarletteHTTPException)
    code = CODE_OF_STATUS.get(exc.status_code, "error")
    headers = dict(exc.headers) if exc.headers else None
    field = getattr(exc, "field", None)  # UnstorableText names the body's field
    return error_response(exc.status_code, code, str(exc.detail), field=field, headers=headers)


async def validation_error_response(_request: Request, exc: Exception) -> JSONResponse:
    """The answer to a RequestValidationError (the dashboard's JSON endpoints use it too)."""
    assert isinstance(exc, RequestValidationError)
    errors = list(exc.errors())
    if not errors:
        return error_response(422, "validation_error", "invalid request")
    first = errors[0]
    if first.get("type") == "json_invalid":  # FastAPI's parse of the body failed
        reason = str(first.get("ctx", {}).get("error", "malformed"))
        at = first.get("loc", ())[1:]
        where = f" at character {at[0]}" if at else ""
        return error_response(
            400, "invalid_json", f"the body is not valid JSON: {reason}{where}", field="body"
        )
    if first.get("type") == "missing" and tuple(first.get("loc", ())) == ("body",):
        return error_response(
            422, "validation_error", "the body is missing: this needs a JSON body", field="body"
        )
    messages = []
    for error in errors:
        where = field_path(error.get("loc", ()))
        message = str(error.get("msg", "invalid"))
        messages.append(f"{where}: {message}" if where else message)
    return error_response(
        422,
        "validation_error",
        "; ".join(messages),
        field=field_path(errors[0].get("loc", ())) or None,
    )


#: What a client is told of each database fault (503 with Retry-After: seconds).
FAULT_ANSWERS: dict[DatabaseFault, tuple[str, str]] = {
    DatabaseFault.UNAVAILABLE: (
        "the database is unavailable or busy; nothing was changed; try again shortly", "1"),
    DatabaseFault.STORAGE_FULL: (
        "the server's storage is full; nothing was stored; try again later", "60"),
    DatabaseFault.READ_ONLY: (
        "the server's storage is read-only; nothing was stored; try again later", "60"),
    DatabaseFault.CANNOT_OPEN: (
        "the server cannot open its database file (its disk is read-only, unmounted or gone); "
        "nothing was changed; try again later", "60"),
}  # fmt: skip


async def _database_fault(request: Request, exc: Exception) -> JSONResponse:
    fault = database_fault(exc)
    if fault is None:  # a bug (a constraint, a bad statement), not the database's state
        return await _internal_error(request, exc)
    logger.error(
        "%s during %s %s: %s",
        fault.value,
        request.method,
        request.url.path,
        first_line(exc),
        extra={"action": fault.value},
    )
    detail, retry_after_s = FAULT_ANSWERS[fault]
    return error_response(503, fault.value, detail, headers={"Retry-After": retry_after_s})


async def _client_disconnected(request: Request, _exc: Exception) -> JSONResponse:
    """A client that went away while sending its body (or was cut off for sending it too slowly,
    ``app.api.connection_guard``): one line of the log (a warning, like the guard's own), and an
    answer nobody reads. Nothing was stored: a body is read whole before anything is written."""
    logger.warning(
        "client disconnected while sending %s %s: nothing stored",
        request.method,
        request.url.path,
        extra={"action": "client_disconnected"},
    )
    return error_response(400, "client_disconnected", "the request's body did not arrive whole")


async def _internal_error(request: Request, exc: Exception) -> JSONResponse:
    logger.error(
        "unhandled error in %s %s",
        request.method,
        request.url.path,
        exc_info=exc,
        extra={"action": "internal_error"},
    )
    return error_response(500, "internal_error", "internal server error")


def field_path(loc: Sequence[Any]) -> str:
    """``("body", "params", "huber_k")`` → ``params.huber_k``; ``("query", "limit")`` → ``limit``;
    list indices in brackets (``pose_data[3]``)."""
    parts = list(loc)
    if parts and parts[0] in {"body", "query", "path", "header", "cookie"}:
        parts = parts[1:]
    text = ""
    for part in parts:
        if isinstance(part, int):
            text += f"[{part}]"
        else:
            text += f".{part}" if text else str(part)
    return text


# --------------------------------------------------------------------------- OpenAPI

#: status → (description, code, detail, field) of the documented example.
_EXAMPLES: dict[int, tuple[str, str, str, str | None]] = {
    400: ("Bad request", "invalid_gzip", "the body is not valid gzip: incorrect header check",
          None),
    401: ("No valid API key", "unauthorized", "missing API key: send Authorization: Bearer <key>",
          None),
    403: ("Needs an admin key", "forbidden", "this needs an admin key; yours is a device key",
          None),
    404: ("Not found", "not_found", "map 42 not found", None),
    409: ("Conflict with the resource's state", "invalid_transition",
          "job 31 is succeeded: cannot cancel it", None),
    412: ("The resource changed since it was read (If-Match)", "edits_changed",
          "the corridor edits of map 8 changed since revision 4 (now 5): read them again and "
          "retry", None),
    413: ("Body too large", "payload_too_large",
          "the body is larger than the limit of 33554432 bytes", None),
    415: ("Unsupported media type or encoding", "unsupported_media_type",
          "Content-Type must be application/json, got text/plain", "Content-Type"),
    422: ("Invalid input", "invalid_session", "pose_data[3].pose: rotation not orthonormal",
          "pose_data[3].pose"),
    429: ("Too many uploads with this key (see Retry-After)", "rate_limited",
          "this key uploaded 30 sessions in the last minute, its limit; try again in 12 s", None),
    503: ("The database is unavailable, full or read-only (database_unavailable, storage_full, "
          "storage_read_only, storage_unavailable); nothing was changed", "database_unavailable",
          "the database is unavailable or busy; nothing was changed; try again shortly", None),
}  # fmt: skip


def error_responses(
    *statuses: int, examples: dict[int, tuple[str, str]] | None = None
) -> dict[int | str, dict[str, Any]]:
    """OpenAPI ``responses`` entries for these error statuses, each with an example body;
    ``examples`` replaces the (code, detail) of some."""
    responses: dict[int | str, dict[str, Any]] = {}
    for status in statuses:
        description, code, detail, field = _EXAMPLES[status]
        if examples and status in examples:
            code, detail = examples[status]
            field = None
        responses[status] = {
            "model": ErrorBody,
            "description": description,
            "content": {
                "application/json": {"example": {"detail": detail, "code": code, "field": field}}
            },
        }
    return responses
