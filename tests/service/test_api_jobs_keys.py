"""/v1/jobs (read, list, cancel, retry and their 409s), /v1/keys, and authentication and roles on
every endpoint. SQLite and PostgreSQL."""

from __future__ import annotations

from collections.abc import Iterator
from datetime import UTC, datetime, timedelta
from typing import Any

import pytest
from api_support import ADMIN, ADMIN_KEY, ONETAG, Api, bearer, run_next_job, running_api

from app.storage import queue
from app.storage.orm import Role

pytestmark = pytest.mark.db


@pytest.fixture
def api(database_url: str) -> Iterator[Api]:
    with running_api(database_url) as running:
        yield running


@pytest.fixture
def upload(api: Api) -> dict[str, Any]:
    return api.uploaded(ONETAG)


def job(api: Api, job_id: int, headers: dict[str, str] = ADMIN) -> dict[str, Any]:
    response = api.client.get(f"/v1/jobs/{job_id}", headers=headers)
    assert response.status_code == 200, response.text
    body: dict[str, Any] = response.json()
    return body


# --------------------------------------------------------------------------- jobs


def test_job_shows_state_progress_attempts_timings_and_log(
    api: Api, upload: dict[str, Any]
) -> None:
    queued = job(api, upload["job_id"])
    assert queued["state"] == "queued"
    assert (queued["progress"], queued["attempts"], queued["stage"]) == (0.0, 0, None)
    assert queued["started_at"] is None
    assert queued["duration_s"] is None
    assert queued["worker"] is None
    assert "queued" in queued["log_tail"]

    lease = queue.claim(api.db, worker_id="w-1", lease_s=60)
    assert lease is not None
    queue.report_progress(api.db, lease, progress=0.5, stage="optimize", log_tail="x\n")
    running = job(api, upload["job_id"])
    assert (running["state"], running["progress"], running["stage"]) == ("running", 0.5, "optimize")
    assert (running["attempts"], running["worker"]) == (1, "w-1")
    assert running["started_at"] is not None
    assert running["duration_s"] >= 0
    assert running["finished_at"] is None

    queue.fail(api.db, lease, error="boom", permanent=True, backoff_s=0, log_tail="x\n")
    failed = job(api, upload["job_id"])
    assert (failed["state"], failed["error"]) == ("failed", "boom")
    assert failed["finished_at"] is not None
    assert "permanent error" in failed["log_tail"]
    started = datetime.fromisoformat(failed["started_at"])
    finished = datetime.fromisoformat(failed["finished_at"])
    assert failed["duration_s"] == pytest.approx((finished - started).total_seconds())


def test_cancel_and_retry_follow_the_state_machine(api: Api, upload: dict[str, Any]) -> None:
    url = f"/v1/jobs/{upload['job_id']}"

    retry_queued = api.client.post(url + "/retry", headers=ADMIN)
    assert retry_queued.status_code == 409
    assert retry_queued.json()["code"] == "invalid_transition"
    assert "is queued: cannot retry" in retry_queued.json()["detail"]

    canceled = api.client.post(url + "/cancel", headers=ADMIN)
    assert canceled.status_code == 200
    assert canceled.json()["state"] == "canceled"

    again = api.client.post(url + "/cancel", headers=ADMIN)
    assert again.status_code == 409
    assert "is canceled: cannot cancel" in again.json()["detail"]

    retried = api.client.post(url + "/retry", headers=ADMIN)
    assert retried.status_code == 200
    assert (retried.json()["state"], retried.json()["attempts"]) == ("queued", 0)

    assert run_next_job(api.db) == upload["job_id"]
    done = api.client.post(url + "/cancel", headers=ADMIN)
    assert done.status_code == 409
    assert "is succeeded: cannot cancel" in done.json()["detail"]
    assert api.client.post(url + "/retry", headers=ADMIN).status_code == 409
    assert job(api, upload["job_id"])["state"] == "succeeded"


