"""Maps of several sessions over HTTP (issue 15), on SQLite and PostgreSQL, with the real worker:
upload two walks, merge them, route across a corridor only the second walked, localize against
the joint map; and the bad cases (no shared tags, inconsistent ones, the last session, a map
merged into itself)."""

from __future__ import annotations

import json
from collections.abc import Iterator
from typing import Any

import networkx as nx
import pytest

from app.config import Settings
from app.domain.localize import session_update_documents
from app.domain.upload.session import load_session
from tests.conftest import PreparedDatabases
from tests.service.api_support import ADMIN, SESSIONS_DIR, Api, running_api
from workers.main import Worker

pytestmark = pytest.mark.db

FLOOR_2 = SESSIONS_DIR / "floor_2_straight.json"
STRAIGHT_209 = SESSIONS_DIR / "straight_209_occam.json"
DESNAT = SESSIONS_DIR / "desnat_straight_once.json"
OCCAM = SESSIONS_DIR / "occam_room.json"
IDENTITY_16 = [1.0, 0, 0, 0, 0, 1.0, 0, 0, 0, 0, 1.0, 0, 0, 0, 0, 1.0]


def with_poi(path: Any, name: str, pose_id: int, *, map_id: str | None = None) -> bytes:
    """The session with one point of interest where pose ``pose_id`` was."""
    document = json.loads(path.read_bytes())
    poses = {pose["id"]: pose for pose in document["pose_data"]}
    document["location_data"] = [
        {
            "name": name,
            "pose_id": pose_id + 1,  # the app writes it one too high; the parser corrects it
            "timestamp": poses[pose_id]["timestamp"],
            "transform": IDENTITY_16,
        }
    ]
    if map_id is not None:
        document["map_id"] = map_id
    return json.dumps(document).encode()


def with_tags_renumbered(path: Any, mapping: dict[int, int]) -> bytes:
    """The session as if its tags had other ids (so it shares tags with the map that are in
    fact somewhere else: inconsistent)."""
    document = json.loads(path.read_bytes())
    for frame in document["tag_data"]:
        for detection in frame:
            detection["tag_id"] = mapping.get(detection["tag_id"], detection["tag_id"])
    document["map_id"] = "renumbered"
    return json.dumps(document).encode()


def build(api: Api) -> None:
    """Run the real worker pipeline on every queued job."""
    worker = Worker(api.db, Settings(database_url="sqlite://", lease_s=60, heartbeat_s=5))
    while worker.run_once():
        pass


def job(api: Api, job_id: int) -> dict[str, Any]:
    response = api.client.get(f"/v1/jobs/{job_id}", headers=ADMIN)
    assert response.status_code == 200, response.text
    body: dict[str, Any] = response.json()
    return body


def get_map(api: Api, map_id: int) -> dict[str, Any]:
    response = api.client.get(f"/v1/maps/{map_id}", headers=ADMIN)
    assert response.status_code == 200, response.text
    body: dict[str, Any] = response.json()
    return body


#: the uploads' answers of :func:`_two_walks_built`, by the database it prepared
_TWO_WALKS: dict[str, tuple[dict[str, Any], dict[str, Any]]] = {}


def _two_walks_built(url: str) -> None:
    with running_api(url) as api:
        first = api.uploaded(with_poi(FLOOR_2, "Room 209", 400))
        build(api)
        second = api.uploaded(with_poi(STRAIGHT_209, "Occam lab door", 900))
        build(api)
    _TWO_WALKS[url.partition(":")[0]] = (first, second)


@pytest.fixture
def two_walks(
    database_url: str, prepared_databases: PreparedDatabases
) -> Iterator[tuple[Api, dict[str, Any], dict[str, Any]]]:
    """floor_2_straight (its own map, built), then straight_209_occam uploaded (its map built);
    built once per test process and database kind, each test on its own copy."""
    prepared_databases.copy_into(database_url, "two_walks", _two_walks_built)
    first, second = _TWO_WALKS[database_url.partition(":")[0]]
    with running_api(database_url) as api:
        yield api, first, second


