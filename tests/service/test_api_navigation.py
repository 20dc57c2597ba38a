"""Navigation over HTTP: points of interest, routes, GeoJSON and live localization, on maps built
by the real worker pipeline (path-graph stage included), on SQLite and PostgreSQL."""

from __future__ import annotations

import json
import math
import threading
import time
from collections.abc import Iterator
from types import SimpleNamespace
from typing import Any

import networkx as nx
import numpy as np
import pytest
from fastapi.testclient import TestClient
from sqlalchemy import text
from sqlalchemy.exc import DBAPIError

from app.api.routes import localization as localization_route
from app.config import Settings
from app.domain.frames import pose_from_xyz_quat_xyzw
from app.domain.localize import LocalizerState, parse_update, session_update_documents, update
from app.domain.upload.session import load_session
from app.main import create_app
from app.storage import maps, navigation
from app.storage.navigation import LocalizationConflict
from tests.conftest import PreparedDatabases
from tests.service.api_support import ADMIN, ADMIN_KEY, SESSIONS_DIR, Api, running_api
from workers.main import Worker

pytestmark = pytest.mark.db

FLOOR_2 = SESSIONS_DIR / "floor_2_straight.json"
DESNAT = SESSIONS_DIR / "desnat_straight_once.json"
IDENTITY_16 = [1.0, 0, 0, 0, 0, 1.0, 0, 0, 0, 0, 1.0, 0, 0, 0, 0, 1.0]


def floor_2_with_pois() -> bytes:
    """floor_2_straight with two points of interest named where poses 400 and 900 were."""
    document = json.loads(FLOOR_2.read_bytes())
    poses = {pose["id"]: pose for pose in document["pose_data"]}
    document["location_data"] = [
        {
            "name": name,
            "pose_id": pose_id + 1,  # the app writes it one too high; the parser corrects it
            "timestamp": poses[pose_id]["timestamp"],
            "transform": IDENTITY_16,
        }
        for name, pose_id in (("Room 209", 400), ("Elevator lobby", 900))
    ]
    return json.dumps(document).encode()


def build(api: Api) -> None:
    """Run the real worker pipeline on every queued job."""
    worker = Worker(api.db, Settings(database_url="sqlite://", lease_s=60, heartbeat_s=5))
    while worker.run_once():
        pass


def _floor_2_built(url: str) -> None:
    with running_api(url) as api:
        assert api.uploaded(floor_2_with_pois())["map_id"] == 1
        build(api)


@pytest.fixture
def nav(database_url: str, prepared_databases: PreparedDatabases) -> Iterator[tuple[Api, int]]:
    """floor_2_straight with two points of interest, uploaded and built by the real worker (once
    per test process and database kind; each test gets its own copy)."""
    prepared_databases.copy_into(database_url, "floor_2_pois", _floor_2_built)
    with running_api(database_url) as api:
        yield api, 1


def route(api: Api, map_id: int, body: dict[str, Any]) -> Any:
    return api.client.post(f"/v1/maps/{map_id}/routes", json=body, headers=ADMIN)


# --------------------------------------------------------------------------- pois, routes


def test_pois_are_searchable_by_name(nav):
    api, map_id = nav
    everything = api.client.get(f"/v1/maps/{map_id}/pois", headers=ADMIN).json()
    assert everything["count"] == 2
    assert everything["map_version"] == 1
    found = api.client.get(f"/v1/maps/{map_id}/pois", params={"q": "ROOM"}, headers=ADMIN).json()
    assert [poi["name"] for poi in found["data"]] == ["Room 209"]
    assert found["data"][0]["floor"] == 1
    none = api.client.get(f"/v1/maps/{map_id}/pois", params={"q": "kitchen"}, headers=ADMIN)
    assert none.json() == {"data": [], "count": 0, "map_version": 1}


def test_route_from_a_tag_to_a_poi(nav):
    api, map_id = nav
    response = route(api, map_id, {"from": {"tag": 300}, "to": {"poi": "Room 209"}})
    assert response.status_code == 200, response.text
    body = response.json()
    assert body["map_version"] == 1
    assert body["floors"] == [1]
    polyline = np.array(body["polyline"])
    assert polyline.shape[1] == 3
    straight_m = float(np.linalg.norm(polyline[-1] - polyline[0]))
    assert body["length_m"] >= straight_m - 1e-9
    along_m = float(np.linalg.norm(np.diff(polyline, axis=0), axis=1).sum())
    assert math.isclose(body["length_m"], along_m, rel_tol=1e-9)
    assert body["steps"][-1]["kind"] == "arrive"
    assert body["steps"][-1]["instruction"].startswith("arrive at Room 209")
    assert all(len(step["position"]) == 3 for step in body["steps"])


