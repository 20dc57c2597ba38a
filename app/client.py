"""A Python client for the Invisible Map server's REST API, over httpx.

    from app.client import Client

    with Client("http://127.0.0.1:8000", api_key="im_…") as client:
        accepted = client.upload_session("data/sessions/occam_room.json", idempotency_key="walk-1")
        job = client.wait_for_job(accepted["job_id"])          # raises JobFailed if it failed
        current = client.get_map(accepted["map_id"])["current_version"]
        app_map = client.app_map(accepted["map_id"])          # the app's download format
        client.put_session_image(accepted["session_id"], jpeg) # the map's picture

Responses are the API's JSON as plain dicts (the schemas are in the OpenAPI document at
``/openapi.json``). Every non-2xx answer raises :class:`ApiError` with the status and the server's
``detail``, ``code`` and ``field``. The transport is injectable (``httpx.MockTransport`` in tests).
"""

from __future__ import annotations

import gzip
import time
import uuid
from pathlib import Path
from types import TracebackType
from typing import Any, Self

import httpx

TERMINAL_JOB_STATES = frozenset({"succeeded", "failed", "canceled"})


class ApiError(Exception):
    """Raised for a non-2xx response; carries the status code and the error body's fields."""

    def __init__(
        self, status_code: int, detail: str, code: str | None = None, field: str | None = None
    ) -> None:
        super().__init__(f"{status_code}: {detail}")
        self.status_code = status_code
        self.detail = detail
        self.code = code
        self.field = field


class JobFailed(Exception):
    """Raised by :meth:`Client.wait_for_job` when the job ends failed or canceled."""

    def __init__(self, job: dict[str, Any]) -> None:
        super().__init__(f"job {job['id']} {job['state']}: {job.get('error') or 'no error given'}")
        self.job = job