#: floor_2_straight and straight_209_occam in one map (measured: optimize_sessions, gtsam 4.3.0).
JOINT_WEIGHTING = [
    "weighed by its own noise: its cost grew by 19.8 on joining, for 32.2 degrees of freedom "
    "gained, which that noise explains",
    "weighed by its own noise: its cost grew by 3.0 on joining, for 1.0 degrees of freedom "
    "gained, which that noise explains",
]
#: Each walk's variances, estimated from its own residuals: straight_209_occam holds tag positions
#: ~12× tighter than floor_2_straight, so it weighs more there.
JOINT_NOISE_VARIANCES = [
    {
        "odom_linear_var_m2_per_s": 0.00021527848871540062,
        "odom_angular_var_rad2_per_s": 1.1559037654697625e-05,
        "tag_position_var_m2": 2.8906887942598522e-05,
        "tag_orientation_var_rad2": 0.0027428110523182447,
    },
    {
        "odom_linear_var_m2_per_s": 2.3093543437525856e-05,
        "odom_angular_var_rad2_per_s": 2.270278815954718e-05,
        "tag_position_var_m2": 2.3733200609321743e-06,
        "tag_orientation_var_rad2": 0.0006935597232557821,
    },
]


def test_merge_route_and_localize_on_the_joint_map(two_walks):
    api, first, second = two_walks
    # the upload says which map it shares tags with; nothing merged by itself
    shares = second["shares_tags_with"]
    assert [s["map_id"] for s in shares] == [first["map_id"]]
    assert shares[0]["shared_tags"] == [302, 303, 304, 305, 306, 307]
    assert shares[0]["merge_url"] == f"/v1/maps/{first['map_id']}/merge"
    assert get_map(api, first["map_id"])["session_ids"] == [first["session_id"]]

    response = api.client.post(
        shares[0]["merge_url"], json={"map_id": second["map_id"]}, headers=ADMIN
    )
    assert response.status_code == 202, response.text
    accepted = response.json()
    assert accepted["session_ids"] == [first["session_id"], second["session_id"]]
    assert response.headers["Location"] == f"/v1/jobs/{accepted['job_id']}"
    assert api.client.get(f"/v1/maps/{second['map_id']}", headers=ADMIN).status_code == 404
    build(api)
    assert job(api, accepted["job_id"])["state"] == "succeeded"
    # one corridor skeleton fused from both walks, and the log says so (issue 26)
    assert (
        "path graph: corridor skeleton fused from 2 walks"
        in job(api, accepted["job_id"])["log_tail"]
    )

    merged = get_map(api, first["map_id"])
    version = merged["current_version"]
    assert version["number"] == 2
    assert version["session_ids"] == [first["session_id"], second["session_id"]]
    assert version["statistics"]["poses"] == 1004 + 1007
    tag_ids = {tag["tag_id"] for tag in version["tags"]}
    assert {300, 324, 1, 330} <= tag_ids  # tags of each walk alone
    contributions = version["statistics"]["sessions"]
    assert [c["session_id"] for c in contributions] == version["session_ids"]
    assert contributions[1]["placed_by_tags"] == [302, 303, 304, 305, 306, 307]
    # issue 25: what each weighs and why: its own noise (as optimize_sessions estimates it from
    # that walk's residuals alone), neither down-weighted
    assert [c["weighting"] for c in contributions] == JOINT_WEIGHTING
    assert [c["disagreement_factor"] for c in contributions] == [1.0, 1.0]
    for contribution, variances in zip(contributions, JOINT_NOISE_VARIANCES, strict=True):
        assert contribution["noise"]["variances"] == pytest.approx(variances, rel=1e-6)
    for contribution in contributions:  # alone vs joint
        report = contribution["alone_vs_joint"]
        assert report["all"]["tags_compared"] == len(contribution["tags"])
        assert report["shared"]["tags"] == [302, 303, 304, 305, 306, 307]

    listed = api.client.get(f"/v1/maps/{first['map_id']}/sessions", headers=ADMIN).json()
    assert [s["session_id"] for s in listed["data"]] == version["session_ids"]
    assert all(s["in_current_version"] for s in listed["data"])
    assert [s["contribution"]["detections_used"] for s in listed["data"]] == [
        c["detections_used"] for c in contributions
    ]
    assert all(s["contribution"]["detections_used"] > 0 for s in listed["data"])

    # a route from a tag only the first walk saw to a place only the second walked
    response = api.client.post(
        f"/v1/maps/{first['map_id']}/routes",
        json={"from": {"tag": 300}, "to": {"poi": "Occam lab door"}},
        headers=ADMIN,
    )
    assert response.status_code == 200, response.text
    assert response.json()["map_version"] == 2
    assert response.json()["length_m"] > 5
    response = api.client.post(
        f"/v1/maps/{first['map_id']}/routes",
        json={"from": {"poi": "Room 209"}, "to": {"tag": 330}},
        headers=ADMIN,
    )
    assert response.status_code == 200, response.text

    # the app's map: one connected navigation graph, unique vertex ids
    app_map = api.client.get(f"/v1/maps/{first['map_id']}/app-map", headers=ADMIN).json()
    ids = [v["poseId"] for v in app_map["odometry_vertices"]]
    assert len(ids) == len(set(ids))
    G: nx.Graph[int] = nx.Graph()
    for vertex in app_map["odometry_vertices"]:
        for neighbor in vertex["neighbors"]:
            G.add_edge(vertex["poseId"], neighbor)
    assert nx.is_connected(G)
    assert {w["id"] for w in app_map["waypoints_vertices"]} == {"Room 209", "Occam lab door"}

    # a third walk localizes against the joint map
    response = api.client.post(f"/v1/maps/{first['map_id']}/localizations", headers=ADMIN)
    assert response.status_code == 201, response.text
    sid = response.json()["id"]
    statuses = []
    for document in session_update_documents(load_session(DESNAT), 20):
        response = api.client.post(f"/v1/localizations/{sid}/updates", json=document, headers=ADMIN)
        assert response.status_code == 200, response.text
        statuses.append(response.json()["status"])
    assert statuses[-1] == "localized"

    # remove the second walk: a new version of the first alone; the last session cannot go
    response = api.client.delete(
        f"/v1/maps/{first['map_id']}/sessions/{second['session_id']}", headers=ADMIN
    )
    assert response.status_code == 202, response.text
    build(api)
    version = get_map(api, first["map_id"])["current_version"]
    assert (version["number"], version["session_ids"]) == (3, [first["session_id"]])
    response = api.client.delete(
        f"/v1/maps/{first['map_id']}/sessions/{first['session_id']}", headers=ADMIN
    )
    assert (response.status_code, response.json()["code"]) == (409, "last_session")
    response = api.client.delete(
        f"/v1/maps/{first['map_id']}/sessions/{second['session_id']}", headers=ADMIN
    )
    assert (response.status_code, response.json()["code"]) == (404, "not_in_map")

    # versions stay as they were made: version 2 still records both sessions
    versions = api.client.get(f"/v1/maps/{first['map_id']}/versions", headers=ADMIN).json()
    assert [v["session_ids"] for v in versions["data"]] == [
        [first["session_id"]],
        [first["session_id"], second["session_id"]],
        [first["session_id"]],
    ]
    # rebuilding version 2's sessions makes version 2 again
    both = versions["data"][1]["session_ids"]
    response = api.client.post(
        f"/v1/maps/{first['map_id']}/rebuild", json={"session_ids": both}, headers=ADMIN
    )
    assert response.status_code == 202, response.text
    assert response.json()["session_ids"] == both
    build(api)
    # this worker built version 2: it starts from that optimum and optimizes no walk alone again
    log = job(api, response.json()["job_id"])["log_tail"]
    names = ", ".join(f"session {s}" for s in both)
    assert f"warm start from this worker's last build of the map ({names} not" in log
    again = api.client.get(f"/v1/maps/{first['map_id']}/versions/4", headers=ADMIN).json()
    before = api.client.get(f"/v1/maps/{first['map_id']}/versions/2", headers=ADMIN).json()
    assert again["session_ids"] == both
    assert again["params"] == before["params"]
    assert [t["tag_id"] for t in again["tags"]] == [t["tag_id"] for t in before["tags"]]
    for tag, old in zip(again["tags"], before["tags"], strict=True):
        assert tag["position_m"] == pytest.approx(old["position_m"], abs=1e-4)  # 0.1 mm
    for bad, field in (([first["session_id"]] * 2, "session_ids.1"), ([999_999], "session_ids.0")):
        response = api.client.post(
            f"/v1/maps/{first['map_id']}/rebuild", json={"session_ids": bad}, headers=ADMIN
        )
        assert response.status_code == 422, response.text
        assert response.json()["field"] == field