def test_route_faces_the_heading_and_words_the_style(nav):
    api, map_id = nav
    plain = route(api, map_id, {"from": {"tag": 300}, "to": {"tag": 311}}).json()
    first = np.array(plain["polyline"][1]) - np.array(plain["polyline"][0])
    way_deg = math.degrees(math.atan2(-first[0], -first[2]))  # the route's first direction
    # Facing the other way, the first step is to turn round (clock face: 6 o'clock).
    body = {
        "from": {"tag": 300},
        "to": {"tag": 311},
        "heading_deg": way_deg + 180.0,
        "style": {"units": "ft", "clock": True},
    }
    response = route(api, map_id, body)
    assert response.status_code == 200, response.text
    steps = response.json()["steps"]
    assert steps[0]["kind"] == "face"
    assert steps[0]["instruction"] == "turn to 6 o'clock to face the way"
    assert any(s["instruction"].endswith(" ft") for s in steps if s["kind"] == "go")
    # Facing the way: no facing step; distances in metres by default.
    facing = route(api, map_id, {"from": {"tag": 300}, "to": {"tag": 311}, "heading_deg": way_deg})
    assert facing.json()["steps"][0]["kind"] == "go"
    assert facing.json()["steps"][0]["instruction"].endswith(" m")
    for bad in ({"heading_deg": 400}, {"style": {"units": "yards"}}):
        refused = route(api, map_id, {"from": {"tag": 300}, "to": {"tag": 311}, **bad})
        assert refused.status_code == 422, refused.text


def test_route_with_a_stride_and_its_text_form(nav):
    """Issue 39: steps counted in the walker's stride, each turn classed by its angle alone and
    given as a clock hour, and the route's text form, in JSON and as ``text/plain``."""
    api, map_id = nav
    question = {"from": {"tag": 300}, "to": {"poi": "Room 209"}, "stride_m": 0.5}
    response = route(api, map_id, question)
    assert response.status_code == 200, response.text
    assert response.headers["vary"] == "Accept"
    body = response.json()
    assert body["stride_m"] == 0.5
    steps = body["steps"]
    walked = [s for s in steps if s["kind"] == "go"]
    assert walked
    for step in walked:
        assert step["steps_count"] == max(1, round(step["distance_m"] / 0.5))
        metres = max(1, round(step["distance_m"]))
        assert step["text"].startswith(f"Go straight {metres} metre")
        assert f"({step['steps_count']} step" in step["text"]
    turns = [s for s in steps if s["kind"] in ("face", "announce", "turn")]
    for step in turns:
        size = abs(step["turn_deg"])
        want = (
            "around" if size >= 150 else "sharp" if size >= 135 else "turn" if size >= 45
            else "bear" if size >= 20 else "straight"
        )  # fmt: skip
        assert step["turn"] == want
        assert 1 <= step["clock"] <= 12
        assert f"to {step['clock']} o'clock" in step["text"]
    assert steps[-1]["landmark"] == "Room 209"
    assert steps[-1]["side"] in ("ahead", "left", "right", "behind", None)
    told = [s["text"] for s in steps if s["kind"] != "announce"]
    assert body["text"].split("\n") == [f"{i}. {t}" for i, t in enumerate(told, start=1)]
    assert body["text"].endswith(steps[-1]["text"])
    # The default stride is 0.7 m.
    default = route(api, map_id, {"from": {"tag": 300}, "to": {"poi": "Room 209"}}).json()
    assert default["stride_m"] == 0.7
    assert default["steps"][0]["steps_count"] == max(1, round(steps[0]["distance_m"] / 0.7))
    # The text form alone, by content negotiation.
    for accept in ("text/plain", "text/*", "application/json;q=0.5, text/plain"):
        plain = api.client.post(
            f"/v1/maps/{map_id}/routes", json=question, headers={**ADMIN, "Accept": accept}
        )
        assert plain.status_code == 200, (accept, plain.text)
        assert plain.headers["content-type"] == "text/plain; charset=utf-8"
        assert plain.text == body["text"] + "\n"
    for accept in ("application/json", "*/*", "text/plain;q=0.5, application/*", ""):
        answer = api.client.post(
            f"/v1/maps/{map_id}/routes", json=question, headers={**ADMIN, "Accept": accept}
        )
        assert answer.status_code == 200, (accept, answer.text)
        assert answer.headers["content-type"].startswith("application/json")
        assert answer.json() == body


