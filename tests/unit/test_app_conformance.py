"""Conformance: the app-map of every session in data/ and of simulated buildings, read by the model
of the iPhone app (app.domain.formats.app_model): it decodes, and no (start vertex, tag or waypoint)
pair traps. Also graphs the builder does not make today (a walk that falls apart, a corridor
skeleton whose nodes are no poses, no edge at all), so the exporter holds on whatever PathGraph is
current.
"""

from __future__ import annotations

import copy
import json
from functools import cache
from pathlib import Path
from typing import Any

import networkx as nx
import numpy as np
import pytest

from app.domain.evaluation.simulate import SimulationConfig, simulate_session
from app.domain.formats.app_model import (
    build_app_graph,
    check_app_map,
    decode_app_map,
    plan_app_route,
)
from app.domain.formats.map_io import map_to_app_format
from app.domain.mapping.map_result import MapResult
from app.domain.mapping.slam import optimize_session
from app.domain.navigation.path_graph import PathGraph, build_path_graph, unique_waypoint_names
from app.domain.navigation.skeleton import build_skeleton
from app.domain.upload.session import parse_session, read_json_document

DATA = Path(__file__).parents[2] / "data"
#: Every session in data/ (the demo's floor_2 with points of interest included).
REAL = [
    *sorted((DATA / "sessions").glob("*.json")),
    *sorted((DATA / "archive").glob("*.json")),
    DATA / "demo" / "floor_2_pois.json",
]
#: The app fetches at most this much per map file.
APP_MAX_BYTES = 10 * 2**20
IDENTITY = [1.0, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]
SIMULATED = {
    "two_floors": SimulationConfig(num_poses=3000, two_floors=True, seed=1),
    "loops": SimulationConfig(num_poses=3000, blocks=(3, 2), seed=2),
    "dead_ends_many_pois": SimulationConfig(
        num_poses=1500, blocks=(3, 1), num_points_of_interest=8, seed=3
    ),
}


def served(result: MapResult, graph: PathGraph | None) -> dict[str, Any]:
    """The app-map as the app receives it (through JSON, as the server sends it)."""
    document = map_to_app_format(result, path_graph=graph)
    text = json.dumps(document, separators=(",", ":"), allow_nan=False)
    assert len(text.encode()) < APP_MAX_BYTES
    loaded: dict[str, Any] = json.loads(text)
    return loaded