def test_add_a_session_and_the_bad_cases(two_walks):
    api, first, second = two_walks
    map_id = first["map_id"]
    # a map merged into itself
    response = api.client.post(f"/v1/maps/{map_id}/merge", json={"map_id": map_id}, headers=ADMIN)
    assert (response.status_code, response.json()["code"]) == (409, "same_map")
    # a session already in it; an unknown session; an unknown map
    response = api.client.post(
        f"/v1/maps/{map_id}/sessions", json={"session_id": first["session_id"]}, headers=ADMIN
    )
    assert (response.status_code, response.json()["code"]) == (409, "already_in_map")
    response = api.client.post(
        f"/v1/maps/{map_id}/sessions", json={"session_id": 999_999}, headers=ADMIN
    )
    assert response.status_code == 404
    response = api.client.post(
        "/v1/maps/999999/sessions", json={"session_id": first["session_id"]}, headers=ADMIN
    )
    assert response.status_code == 404
    # devices cannot change maps
    device = api.device()
    response = api.client.post(
        f"/v1/maps/{map_id}/sessions", json={"session_id": second["session_id"]}, headers=device
    )
    assert response.status_code == 403

    # a walk that shares no tag with this map: the build fails with the reason, the map keeps
    # its version (occam_room shares tags 1–7 with straight_209_occam's map only)
    occam = api.uploaded(OCCAM)
    assert map_id not in [s["map_id"] for s in occam["shares_tags_with"]]
    build(api)
    response = api.client.post(
        f"/v1/maps/{map_id}/sessions", json={"session_id": occam["session_id"]}, headers=ADMIN
    )
    assert response.status_code == 202
    build(api)
    failed = job(api, response.json()["job_id"])
    assert failed["state"] == "failed"
    assert "no_shared_tags" in failed["error"]
    assert get_map(api, map_id)["current_version"]["number"] == 1
    response = api.client.delete(f"/v1/maps/{map_id}/sessions/{occam['session_id']}", headers=ADMIN)
    assert response.status_code == 202
    build(api)

    # add the second walk (it stays in its own map too): a version of both
    response = api.client.post(
        f"/v1/maps/{map_id}/sessions", json={"session_id": second["session_id"]}, headers=ADMIN
    )
    assert response.status_code == 202, response.text
    build(api)
    current = get_map(api, map_id)["current_version"]
    assert current["number"] == 3
    assert current["session_ids"] == [first["session_id"], second["session_id"]]
    assert get_map(api, second["map_id"])["session_ids"] == [second["session_id"]]

    # a walk whose tags claim ids the map has elsewhere: inconsistent shared tags
    renumbered = api.uploaded(with_tags_renumbered(DESNAT, {300 + k: 308 + k for k in range(8)}))
    build(api)
    response = api.client.post(
        f"/v1/maps/{map_id}/merge", json={"map_id": renumbered["map_id"]}, headers=ADMIN
    )
    assert response.status_code == 202
    build(api)
    failed = job(api, response.json()["job_id"])
    assert failed["state"] == "failed"
    assert "inconsistent_shared_tags" in failed["error"]
    assert get_map(api, map_id)["current_version"]["number"] == 3