@pytest.mark.parametrize("stride_m", [0.29, 1.51, -1, "long", None])
def test_a_stride_out_of_range_is_refused_naming_the_field(nav, stride_m):
    api, map_id = nav
    response = route(api, map_id, {"from": {"tag": 300}, "to": {"tag": 311}, "stride_m": stride_m})
    assert response.status_code == 422, response.text
    assert response.json()["code"] == "validation_error"
    assert response.json()["field"] == "stride_m"


@pytest.mark.parametrize(
    "accept", ["image/png", "text/html", "application/json;q=0, text/plain;q=0", "text/plain;q=0"]
)
def test_a_route_in_a_media_type_it_has_not_is_refused(nav, accept):
    api, map_id = nav
    response = api.client.post(
        f"/v1/maps/{map_id}/routes",
        json={"from": {"tag": 300}, "to": {"tag": 311}},
        headers={**ADMIN, "Accept": accept},
    )
    assert response.status_code == 406, response.text
    error = response.json()
    assert (error["code"], error["field"]) == ("not_acceptable", "Accept")
    assert repr(accept) in error["detail"]


def test_route_steps_are_decisions_only(nav):
    """On the corridor skeleton of floor 2 (one gently curving corridor), a route along it has
    no turn closer than 5 m to another and none that reverses."""
    api, map_id = nav
    body = route(api, map_id, {"from": {"tag": 300}, "to": {"tag": 324}}).json()
    turns = [s for s in body["steps"] if s["kind"] == "turn"]
    assert all("around" not in s["instruction"] for s in turns)
    positions = np.array([s["position"] for s in turns]).reshape(-1, 3)
    gaps_m = np.linalg.norm(np.diff(positions, axis=0), axis=1)
    assert np.all(gaps_m >= 5.0 - 1e-6)
    assert len(turns) <= 4


def test_route_between_positions_and_nodes(nav):
    api, map_id = nav
    geo = api.client.get(f"/v1/maps/{map_id}/geojson", headers=ADMIN).json()
    nodes = [f for f in geo["features"] if f["properties"]["kind"] in ("node", "junction")]
    first, last = nodes[0]["properties"]["id"], nodes[-1]["properties"]["id"]
    by_node = route(api, map_id, {"from": {"node": first}, "to": {"node": last}})
    assert by_node.status_code == 200, by_node.text
    start = by_node.json()["polyline"][0]
    by_position = route(api, map_id, {"from": {"position": start}, "to": {"node": last}})
    assert by_position.status_code == 200, by_position.text
    assert math.isclose(by_position.json()["length_m"], by_node.json()["length_m"], abs_tol=1e-6)


@pytest.mark.parametrize(
    ("body", "status", "code"),
    [
        ({"from": {"tag": 99999}, "to": {"poi": "Room 209"}}, 404, "not_found"),
        ({"from": {"tag": 300}, "to": {"poi": "Room 999"}}, 404, "not_found"),
        ({"from": {"node": 10**9}, "to": {"tag": 300}}, 404, "not_found"),
        ({"from": {"tag": 300, "poi": "Room 209"}, "to": {"tag": 301}}, 422, "validation_error"),
        ({"from": {}, "to": {"tag": 301}}, 422, "validation_error"),
        ({"to": {"tag": 301}}, 422, "validation_error"),
        ({"from": {"tag": 300}, "to": {"tag": 301}, "avoid": ["ramps"]}, 422, "validation_error"),
        ({"from": {"position": [0, 0]}, "to": {"tag": 301}}, 422, "validation_error"),
    ],
)
def test_route_failures(nav, body, status, code):
    api, map_id = nav
    response = route(api, map_id, body)
    assert response.status_code == status, response.text
    assert response.json()["code"] == code


