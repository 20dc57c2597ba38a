"""The path graph of a map of several sessions (app/domain/navigation/joint_path_graph.py)."""

from __future__ import annotations

import itertools
from functools import cache

import networkx as nx
import numpy as np

from app.domain.evaluation.simulate import SimulationConfig
from app.domain.evaluation.simulate_building import simulate_building_sessions
from app.domain.formats.map_io import map_to_app_format
from app.domain.mapping.joint import JointMap, optimize_sessions
from app.domain.navigation.joint_path_graph import build_joint_path_graph
from app.domain.navigation.path_graph import JUNCTION, NODE, build_path_graph
from app.domain.upload.session import parse_session


@cache
def joint_map() -> JointMap:
    sim = simulate_building_sessions(SimulationConfig(num_poses=800, seed=5), count=3)
    return optimize_sessions([parse_session(s.upload) for s in sim.sessions])


def starts(joint: JointMap) -> list[int]:
    return [part.pose_rows.start for part in joint.parts]


def test_one_graph_over_every_walk_and_no_edge_between_walk_ends():
    joint = joint_map()
    pg = build_joint_path_graph(joint.map, starts(joint))
    G = pg.graph
    assert nx.is_connected(G)
    rows = [p.pose_rows for p in joint.parts]
    for a, b in itertools.pairwise(rows):
        assert not G.has_edge(a.stop - 1, b.start)
    sessions_present = {
        k
        for node, data in G.nodes(data=True)
        if data["kind"] == NODE
        for k, r in enumerate(rows)
        if r.start <= node < r.stop
    }
    assert sessions_present == {0, 1, 2}
    # walks of different sessions meet: an edge joins nodes of two sessions, or a junction
    assert any(data["kind"] == JUNCTION for _, data in G.nodes(data=True))
    assert set(pg.tags) == {int(t) for t in joint.map.tag_ids}
    for _, _, data in G.edges(data=True):
        assert data["length_m"] >= 0


def test_the_apps_map_of_a_joint_map_is_one_navigation_graph():
    joint = joint_map()
    app_map = map_to_app_format(
        joint.map, path_graph=build_joint_path_graph(joint.map, starts(joint))
    )
    ids = [v["poseId"] for v in app_map["odometry_vertices"]]
    assert len(ids) == len(set(ids))
    G: nx.Graph[int] = nx.Graph()
    for vertex in app_map["odometry_vertices"]:
        assert vertex["neighbors"]  # no isolated vertex
        for neighbor in vertex["neighbors"]:
            G.add_edge(vertex["poseId"], neighbor)
    assert nx.is_connected(G)


def test_one_session_is_the_usual_path_graph():
    joint = joint_map()
    one = optimize_sessions([joint.sessions[0]])
    ours = build_joint_path_graph(one.map, [0])
    usual = build_path_graph(one.map)
    assert sorted(ours.graph.nodes) == sorted(usual.graph.nodes)
    assert np.isclose(
        sum(d["length_m"] for *_, d in ours.graph.edges(data=True)),
        sum(d["length_m"] for *_, d in usual.graph.edges(data=True)),
    )