class Client:
    """One server and one API key. Keyword-only options after ``base_url``."""

    def __init__(
        self,
        base_url: str,
        *,
        api_key: str | None = None,
        timeout_s: float = 30.0,
        transport: httpx.BaseTransport | None = None,
    ) -> None:
        headers = {"Authorization": f"Bearer {api_key}"} if api_key else {}
        self._http = httpx.Client(
            base_url=base_url, headers=headers, timeout=timeout_s, transport=transport
        )

    # ----------------------------------------------------------------------- plumbing

    def close(self) -> None:
        self._http.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        self.close()

    def request(self, method: str, path: str, **kwargs: Any) -> httpx.Response:
        """Send a request; raise :class:`ApiError` unless the status is 2xx or 304."""
        response = self._http.request(method, path, **kwargs)
        if response.status_code >= 400:
            raise _api_error(response)
        return response

    def _json(self, method: str, path: str, **kwargs: Any) -> Any:
        return self.request(method, path, **kwargs).json()

    # ----------------------------------------------------------------------- system

    def health(self) -> dict[str, Any]:
        result: dict[str, Any] = self._json("GET", "/healthz")
        return result

    def ready(self) -> dict[str, Any]:
        result: dict[str, Any] = self._json("GET", "/readyz")
        return result

    def info(self) -> dict[str, Any]:
        result: dict[str, Any] = self._json("GET", "/v1/info")
        return result

    # ----------------------------------------------------------------------- sessions

    def upload_session(
        self,
        session: str | Path | bytes,
        *,
        idempotency_key: str | None = None,
        compress: bool = False,
        retries: int = 0,
        retry_wait_s: float = 1.0,
    ) -> dict[str, Any]:
        """Upload a mapping session (a file path or the JSON bytes); returns the 202 body.

        With ``retries`` > 0, an upload whose answer never came (the connection refused, dropped
        or timed out) or was a 503 is sent again, up to ``retries`` more times ``retry_wait_s``
        apart, with the same ``Idempotency-Key`` (a new random one if none is given): the server
        stores it once, and a retry of an upload that was stored answers with the first result.
        """
        body = session if isinstance(session, bytes) else Path(session).read_bytes()
        headers = {"Content-Type": "application/json"}
        if body[:2] == b"\x1f\x8b":
            headers["Content-Encoding"] = "gzip"
        elif compress:
            body = gzip.compress(body)
            headers["Content-Encoding"] = "gzip"
        if idempotency_key is None and retries > 0:
            idempotency_key = f"upload-{uuid.uuid4()}"
        if idempotency_key is not None:
            headers["Idempotency-Key"] = idempotency_key
        for attempt in range(retries + 1):
            last = attempt == retries
            try:
                result: dict[str, Any] = self._json(
                    "POST", "/v1/sessions", content=body, headers=headers
                )
                return result
            except httpx.TransportError:
                if last:
                    raise
            except ApiError as err:
                if last or err.status_code != 503:
                    raise
            time.sleep(retry_wait_s)
        raise AssertionError("unreachable: the last attempt returns or raises")

    def list_sessions(self, *, limit: int = 50, offset: int = 0) -> dict[str, Any]:
        result: dict[str, Any] = self._json(
            "GET", "/v1/sessions", params={"limit": limit, "offset": offset}
        )
        return result

    def get_session(self, session_id: int) -> dict[str, Any]:
        result: dict[str, Any] = self._json("GET", f"/v1/sessions/{session_id}")
        return result

    def raw_session(self, session_id: int) -> bytes:
        """The upload exactly as it was sent (uncompressed)."""
        return self.request("GET", f"/v1/sessions/{session_id}/raw").content

    # ----------------------------------------------------------------------- jobs

    def get_job(self, job_id: int) -> dict[str, Any]:
        result: dict[str, Any] = self._json("GET", f"/v1/jobs/{job_id}")
        return result

    def list_jobs(
        self, *, state: str | None = None, limit: int = 50, offset: int = 0
    ) -> dict[str, Any]:
        params: dict[str, Any] = {"limit": limit, "offset": offset}
        if state is not None:
            params["state"] = state
        result: dict[str, Any] = self._json("GET", "/v1/jobs", params=params)
        return result

    def cancel_job(self, job_id: int) -> dict[str, Any]:
        result: dict[str, Any] = self._json("POST", f"/v1/jobs/{job_id}/cancel")
        return result

    def retry_job(self, job_id: int) -> dict[str, Any]:
        result: dict[str, Any] = self._json("POST", f"/v1/jobs/{job_id}/retry")
        return result

    def wait_for_job(
        self, job_id: int, *, timeout_s: float = 120.0, poll_s: float = 0.1
    ) -> dict[str, Any]:
        """Poll until the job ends; returns it if it succeeded, raises :class:`JobFailed` if it
        failed or was canceled, and TimeoutError if it is still going after ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        while True:
            job = self.get_job(job_id)
            if job["state"] == "succeeded":
                return job
            if job["state"] in TERMINAL_JOB_STATES:
                raise JobFailed(job)
            if time.monotonic() > deadline:
                raise TimeoutError(
                    f"job {job_id} still {job['state']} after {timeout_s:g} s "
                    f"(progress {job['progress']:.0%})"
                )
            time.sleep(poll_s)

    # ----------------------------------------------------------------------- maps

    def list_maps(
        self, *, limit: int = 50, offset: int = 0, tag_id: int | None = None
    ) -> dict[str, Any]:
        params: dict[str, Any] = {"limit": limit, "offset": offset}
        if tag_id is not None:
            params["tag_id"] = tag_id
        result: dict[str, Any] = self._json("GET", "/v1/maps", params=params)
        return result

    def get_map(self, map_id: int) -> dict[str, Any]:
        result: dict[str, Any] = self._json("GET", f"/v1/maps/{map_id}")
        return result

    def map_versions(self, map_id: int) -> list[dict[str, Any]]:
        body = self._json("GET", f"/v1/maps/{map_id}/versions")
        versions: list[dict[str, Any]] = body["data"] if isinstance(body, dict) else body
        return versions

    def rebuild_map(
        self,
        map_id: int,
        params: dict[str, Any] | None = None,
        *,
        ground_truth: dict[str, Any] | None = None,
    ) -> dict[str, Any]:
        """Queue a new version of the map, optionally with other SLAM parameters, and with
        ground truth of its tags (the JSON form; the version then carries the ground-truth
        metric)."""
        body: dict[str, Any] = {"params": params or {}}
        if ground_truth is not None:
            body["ground_truth"] = ground_truth
        result: dict[str, Any] = self._json("POST", f"/v1/maps/{map_id}/rebuild", json=body)
        return result

    def app_map(self, map_id: int) -> dict[str, Any]:
        """The current version in the app's download format."""
        result: dict[str, Any] = self._json("GET", f"/v1/maps/{map_id}/app-map")
        return result

    def plot_png(self, map_id: int) -> bytes:
        return self.request("GET", f"/v1/maps/{map_id}/plot.png").content

    def put_session_image(self, session_id: int, jpeg: bytes) -> dict[str, Any]:
        """Upload the session's picture (a JPEG, shown with its map); the same bytes again
        change nothing (``changed: False``)."""
        result: dict[str, Any] = self._json(
            "PUT",
            f"/v1/sessions/{session_id}/image",
            content=jpeg,
            headers={"Content-Type": "image/jpeg"},
        )
        return result

    def map_image(self, map_id: int) -> bytes:
        """The map's picture (ApiError 404 ``no_image`` without one)."""
        return self.request("GET", f"/v1/maps/{map_id}/image").content

    def rename_map(self, map_id: int, display_name: str) -> dict[str, Any]:
        """Set the name people see (admin)."""
        result: dict[str, Any] = self._json(
            "PATCH", f"/v1/maps/{map_id}", json={"display_name": display_name}
        )
        return result

    def delete_map(self, map_id: int) -> None:
        self.request("DELETE", f"/v1/maps/{map_id}")

    # ----------------------------------------------------------------------- navigation

    def search_pois(self, map_id: int, query: str = "") -> list[dict[str, Any]]:
        """Points of interest of the map whose name contains ``query`` (all when empty)."""
        body = self._json("GET", f"/v1/maps/{map_id}/pois", params={"q": query})
        pois: list[dict[str, Any]] = body["data"]
        return pois

    def plan_route(
        self,
        map_id: int,
        start: dict[str, Any],
        goal: dict[str, Any],
        *,
        avoid: list[str] | None = None,
        heading_deg: float | None = None,
        style: dict[str, Any] | None = None,
    ) -> dict[str, Any]:
        """A route: ends like ``{"tag": 300}``, ``{"poi": "Room 209"}``, ``{"node": 12}`` or
        ``{"position": [x, y, z]}``; ``avoid`` ⊆ ``["stairs", "elevator"]``; ``heading_deg`` the
        phone's walking direction (0 faces −z, +90 faces −x) for a first "face the way" step;
        ``style`` like ``{"units": "ft", "clock": True}``."""
        body: dict[str, Any] = {"from": start, "to": goal, "avoid": avoid or []}
        if heading_deg is not None:
            body["heading_deg"] = heading_deg
        if style is not None:
            body["style"] = style
        result: dict[str, Any] = self._json("POST", f"/v1/maps/{map_id}/routes", json=body)
        return result

    def geojson(self, map_id: int) -> dict[str, Any]:
        """The current version's path graph as a GeoJSON FeatureCollection."""
        result: dict[str, Any] = self._json("GET", f"/v1/maps/{map_id}/geojson")
        return result

    def start_localization(self, map_id: int) -> dict[str, Any]:
        """Start a navigation session in the map's current version."""
        result: dict[str, Any] = self._json("POST", f"/v1/maps/{map_id}/localizations")
        return result

    def update_localization(
        self,
        localization_id: int,
        *,
        poses: list[dict[str, Any]],
        tag_data: list[list[dict[str, Any]]] | None = None,
    ) -> dict[str, Any]:
        """Send new odometry poses and tag detections (at most 1,000 poses and 200 detections a
        call: send a backlog in several); returns the phone's estimate in the map."""
        body = {"poses": poses, "tag_data": tag_data or []}
        result: dict[str, Any] = self._json(
            "POST", f"/v1/localizations/{localization_id}/updates", json=body
        )
        return result

    def get_localization(self, localization_id: int) -> dict[str, Any]:
        result: dict[str, Any] = self._json("GET", f"/v1/localizations/{localization_id}")
        return result

    # ----------------------------------------------------------------------- keys

    def create_key(self, *, role: str, name: str = "") -> dict[str, Any]:
        """Create an API key (admin); the body's ``key`` is shown only this once."""
        result: dict[str, Any] = self._json("POST", "/v1/keys", json={"role": role, "name": name})
        return result

    def list_keys(self) -> list[dict[str, Any]]:
        body = self._json("GET", "/v1/keys")
        keys: list[dict[str, Any]] = body["data"] if isinstance(body, dict) else body
        return keys

    def revoke_key(self, key_id: int) -> None:
        self.request("DELETE", f"/v1/keys/{key_id}")


def _api_error(response: httpx.Response) -> ApiError:
    try:
        body = response.json()
    except ValueError:
        return ApiError(response.status_code, response.text[:200] or response.reason_phrase)
    if not isinstance(body, dict):
        return ApiError(response.status_code, str(body)[:200])
    detail = body.get("detail")
    return ApiError(
        response.status_code,
        detail if isinstance(detail, str) else str(detail),
        body.get("code"),
        body.get("field"),
    )
