"""/healthz, /readyz, /v1/info, the error body for what no route handles (404 route, 405, 500,
database down), and the OpenAPI document: every operation has a summary and examples."""

from __future__ import annotations

from collections.abc import Iterator
from datetime import UTC, datetime, timedelta
from importlib.metadata import version
from pathlib import Path
from typing import Any

import pytest
from api_support import ADMIN, ONETAG, Api, running_api
from fastapi.testclient import TestClient

from app.config import Settings
from app.main import create_app
from app.storage import queue
from app.storage.migrate import head_revision
from app.web.deps import read_db_session

pytestmark = pytest.mark.db

UNREACHABLE_POSTGRES = "postgresql+psycopg://postgres@127.0.0.1:1/none?connect_timeout=2"


@pytest.fixture
def api(database_url: str) -> Iterator[Api]:
    with running_api(database_url) as running:
        yield running


def test_healthz_needs_no_key(api: Api) -> None:
    response = api.client.get("/healthz")

    assert (response.status_code, response.json()) == (200, {"status": "ok"})


def test_readyz_on_a_migrated_database(api: Api) -> None:
    response = api.client.get("/readyz")

    assert response.status_code == 200
    assert response.json() == {
        "status": "ready",
        "database": api.db.backend,
        "schema_revision": head_revision(),
    }


def test_readyz_is_503_on_a_database_without_migrations(tmp_path: Path) -> None:
    empty = tmp_path / "empty.sqlite3"
    app = create_app(Settings(database_url=f"sqlite:///{empty}"))
    with TestClient(app) as client:
        response = client.get("/readyz")

    assert response.status_code == 503
    assert response.json()["code"] == "not_ready"
    assert "not migrated: at None" in response.json()["detail"]
    assert head_revision() in response.json()["detail"]


def test_readyz_is_503_when_the_database_is_unreachable() -> None:
    app = create_app(Settings(database_url=UNREACHABLE_POSTGRES))
    with TestClient(app) as client:
        response = client.get("/readyz")
        assert client.get("/healthz").status_code == 200

    assert response.status_code == 503
    assert response.json() == {
        "detail": "database unreachable (OperationalError)",
        "code": "not_ready",
        "field": None,
    }


def test_a_database_down_during_a_request_is_503_without_internals() -> None:
    key = "k" * 32
    app = create_app(Settings(database_url=UNREACHABLE_POSTGRES, admin_key=key))
    with TestClient(app) as client:
        response = client.get("/v1/info", headers={"Authorization": f"Bearer {key}"})

    assert response.status_code == 503
    assert response.json()["code"] == "database_unavailable"
    assert response.headers["Retry-After"] == "1"
    assert "127.0.0.1" not in response.text
    assert "psycopg" not in response.text


def test_info_reports_version_queue_and_live_workers(api: Api) -> None:
    for _ in range(3):
        api.uploaded(ONETAG)
    api.client.post("/v1/jobs/3/cancel", headers=ADMIN)
    queue.register_worker(api.db, worker_id="host-a:1", hostname="host-a", pid=1)
    queue.worker_heartbeat(
        api.db, worker_id="host-a:1", state="busy", current_job_id=2, jobs_done=5
    )
    stale = datetime.now(UTC) - timedelta(seconds=10 * api.settings.heartbeat_s)
    queue.register_worker(api.db, worker_id="host-b:2", hostname="host-b", pid=2, now=stale)

    response = api.client.get("/v1/info", headers=api.device())

    assert response.status_code == 200
    info = response.json()
    assert info["version"] == version("invisible-map")
    assert info["database"] == api.db.backend
    assert info["queue_depth"] == 2
    assert info["jobs_by_state"] == {
        "queued": 2,
        "running": 0,
        "succeeded": 0,
        "failed": 0,
        "canceled": 1,
    }
    assert [w["id"] for w in info["workers"]] == ["host-a:1"]
    worker = info["workers"][0]
    assert (worker["state"], worker["current_job_id"], worker["jobs_done"]) == ("busy", 2, 5)
    assert info["principal"]["role"] == "device"


def test_unknown_route_and_method_have_the_error_shape(api: Api) -> None:
    unknown = api.client.get("/v1/nothing-here", headers=ADMIN)
    wrong_method = api.client.put("/v1/maps", headers=ADMIN)

    assert (unknown.status_code, unknown.json()["code"]) == (404, "not_found")
    assert (wrong_method.status_code, wrong_method.json()["code"]) == (405, "method_not_allowed")
    assert "GET" in wrong_method.headers["Allow"]
    assert set(unknown.json()) == {"detail", "code", "field"}


def test_an_unexpected_error_is_500_with_a_generic_body(database_url: str) -> None:
    def broken() -> Iterator[Any]:
        raise RuntimeError("SELECT secret FROM internals")
        yield  # pragma: no cover

    with running_api(database_url) as api:
        api.app.dependency_overrides[read_db_session] = broken
        client = TestClient(api.app, raise_server_exceptions=False)
        response = client.get("/v1/keys", headers=ADMIN)  # a route with a request transaction

    assert response.status_code == 500
    assert response.json() == {
        "detail": "internal server error",
        "code": "internal_error",
        "field": None,
    }
    assert "secret" not in response.text
    assert "Traceback" not in response.text


