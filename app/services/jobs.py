"""What a device is told of a job's error, and what only operators see.

A worker stores a failed attempt's error as ``"<stage>: <ExceptionType>: <message>"``
(``workers.pipeline``), in full: operators read it in the worker's log, in ``/v1/jobs`` with an
admin key and on the dashboard. A device (``GET /v1/jobs/{id}`` with the key that uploaded) gets
:func:`public_job_error`: the message of an error the core raised about its input (a malformed
upload, a bad parameter, a corrupt stored upload), which tells the phone's user what to change;
anything else (a database error with its SQL and parameters, a bug) becomes a plain "internal
error" line naming the stage.
"""

from __future__ import annotations

import re

from app.domain.errors import InvisibleMapError

#: The stored form of a worker's error (``workers.pipeline.run_job``).
_STORED_ERROR = re.compile(
    r"(?P<stage>[a-z_]+): (?P<type>[A-Za-z_][A-Za-z0-9_]*): (?P<message>.*)", re.S
)
#: Raised by a stage when a stored input is missing or corrupt (``workers.pipeline``).
_PERMANENT_JOB_ERROR = "PermanentJobError"


def _error_names(cls: type[BaseException]) -> set[str]:
    return {cls.__name__}.union(*(_error_names(sub) for sub in cls.__subclasses__()))


def public_job_error(error: str | None) -> str | None:
    """``error`` as a device may read it (see the module docstring)."""
    if error is None:
        return None
    match = _STORED_ERROR.fullmatch(error)
    if match is None:
        return error  # written by the queue itself (a lease lost on the last attempt, …)
    if match["type"] in _error_names(InvisibleMapError) | {_PERMANENT_JOB_ERROR}:
        return f"{match['stage']}: {match['message']}"
    return (
        f"{match['stage']}: an internal error of the server stopped this build; it is logged "
        "for its operators"
    )
