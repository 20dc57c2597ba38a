"""Corridor edits over HTTP (issue 27), on the floor_2 map built by the real worker pipeline, on
SQLite and PostgreSQL: an edit is served at the next route request, the app-map stays one the
app can use, bad edits are refused naming what is wrong with nothing stored, two operators lose
no edit, and edits survive a rebuild and a walk added.

One map is built per database (module scope); each test deletes the edits it made.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from app.domain.formats.app_model import check_app_map
from app.domain.navigation.corridor_edits import edit_from_json
from app.services import navigation
from app.services.version_cache import VersionCache
from app.storage import corridor_edits as corridor_storage
from app.storage.orm import CorridorEditRow
from tests.conftest import fresh_database_url
from tests.service.api_support import ADMIN, SESSIONS_DIR, Api, running_api
from tests.service.test_api_navigation import build, floor_2_with_pois

pytestmark = pytest.mark.db

DESNAT = SESSIONS_DIR / "desnat_straight_once.json"


@pytest.fixture(scope="module", params=["sqlite", "postgresql"])
def built(
    request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory
) -> Iterator[tuple[Api, int]]:
    urls = fresh_database_url(request.param, request, tmp_path_factory.mktemp("edits"))
    try:
        with running_api(next(urls)) as api:
            map_id = api.uploaded(floor_2_with_pois())["map_id"]
            build(api)
            yield api, map_id
    finally:
        urls.close()


@pytest.fixture
def nav(built: tuple[Api, int]) -> Iterator[tuple[Api, int]]:
    """The built map, its edits deleted after the test."""
    yield built
    api, map_id = built
    for item in edits(api, map_id, limit=1000)["data"]:
        api.client.delete(f"/v1/maps/{map_id}/corridor-edits/{item['id']}", headers=ADMIN)


def edits(api: Api, map_id: int, **params: Any) -> Any:
    response = api.client.get(f"/v1/maps/{map_id}/corridor-edits", headers=ADMIN, params=params)
    assert response.status_code == 200, response.text
    return response.json()


def post(api: Api, map_id: int, document: Any, **headers: str) -> Any:
    return api.client.post(
        f"/v1/maps/{map_id}/corridor-edits", json=document, headers={**ADMIN, **headers}
    )


def route(api: Api, map_id: int, start: dict[str, Any], goal: dict[str, Any]) -> Any:
    response = api.client.post(
        f"/v1/maps/{map_id}/routes", json={"from": start, "to": goal}, headers=ADMIN
    )
    assert response.status_code == 200, response.text
    return response.json()


def graph(api: Api, map_id: int) -> tuple[dict[int, list[float]], list[tuple[int, int]], Any]:
    """The served graph: node id → [x, y, z] (map frame), edges, and the GeoJSON."""
    document = api.client.get(f"/v1/maps/{map_id}/geojson", headers=ADMIN).json()
    nodes, links = {}, []
    for feature in document["features"]:
        kind, c = feature["properties"]["kind"], feature["geometry"]["coordinates"]
        if kind in ("node", "junction"):
            nodes[feature["properties"]["id"]] = [c[0], c[2], -c[1]]  # [x, −z, y] → [x, y, z]
        elif feature["geometry"]["type"] == "LineString":
            links.append((feature["properties"]["from"], feature["properties"]["to"]))
    return nodes, links, document


def shifted(point: list[float], dx_m: float) -> list[float]:
    return [point[0] + dx_m, point[1], point[2]]


def a_turn(api: Api, map_id: int) -> tuple[dict[str, Any], dict[str, Any], list[float]]:
    """A route between two tags with a turn, and where the turn is."""
    for goal in (324, 320, 316, 312, 308):
        body = route(api, map_id, {"tag": 300}, {"tag": goal})
        turns = [s for s in body["steps"] if s["kind"] == "turn"]
        if turns:
            return {"tag": 300}, {"tag": goal}, turns[0]["position"]
    raise AssertionError("no route of floor_2 turns")


# --------------------------------------------------------------------------- serving edits


def test_a_quiet_turn_is_gone_at_the_next_route_and_back_after_undo(nav):
    api, map_id = nav
    start, goal, at = a_turn(api, map_id)
    before = route(api, map_id, start, goal)
    app_map = api.client.get(f"/v1/maps/{map_id}/app-map", headers=ADMIN)
    geojson = api.client.get(f"/v1/maps/{map_id}/geojson", headers=ADMIN)

    created = post(api, map_id, {"op": "quiet", "at": at})

    assert created.status_code == 201, created.text
    body = created.json()
    assert body["applied"] is True
    assert body["edit"] == {"op": "quiet", "at": at}
    assert body["created_by"] == "env-admin"
    assert body["who"] == "the server's admin key"
    assert created.headers["Location"] == f"/v1/maps/{map_id}/corridor-edits/{body['id']}"
    after = route(api, map_id, start, goal)
    turns_at = [s["position"] for s in after["steps"] if s["kind"] == "turn"]
    assert at not in turns_at
    assert len(after["steps"]) < len(before["steps"])
    assert after["polyline"] == before["polyline"]  # the way is the same; only what is said
    # documents made from the graph get new ETags (a phone downloads the edited map again)
    for old in (app_map, geojson):
        path = str(old.request.url.path)
        again = api.client.get(path, headers={**ADMIN, "If-None-Match": old.headers["ETag"]})
        assert again.status_code == 200, path
        assert again.headers["ETag"] != old.headers["ETag"]
    listed = edits(api, map_id)
    assert (listed["count"], listed["applied_count"]) == (1, 1)
    assert listed["data"][0]["id"] == body["id"]

    undo = api.client.delete(f"/v1/maps/{map_id}/corridor-edits/{body['id']}", headers=ADMIN)

    assert undo.status_code == 204
    assert route(api, map_id, start, goal)["steps"] == before["steps"]
    assert (
        api.client.get(f"/v1/maps/{map_id}/app-map", headers=ADMIN).headers["ETag"]
        == (app_map.headers["ETag"])
    )  # no edits: the version's own file again
    gone = api.client.delete(f"/v1/maps/{map_id}/corridor-edits/{body['id']}", headers=ADMIN)
    assert gone.status_code == 404


def test_an_edited_app_map_is_one_the_app_can_use(nav):
    """A shortcut, a moved node, a point of interest added and one renamed: the app-map shows
    them and the model of the app's planner routes every pair."""
    api, map_id = nav
    nodes, links, _ = graph(api, map_id)
    ends = [n for n in nodes if sum(n in link for link in links) == 1]
    a, b = ends[0], ends[-1]
    documents = [
        {"op": "add_edge", "from": nodes[a], "to": nodes[b], "kind": "door"},
        {"op": "move_node", "from": nodes[a], "to": shifted(nodes[a], 0.5)},
        {"op": "add_poi", "name": "Printer", "at": [nodes[b][0] + 1, nodes[b][1], nodes[b][2]]},
        {"op": "rename_poi", "name": "Room 209", "new_name": "Room 209 (lab)"},
    ]
    for document in documents:
        created = post(api, map_id, document)
        assert created.status_code == 201, (document, created.text)

    app_map = api.client.get(f"/v1/maps/{map_id}/app-map", headers=ADMIN).json()
    report = check_app_map(app_map)
    assert report.decode_error is None
    assert report.isolated_vertices == (), report
    assert report.crashing_pairs == 0, report
    assert report.components == 1
    names = {w["id"] for w in app_map["waypoints_vertices"]}
    assert names == {"Room 209 (lab)", "Elevator lobby", "Printer"}
    pois = api.client.get(f"/v1/maps/{map_id}/pois", headers=ADMIN).json()
    assert {p["name"] for p in pois["data"]} == names
    to_printer = route(api, map_id, {"tag": 300}, {"poi": "Printer"})
    assert to_printer["steps"][-1]["instruction"].startswith("arrive at Printer")
    moved, _, _ = graph(api, map_id)
    assert (
        min(math.dist(p, [nodes[a][0] + 0.5, nodes[a][1], nodes[a][2]]) for p in moved.values())
        < 1e-6
    )