def test_cors_is_not_enabled(api: Api) -> None:
    response = api.client.options(
        "/v1/maps",
        headers={"Origin": "https://evil.example", "Access-Control-Request-Method": "GET"},
    )

    assert "access-control-allow-origin" not in response.headers


# --------------------------------------------------------------------------- body limits


@pytest.fixture
def small_limit_api(database_url: str) -> Iterator[Api]:
    with running_api(database_url, max_request_bytes=1000) as running:
        yield running


def test_a_body_over_the_request_limit_is_413_before_it_is_read(small_limit_api: Api) -> None:
    big = b'{"from": {"tag": 0}, "to": {"tag": 1}, "pad": "' + b"x" * 2000 + b'"}'
    response = small_limit_api.client.post(
        "/v1/maps/1/routes", content=big, headers={**ADMIN, "Content-Type": "application/json"}
    )

    assert response.status_code == 413
    assert response.json() == {
        "detail": f"the request body ({len(big)} bytes) is larger than the limit of 1000 bytes "
        "for this endpoint",
        "code": "payload_too_large",
        "field": None,
    }


def test_a_chunked_body_over_the_request_limit_is_413(small_limit_api: Api) -> None:
    def chunks() -> Iterator[bytes]:
        yield b'{"name": "'
        for _ in range(10):
            yield b"k" * 200
        yield b'", "role": "device"}'

    response = small_limit_api.client.post(
        "/v1/keys", content=chunks(), headers={**ADMIN, "Content-Type": "application/json"}
    )

    assert response.status_code == 413
    assert response.json()["code"] == "payload_too_large"
    assert small_limit_api.client.get("/v1/keys", headers=ADMIN).json()["count"] == 0


def test_a_body_under_the_limit_and_an_upload_over_it_are_let_through(
    small_limit_api: Api,
) -> None:
    key = small_limit_api.client.post(
        "/v1/keys", json={"name": "phone", "role": "device"}, headers=ADMIN
    )
    upload = small_limit_api.upload(ONETAG)  # 1000+ bytes: uploads have their own limits

    assert key.status_code == 201
    assert len(ONETAG.read_bytes()) > 1000
    assert upload.status_code == 202


# --------------------------------------------------------------------------- OpenAPI


def resolve(spec: dict[str, Any], schema: dict[str, Any]) -> dict[str, Any]:
    while "$ref" in schema:
        name = schema["$ref"].rsplit("/", 1)[-1]
        schema = spec["components"]["schemas"][name]
    return schema


def has_example(spec: dict[str, Any], media: dict[str, Any]) -> bool:
    if "example" in media or media.get("examples"):
        return True
    schema = resolve(spec, media.get("schema", {}))
    choices = [resolve(spec, choice) for choice in schema.get("anyOf", [])]  # Model | None
    return any(s.get("examples") or s.get("example") for s in [schema, *choices])


def test_every_operation_is_documented_with_summary_tags_and_examples(api: Api) -> None:
    spec = api.app.openapi()
    operations = [
        (method, path, operation)
        for path, item in spec["paths"].items()
        for method, operation in item.items()
    ]
    # 26 of the server (3 for the app's pictures and names), 6 of navigation and localization,
    # 7 sweeps, 4 of a map's sessions, 4 of corridor edits
    assert len(operations) == 47

    for method, path, operation in operations:
        where = f"{method.upper()} {path}"
        assert operation.get("summary"), where
        assert operation.get("description"), where
        assert operation.get("tags"), where
        body = operation.get("requestBody")
        if body is not None:
            assert all(has_example(spec, m) for m in body["content"].values()), where
        for status, response in operation["responses"].items():
            for media in response.get("content", {}).values():
                assert has_example(spec, media), f"{where} {status}"
        successes = [s for s in operation["responses"] if s.startswith("2")]
        assert successes, where
        if path.startswith("/v1"):
            assert "401" in operation["responses"], where
            assert operation.get("security"), where
        if "{" in path:
            assert "404" in operation["responses"], where

    upload = spec["paths"]["/v1/sessions"]["post"]
    assert {"400", "401", "409", "413", "415", "422"} <= set(upload["responses"])
    assert "202" in upload["responses"]
    headers = {p["name"] for p in upload["parameters"] if p["in"] == "header"}
    assert {"Idempotency-Key", "Content-Encoding"} <= headers
    assert "403" in spec["paths"]["/v1/keys"]["get"]["responses"]
    assert "409" in spec["paths"]["/v1/jobs/{job_id}/cancel"]["post"]["responses"]
    assert spec["components"]["securitySchemes"]["ApiKey"]["scheme"] == "bearer"


def test_every_component_schema_with_properties_has_an_example_or_is_nested(api: Api) -> None:
    spec = api.app.openapi()
    nested = {"Vector3", "Quaternion", "AppTagVertex", "AppOdometryVertex", "AppWaypointVertex"}
    nested |= {"HTTPValidationError", "ValidationError"}
    for name, schema in spec["components"]["schemas"].items():
        if name not in nested and schema.get("type") == "object":
            assert schema.get("examples"), name