def test_a_sweep_of_a_merged_map_tunes_the_joint_map(two_walks):
    api, first, second = two_walks
    map_id = first["map_id"]
    response = api.client.post(
        f"/v1/maps/{map_id}/merge", json={"map_id": second["map_id"]}, headers=ADMIN
    )
    assert response.status_code == 202
    build(api)
    space = {"odom_linear_var_m2_per_s": {"low": 1e-4, "high": 1e-2, "num": 2}}
    response = api.client.post(f"/v1/maps/{map_id}/sweeps", json={"space": space}, headers=ADMIN)
    assert response.status_code == 202, response.text
    sweep_id = response.json()["sweep_id"]
    build(api)
    sweep = api.client.get(f"/v1/sweeps/{sweep_id}?runs=true", headers=ADMIN).json()
    assert sweep["state"] == "succeeded", sweep["error"]
    assert sweep["session_ids"] == [first["session_id"], second["session_id"]]
    assert sweep["shift_metric_version"] == 2
    assert len(sweep["runs"]) == 2
    response = api.client.post(f"/v1/sweeps/{sweep_id}/apply", headers=ADMIN)
    assert response.status_code == 202, response.text
    build(api)
    version = get_map(api, map_id)["current_version"]
    assert version["session_ids"] == [first["session_id"], second["session_id"]]
    # the applied build is the map the best trial measured
    assert version["shift_metric"] == pytest.approx(sweep["summary"]["best_shift"], rel=1e-9)


