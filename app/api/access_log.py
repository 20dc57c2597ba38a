"""Keys never reach the access log.

The API takes a key only in ``Authorization``; one sent in the query string (``?api_key=…``) is
refused, but uvicorn's access log writes the whole target of every request. :class:`RedactKeys`,
a filter on the ``uvicorn.access`` logger (``serve`` installs it), replaces the value of every
query parameter whose name speaks of a key, token, secret or password, and anything shaped like
one of our keys (``im_<prefix>_<secret>``) anywhere in the target, with ``***``.
"""

from __future__ import annotations

import logging
import re

_SECRET_PARAMETER = re.compile(
    r"(?P<name>[?&;][^=&;#]*(?:key|token|secret|password|auth)[^=&;#]*=)[^&;#]*", re.IGNORECASE
)
_OUR_KEY = re.compile(r"im_[0-9A-Za-z]+_[0-9A-Za-z_\-]+")


def redact(target: str) -> str:
    """``target`` (a request's path and query) without secrets."""
    return _OUR_KEY.sub("im_***", _SECRET_PARAMETER.sub(r"\g<name>***", target))


class RedactKeys(logging.Filter):
    """Redacts the request target of uvicorn's access log records (their third argument)."""

    def filter(self, record: logging.LogRecord) -> bool:
        args = record.args
        if isinstance(args, tuple) and len(args) >= 3 and isinstance(args[2], str):
            record.args = (*args[:2], redact(args[2]), *args[3:])
        return True


def install() -> None:
    """Put :class:`RedactKeys` on uvicorn's access logger (once)."""
    access = logging.getLogger("uvicorn.access")
    if not any(isinstance(f, RedactKeys) for f in access.filters):
        access.addFilter(RedactKeys())
