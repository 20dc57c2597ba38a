"""The log as JSON lines (``serve --log-format json``, ``worker --log-format json``).

    configure_json_logging()                          # the root logger: one JSON object a line
    uvicorn.Config(app, **uvicorn_log_options("json"))  # uvicorn's loggers through the root's

Each line is one record::

    {"time": "2026-12-02T02:41:07.316+00:00", "level": "INFO", "logger": "workers",
     "message": "job 7 succeeded after 1.92 s: map 3 version 1", "process": "worker-1",
     "pid": 4121, "action": "job_succeeded", "job_id": 7, "map_id": 3, "session_id": 5}

``time`` is UTC; every field a record carries through ``extra=`` (the worker's ``action``,
``job_id``, ``map_id``, ``session_id``, …) is a field of its own when it is not null; uvicorn's
access lines add ``client``, ``method``, ``path`` (keys redacted: ``app.api.access_log``) and
``status``; a record with an exception adds ``exception``, its traceback. The default, ``text``,
is the log as it always was.
"""

from __future__ import annotations

import json
import logging
import sys
from datetime import UTC, datetime
from typing import Any

#: The text log's line (``--log-format text``, the default).
TEXT_FORMAT = "%(asctime)s %(levelname)s %(processName)s[%(process)d] %(name)s: %(message)s"
#: Its INFO lines (each schema check of ``/readyz``, each migration step) are left out, as the
#: text log, which has no handler for them, leaves them out.
QUIET_LOGGER = "alembic"
#: What every LogRecord has: anything else on a record came through ``extra=``.
_RECORD_ATTRIBUTES = frozenset(
    {
        *vars(logging.LogRecord("", logging.INFO, "", 0, "", (), None)),
        "message",
        "asctime",
        "color_message",  # uvicorn's copy of its message with terminal colors
        "taskName",
    }
)


class JsonFormatter(logging.Formatter):
    """Formats a record as one line of JSON (see the module docstring)."""

    def format(self, record: logging.LogRecord) -> str:
        line: dict[str, Any] = {
            "time": datetime.fromtimestamp(record.created, UTC).isoformat(timespec="milliseconds"),
            "level": record.levelname,
            "logger": record.name,
            "message": record.getMessage(),
            "process": record.processName,
            "pid": record.process,
        }
        args = record.args
        if record.name == "uvicorn.access" and isinstance(args, tuple) and len(args) == 5:
            client, method, path, _version, status = args
            line.update(client=client, method=method, path=path, status=status)
        for name, value in vars(record).items():
            if name not in _RECORD_ATTRIBUTES and value is not None and name not in line:
                line[name] = value
        if record.exc_info:
            line["exception"] = self.formatException(record.exc_info)
        if record.stack_info:
            line["stack"] = self.formatStack(record.stack_info)
        return json.dumps(line, default=str, ensure_ascii=False)


def json_handler() -> logging.Handler:
    """A handler writing JSON lines to stderr."""
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(JsonFormatter())
    return handler


def configure_json_logging(level: int = logging.INFO) -> None:
    """Make the root logger write JSON lines to stderr (its handlers replaced), and warnings go
    through it too."""
    root = logging.getLogger()
    for handler in list(root.handlers):
        root.removeHandler(handler)
    root.addHandler(json_handler())
    root.setLevel(level)
    logging.getLogger(QUIET_LOGGER).setLevel(logging.WARNING)
    logging.captureWarnings(True)


def json_logging_active() -> bool:
    """Whether the root logger writes JSON lines (:func:`configure_json_logging`)."""
    return any(isinstance(h.formatter, JsonFormatter) for h in logging.getLogger().handlers)


def uvicorn_log_options(log_format: str) -> dict[str, Any]:
    """uvicorn.Config's logging options: none for text (uvicorn's own lines); for json, a
    configuration in which the root logger writes JSON lines and uvicorn's loggers pass their
    records up to it."""
    if log_format != "json":
        return {}
    return {
        "log_config": {
            "version": 1,
            "disable_existing_loggers": False,
            "formatters": {"json": {"()": f"{__name__}.JsonFormatter"}},
            "handlers": {
                "json": {
                    "class": "logging.StreamHandler",
                    "formatter": "json",
                    "stream": "ext://sys.stderr",
                }
            },
            "loggers": {
                **{
                    name: {"handlers": [], "level": "INFO", "propagate": True}
                    for name in ("uvicorn", "uvicorn.error", "uvicorn.access")
                },
                QUIET_LOGGER: {"level": "WARNING"},
            },
            "root": {"handlers": ["json"], "level": "INFO"},
        }
    }