def test_upload_into_an_existing_map(database_url: str) -> None:
    with running_api(database_url) as api:
        first = api.uploaded(FLOOR_2.read_bytes())
        build(api)
        body = DESNAT.read_bytes()
        device = api.device()
        refused = api.client.post(
            f"/v1/sessions?into_map={first['map_id']}",
            content=body,
            headers={**device, "Content-Type": "application/json"},
        )
        assert refused.status_code == 403
        sessions_before = api.client.get("/v1/sessions", headers=ADMIN).json()["count"]
        missing = api.client.post(
            "/v1/sessions?into_map=999999",
            content=body,
            headers={**ADMIN, "Content-Type": "application/json"},
        )
        assert missing.status_code == 404
        assert api.client.get("/v1/sessions", headers=ADMIN).json()["count"] == sessions_before

        into = api.client.post(
            f"/v1/sessions?into_map={first['map_id']}",
            content=body,
            headers={**ADMIN, "Content-Type": "application/json", "Idempotency-Key": "desnat-1"},
        )
        assert into.status_code == 202, into.text
        created = into.json()
        assert created["map_id"] == first["map_id"]
        build(api)
        assert job(api, created["job_id"])["state"] == "succeeded"
        version = get_map(api, first["map_id"])["current_version"]
        assert version["session_ids"] == [first["session_id"], created["session_id"]]
        # the same upload again (a phone retrying) answers the same map and job
        again = api.client.post(
            f"/v1/sessions?into_map={first['map_id']}",
            content=body,
            headers={**ADMIN, "Content-Type": "application/json", "Idempotency-Key": "desnat-1"},
        )
        assert again.status_code == 202, again.text
        assert (again.json()["map_id"], again.json()["session_id"]) == (
            first["map_id"],
            created["session_id"],
        )