def test_cancel_of_a_running_job_requests_it(api: Api, upload: dict[str, Any]) -> None:
    lease = queue.claim(api.db, worker_id="w-1", lease_s=60)
    assert lease is not None

    response = api.client.post(f"/v1/jobs/{upload['job_id']}/cancel", headers=ADMIN)

    assert response.status_code == 200
    assert (response.json()["state"], response.json()["cancel_requested"]) == ("running", True)
    assert queue.heartbeat(api.db, lease, lease_s=60) is True  # the worker hears of it


def test_list_jobs_filters_and_pages(api: Api) -> None:
    created = [api.uploaded(ONETAG) for _ in range(3)]
    api.client.post(f"/v1/jobs/{created[0]['job_id']}/cancel", headers=ADMIN)

    everything = api.client.get("/v1/jobs", headers=ADMIN).json()
    assert everything["count"] == 3
    assert [j["id"] for j in everything["data"]] == [c["job_id"] for c in reversed(created)]
    canceled = api.client.get("/v1/jobs?state=canceled", headers=ADMIN).json()
    assert [j["id"] for j in canceled["data"]] == [created[0]["job_id"]]
    queued = api.client.get("/v1/jobs?state=queued&limit=1&offset=1", headers=ADMIN).json()
    assert (queued["count"], [j["id"] for j in queued["data"]]) == (2, [created[1]["job_id"]])
    of_map = api.client.get(f"/v1/jobs?map_id={created[2]['map_id']}", headers=ADMIN).json()
    assert [j["id"] for j in of_map["data"]] == [created[2]["job_id"]]

    bad = api.client.get("/v1/jobs?state=sleeping", headers=ADMIN)
    assert bad.status_code == 422
    assert bad.json()["field"] == "state"
    assert "queued" in bad.json()["detail"]
    assert api.client.get("/v1/jobs?limit=1000", headers=ADMIN).status_code == 422


@pytest.mark.parametrize("job_id", ["424242", "0", "-1", str(2**65)])
def test_unknown_job_is_404(api: Api, job_id: str) -> None:
    for method, path in (
        ("GET", f"/v1/jobs/{job_id}"),
        ("POST", f"/v1/jobs/{job_id}/cancel"),
        ("POST", f"/v1/jobs/{job_id}/retry"),
    ):
        response = api.client.request(method, path, headers=ADMIN)
        assert response.status_code == 404, path
        assert response.json()["detail"] == f"job {job_id} not found"


def test_a_device_reads_the_jobs_of_its_own_uploads_only(api: Api) -> None:
    alice, bob = api.device(), api.device()
    hers = api.uploaded(ONETAG, auth=alice)
    url = f"/v1/jobs/{hers['job_id']}"

    assert job(api, hers["job_id"], alice)["state"] == "queued"
    assert api.client.get(url, headers=bob).status_code == 404
    assert api.client.get("/v1/jobs", headers=alice).status_code == 403
    assert api.client.post(url + "/cancel", headers=alice).status_code == 403
    assert api.client.post(url + "/retry", headers=alice).status_code == 403
    assert job(api, hers["job_id"])["state"] == "queued"


# --------------------------------------------------------------------------- keys


def test_create_use_list_and_revoke_a_key(api: Api) -> None:
    created = api.client.post(
        "/v1/keys", headers=ADMIN, json={"name": "lab iPhone", "role": "device"}
    )

    assert created.status_code == 201, created.text
    key = created.json()
    assert key["key"].startswith(f"im_{key['prefix']}_")
    assert created.headers["Location"] == f"/v1/keys/{key['id']}"
    assert (key["role"], key["name"], key["revoked_at"]) == ("device", "lab iPhone", None)
    device = bearer(key["key"])

    info = api.client.get("/v1/info", headers=device)
    assert info.status_code == 200
    assert info.json()["principal"] == {"subject": f"key:{key['id']}", "role": "device"}
    assert api.uploaded(ONETAG, auth=device)["session_id"] == 1

    listed = api.client.get("/v1/keys", headers=ADMIN).json()
    assert listed["count"] == 1
    assert "key" not in listed["data"][0]
    assert key["key"] not in api.client.get("/v1/keys", headers=ADMIN).text
    one = api.client.get(f"/v1/keys/{key['id']}", headers=ADMIN).json()
    assert one["last_used_at"] is not None

    revoked = api.client.delete(f"/v1/keys/{key['id']}", headers=ADMIN)
    assert revoked.status_code == 200
    assert revoked.json()["revoked_at"] is not None
    refused = api.client.get("/v1/info", headers=device)
    assert refused.status_code == 401
    assert 'error="invalid_token"' in refused.headers["WWW-Authenticate"]
    again = api.client.delete(f"/v1/keys/{key['id']}", headers=ADMIN)
    assert again.json()["revoked_at"] == revoked.json()["revoked_at"]