def test_a_non_finite_position_is_refused(nav):
    api, map_id = nav
    body = '{"from": {"position": [NaN, 0, 0]}, "to": {"tag": 301}}'
    response = api.client.post(
        f"/v1/maps/{map_id}/routes",
        content=body,
        headers={**ADMIN, "Content-Type": "application/json"},
    )
    assert response.status_code == 422
    assert "from" in (response.json()["field"] or "")


def test_navigation_of_an_unknown_or_unbuilt_map(database_url):
    with running_api(database_url) as api:
        map_id = api.uploaded(FLOOR_2)["map_id"]  # not built: no worker ran
        for method, path, body in [
            ("GET", f"/v1/maps/{map_id}/pois", None),
            ("POST", f"/v1/maps/{map_id}/routes", {"from": {"tag": 300}, "to": {"tag": 301}}),
            ("GET", f"/v1/maps/{map_id}/geojson", None),
            ("POST", f"/v1/maps/{map_id}/localizations", None),
        ]:
            response = api.client.request(method, path, json=body, headers=ADMIN)
            assert response.status_code == 409, (path, response.text)
            assert response.json()["code"] == "map_not_ready"
            missing = api.client.request(
                method, path.replace(f"/{map_id}/", "/999/"), json=body, headers=ADMIN
            )
            assert missing.status_code == 404, path


def test_geojson_has_the_kinds_the_issue_names(nav):
    api, map_id = nav
    response = api.client.get(f"/v1/maps/{map_id}/geojson", headers=ADMIN)
    assert response.status_code == 200
    assert response.headers["content-type"].startswith("application/geo+json")
    document = response.json()
    assert document["type"] == "FeatureCollection"
    points = [f for f in document["features"] if f["geometry"]["type"] == "Point"]
    lines = [f for f in document["features"] if f["geometry"]["type"] == "LineString"]
    assert {f["properties"]["kind"] for f in points} >= {"node", "tag", "poi"}
    assert {f["properties"]["kind"] for f in lines} <= {"walk", "stairs", "elevator"}
    assert all(f["properties"]["length_m"] > 0 for f in lines)
    tags = {f["properties"]["id"] for f in points if f["properties"]["kind"] == "tag"}
    map_tags = api.client.get(f"/v1/maps/{map_id}", headers=ADMIN).json()
    assert len(tags) == map_tags["current_version"]["tag_count"]


def test_app_map_neighbors_come_from_the_path_graph(nav):
    api, map_id = nav
    app_map = api.client.get(f"/v1/maps/{map_id}/app-map", headers=ADMIN).json()
    vertices = {v["poseId"]: v for v in app_map["odometry_vertices"]}
    links = nx.Graph()
    links.add_nodes_from(vertices)
    for pose_id, vertex in vertices.items():
        assert vertex["neighbors"], f"vertex {pose_id} cannot reach the path"
        for neighbor in vertex["neighbors"]:
            assert neighbor in vertices, (pose_id, neighbor)
            links.add_edge(pose_id, neighbor)
    assert nx.is_connected(links)
    # The corridor skeleton's nodes are extra vertices after the last pose, linked among
    # themselves; every pose links to the skeleton, not to the previous and next pose.
    last_pose_id = max(p["id"] for p in json.loads(FLOOR_2.read_bytes())["pose_data"])
    skeleton = {pose_id for pose_id in vertices if pose_id > last_pose_id}
    assert len(skeleton) >= 2
    assert nx.is_connected(links.subgraph(skeleton))
    assert all(
        set(vertex["neighbors"]) <= skeleton
        for pose_id, vertex in vertices.items()
        if pose_id <= last_pose_id
    )
    # The app adds an edge only from the vertex whose neighbor id is smaller than its own: the
    # skeleton lists its poses back, so the app's graph is one connected graph too.
    as_the_app = nx.Graph()
    as_the_app.add_nodes_from(vertices)
    as_the_app.add_edges_from(
        (pose_id, neighbor)
        for pose_id, vertex in vertices.items()
        for neighbor in vertex["neighbors"]
        if neighbor < pose_id
    )
    assert nx.is_connected(as_the_app)
    assert {w["id"] for w in app_map["waypoints_vertices"]} == {"Room 209", "Elevator lobby"}


