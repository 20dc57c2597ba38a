"""How a worker logs a failure it goes on after: one line for a database fault (an outage
explains itself), a traceback for anything else (a bug, to be read).

    log_failure(logger, f"job {job_id}: heartbeat failed; trying again in 5 s", err)
"""

from __future__ import annotations

import logging
from typing import Any

from app.storage.db import database_fault, first_line


def log_failure(
    logger: logging.Logger,
    message: str,
    err: BaseException,
    *,
    level: int = logging.WARNING,
    extra: dict[str, Any] | None = None,
) -> None:
    """Log ``message: <the first line of err>``, with ``err``'s traceback unless it is a database
    fault (``app.storage.db.database_fault``)."""
    logger.log(
        level, "%s: %s", message, first_line(err), exc_info=database_fault(err) is None, extra=extra
    )