def test_the_map_says_what_its_version_is_built_from_and_tuning_it_is_refused(
    database_url: str,
) -> None:
    """Issue 25: a change of a map's sessions answers what it queued (the generation, and
    whether it was folded into a build queued before); the map and its sessions list say which
    sessions the current version was built from and whether the build of the current ones is
    under way; tuning a map of several sessions is a 422 naming the field, at the door."""
    walk = (SESSIONS_DIR / "pgt_tester3.json").read_bytes()
    with running_api(database_url) as api:
        first = api.uploaded(walk)
        second = api.uploaded(with_tags_renumbered(SESSIONS_DIR / "pgt_tester3.json", {}))
        build(api)
        map_id = first["map_id"]
        settled = get_map(api, map_id)
        assert (settled["up_to_date"], settled["pending_job_id"]) == (True, None)
        assert settled["current_version"]["generation"] == settled["generation"] == 0

        response = api.client.post(
            f"/v1/maps/{map_id}/sessions", json={"session_id": second["session_id"]}, headers=ADMIN
        )
        assert response.status_code == 202, response.text
        added = response.json()
        assert (added["generation"], added["coalesced"], added["superseded_job_ids"]) == (
            1,
            False,
            [],
        )
        both = [first["session_id"], second["session_id"]]
        pending = get_map(api, map_id)
        assert pending["session_ids"] == both
        assert pending["current_version"]["session_ids"] == [first["session_id"]]
        assert (pending["up_to_date"], pending["pending_job_id"]) == (False, added["job_id"])
        listed = api.client.get(f"/v1/maps/{map_id}/sessions", headers=ADMIN).json()
        assert listed["current_session_ids"] == [first["session_id"]]
        assert (listed["up_to_date"], listed["pending_job_id"]) == (False, added["job_id"])
        assert [s["in_current_version"] for s in listed["data"]] == [True, False]

        # tuning a map of several sessions: refused at the door, nothing queued or stored
        response = api.client.post(
            f"/v1/maps/{map_id}/rebuild", json={"auto_tune_trials": 1000}, headers=ADMIN
        )
        assert response.status_code == 422, response.text
        assert (response.json()["code"], response.json()["field"]) == (
            "invalid_parameter",
            "auto_tune_trials",
        )
        sessions_before = api.client.get("/v1/sessions", headers=ADMIN).json()["count"]
        response = api.client.post(
            f"/v1/sessions?into_map={map_id}&auto_tune_trials=50",
            content=walk,
            headers={**ADMIN, "Content-Type": "application/json"},
        )
        assert response.status_code == 422, response.text
        assert response.json()["field"] == "auto_tune_trials"
        assert api.client.get("/v1/sessions", headers=ADMIN).json()["count"] == sessions_before
        assert get_map(api, map_id)["pending_job_id"] == added["job_id"]

        # a rebuild before the add's build started: folded into it, one build of both
        response = api.client.post(
            f"/v1/maps/{map_id}/rebuild", json={"params": {"huber_k": 2.0}}, headers=ADMIN
        )
        assert response.status_code == 202, response.text
        rebuilt = response.json()
        assert (rebuilt["job_id"], rebuilt["coalesced"], rebuilt["generation"]) == (
            added["job_id"],
            True,
            2,
        )
        build(api)
        built = get_map(api, map_id)
        assert built["version_count"] == 2
        assert built["current_version"]["session_ids"] == both
        assert built["current_version"]["params"]["huber_k"] == 2.0
        assert (built["up_to_date"], built["pending_job_id"], built["generation"]) == (
            True,
            None,
            2,
        )
        assert "coalesced: rebuild requested" in job(api, added["job_id"])["log_tail"]

        # a map of one session may still be tuned
        response = api.client.post(
            f"/v1/maps/{second['map_id']}/rebuild", json={"auto_tune_trials": 3}, headers=ADMIN
        )
        assert response.status_code == 202, response.text