# --------------------------------------------------------------------------- localization


def start_localization(api: Api, map_id: int, headers: dict[str, str] = ADMIN) -> int:
    response = api.client.post(f"/v1/maps/{map_id}/localizations", headers=headers)
    assert response.status_code == 201, response.text
    assert response.headers["Location"] == f"/v1/localizations/{response.json()['id']}"
    assert response.json()["estimate"] is None
    return int(response.json()["id"])


def desnat_updates() -> list[dict[str, Any]]:
    return session_update_documents(load_session(DESNAT), 20)


def test_localization_replays_another_session_into_the_map(nav):
    api, map_id = nav
    sid = start_localization(api, map_id)
    statuses, sigmas = [], []
    for document in desnat_updates():
        response = api.client.post(f"/v1/localizations/{sid}/updates", json=document, headers=ADMIN)
        assert response.status_code == 200, response.text
        estimate = response.json()
        statuses.append(estimate["status"])
        if estimate["status"] == "localized":
            sigmas.append(estimate["position_sigma_m"])
            assert len(estimate["position"]) == 3
            assert np.allclose(np.array(estimate["map_T_phone"])[3], [0, 0, 0, 1])
    assert statuses[0] == "not_localized"
    assert statuses[-1] == "localized"
    assert statuses.index("localized") > 0
    assert min(sigmas) < 0.5
    current = api.client.get(f"/v1/localizations/{sid}", headers=ADMIN).json()
    assert current["updates"] == len(statuses)
    assert current["map_version"] == 1
    assert current["estimate"]["status"] == "localized"


def test_localization_survives_a_restart_of_the_api(nav, database_url):
    api, map_id = nav
    sid = start_localization(api, map_id)
    updates = desnat_updates()
    half = len(updates) // 2
    for document in updates[:half]:
        api.client.post(f"/v1/localizations/{sid}/updates", json=document, headers=ADMIN)
    settings = Settings(database_url=database_url, admin_key=ADMIN_KEY)
    with TestClient(create_app(settings)) as other_process:
        response = other_process.post(
            f"/v1/localizations/{sid}/updates", json=updates[half], headers=ADMIN
        )
        assert response.status_code == 200, response.text
        assert (
            other_process.get(f"/v1/localizations/{sid}", headers=ADMIN).json()["updates"]
            == half + 1
        )


def _with_tag(document: dict[str, Any], tag_id: int) -> dict[str, Any]:
    changed = json.loads(json.dumps(document))
    pose = changed["poses"][0]
    changed["tag_data"] = [
        [
            {
                "tag_id": tag_id,
                "pose_id": pose["id"],
                "timestamp": pose["timestamp"],
                "tag_pose": [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 1.5, 0, 0, 0, 1],
                "camera_intrinsics": [1400, 1400, 960, 720],
                "tag_corners_pixel_coordinates": [0] * 8,
            }
        ]
    ]
    return changed


def _broken(kind: str, document: dict[str, Any]) -> dict[str, Any]:
    changed = json.loads(json.dumps(document))
    if kind == "unknown tag":
        return _with_tag(changed, 999)
    if kind == "not rigid":
        changed["poses"][0]["pose"][0] = 3.0
    elif kind == "backwards":
        changed["poses"][0]["id"] = 0
        changed["poses"][0]["timestamp"] = 0.0
    elif kind == "missing pose field":
        del changed["poses"][0]["pose"]
    elif kind == "400 digits":  # Python's JSON parser reads an int no float holds
        changed["poses"][1]["pose"][13] = 10**400
    elif kind == "too many poses":  # a backlog goes in several updates
        first = changed["poses"][0]
        changed["poses"] = [
            {**first, "id": first["id"] + i, "timestamp": first["timestamp"] + 0.01 * i}
            for i in range(localization_route.MAX_UPDATE_POSES + 1)
        ]
    return changed


