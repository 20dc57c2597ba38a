"""The model of the app's decoder and route planner (app.domain.formats.app_model) on hand-made
maps: each of its rules is shown to fire, so a clean report on our maps means something."""

from __future__ import annotations

import copy

import pytest

from app.domain.formats.app_model import (
    AppTrap,
    build_app_graph,
    check_app_map,
    decode_app_map,
    plan_app_route,
)

ROTATION = {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}


def vertex(pose_id, x, neighbors):
    return {
        "poseId": pose_id,
        "translation": {"x": float(x), "y": 0.0, "z": 0.0},
        "rotation": dict(ROTATION),
        "neighbors": neighbors,
    }


def line_map(n=4, *, both_ends=True):
    """Vertices 0..n-1 on the x axis, each linked to the next."""
    vertices = []
    for i in range(n):
        neighbors = [j for j in (i - 1, i + 1) if 0 <= j < n]
        if not both_ends:
            neighbors = [j for j in neighbors if j > i]  # only at the smaller-id end
        vertices.append(vertex(i, i, neighbors))
    return {
        "tag_vertices": [
            {"id": 7, "translation": {"x": 0.1, "y": 0, "z": 0}, "rotation": ROTATION}
        ],
        "odometry_vertices": vertices,
        "waypoints_vertices": [
            {"id": "Exit", "translation": {"x": n - 1.0, "y": 0, "z": 0}, "rotation": ROTATION}
        ],
    }


def test_a_connected_map_with_links_at_both_ends_routes_every_pair():
    report = check_app_map(line_map())
    assert report.ok, report
    assert report.pairs == 2 * 3  # 2 destinations × every vertex but the endpoint
    assert report.components == 1
    graph = build_app_graph(decode_app_map(line_map()))
    assert plan_app_route(graph, (3.0, 0, 0), (0.1, 0, 0)) == [3, 2, 1, 0]


def test_links_listed_only_at_the_smaller_id_end_are_lost():
    report = check_app_map(line_map(both_ends=False))
    assert report.isolated_vertices == (0, 1, 2, 3)
    assert report.crashing_pairs == report.pairs == 6
    graph = build_app_graph(decode_app_map(line_map(both_ends=False)))
    with pytest.raises(AppTrap, match="unreachable"):
        plan_app_route(graph, (3.0, 0, 0), (0.1, 0, 0))


def test_a_second_component_crashes_the_pairs_that_cross_it():
    document = line_map()
    document["odometry_vertices"] += [vertex(10, 50, [11]), vertex(11, 51, [10])]
    report = check_app_map(document)
    assert report.components == 2
    assert not report.isolated_vertices
    # each destination's endpoint is in the first part: the 2 far vertices cannot reach it
    assert report.crashing_pairs == 2 * 2
    assert report.pairs == 2 * 5
    assert "unreachable" in report.traps[0]


@pytest.mark.parametrize(
    ("change", "path"),
    [
        (lambda d: d.pop("waypoints_vertices"), "$.waypoints_vertices"),
        (lambda d: d["odometry_vertices"][1].pop("neighbors"), "odometry_vertices[1].neighbors"),
        (lambda d: d["odometry_vertices"][0].update(poseId=None), "odometry_vertices[0].poseId"),
        (lambda d: d["odometry_vertices"][0].update(poseId=1.5), "odometry_vertices[0].poseId"),
        (lambda d: d["odometry_vertices"][0].update(poseId=True), "odometry_vertices[0].poseId"),
        (lambda d: d["tag_vertices"][0]["rotation"].pop("w"), "tag_vertices[0].rotation.w"),
        (lambda d: d["tag_vertices"][0]["translation"].update(x="1"), "translation.x"),
        (lambda d: d["tag_vertices"][0]["translation"].update(x=1e39), "translation.x"),
        (lambda d: d["waypoints_vertices"][0].update(id=3), "waypoints_vertices[0].id"),
        (lambda d: d["odometry_vertices"][2]["neighbors"].append("1"), "neighbors[2]"),
    ],
)
def test_what_json_decoder_refuses_fails_the_whole_map(change, path):
    document = copy.deepcopy(line_map())
    change(document)
    report = check_app_map(document)
    assert report.decode_error is not None
    assert path in report.decode_error
    assert not report.ok


def test_extra_keys_are_ignored():
    document = line_map()
    document["odometry_vertices"][0]["adjChi2"] = 1.0
    document["note"] = "anything"
    assert check_app_map(document).ok


def test_a_duplicate_pose_id_and_an_unknown_smaller_neighbor_trap():
    duplicate = line_map()
    duplicate["odometry_vertices"][3]["poseId"] = 2
    assert "duplicate poseId 2" in check_app_map(duplicate).traps[0]
    unknown = line_map()
    unknown["odometry_vertices"][3]["neighbors"].append(-5)
    assert "neighbor -5" in check_app_map(unknown).traps[0]
    # an unknown *larger* neighbor is never looked up by the app
    larger = line_map()
    larger["odometry_vertices"][0]["neighbors"].append(99)
    assert check_app_map(larger).ok


def test_a_one_vertex_map_has_no_route():
    document = line_map(1)
    report = check_app_map(document)
    assert report.crashing_pairs == report.pairs == 2
    with pytest.raises(AppTrap, match="one stop"):
        plan_app_route(build_app_graph(decode_app_map(document)), (0, 0, 0), (0, 0, 0))


def test_repeated_waypoint_names_shadow_all_but_the_last():
    document = line_map()
    document["waypoints_vertices"].append(dict(document["waypoints_vertices"][0]))
    report = check_app_map(document)
    assert report.unreachable_waypoints == ("Exit",)
    assert not report.ok