def assert_app_survives(document: dict[str, Any]) -> None:
    report = check_app_map(document)
    assert report.decode_error is None, report.decode_error
    assert report.ok, str(report)
    assert report.pairs > 0
    # and the app's own Dijkstra from phones standing at a spread of vertices to each destination
    app_map = decode_app_map(document)
    graph = build_app_graph(app_map)
    vertices = sorted(graph.position)
    phones = [graph.position[v] for v in vertices[:: max(1, len(vertices) // 4)]]
    for destination in (*app_map.tags, *app_map.waypoints):
        endpoint = graph.nearest(destination.position)
        for phone in phones:
            stops = plan_app_route(graph, phone, destination.position)
            assert len(stops) >= 2
            assert stops[-1] == endpoint


def with_app_made_pois(upload: dict[str, Any]) -> dict[str, Any]:
    """The upload with points of interest as the app can make them: unnamed and repeated."""
    changed = copy.deepcopy(upload)
    ids = [pose["id"] for pose in changed["pose_data"]]
    names = ["", "Kitchen", "Kitchen", "  "]
    changed["location_data"] = [
        {"name": name, "pose_id": ids[len(ids) * (k + 1) // 5] + 1, "transform": IDENTITY}
        for k, name in enumerate(names)
    ]
    changed["map_id"] = ""
    return changed


@pytest.fixture(scope="module")
def occam() -> MapResult:
    return optimize_session(
        parse_session(read_json_document(DATA / "sessions" / "occam_room.json"))
    )


CASES = [(path, False) for path in REAL] + [
    (path, True) for path in REAL if path.parent.name == "sessions"
]


#: The graphs an app-map is made from: the corridor skeleton (what the worker builds) and the
#: walked path graph; the exporter must hold on either.
BUILDERS = {"skeleton": build_skeleton, "walked": build_path_graph}


@cache
def built(path: Path, pois: bool) -> MapResult:
    """The map of a session in data (with the app's points of interest), made once for both
    path-graph builders: a build estimates the walk's noise (issue 25), which takes 1–2 s on the
    2020 archive walks."""
    upload = read_json_document(path)
    if pois:
        upload = with_app_made_pois(upload)
    return optimize_session(parse_session(upload))


@pytest.mark.parametrize("builder", sorted(BUILDERS))
@pytest.mark.parametrize(
    ("path", "pois"),
    CASES,
    ids=[f"{p.parent.name}/{p.stem}{'+app-made-pois' if pois else ''}" for p, pois in CASES],
)
def test_the_app_survives_the_map_of_every_session_in_data(path, pois, builder):
    result = built(path, pois)
    document = served(result, BUILDERS[builder](result))
    assert_app_survives(document)
    if pois:
        names = [w["id"] for w in document["waypoints_vertices"]]
        assert names == ["Point 1", "Kitchen", "Kitchen (2)", "Point 4"]
        assert any("'Kitchen (2)'" in note for note in document["notes"])


@pytest.mark.parametrize("builder", sorted(BUILDERS))
@pytest.mark.parametrize("name", sorted(SIMULATED))
def test_the_app_survives_simulated_buildings(name, builder):
    sim = simulate_session(SIMULATED[name])
    result = optimize_session(parse_session(sim.upload))
    graph = BUILDERS[builder](result)
    if SIMULATED[name].two_floors:
        kinds = {graph.graph.edges[e]["kind"] for e in graph.graph.edges}
        assert "stairs" in kinds or "elevator" in kinds
        assert len(graph.floor_levels_m) == 2
    assert any(d == 1 for _, d in graph.graph.degree)  # dead ends
    assert nx.cycle_basis(graph.graph)  # loops
    assert_app_survives(served(result, graph))


def test_a_walk_that_falls_apart_keeps_its_largest_part_and_says_so(occam):
    graph = build_path_graph(occam)
    G = graph.graph.copy()
    # cut the graph across x = its median: every edge crossing that line is removed
    x_median = float(np.median([G.nodes[n]["position_m"][0] for n in G]))
    side = {n: G.nodes[n]["position_m"][0] < x_median for n in G}
    G.remove_edges_from([(u, v) for u, v in list(G.edges) if side[u] != side[v]])
    parts = sorted(  # the longest part first: the one the app gets
        (p for p in nx.connected_components(G) if len(p) > 1),
        key=lambda p: G.subgraph(p).size(weight="length_m"),
        reverse=True,
    )
    assert len(parts) >= 2
    cut = PathGraph(graph=G, floor_levels_m=graph.floor_levels_m, tags=graph.tags, pois=graph.pois)

    document = served(occam, cut)

    assert_app_survives(document)
    assert any(
        f"falls apart into {len(parts)} unconnected parts" in note for note in document["notes"]
    )
    listed = {v["poseId"] for v in document["odometry_vertices"]}
    pose_ids = occam.pose_id.tolist()
    left_out = [
        pose_ids[G.nodes[n]["pose_index"]]
        for part in parts[1:]
        for n in part
        if G.nodes[n]["pose_index"] is not None
    ]
    assert left_out
    assert not listed & set(left_out)  # the other parts are left out


def test_a_graph_whose_nodes_are_no_poses_still_attaches_every_pose(occam):
    """A corridor skeleton (issue 18) has nodes of its own: the exporter must not assume poses."""
    graph = build_path_graph(occam)
    skeleton = nx.relabel_nodes(graph.graph, {n: 10_000 + n for n in graph.graph})
    for node in skeleton:
        skeleton.nodes[node]["pose_index"] = None
        skeleton.nodes[node]["kind"] = "corridor"

    document = served(occam, PathGraph(graph=skeleton, floor_levels_m=graph.floor_levels_m))

    assert_app_survives(document)
    vertices = document["odometry_vertices"]
    n = occam.pose_id.size
    assert [v["poseId"] for v in vertices[:n]] == occam.pose_id.tolist()
    assert len(vertices) == n + skeleton.number_of_nodes()
    assert all(v["poseId"] > occam.pose_id.max() for v in vertices[n:])
    assert all(len(v["neighbors"]) == 2 for v in vertices[:n])  # each on its nearest edge


def test_a_graph_without_edges_and_no_graph_give_the_chain_of_poses(occam):
    lonely = PathGraph(graph=nx.Graph())
    lonely.graph.add_node(0, position_m=(0.0, 0.0, 0.0), pose_index=0)
    for graph in (None, lonely):
        document = served(occam, graph)
        assert_app_survives(document)
        assert document["odometry_vertices"][1]["neighbors"] == occam.pose_id[[0, 2]].tolist()


def test_unique_waypoint_names_skip_names_already_taken():
    names, notes = unique_waypoint_names(["Desk", "Desk (2)", "Desk", "Desk", "Exit"])
    assert names == ["Desk", "Desk (2)", "Desk (3)", "Desk (4)", "Exit"]
    assert len(notes) == 2
    assert unique_waypoint_names(["A", "B"]) == (["A", "B"], [])