@pytest.mark.parametrize(
    ("kind", "field"),
    [
        ("unknown tag", "tag_data[0][0].tag_id"),
        ("not rigid", "poses[0].pose"),
        ("backwards", "poses[0]"),
        ("missing pose field", "poses[0].pose"),
        ("400 digits", "poses[1].pose[13]"),
        ("too many poses", "poses"),
    ],
)
def test_malformed_updates_are_refused_and_change_nothing(nav, kind, field):
    api, map_id = nav
    sid = start_localization(api, map_id)
    updates = desnat_updates()
    for document in updates[:3]:
        api.client.post(f"/v1/localizations/{sid}/updates", json=document, headers=ADMIN)
    with api.db.read() as db_session:
        before = navigation.get_localization(db_session, sid)

    response = api.client.post(
        f"/v1/localizations/{sid}/updates", json=_broken(kind, updates[3]), headers=ADMIN
    )

    assert response.status_code == 422, response.text
    assert response.json()["code"] == "invalid_update"
    assert (response.json()["field"] or "").startswith(field)
    with api.db.read() as db_session:
        after = navigation.get_localization(db_session, sid)
    assert (after.revision, after.state) == (before.revision, before.state)
    good = api.client.post(f"/v1/localizations/{sid}/updates", json=updates[3], headers=ADMIN)
    assert good.status_code == 200, good.text


def test_a_device_sees_only_its_own_navigation_sessions(nav):
    api, map_id = nav
    mine, theirs = api.device(), api.device()
    sid = start_localization(api, map_id, headers=mine)
    assert api.client.get(f"/v1/localizations/{sid}", headers=mine).status_code == 200
    assert api.client.get(f"/v1/localizations/{sid}", headers=theirs).status_code == 404
    update = api.client.post(
        f"/v1/localizations/{sid}/updates", json=desnat_updates()[0], headers=theirs
    )
    assert update.status_code == 404
    assert api.client.get("/v1/localizations/999999", headers=mine).status_code == 404


def test_a_stale_revision_cannot_overwrite_a_newer_state(nav):
    api, map_id = nav
    sid = start_localization(api, map_id)
    api.client.post(f"/v1/localizations/{sid}/updates", json=desnat_updates()[0], headers=ADMIN)
    with api.db.read() as db_session:
        info = navigation.get_localization(db_session, sid)
    with pytest.raises(LocalizationConflict), api.db.transaction() as db_session:
        navigation.save_update(
            db_session, sid, expected_revision=info.revision - 1, status="x", state={}
        )
    with api.db.read() as db_session:
        assert navigation.get_localization(db_session, sid).state == info.state


def _replayed(map_tags_of: Api, map_id: int, documents: list[dict[str, Any]]) -> dict[str, Any]:
    """The localizer's state after ``documents``, computed in this process (no HTTP)."""
    with map_tags_of.db.read() as db_session:
        version_id = maps.get_map(db_session, map_id).current
        assert version_id is not None
        rows = maps.tag_poses(db_session, version_id.id)
    tags = {r.tag_id: pose_from_xyz_quat_xyzw([*r.position_m, *r.quat_xyzw]) for r in rows}
    state = LocalizerState.initial()
    for document in documents:
        state, _result = update(state, parse_update(document), tags)
    return state.to_json()


def test_updates_alternating_between_two_api_processes_use_the_newest_state(nav, database_url):
    # Each process keeps the states it wrote (HotStates); after the other process's update its
    # copy is one revision behind and must not be used.
    api, map_id = nav
    sid = start_localization(api, map_id)
    updates = desnat_updates()[:9]
    settings = Settings(database_url=database_url, admin_key=ADMIN_KEY)
    with TestClient(create_app(settings)) as other_process:
        for k, document in enumerate(updates):
            client = api.client if k % 3 != 2 else other_process
            response = client.post(f"/v1/localizations/{sid}/updates", json=document, headers=ADMIN)
            assert response.status_code == 200, response.text
    with api.db.read() as db_session:
        stored = navigation.get_localization(db_session, sid)
    assert (stored.revision, stored.update_count) == (len(updates), len(updates))
    assert stored.state["localizer"] == json.loads(json.dumps(_replayed(api, map_id, updates)))


