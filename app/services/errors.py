"""The errors a service raises, and the one table that says what each error means to a client.

    ServiceError              a request the server will not carry out, for a reason given
    ├── BadRequest            400 a malformed request (bad gzip, bad encoding)
    ├── Forbidden             403 the caller may not do this
    ├── NotFound              404 the thing named does not exist (for this caller)
    ├── Conflict              409 not possible in the resource's present state
    ├── PreconditionFailed    412 an If-Match that no longer matches
    ├── InvalidInput          422 a value is wrong; ``field`` names it
    └── Unavailable           503 a dependency is down; nothing was changed

Each carries a stable ``code`` ("map_not_ready"), a ``detail`` for people and the ``field`` at
fault. Errors raised below the services (storage's ``MapNotFound``, the queue's
``InvalidTransition``, the domain's ``ParameterError`` …) keep their own types;
:func:`status_and_code` maps every one of them, so the API (JSON bodies) and the dashboard (error
pages) answer the same error with the same status.
"""

from __future__ import annotations

from app.domain.errors import ParameterError, SessionFormatError
from app.domain.upload.fields import text_fault
from app.storage.keys import KeyNotFound
from app.storage.maps import MapNotFound
from app.storage.navigation import LocalizationNotFound
from app.storage.queue import InvalidTransition, JobNotFound
from app.storage.sessions import IdempotencyConflict, SessionNotFound
from app.storage.sweeps import SweepNotFound


class ServiceError(Exception):
    """A request the server will not carry out: ``code`` (stable), ``detail`` (for people),
    ``field`` (the value at fault, if one is), ``headers`` (to send with the answer)."""

    status_code = 400

    def __init__(
        self,
        code: str,
        detail: str,
        *,
        field: str | None = None,
        headers: dict[str, str] | None = None,
    ) -> None:
        super().__init__(detail)
        self.code = code
        self.detail = detail
        self.field = field
        self.headers = headers or {}


class BadRequest(ServiceError):
    """A request that cannot be read (corrupt gzip, an encoding we do not take)."""

    status_code = 400


class Forbidden(ServiceError):
    """The caller is known but may not do this."""

    status_code = 403


class NotFound(ServiceError):
    """What the request names does not exist, or is not the caller's."""

    status_code = 404


class Conflict(ServiceError):
    """Not possible in the resource's present state (no version yet, a finished job …)."""

    status_code = 409


class PreconditionFailed(ServiceError):
    """A conditional request (``If-Match``) whose condition no longer holds: the resource
    changed since the caller read it. Nothing was changed."""

    status_code = 412


class InvalidInput(ServiceError):
    """A value of the request is wrong; ``field`` names it."""

    status_code = 422


def require_text(field: str, value: str) -> None:
    """InvalidInput (422 ``validation_error`` naming ``field``) if ``value`` is no text the
    database can hold: the one rule of every text that reaches it
    (:func:`app.domain.upload.fields.text_fault`)."""
    reason = text_fault(value)
    if reason is not None:
        raise InvalidInput("validation_error", f"{field} {reason}", field=field)


class Unavailable(ServiceError):
    """Something the request needs is down; nothing was changed."""

    status_code = 503


#: What the storage layer raises for an id that names nothing: a 404 in the API and the dashboard.
NOT_FOUND_ERRORS: tuple[type[Exception], ...] = (
    MapNotFound,
    JobNotFound,
    SessionNotFound,
    KeyNotFound,
    LocalizationNotFound,
    SweepNotFound,
)

#: Errors of the layers below the services, by what they mean to a client: (status, code).
STATUS_OF_ERROR: tuple[tuple[tuple[type[Exception], ...], int, str], ...] = (
    (NOT_FOUND_ERRORS, 404, "not_found"),
    ((InvalidTransition,), 409, "invalid_transition"),
    ((IdempotencyConflict,), 409, "idempotency_conflict"),
    ((SessionFormatError,), 422, "invalid_session"),
    ((ParameterError,), 422, "invalid_parameter"),
)


def status_and_code(exc: BaseException) -> tuple[int, str] | None:
    """The (HTTP status, code) a client is answered for ``exc``; None if it is not a known
    refusal (a bug or a fault, which the caller answers as such)."""
    if isinstance(exc, ServiceError):
        return exc.status_code, exc.code
    for types, status, code in STATUS_OF_ERROR:
        if isinstance(exc, types):
            return status, code
    return None
