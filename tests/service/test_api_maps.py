"""/v1/maps: a map before and after its first build, ETags, versions, the app's download format,
the plot, rebuild (with parameters, and refused parameters), delete. SQLite and PostgreSQL.

Versions are made without a worker process: ``run_next_job`` runs the worker's stages here."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from api_support import ADMIN, OCCAM, ONETAG, Api, run_next_job, running_api, session_variant

from app.config import Settings
from app.domain.evaluation.ground_truth import load_ground_truth
from app.domain.evaluation.table import evaluate_map
from app.domain.formats.map_io import map_to_app_format
from app.domain.frames import pose_to_xyz_quat_xyzw
from app.domain.mapping.params import SlamParams
from app.domain.mapping.slam import optimize_session
from app.domain.upload.session import load_session
from app.storage.orm import Job, MapRow, MapVersion, SessionRow
from workers.main import Worker

pytestmark = pytest.mark.db

#: The real processed map in shared/ (beside the repository; absent in a bare clone).
PROCESSED_EXAMPLES = sorted(
    (Path(__file__).resolve().parents[3] / "shared/data/processed_examples").glob("*.json")
)

#: The app's download format, docs/architecture.md §7 (and our notes, which the app ignores).
APP_MAP_KEYS = {"tag_vertices", "odometry_vertices", "waypoints_vertices", "notes"}
TAG_VERTEX_KEYS = {"id", "translation", "rotation"}
ODOMETRY_VERTEX_KEYS = {"poseId", "translation", "rotation", "adjChi2", "vizTags", "neighbors"}


@pytest.fixture
def api(database_url: str) -> Iterator[Api]:
    with running_api(database_url) as running:
        yield running


@pytest.fixture
def built(api: Api) -> dict[str, Any]:
    """occam_room uploaded and built once (version 1)."""
    created = api.uploaded(OCCAM)
    assert run_next_job(api.db) == created["job_id"]
    return created


def get(api: Api, path: str, **headers: str) -> Any:
    response = api.client.get(path, headers={**ADMIN, **headers})
    assert response.status_code == 200, response.text
    return response.json()


# --------------------------------------------------------------------------- before and after


def test_map_before_its_first_version(api: Api) -> None:
    created = api.uploaded(ONETAG)
    url = created["map_url"]

    body = get(api, url)
    assert body["current_version"] is None
    assert body["version_count"] == 0
    assert body["latest_job"] == {"id": created["job_id"], "kind": "build_map", "state": "queued"}
    assert body["session_id"] == created["session_id"]
    assert get(api, url + "/versions") == {"data": [], "count": 0}
    for path in (url + "/app-map", url + "/plot.png"):
        response = api.client.get(path, headers=ADMIN)
        assert response.status_code == 409
        assert response.json()["code"] == "map_not_ready"
        assert f"build job {created['job_id']} is queued" in response.json()["detail"]
    assert api.client.get(url + "/versions/1", headers=ADMIN).status_code == 404


def test_map_after_its_build_has_version_metrics_and_tag_poses(
    api: Api, built: dict[str, Any]
) -> None:
    body = get(api, built["map_url"])

    version = body["current_version"]
    assert body["version_count"] == 1
    assert body["latest_job"]["state"] == "succeeded"
    assert version["number"] == 1
    assert version["job_id"] == built["job_id"]
    assert version["params"] == SlamParams().to_dict()
    assert version["shift_metric"] == version["metrics"]["shift_opt"]
    assert version["shift_metric"] > 0
    assert {"shift_pre", "shift_opt"} <= set(version["metrics"])
    assert version["statistics"]["poses"] == 621
    assert version["detections_used"] + version["detections_rejected"] == 200

    expected = optimize_session(load_session(OCCAM))
    assert [t["tag_id"] for t in version["tags"]] == expected.tag_ids.tolist()
    assert version["tag_count"] == len(expected.tag_ids)
    for tag, world_T_tag in zip(version["tags"], expected.world_T_tag, strict=True):
        pose = pose_to_xyz_quat_xyzw(world_T_tag)
        np.testing.assert_allclose(tag["position_m"], pose[:3], atol=1e-9)
        np.testing.assert_allclose(tag["quat_xyzw"], pose[3:], atol=1e-9)
        assert tag["covariance"] is None or len(tag["covariance"]) == 36


def test_etag_and_if_none_match(api: Api, built: dict[str, Any]) -> None:
    url = built["map_url"]
    first = api.client.get(url, headers=ADMIN)
    etag = first.headers["ETag"]
    assert etag.startswith('"')
    assert etag.endswith('"')

    for if_none_match in (etag, f"W/{etag}", f'"other", {etag}', "*"):
        cached = api.client.get(url, headers={**ADMIN, "If-None-Match": if_none_match})
        assert cached.status_code == 304, if_none_match
        assert cached.content == b""
        assert cached.headers["ETag"] == etag
    assert api.client.get(url, headers={**ADMIN, "If-None-Match": '"old"'}).status_code == 200

    # A queued rebuild changes the representation (latest_job), then the new version does.
    assert api.client.post(url + "/rebuild", headers=ADMIN).status_code == 202
    queued = api.client.get(url, headers={**ADMIN, "If-None-Match": etag})
    assert queued.status_code == 200
    assert queued.headers["ETag"] != etag
    run_next_job(api.db)
    rebuilt = api.client.get(url, headers={**ADMIN, "If-None-Match": queued.headers["ETag"]})
    assert rebuilt.status_code == 200
    assert rebuilt.json()["current_version"]["number"] == 2
    assert len({etag, queued.headers["ETag"], rebuilt.headers["ETag"]}) == 3


# --------------------------------------------------------------------------- downloads


def test_app_map_has_the_apps_format(api: Api, built: dict[str, Any]) -> None:
    response = api.client.get(built["map_url"] + "/app-map", headers=ADMIN)

    assert response.status_code == 200
    assert response.headers["Content-Type"] == "application/json"
    app_map = response.json()
    assert set(app_map) == APP_MAP_KEYS
    assert len(app_map["odometry_vertices"]) == 621
    assert (
        len(app_map["tag_vertices"]) == get(api, built["map_url"])["current_version"]["tag_count"]
    )
    for vertex in app_map["tag_vertices"]:
        assert set(vertex) == TAG_VERTEX_KEYS
        assert set(vertex["translation"]) == {"x", "y", "z"}
        assert set(vertex["rotation"]) == {"x", "y", "z", "w"}
    for vertex in app_map["odometry_vertices"]:
        assert set(vertex) == ODOMETRY_VERTEX_KEYS
    assert app_map["odometry_vertices"][1]["neighbors"] == [0, 2]
    assert app_map["notes"] == []
    # The same as the core makes from the same session.
    expected = map_to_app_format(optimize_session(load_session(OCCAM)))
    assert [v["id"] for v in app_map["tag_vertices"]] == [v["id"] for v in expected["tag_vertices"]]
    np.testing.assert_allclose(
        [list(v["translation"].values()) for v in app_map["tag_vertices"]],
        [list(v["translation"].values()) for v in expected["tag_vertices"]],
        atol=1e-9,
    )
    # And its keys are those of the real processed map shipped in shared/ (when present).
    for path in PROCESSED_EXAMPLES:
        example = json.loads(path.read_text())
        assert set(example) == APP_MAP_KEYS - {"notes"}  # notes: ours, which the app ignores
        assert set(example["tag_vertices"][0]) == TAG_VERTEX_KEYS
        assert set(example["odometry_vertices"][0]) == ODOMETRY_VERTEX_KEYS

    etag = response.headers["ETag"]
    cached = api.client.get(built["map_url"] + "/app-map", headers={**ADMIN, "If-None-Match": etag})
    assert cached.status_code == 304


def test_app_map_of_a_version_and_waypoints(api: Api) -> None:
    session = json.loads(ONETAG.read_bytes())
    session["location_data"] = [
        {
            "name": "Room 101",
            "pose_id": 5,
            "timestamp": 0.0,
            "transform": np.eye(4).ravel().tolist(),
        }
    ]
    created = api.uploaded(json.dumps(session).encode())
    run_next_job(api.db)

    app_map = get(api, created["map_url"] + "/app-map?version=1")

    assert [w["id"] for w in app_map["waypoints_vertices"]] == ["Room 101"]
    assert set(app_map["waypoints_vertices"][0]) == {"id", "translation", "rotation"}
    missing = api.client.get(created["map_url"] + "/app-map?version=2", headers=ADMIN)
    assert missing.status_code == 404
    assert missing.json()["detail"] == f"version 2 of map {created['map_id']} not found"


def test_plot_png(api: Api) -> None:
    created = api.uploaded(ONETAG)
    run_next_job(api.db, plot=True)

    response = api.client.get(created["map_url"] + "/plot.png", headers=ADMIN)

    assert response.status_code == 200
    assert response.headers["Content-Type"] == "image/png"
    assert response.content.startswith(b"\x89PNG\r\n\x1a\n")
    cached = api.client.get(
        created["map_url"] + "/plot.png",
        headers={**ADMIN, "If-None-Match": response.headers["ETag"]},
    )
    assert cached.status_code == 304


def test_a_version_without_plot_is_404_for_the_plot(api: Api, built: dict[str, Any]) -> None:
    response = api.client.get(built["map_url"] + "/plot.png", headers=ADMIN)

    assert response.status_code == 404
    assert "has no plot" in response.json()["detail"]


# --------------------------------------------------------------------------- versions, rebuild


def test_rebuild_with_parameters_adds_a_version_and_leaves_the_session_alone(
    api: Api, built: dict[str, Any]
) -> None:
    raw_before = api.client.get(f"/v1/sessions/{built['session_id']}/raw", headers=ADMIN).content
    url = built["map_url"]

    response = api.client.post(
        url + "/rebuild",
        headers=ADMIN,
        json={"params": {"tag_position_var_m2": "1e-3", "tag_sizes_m": {"3": 0.15}}},
    )

    assert response.status_code == 202, response.text
    accepted = response.json()
    assert response.headers["Location"] == f"/v1/jobs/{accepted['job_id']}"
    assert accepted["params"] == {"tag_position_var_m2": 1e-3, "tag_sizes_m": {"3": 0.15}}
    assert accepted["map_id"] == built["map_id"]
    job = get(api, f"/v1/jobs/{accepted['job_id']}")
    assert (job["state"], job["params"]) == ("queued", accepted["params"])
    assert run_next_job(api.db) == accepted["job_id"]

    versions = get(api, url + "/versions")
    assert versions["count"] == 2
    assert [v["number"] for v in versions["data"]] == [1, 2]
    assert versions["data"][1]["params"]["tag_position_var_m2"] == 1e-3
    assert versions["data"][0]["params"]["tag_position_var_m2"] == 1e-4
    assert "tags" not in versions["data"][0]
    assert get(api, url)["current_version"]["number"] == 2
    detail = get(api, url + "/versions/1")
    assert detail["number"] == 1
    assert len(detail["tags"]) == detail["tag_count"]
    assert len(detail["rejections"]) == detail["detections_rejected"]
    assert {"reason", "value", "limit", "tag_id"} <= set(detail["rejections"][0])
    assert api.client.get(f"/v1/sessions/{built['session_id']}/raw", headers=ADMIN).content == (
        raw_before
    )
    assert api.count(SessionRow) == 1


def test_a_rebuild_with_ground_truth_makes_a_version_with_the_ground_truth_metric(
    api: Api, built: dict[str, Any], data_dir: Path
) -> None:
    """What the demo does for its maps with ground truth: the version shows the metric in the
    API (and so on the map page), the same figures as ``invisible-map evaluate`` gives."""
    truth_path = data_dir / "ground_truth" / "occam_room_tape.json"
    truth = json.loads(truth_path.read_text())
    truth["note"] = "measured with tape"  # unknown keys are not kept (a NUL in any text is a
    # 422 at the door: tests/service/test_stored_text.py)
    response = api.client.post(
        built["map_url"] + "/rebuild", headers=ADMIN, json={"ground_truth": truth}
    )
    assert response.status_code == 202, response.text
    assert response.json()["params"] == {}  # the ground truth is not echoed
    kept = get(api, f"/v1/jobs/{response.json()['job_id']}")["params"]["ground_truth"]
    assert set(kept) == {"poses"}
    worker = Worker(api.db, Settings(database_url="sqlite://", lease_s=60, heartbeat_s=5))
    assert worker.run_once()

    current = get(api, built["map_url"])["current_version"]
    assert current["number"] == 2
    session = load_session(OCCAM)
    expected = evaluate_map(
        session, optimize_session(session, SlamParams()), load_ground_truth(truth_path)
    )
    metrics = current["metrics"]
    assert metrics["gt_metric_opt"] == pytest.approx(expected.gt_metric_opt, rel=1e-6)
    assert metrics["gt_metric_pre"] == pytest.approx(expected.gt_metric_pre, rel=1e-6)
    assert metrics["tag_rmse_opt_m"] == pytest.approx(expected.tag_rmse_opt_m, rel=1e-6)
    assert metrics["tags_with_ground_truth"] == 8
    assert (
        "ground-truth metric 0.05" in get(api, f"/v1/jobs/{response.json()['job_id']}")["log_tail"]
    )
    first = get(api, built["map_url"] + "/versions/1")
    assert "gt_metric_opt" not in first["metrics"]  # built without ground truth


#: Bad ground truth for a rebuild, and what the 422's detail names.
BAD_GROUND_TRUTH = [
    ({"poses": []}, "poses: empty, no tag poses"),
    ({"poses": [{"tag_id": 1, "pose": [0, 0, 0, 0, 0, 0]}]}, "poses[0].pose"),
    ({"tags": []}, "poses: missing"),
]


def test_a_rebuild_with_bad_ground_truth_is_422_and_queues_nothing(
    api: Api, built: dict[str, Any]
) -> None:
    jobs_before = api.count(Job)
    for truth, detail in BAD_GROUND_TRUTH:
        response = api.client.post(
            built["map_url"] + "/rebuild", headers=ADMIN, json={"ground_truth": truth}
        )
        assert response.status_code == 422, truth
        body = response.json()
        assert (body["code"], body["field"]) == ("invalid_ground_truth", "ground_truth")
        assert detail in body["detail"]
    assert api.count(Job) == jobs_before


def test_rebuild_without_body_uses_the_defaults(api: Api, built: dict[str, Any]) -> None:
    response = api.client.post(built["map_url"] + "/rebuild", headers=ADMIN)

    assert response.status_code == 202
    assert response.json()["params"] == {}


@pytest.mark.parametrize(
    ("body", "field", "reason"),
    [
        ({"params": {"no_such_param": 1}}, "params.no_such_param", "unknown parameter"),
        ({"params": {"huber_k": -1}}, "params.huber_k", "must be ≥ 0"),
        ({"params": {"tag_size_m": "abc"}}, "params.tag_size_m", "cannot use 'abc'"),
        ({"params": {"max_view_angle_deg": 120}}, "params.max_view_angle_deg", "(0, 90]"),
        ({"params": {"tag_position_var_m2": float("nan")}}, "params.tag_position_var_m2", "finite"),
        ({"params": [1, 2]}, "params", "valid dictionary"),
        ({"parameters": {}}, "parameters", "Extra inputs"),
    ],
    ids=["unknown", "out-of-range", "not-a-number", "angle", "nan-json", "list", "extra-key"],
)
def test_rebuild_with_bad_parameters_is_422_and_queues_nothing(
    api: Api, built: dict[str, Any], body: Any, field: str | None, reason: str | None
) -> None:
    jobs_before = api.count(Job)
    content = json.dumps(body, allow_nan=True).encode()

    response = api.client.post(
        built["map_url"] + "/rebuild",
        headers={**ADMIN, "Content-Type": "application/json"},
        content=content,
    )

    assert response.status_code == 422, response.text
    error = response.json()
    assert error["field"] == field
    assert reason in error["detail"]
    assert api.count(Job) == jobs_before


def test_rebuild_of_a_bad_json_body_is_400(api: Api, built: dict[str, Any]) -> None:
    response = api.client.post(
        built["map_url"] + "/rebuild",
        headers={**ADMIN, "Content-Type": "application/json"},
        content=b"{not json",
    )

    assert response.status_code == 400
    assert response.json()["code"] == "invalid_json"
    assert response.json()["field"] == "body"


# --------------------------------------------------------------------------- list, delete


def test_list_maps_paginated_and_by_tag(api: Api) -> None:
    occam = api.uploaded(OCCAM)
    run_next_job(api.db)
    onetag = api.uploaded(ONETAG)
    run_next_job(api.db)
    unbuilt = api.uploaded(session_variant(ONETAG, map_id="unbuilt"))

    page = get(api, "/v1/maps?limit=2")
    assert page["count"] == 3
    assert [m["id"] for m in page["data"]] == [unbuilt["map_id"], onetag["map_id"]]
    assert page["data"][0]["current_version"] is None
    assert page["data"][1]["current_version"]["number"] == 1
    assert "tags" not in page["data"][1]["current_version"]
    assert [m["id"] for m in get(api, "/v1/maps?limit=2&offset=2")["data"]] == [occam["map_id"]]

    by_tag = get(api, "/v1/maps?tag_id=306")  # onetag's tag
    assert [m["id"] for m in by_tag["data"]] == [onetag["map_id"]]
    assert by_tag["count"] == 1
    assert get(api, "/v1/maps?tag_id=3")["count"] == 1  # one of occam_room's
    assert get(api, "/v1/maps?tag_id=9999")["count"] == 0
    for bad in ("limit=0", "limit=500", "offset=-3", "tag_id=-1"):
        assert api.client.get(f"/v1/maps?{bad}", headers=ADMIN).status_code == 422


def test_delete_cancels_jobs_removes_map_and_versions_keeps_the_session_and_jobs(
    api: Api, built: dict[str, Any]
) -> None:
    url = built["map_url"]
    rebuild = api.client.post(url + "/rebuild", headers=ADMIN).json()

    response = api.client.delete(url, headers=ADMIN)

    assert response.status_code == 204
    assert response.content == b""
    for path in ("", "/versions", "/versions/1", "/app-map", "/plot.png"):
        assert api.client.get(url + path, headers=ADMIN).status_code == 404, path
    assert api.client.post(url + "/rebuild", headers=ADMIN).status_code == 404
    assert api.client.delete(url, headers=ADMIN).status_code == 404
    # The jobs stay, with no map, saying so; one whose map is gone cannot be retried.
    for job_id, state in ((built["job_id"], "succeeded"), (rebuild["job_id"], "canceled")):
        kept = get(api, f"/v1/jobs/{job_id}")
        assert (kept["state"], kept["map_id"]) == (state, None)
        assert kept["log_tail"].endswith(f"map {built['map_id']} deleted; this job is kept\n")
    retry = api.client.post(f"/v1/jobs/{rebuild['job_id']}/retry", headers=ADMIN)
    assert retry.status_code == 409
    assert retry.json()["detail"] == f"job {rebuild['job_id']}'s map was deleted: cannot retry it"
    assert (api.count(MapRow), api.count(MapVersion), api.count(Job)) == (0, 0, 2)
    session = get(api, f"/v1/sessions/{built['session_id']}")
    assert (session["map_id"], session["job_ids"]) == (None, [built["job_id"], rebuild["job_id"]])
    assert api.client.get(f"/v1/sessions/{built['session_id']}/raw", headers=ADMIN).content == (
        OCCAM.read_bytes()
    )


@pytest.mark.parametrize("map_id", ["999", "0", "-5", str(2**64)])
def test_unknown_map_is_404_on_every_route(api: Api, map_id: str) -> None:
    url = f"/v1/maps/{map_id}"
    responses = [
        api.client.get(url + path, headers=ADMIN)
        for path in ("", "/versions", "/versions/1", "/app-map", "/plot.png")
    ]
    responses.append(api.client.post(url + "/rebuild", headers=ADMIN))
    responses.append(api.client.delete(url, headers=ADMIN))

    for response in responses:
        assert response.status_code == 404, response.request.url
        assert response.json() == {
            "detail": f"map {map_id} not found",
            "code": "not_found",
            "field": None,
        }


def test_devices_read_maps_but_not_change_them(api: Api, built: dict[str, Any]) -> None:
    device = api.device()
    url = built["map_url"]

    for path in ("", "/versions", "/versions/1", "/app-map"):
        assert api.client.get(url + path, headers=device).status_code == 200, path
    assert api.client.get("/v1/maps", headers=device).json()["count"] == 1
    assert api.client.post(url + "/rebuild", headers=device).status_code == 403
    assert api.client.delete(url, headers=device).status_code == 403
    assert api.count(MapRow) == 1