def test_two_updates_racing_on_one_session_give_one_200_and_one_409(nav, database_url, monkeypatch):
    api, map_id = nav
    sid = start_localization(api, map_id)
    updates = desnat_updates()
    api.client.post(f"/v1/localizations/{sid}/updates", json=updates[0], headers=ADMIN)
    both_read = threading.Barrier(2, timeout=30)
    real_update = localization_route.update

    def update_after_both_read(*args: Any) -> Any:
        both_read.wait()  # both requests have read revision 1 before either writes
        return real_update(*args)

    monkeypatch.setattr(localization_route, "update", update_after_both_read)
    settings = Settings(database_url=database_url, admin_key=ADMIN_KEY)
    answers: list[Any] = []
    with TestClient(create_app(settings)) as other_process:

        def send(client: TestClient) -> None:
            answers.append(
                client.post(f"/v1/localizations/{sid}/updates", json=updates[1], headers=ADMIN)
            )

        threads = [threading.Thread(target=send, args=(c,)) for c in (api.client, other_process)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join(timeout=60)
    assert sorted(a.status_code for a in answers) == [200, 409], [a.text for a in answers]
    conflict = next(a for a in answers if a.status_code == 409)
    assert conflict.json()["code"] == "concurrent_update"
    with api.db.read() as db_session:
        stored = navigation.get_localization(db_session, sid)
    assert (stored.revision, stored.update_count) == (2, 2)
    assert stored.state["localizer"] == json.loads(json.dumps(_replayed(api, map_id, updates[:2])))
    # the loser sends it again and is told the pose ids must increase (its update is in)
    monkeypatch.setattr(localization_route, "update", real_update)
    again = api.client.post(f"/v1/localizations/{sid}/updates", json=updates[2], headers=ADMIN)
    assert again.status_code == 200, again.text


def test_an_api_process_runs_one_update_at_a_time(nav, monkeypatch):
    # Updates of different sessions sent at once: all answered, their computations one after
    # another on the process's one localizer thread (several would fight over the GIL).
    api, map_id = nav
    sessions = [start_localization(api, map_id) for _ in range(4)]
    first = desnat_updates()[0]
    running: list[int] = []
    most_at_once = 0
    lock = threading.Lock()
    real_update = localization_route.update

    def counted_update(*args: Any) -> Any:
        nonlocal most_at_once
        with lock:
            running.append(1)
            most_at_once = max(most_at_once, len(running))
        try:
            time.sleep(0.05)  # long enough for the other requests to arrive meanwhile
            return real_update(*args)
        finally:
            with lock:
                running.pop()

    monkeypatch.setattr(localization_route, "update", counted_update)
    answers: list[Any] = []

    def send(sid: int) -> None:
        answers.append(
            api.client.post(f"/v1/localizations/{sid}/updates", json=first, headers=ADMIN)
        )

    threads = [threading.Thread(target=send, args=(sid,)) for sid in sessions]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout=60)
    assert [a.status_code for a in answers] == [200] * len(sessions), [a.text for a in answers]
    assert most_at_once == localization_route.LOCALIZER_THREADS == 1


def test_the_narrow_state_statements_compare_and_set(nav):
    api, map_id = nav
    sid = start_localization(api, map_id)
    with api.db.autocommit() as connection:
        row = navigation.read_state(connection, sid)
        assert (row.revision, row.created_by) == (0, "env-admin")
        assert row.state_json is not None
        assert json.loads(row.state_json)["last_result"] is None
        assert navigation.read_state(connection, sid, unless_revision=0).state_json is None
        assert navigation.read_state(connection, sid, unless_revision=5).state_json is not None
        new_state = {"localizer": json.loads(row.state_json)["localizer"], "last_result": None}
        revision = navigation.write_state(
            connection,
            sid,
            expected_revision=0,
            status="not_localized",
            state_json=json.dumps(new_state),
        )
        assert revision == 1
        with pytest.raises(LocalizationConflict):
            navigation.write_state(
                connection, sid, expected_revision=0, status="x", state_json="{}"
            )
        with pytest.raises(navigation.LocalizationNotFound):
            navigation.read_state(connection, 999_999)
        with pytest.raises(navigation.LocalizationNotFound):
            navigation.write_state(
                connection, 999_999, expected_revision=0, status="x", state_json="{}"
            )
    with api.db.read() as db_session:  # committed without a transaction around it
        stored = navigation.get_localization(db_session, sid)
    assert (stored.revision, stored.update_count, stored.state) == (1, 1, new_state)