def test_an_admin_key_from_the_api_is_an_admin(api: Api) -> None:
    created = api.client.post(
        "/v1/keys",
        headers=ADMIN,
        json={"name": "ops", "role": "admin", "expires_at": "2999-01-01T00:00:00Z"},
    )
    assert created.status_code == 201
    admin = bearer(created.json()["key"])

    assert api.client.get("/v1/keys", headers=admin).status_code == 200
    assert created.json()["expires_at"].startswith("2999-01-01T00:00:00")


@pytest.mark.parametrize(
    ("body", "field"),
    [
        ({"name": "x", "role": "root"}, "role"),
        ({"name": "", "role": "device"}, "name"),
        ({"name": "x" * 101, "role": "device"}, "name"),
        ({"role": "device"}, "name"),
        ({"name": "x", "role": "device", "expires_at": "2999-01-01T00:00:00"}, "expires_at"),
        ({"name": "x", "role": "device", "expires_at": "2001-01-01T00:00:00Z"}, "expires_at"),
        ({"name": "x", "role": "device", "scopes": ["all"]}, "scopes"),
    ],
    ids=["role", "empty-name", "long-name", "no-name", "naive-time", "past", "extra"],
)
def test_invalid_key_requests_are_422(api: Api, body: dict[str, Any], field: str) -> None:
    response = api.client.post("/v1/keys", headers=ADMIN, json=body)

    assert response.status_code == 422, response.text
    assert response.json()["field"] == field
    assert api.client.get("/v1/keys", headers=ADMIN).json()["count"] == 0


@pytest.mark.parametrize("key_id", ["77", "0", str(2**64)])
def test_unknown_key_is_404(api: Api, key_id: str) -> None:
    assert api.client.get(f"/v1/keys/{key_id}", headers=ADMIN).status_code == 404
    assert api.client.delete(f"/v1/keys/{key_id}", headers=ADMIN).status_code == 404


# --------------------------------------------------------------------------- authentication


def v1_routes(api: Api) -> list[tuple[str, str]]:
    """Every (method, path) under /v1 (from the OpenAPI document), ids filled in with 1."""
    routes = []
    for path, operations in api.app.openapi()["paths"].items():
        if path.startswith("/v1"):
            ids = ("session_id", "job_id", "map_id", "key_id", "number", "sweep_id", "edit_id")
            for name in ids:
                path = path.replace("{" + name + "}", "1")
            routes.extend((method.upper(), path) for method in operations)
    assert len(routes) >= 20
    return routes


def test_every_v1_endpoint_needs_a_valid_key(api: Api) -> None:
    _, expired = api.create_key(expires_at=datetime.now(UTC) - timedelta(seconds=1))
    revoked_id, revoked = api.create_key()
    api.client.delete(f"/v1/keys/{revoked_id}", headers=ADMIN)
    refused_headers: list[dict[str, str]] = [
        {},
        bearer("im_deadbeef_wrongsecretwrongsecretwrongsecr"),
        bearer(ADMIN_KEY + "x"),
        bearer(expired),
        bearer(revoked),
        {"Authorization": f"Basic {ADMIN_KEY}"},
        {"Authorization": "Bearer"},
    ]

    for method, path in v1_routes(api):
        for headers in refused_headers:
            response = api.client.request(method, path, headers=headers)
            assert response.status_code == 401, (method, path, headers)
            assert response.headers["WWW-Authenticate"].startswith("Bearer")
            assert response.json()["code"] == "unauthorized"