# --------------------------------------------------------------------------- refusals


def test_bad_edits_are_refused_naming_what_is_wrong_and_nothing_is_stored(nav):
    api, map_id = nav
    nodes, links, document = graph(api, map_id)
    u, v = links[len(links) // 2]
    tag_anchor = next(
        f["properties"]["node"] for f in document["features"] if f["properties"]["kind"] == "tag"
    )
    tag_link = next(link for link in links if tag_anchor in link)
    near_u = [nodes[u][0] + 0.3, nodes[u][1], nodes[u][2]]
    far = [nodes[u][0] + 500, nodes[u][1], nodes[u][2]]
    cases = [
        ({"op": "straighten", "at": nodes[u]}, 422, "op"),
        ({"op": "quiet", "at": far}, 422, "at"),
        ({"op": "quiet", "at": [nodes[u][0], nodes[u][1] + 30, nodes[u][2]]}, 422, "at"),
        ({"op": "quiet", "at": [1, 2]}, 422, "at"),
        ({"op": "add_edge", "from": nodes[u], "to": near_u, "kind": "walk"}, 422, "to"),
        ({"op": "add_edge", "from": nodes[u], "to": nodes[v], "kind": "walk"}, 409, "to"),
        ({"op": "add_edge", "from": nodes[u], "to": nodes[v], "kind": "ramp"}, 422, "kind"),
        ({"op": "remove_edge", "from": nodes[tag_link[0]], "to": nodes[tag_link[1]]}, 409, "to"),
        ({"op": "rename_poi", "name": "Room 999", "new_name": "x"}, 422, "name"),
        ({"op": "add_poi", "name": "Room 209", "at": nodes[u]}, 409, "name"),
        ([1, 2, 3], 422, None),
    ]
    revision = edits(api, map_id)["revision"]
    for body, status, field in cases:
        refused = post(api, map_id, body)
        assert refused.status_code == status, (body, refused.text)
        assert refused.json()["field"] == field, (body, refused.json())
        assert refused.json()["detail"]
    assert "would cut" in post(api, map_id, cases[7][0]).json()["detail"]
    assert api.count(CorridorEditRow) == 0
    assert edits(api, map_id)["revision"] == revision  # a refused edit changes nothing


def test_who_may_edit_and_which_maps(nav):
    api, map_id = nav
    device = api.device()
    body = {"op": "quiet", "at": [0, 0, 0]}
    assert post(api, map_id, body, **device).status_code == 403
    assert api.client.get(f"/v1/maps/{map_id}/corridor-edits", headers=device).status_code == 403
    assert post(api, 999_999, body).status_code == 404
    assert post(api, 0, body).status_code == 404
    # a map with no version yet: nothing to check the edit against
    unbuilt = api.uploaded(Path(SESSIONS_DIR / "onetag.json").read_bytes())["map_id"]
    refused = post(api, unbuilt, body)
    assert refused.status_code == 409
    assert refused.json()["code"] == "map_not_ready"
    listed = api.client.get(f"/v1/maps/{unbuilt}/corridor-edits", headers=ADMIN)
    assert listed.status_code == 409
    assert api.count(CorridorEditRow) == 0


# --------------------------------------------------------------------------- two operators


def test_two_operators_lose_no_edit(nav):
    api, map_id = nav
    nodes, _, _ = graph(api, map_id)
    places = list(nodes.values())[:8]
    answers: list[int] = []

    def operator(points: list[list[float]]) -> None:
        for point in points:
            answers.append(post(api, map_id, {"op": "quiet", "at": point}).status_code)

    threads = [threading.Thread(target=operator, args=(places[k::2],)) for k in range(2)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    stored = edits(api, map_id)
    assert sorted(answers) == [201] * len(places)
    assert stored["count"] == len(places) == stored["applied_count"]
    # An operator who read the edits before another's change is told so (If-Match).
    seen = api.client.get(f"/v1/maps/{map_id}/corridor-edits", headers=ADMIN).headers["ETag"]
    first = stored["data"][0]["id"]
    assert (
        api.client.delete(
            f"/v1/maps/{map_id}/corridor-edits/{first}", headers={**ADMIN, "If-Match": seen}
        ).status_code
        == 204
    )
    stale = post(api, map_id, {"op": "quiet", "at": places[0]}, **{"If-Match": seen})
    assert stale.status_code == 412
    assert stale.json()["code"] == "edits_changed"
    bad = post(api, map_id, {"op": "quiet", "at": places[0]}, **{"If-Match": "yesterday"})
    assert bad.status_code == 400
    assert bad.json()["field"] == "If-Match"
    assert edits(api, map_id)["count"] == len(places) - 1


# --------------------------------------------------------------------------- at scale


def test_the_list_comes_a_page_at_a_time(nav):
    """``limit`` edits a page, ``next_cursor`` to the next, null on the last; the pages together
    are the edits in order, each once, also when an edit is deleted between two pages."""
    api, map_id = nav
    nodes, _, _ = graph(api, map_id)
    points = list(nodes.values())[:5]
    ids = [post(api, map_id, {"op": "quiet", "at": p}).json()["id"] for p in points]

    first = edits(api, map_id, limit=2)
    assert [item["id"] for item in first["data"]] == ids[:2]
    assert first["count"] == 5 == first["applied_count"]
    assert first["next_cursor"]
    deleted = api.client.delete(f"/v1/maps/{map_id}/corridor-edits/{ids[2]}", headers=ADMIN)
    assert deleted.status_code == 204
    seen = [item["id"] for item in first["data"]]
    cursor = first["next_cursor"]
    while cursor is not None:
        page = edits(api, map_id, limit=2, cursor=cursor)
        assert page["count"] == 4
        seen += [item["id"] for item in page["data"]]
        cursor = page["next_cursor"]
    assert seen == [ids[0], ids[1], ids[3], ids[4]]
    whole = edits(api, map_id)  # the default page holds them all
    assert [item["id"] for item in whole["data"]] == seen
    assert whole["next_cursor"] is None


@pytest.mark.parametrize(
    ("params", "field", "code"),
    [
        ({"limit": 0}, "limit", "validation_error"),
        ({"limit": 1001}, "limit", "validation_error"),
        ({"limit": "many"}, "limit", "validation_error"),
        ({"cursor": "nonsense"}, "cursor", "invalid_cursor"),
        ({"cursor": "YWZ0ZXI6MQ=="}, "cursor", "invalid_cursor"),  # padded: not ours
        ({"cursor": "YWZ0ZXI6-1"}, "cursor", "invalid_cursor"),
        ({"cursor": "x" * 65}, "cursor", "validation_error"),
    ],
)
def test_a_bad_page_is_a_422_naming_the_parameter(nav, params, field, code):
    api, map_id = nav
    response = api.client.get(f"/v1/maps/{map_id}/corridor-edits", headers=ADMIN, params=params)
    assert response.status_code == 422, response.text
    assert response.json()["field"] == field
    assert response.json()["code"] == code


def test_a_map_holds_at_most_the_cap_also_when_operators_add_at_once(nav, monkeypatch):
    api, map_id = nav
    monkeypatch.setattr(api.app.state.settings, "max_corridor_edits", 4)
    nodes, _, _ = graph(api, map_id)
    points = list(nodes.values())
    for point in points[:2]:
        assert post(api, map_id, {"op": "quiet", "at": point}).status_code == 201
    answers: list[Any] = []
    start = threading.Barrier(4)

    def operator(point: list[float]) -> None:
        start.wait()
        answers.append(post(api, map_id, {"op": "quiet", "at": point}))

    threads = [threading.Thread(target=operator, args=(p,)) for p in points[2:6]]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert sorted(a.status_code for a in answers) == [201, 201, 409, 409]
    refused = next(a for a in answers if a.status_code == 409).json()
    assert refused["code"] == "too_many_corridor_edits"
    assert "INVISIBLE_MAP_MAX_CORRIDOR_EDITS = 4" in refused["detail"]
    assert edits(api, map_id)["count"] == 4
    assert api.count(CorridorEditRow) == 4
    # deleting one makes room for one
    first = edits(api, map_id)["data"][0]["id"]
    api.client.delete(f"/v1/maps/{map_id}/corridor-edits/{first}", headers=ADMIN)
    assert post(api, map_id, {"op": "quiet", "at": points[7]}).status_code == 201


def test_a_new_edit_costs_the_same_however_many_came_before(nav, monkeypatch):
    """Once this process has the edited graph, adding an edit and the route after it neither
    read the map's edits again nor apply them again: only the new one is applied."""
    api, map_id = nav
    nodes, _, _ = graph(api, map_id)
    points = list(nodes.values())
    for point in points[:3]:
        assert post(api, map_id, {"op": "quiet", "at": point}).status_code == 201
    route(api, map_id, {"tag": 300}, {"tag": 324})  # the process has the edited graph
    calls: list[str] = []

    def counted(name: str, function: Any) -> Any:
        def wrapper(*args: Any, **kwargs: Any) -> Any:
            calls.append(name)
            return function(*args, **kwargs)

        return wrapper

    monkeypatch.setattr(
        corridor_storage, "list_edits", counted("list_edits", corridor_storage.list_edits)
    )
    monkeypatch.setattr(navigation, "list_edits", counted("list_edits", navigation.list_edits))
    monkeypatch.setattr(navigation, "apply_edits", counted("apply_edits", navigation.apply_edits))
    added = post(api, map_id, {"op": "add_poi", "name": "Copier", "at": points[4]})
    assert added.status_code == 201, added.text
    assert added.json()["applied"] is True
    assert route(api, map_id, {"tag": 300}, {"poi": "Copier"})["steps"]
    assert edits(api, map_id)["count"] == 4
    assert calls == []


def test_an_edit_another_process_added_is_applied_alone(nav, monkeypatch):
    """A process that has the edited graph of an earlier revision reads the list and applies
    only the edits added since (by another process), not all of them."""
    api, map_id = nav
    nodes, _, _ = graph(api, map_id)
    points = list(nodes.values())
    assert post(api, map_id, {"op": "quiet", "at": points[0]}).status_code == 201
    route(api, map_id, {"tag": 300}, {"tag": 324})
    with api.db.transaction() as db_session:  # another process's POST
        corridor_storage.lock_edits(db_session, map_id)
        corridor_storage.add_edit(
            db_session,
            map_id,
            edit_from_json({"op": "add_poi", "name": "Elsewhere", "at": points[2]}),
            created_by="env-admin",
            created_by_name=None,
        )
    applied: list[int] = []
    apply_all = navigation.apply_edits

    def counted(pg: Any, edits_: Any) -> Any:
        applied.append(len(edits_))
        return apply_all(pg, edits_)

    monkeypatch.setattr(navigation, "apply_edits", counted)
    report = edits(api, map_id)
    assert report["count"] == 2 == report["applied_count"]
    assert route(api, map_id, {"tag": 300}, {"poi": "Elsewhere"})["steps"]
    assert applied == []


def test_an_edit_added_to_the_kept_graph_serves_what_all_the_edits_make(nav):
    """The graph a POST extends is the graph the edits make from scratch (another process, a
    restart): the same GeoJSON, node ids included, the same outcomes, the same app-map ETag."""
    api, map_id = nav
    nodes, links, _ = graph(api, map_id)
    ends = [n for n in nodes if sum(n in link for link in links) == 1]
    middle = list(nodes)[len(nodes) // 2]
    documents = [
        {"op": "quiet", "at": nodes[middle]},
        {"op": "add_poi", "name": "Printer", "at": shifted(nodes[ends[0]], 0.3)},
        {"op": "move_node", "from": nodes[middle], "to": shifted(nodes[middle], 0.4)},
        {"op": "add_edge", "from": nodes[ends[0]], "to": nodes[ends[-1]], "kind": "door"},
        {"op": "rename_poi", "name": "Printer", "new_name": "Printer 2"},
    ]
    for document in documents:
        assert post(api, map_id, document).status_code == 201
    kept = api.client.get(f"/v1/maps/{map_id}/geojson", headers=ADMIN)
    kept_map = api.client.get(f"/v1/maps/{map_id}/app-map", headers=ADMIN)
    kept_list = edits(api, map_id)

    api.app.state.version_cache = VersionCache()  # as a process that made none of it
    fresh = api.client.get(f"/v1/maps/{map_id}/geojson", headers=ADMIN)
    assert fresh.json() == kept.json()
    assert fresh.headers["ETag"] == kept.headers["ETag"]
    assert (
        api.client.get(f"/v1/maps/{map_id}/app-map", headers=ADMIN).headers["ETag"]
        == (kept_map.headers["ETag"])
    )
    assert edits(api, map_id) == kept_list


# --------------------------------------------------------------------------- new versions


def test_edits_survive_a_rebuild_and_a_walk_added(nav):
    """Edits made on version 1 apply to the rebuild (other parameters) and, where the joint map
    of two walks still has their places, to the version with a walk added; the rest are
    reported, with the reason."""
    api, map_id = nav
    nodes, links, _ = graph(api, map_id)
    ends = [n for n in nodes if sum(n in link for link in links) == 1]
    junctions = [n for n in nodes if sum(n in link for link in links) >= 3]
    middle = list(nodes)[len(nodes) // 2]
    documents = [
        {"op": "quiet", "at": nodes[(junctions or [middle])[0]]},
        {"op": "move_node", "from": nodes[middle], "to": shifted(nodes[middle], 0.4)},
        {"op": "add_edge", "from": nodes[ends[0]], "to": nodes[ends[-1]], "kind": "walk"},
        {"op": "add_poi", "name": "Printer", "at": nodes[ends[0]]},
    ]
    for document in documents:
        assert post(api, map_id, document).status_code == 201
    before = api.client.get(f"/v1/maps/{map_id}", headers=ADMIN).json()["current_version"]

    rebuilt = api.client.post(
        f"/v1/maps/{map_id}/rebuild", json={"params": {"max_reprojection_px": 7.0}}, headers=ADMIN
    )
    assert rebuilt.status_code == 202, rebuilt.text
    build(api)
    report = edits(api, map_id)
    assert report["map_version"] == before["number"] + 1
    assert report["applied_count"] == len(documents), report
    assert route(api, map_id, {"tag": 300}, {"poi": "Printer"})["steps"]

    added = api.client.post(
        f"/v1/maps/{map_id}/sessions",
        json={"session_id": api.uploaded(DESNAT.read_bytes())["session_id"]},
        headers=ADMIN,
    )
    assert added.status_code == 202, added.text
    build(api)
    report = edits(api, map_id)
    assert report["map_version"] == before["number"] + 2
    grown, _, _ = graph(api, map_id)
    for item in report["data"]:
        if item["applied"]:
            continue
        assert item["reason"], item  # reported, with the place not found
        assert item["field"], item
        point = item["edit"][item["field"]]
        near = min(math.hypot(p[0] - point[0], p[2] - point[2]) for p in grown.values())
        assert near > 1.5, (item, near)  # its place is gone indeed
    print("applied after a walk added:", report["applied_count"], "of", report["count"])
    old_report = edits(api, map_id, version=before["number"])
    assert old_report["applied_count"] == len(documents)