def test_the_narrow_statements_raise_driver_errors_as_sqlalchemy_errors(nav, monkeypatch):
    # They run on the driver's own cursor; its errors must still reach the API as SQLAlchemy's
    # DBAPIError (which the error handlers turn into 503s), the driver's error kept as ``orig``.
    api, map_id = nav
    sid = start_localization(api, map_id)
    dialect = api.db.backend
    broken = dict(navigation._STATEMENTS[dialect], read="SELECT no_such_column FROM localization")
    monkeypatch.setitem(navigation._STATEMENTS, dialect, broken)
    with api.db.autocommit() as connection:
        with pytest.raises(DBAPIError) as raised:
            navigation.read_state(connection, sid)
        assert "no_such_column" in str(raised.value.orig)
        assert "no_such_column" in str(raised.value.statement)
    monkeypatch.undo()
    with api.db.autocommit() as connection:  # the pool's connections still work
        assert navigation.read_state(connection, sid).revision == 0


def test_an_unbounded_covariance_is_null_in_the_answer_and_the_state(nav, monkeypatch):
    api, map_id = nav
    sid = start_localization(api, map_id)
    real_update = localization_route.update

    def unbounded(*args: Any) -> Any:
        state, result = real_update(*args)
        document = result.to_json()
        document["covariance"] = [[math.inf] * 6 for _ in range(6)]
        document["position_sigma_m"] = math.nan
        return state, SimpleNamespace(status=result.status, to_json=lambda: document)

    monkeypatch.setattr(localization_route, "update", unbounded)
    response = api.client.post(
        f"/v1/localizations/{sid}/updates", json=desnat_updates()[0], headers=ADMIN
    )
    assert response.status_code == 200, response.text
    assert response.json()["covariance"] == [[None] * 6 for _ in range(6)]
    assert response.json()["position_sigma_m"] is None
    with api.db.read() as db_session:
        stored = navigation.get_localization(db_session, sid).state["last_result"]
    assert stored["covariance"] == [[None] * 6 for _ in range(6)]
    assert stored["position_sigma_m"] is None


def test_localization_writes_do_not_wait_for_the_disk(nav):
    # PostgreSQL: Database.autocommit(durable=False) commits without waiting for the WAL's
    # flush; every other connection still does. (SQLite never waits here: synchronous=NORMAL.)
    api, _map_id = nav
    if api.db.is_sqlite:
        with api.db.autocommit(durable=False) as connection:
            assert connection.exec_driver_sql("PRAGMA synchronous").scalar() == 1  # NORMAL
        return
    with api.db.autocommit(durable=False) as connection:
        assert connection.exec_driver_sql("SHOW synchronous_commit").scalar() == "off"
    with api.db.autocommit() as connection:
        assert connection.exec_driver_sql("SHOW synchronous_commit").scalar() == "on"
    with api.db.transaction() as db_session:
        assert db_session.execute(text("SHOW synchronous_commit")).scalar() == "on"


def test_the_route_answer_is_documented_for_its_readers(database_url):
    """The OpenAPI document names the new step fields, the stride's range, the text form and
    the 406, with examples (issue 39)."""
    with running_api(database_url) as api:
        spec = api.app.openapi()
    operation = spec["paths"]["/v1/maps/{map_id}/routes"]["post"]
    plain = operation["responses"]["200"]["content"]["text/plain"]
    assert plain["example"].startswith("1. Go straight 12 metres (17 steps).\n")
    assert operation["responses"]["406"]["content"]["application/json"]["example"]["field"] == (
        "Accept"
    )
    assert any(p["name"] == "Accept" for p in operation["parameters"] if p["in"] == "header")
    schemas = spec["components"]["schemas"]
    stride = schemas["RouteRequest"]["properties"]["stride_m"]
    assert (stride["minimum"], stride["maximum"], stride["default"]) == (0.3, 1.5, 0.7)
    step = schemas["StepPublic"]["properties"]
    new = {"turn", "clock", "steps_count", "landmark", "side", "text"}
    old = {"instruction", "kind", "position", "distance_m", "turn_deg", "floor"}
    assert new | old <= set(step)
    assert all(step[name].get("description") for name in new)
    example = schemas["RoutePublic"]["examples"][0]
    assert {"text", "stride_m"} <= set(example)
    turn = example["steps"][1]  # (the document leaves out an example's null members)
    assert {"turn", "clock", "landmark", "text"} <= set(turn)
    assert example["steps"][2]["steps_count"] == 13
    assert example["steps"][2]["side"] == "right"