#: Every endpoint a device key may not use (the matrix in app/web/deps.py).
ADMIN_ONLY = [
    ("GET", "/v1/jobs"),
    ("POST", "/v1/jobs/1/cancel"),
    ("POST", "/v1/jobs/1/retry"),
    ("POST", "/v1/maps/1/rebuild"),
    ("DELETE", "/v1/maps/1"),
    ("PATCH", "/v1/maps/1"),
    ("POST", "/v1/maps/1/sessions"),
    ("DELETE", "/v1/maps/1/sessions/1"),
    ("POST", "/v1/maps/1/merge"),
    ("POST", "/v1/keys"),
    ("GET", "/v1/keys"),
    ("GET", "/v1/keys/1"),
    ("DELETE", "/v1/keys/1"),
    ("POST", "/v1/maps/1/sweeps"),
    ("GET", "/v1/sweeps"),
    ("GET", "/v1/sweeps/1"),
    ("GET", "/v1/sweeps/1/heatmap.png"),
    ("GET", "/v1/sweeps/1/shift-vs-gt.png"),
    ("POST", "/v1/sweeps/1/apply"),
    ("POST", "/v1/sweeps/1/cancel"),
    ("GET", "/v1/maps/1/corridor-edits"),
    ("POST", "/v1/maps/1/corridor-edits"),
    ("GET", "/v1/maps/1/corridor-edits/1"),
    ("DELETE", "/v1/maps/1/corridor-edits/1"),
]


#: Every endpoint a device key may use (the phone's: upload, read maps, navigate, localize).
DEVICE_ALLOWED = [
    ("GET", "/v1/info"),
    ("POST", "/v1/sessions"),
    ("GET", "/v1/sessions"),
    ("GET", "/v1/sessions/1"),
    ("GET", "/v1/sessions/1/raw"),
    ("PUT", "/v1/sessions/1/image"),
    ("GET", "/v1/jobs/1"),
    ("GET", "/v1/maps"),
    ("GET", "/v1/maps/1"),
    ("GET", "/v1/maps/1/versions"),
    ("GET", "/v1/maps/1/versions/1"),
    ("GET", "/v1/maps/1/sessions"),
    ("GET", "/v1/maps/1/app-map"),
    ("GET", "/v1/maps/1/plot.png"),
    ("GET", "/v1/maps/1/image"),
    ("GET", "/v1/maps/1/geojson"),
    ("GET", "/v1/maps/1/pois"),
    ("POST", "/v1/maps/1/routes"),
    ("POST", "/v1/maps/1/localizations"),
    ("GET", "/v1/localizations/1"),
    ("POST", "/v1/localizations/1/updates"),
]


def test_every_v1_endpoint_is_either_for_devices_or_for_admins(api: Api) -> None:
    """A new endpoint must be put on one list or the other, so that nobody adds an admin
    endpoint and forgets to keep device keys out of it."""
    routes = [(m, p.replace("{localization_id}", "1")) for m, p in v1_routes(api)]
    assert sorted(routes) == sorted(ADMIN_ONLY + DEVICE_ALLOWED)
    assert not set(ADMIN_ONLY) & set(DEVICE_ALLOWED)


def test_a_device_key_on_each_admin_endpoint_is_403(api: Api, upload: dict[str, Any]) -> None:
    device = api.device()
    assert upload["map_id"] == upload["job_id"] == 1

    for method, path in ADMIN_ONLY:
        json = {"name": "x", "role": "admin"} if path == "/v1/keys" else None
        response = api.client.request(method, path, headers=device, json=json)
        assert response.status_code == 403, (method, path)
        assert response.json()["code"] == "forbidden"
    # … and everything else under /v1 is open to it (404 at most, never 401/403).
    for method, path in v1_routes(api):
        if (method, path) not in ADMIN_ONLY and method == "GET":
            response = api.client.request(method, path, headers=device)
            assert response.status_code not in (401, 403), (method, path)
    assert api.client.get("/v1/keys", headers=ADMIN).json()["count"] == 1  # nothing created


def test_the_environment_admin_key_is_optional(database_url: str) -> None:
    with running_api(database_url, admin_key=None) as api:
        assert api.client.get("/v1/info", headers=ADMIN).status_code == 401
        _, secret = api.create_key(Role.ADMIN)
        assert api.client.get("/v1/keys", headers=bearer(secret)).status_code == 200
