"""The JSON log's lines (``app.observability.logs``): one object per record, with what the record
carries through ``extra=`` as fields, uvicorn's access lines taken apart, exceptions kept."""

from __future__ import annotations

import json
import logging
import sys

import pytest

from app.observability.logs import JsonFormatter, uvicorn_log_options


def formatted(record: logging.LogRecord) -> dict[str, object]:
    line = JsonFormatter().format(record)
    assert "\n" not in line  # one line, whatever the message holds
    document = json.loads(line)
    assert isinstance(document, dict)
    return document


def record_of(logger_name: str, message: str, *args: object, **extra: object) -> logging.LogRecord:
    logger = logging.getLogger(logger_name)
    records: list[logging.LogRecord] = []

    class Keep(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            records.append(record)

    handler = Keep()
    logger.addHandler(handler)
    try:
        logger.warning(message, *args, extra=extra)
    finally:
        logger.removeHandler(handler)
    (record,) = records
    return record


def test_a_worker_line_carries_its_ids_as_fields() -> None:
    record = record_of(
        "workers.test",
        "job %d succeeded\nafter %.2f s",
        7,
        1.5,
        action="job_succeeded",
        job_id=7,
        map_id=3,
        session_id=None,
    )
    line = formatted(record)
    assert line["message"] == "job 7 succeeded\nafter 1.50 s"
    assert (line["level"], line["logger"]) == ("WARNING", "workers.test")
    assert (line["action"], line["job_id"], line["map_id"]) == ("job_succeeded", 7, 3)
    assert "session_id" not in line  # null: left out
    assert str(line["time"]).endswith("+00:00")
    assert {"process", "pid"} <= set(line)
    assert not {"args", "msg", "exc_info", "levelno", "created"} & set(line)


def test_an_access_line_is_taken_apart_and_an_exception_kept() -> None:
    access = logging.LogRecord(
        "uvicorn.access",
        logging.INFO,
        __file__,
        1,
        '%s - "%s %s HTTP/%s" %d',
        ("127.0.0.1:5000", "POST", "/v1/sessions", "1.1", 202),
        None,
    )
    line = formatted(access)
    assert (line["client"], line["method"], line["path"], line["status"]) == (
        "127.0.0.1:5000",
        "POST",
        "/v1/sessions",
        202,
    )
    assert line["message"] == '127.0.0.1:5000 - "POST /v1/sessions HTTP/1.1" 202'

    try:
        raise ValueError("no such tag")
    except ValueError:
        failed = logging.LogRecord(
            "workers", logging.ERROR, __file__, 1, "job failed", (), sys.exc_info()
        )
    line = formatted(failed)
    assert "ValueError: no such tag" in str(line["exception"])


@pytest.mark.parametrize("log_format", ["text", "json"])
def test_uvicorn_keeps_its_own_lines_unless_json(log_format: str) -> None:
    options = uvicorn_log_options(log_format)
    if log_format == "text":
        assert options == {}
    else:
        config = options["log_config"]
        assert config["root"]["handlers"] == ["json"]
        assert all(config["loggers"][name]["propagate"] for name in ("uvicorn", "uvicorn.access"))
