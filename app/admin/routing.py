"""The dashboard's route class: errors become pages, every response gets the security headers.

The API answers errors with JSON (``app.web.errors``); a person in a browser should get a page
that says what went wrong, with the same status. :class:`AdminRoute` wraps each dashboard
endpoint (its dependencies included) so that:

    LoginRequired                         303 to /admin/login?next=…
    CsrfRefused                           403 page
    ServiceError, and every error of      the status app.services.errors gives it (as the
    STATUS_OF_ERROR (MapNotFound …)       API answers it), with its detail
    RequestValidationError                422 page (a malformed query or path parameter)
    a database fault (app.storage.db)     503 page saying which (unavailable, full, read-only)
    anything else                         500 page (logged with its traceback)

Pages and forms that can say more (the rebuild form re-shown with its error) catch their errors
themselves.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Coroutine
from typing import Any

from fastapi import APIRouter, Request, Response
from fastapi.exceptions import RequestValidationError
from fastapi.responses import RedirectResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

from app.admin.auth import CsrfRefused, LoginRequired
from app.admin.templating import add_security_headers, render
from app.services.errors import ServiceError, status_and_code
from app.storage.db import database_fault, first_line
from app.web.errors import (
    CODE_OF_STATUS,
    FAULT_ANSWERS,
    error_response,
    field_path,
    validation_error_response,
)
from app.web.route_class import SessionEndingRoute

logger = logging.getLogger(__name__)

TITLE_OF_STATUS = {
    400: "Bad request",
    403: "Refused",
    404: "Not found",
    409: "Not possible now",
    422: "Invalid input",
    429: "Too many attempts",
    500: "Server error",
    503: "Service unavailable",
}


class AdminRoute(SessionEndingRoute):
    """An :class:`APIRoute` whose errors are dashboard pages (see the module docstring), and
    whose transaction ends as its function returns (``app.web.route_class``)."""

    def get_route_handler(self) -> Callable[[Request], Coroutine[Any, Any, Response]]:
        handler = super().get_route_handler()

        async def admin_handler(request: Request) -> Response:
            try:
                response = await handler(request)
            except LoginRequired as exc:
                response = RedirectResponse(exc.login_url, status_code=303)
            except Exception as exc:  # every error is a page; unexpected ones are logged
                response = (
                    await error_json(request, exc)
                    if _sent_json(request)
                    else error_page(request, exc)
                )
            add_security_headers(response)
            return response

        return admin_handler


def admin_router() -> APIRouter:
    """A router for dashboard pages: under ``/admin``, hidden from the OpenAPI document."""
    return APIRouter(prefix="/admin", route_class=AdminRoute, include_in_schema=False)


def error_page(request: Request, exc: Exception) -> Response:
    """The page for an error raised while serving a dashboard request."""
    status, message = _status_and_message(request, exc)
    response = render(
        request,
        "error.html",
        status_code=status,
        section=None,
        title=TITLE_OF_STATUS.get(status, "Error"),
        status=status,
        message=message,
    )
    if isinstance(exc, ServiceError):
        for name, value in exc.headers.items():
            if name.lower() != "www-authenticate":
                response.headers[name] = value
    return response


def _sent_json(request: Request) -> bool:
    """Whether the request is a script's call with a JSON body (the corridor editor's): its
    errors are answered as the API's are, in JSON, not as a page."""
    content_type = request.headers.get("content-type", "")
    return content_type.split(";")[0].strip().lower() == "application/json"


async def error_json(request: Request, exc: Exception) -> Response:
    """The API's JSON error (``app.web.errors``) for an error of a script's JSON request: a
    malformed body is a 400 ``invalid_json`` naming it, as on ``/v1``."""
    if isinstance(exc, RequestValidationError):
        return await validation_error_response(request, exc)
    status, message = _status_and_message(request, exc)
    known = status_and_code(exc)
    code = known[1] if known is not None else CODE_OF_STATUS.get(status, "error")
    return error_response(status, code, message)


def _status_and_message(request: Request, exc: Exception) -> tuple[int, str]:
    if isinstance(exc, CsrfRefused):
        return 403, f"{exc} Go back, reload the page and try again."
    known = status_and_code(exc)
    if known is not None:
        return known[0], sentence(str(exc))
    if isinstance(exc, RequestValidationError):
        parts = []
        for error in exc.errors():
            where = field_path(error.get("loc", ())) or "request"
            message = str(error.get("msg", "invalid"))
            parts.append(f"Invalid {where}: {message[:1].lower()}{message[1:]}")
        return 422, sentence("; ".join(parts) or "Invalid request")
    if isinstance(exc, StarletteHTTPException):
        return exc.status_code, sentence(str(exc.detail))
    fault = database_fault(exc)
    if fault is not None:
        logger.error(
            "%s during %s %s: %s", fault.value, request.method, request.url.path, first_line(exc)
        )
        return 503, sentence(FAULT_ANSWERS[fault][0])
    logger.error(
        "unhandled error in %s %s",
        request.method,
        request.url.path,
        exc_info=exc,
        extra={"action": "internal_error"},
    )
    return 500, "Something went wrong on the server; it has been logged."


def sentence(text: str) -> str:
    """``text`` as a sentence for a page: capitalized, ending with a full stop."""
    text = text.strip()
    if not text:
        return text
    return text[0].upper() + text[1:] + ("" if text.endswith((".", "!", "?")) else ".")
