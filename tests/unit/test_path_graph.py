"""The path graph (§6, issue 5 item 1): junctions only where the walk really crosses itself,
merged passes, closed loops, floors with stairs and elevators, simplification within tolerance,
anchors, and the JSON, GeoJSON and app exports.

Walks are built in code (``make_walk``) in the map frame: y up, the floor is the x–z plane.
"""

from __future__ import annotations

import itertools
import json
import math
from pathlib import Path

import networkx as nx
import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from app.domain.errors import MapFormatError, ParameterError
from app.domain.evaluation.simulate import SimulationConfig, simulate_session
from app.domain.formats.map_io import map_to_app_format
from app.domain.mapping.slam import optimize_session
from app.domain.navigation.instructions import plan_guided_route
from app.domain.navigation.path_graph import (
    ELEVATOR,
    JUNCTION,
    NODE,
    STAIRS,
    WALK,
    PathGraph,
    PathGraphParams,
    build_path_graph,
    build_path_graph_from_arrays,
    path_graph_from_json,
    path_graph_to_geojson,
    path_graph_to_json,
)
from app.domain.navigation.routing import NodeEnd, Unreachable, plan_walk
from app.domain.upload.session import load_session

SESSIONS = Path(__file__).parents[2] / "data" / "sessions"

#: Only what the issue asks of crossings: no merging, loop erasing, closing or knot contraction.
CROSSINGS_ONLY = PathGraphParams(
    erase_loops_within_m=0.0,
    merge_distance_m=0.0,
    close_ends_within_m=0.0,
    contract_junctions_within_m=0.0,
    simplify_tolerance_m=0.0,
)


# --------------------------------------------------------------------------- helpers


def make_walk(points, spacing_m=0.5, height_m=0.0):
    """(N, 3) positions along the polyline through ``points``, about ``spacing_m`` apart.

    points: (x, z) on the floor at ``height_m``, or (x, y, z). Each leg gets whole steps, so every
    corner is a pose.
    """
    corners = np.asarray(points, dtype=np.float64)
    if corners.shape[1] == 2:
        corners = np.column_stack([corners[:, 0], np.full(len(corners), height_m), corners[:, 1]])
    walk = [corners[0]]
    for a, b in itertools.pairwise(corners):
        steps = max(1, math.ceil(np.linalg.norm(b - a) / spacing_m))
        walk += [a + (b - a) * k / steps for k in range(1, steps + 1)]
    return np.array(walk)


def make_figure_eight(n=400, size_m=10.0, turns=0.9):
    """A lemniscate of Bernoulli walked from its right end, ``turns`` of the way round (open)."""
    t = np.linspace(0.0, 2 * np.pi * turns, n)
    scale = size_m / (1 + np.sin(t) ** 2)
    return np.column_stack([scale * np.cos(t), np.zeros(n), scale * np.sin(t) * np.cos(t)])


def walk_length_m(positions_m):
    return float(np.linalg.norm(np.diff(positions_m, axis=0), axis=1).sum())


def junctions(pg: PathGraph) -> list[int]:
    return [n for n, kind in pg.graph.nodes(data="kind") if kind == JUNCTION]


def total_length_m(pg: PathGraph) -> float:
    return float(sum(d["length_m"] for _, _, d in pg.graph.edges(data=True)))


def position(pg: PathGraph, node: int) -> np.ndarray:
    return np.asarray(pg.graph.nodes[node]["position_m"])


def nearest_node(pg: PathGraph, point) -> int:
    return min(pg.graph.nodes, key=lambda n: np.linalg.norm(position(pg, n) - np.asarray(point)))


def route_length_m(pg: PathGraph, a, b) -> float:
    return nx.shortest_path_length(
        pg.graph, nearest_node(pg, a), nearest_node(pg, b), weight="length_m"
    )


def point_segment_distance(points, a, b):
    """(M, K) distance of each of M points to each of K segments a→b (3-D)."""
    d = b - a
    length2 = np.maximum(np.sum(d * d, axis=1), 1e-300)
    t = np.clip(np.einsum("mkj,kj->mk", points[:, None, :] - a[None], d) / length2, 0, 1)
    nearest = a[None] + t[..., None] * d[None]
    return np.linalg.norm(points[:, None, :] - nearest, axis=2)


def distance_to_graph_m(pg: PathGraph, points) -> np.ndarray:
    """(M,) 3-D distance of each point to the nearest edge of the graph."""
    edges = list(pg.graph.edges)
    a = np.array([position(pg, u) for u, _ in edges])
    b = np.array([position(pg, v) for _, v in edges])
    return point_segment_distance(np.asarray(points), a, b).min(axis=1)


def crossings_brute_force(points_xz) -> int:
    """Proper crossings between non-adjacent segments of a polyline in general position."""
    return len(crossing_points_brute_force(points_xz))


def crossing_points_brute_force(points_xz) -> list[np.ndarray]:
    p = np.asarray(points_xz)
    found = []
    for i in range(len(p) - 1):
        for j in range(i + 2, len(p) - 1):
            a, b, c, d = p[i], p[i + 1], p[j], p[j + 1]
            r, s = b - a, d - c
            den = r[0] * s[1] - r[1] * s[0]
            if den == 0:
                continue
            t = ((c - a)[0] * s[1] - (c - a)[1] * s[0]) / den
            u = ((c - a)[0] * r[1] - (c - a)[1] * r[0]) / den
            if 0 < t < 1 and 0 < u < 1:
                found.append(a + t * r)
    return found


# --------------------------------------------------------------------------- junctions


def test_a_figure_eight_has_exactly_one_junction_at_its_centre():
    walk = make_figure_eight()
    pg = build_path_graph_from_arrays(walk)

    (junction,) = junctions(pg)
    np.testing.assert_allclose(position(pg, junction), [0.0, 0.0, 0.0], atol=1e-3)
    assert pg.graph.degree(junction) == 4
    assert nx.is_connected(pg.graph)


@pytest.mark.parametrize(
    "corners",
    [
        pytest.param([(0, 0), (20, 0)], id="straight"),
        pytest.param([(0, 0), (20, 0), (20, 3), (0, 3)], id="U"),
        pytest.param([(0, 0), (10, 0), (10, 10)], id="L"),
    ],
)
def test_walks_that_never_cross_themselves_have_no_junction(corners):
    for params in (PathGraphParams(), CROSSINGS_ONLY):
        pg = build_path_graph_from_arrays(make_walk(corners, spacing_m=0.3), params=params)
        assert junctions(pg) == []
        assert nx.is_connected(pg.graph)


def test_segments_that_share_an_endpoint_never_make_a_junction():
    # A zig-zag: every pose is a sharp corner where two segments meet and nothing else does.
    zigzag = [(x, 0.2 * (x % 2)) for x in range(40)]
    pg = build_path_graph_from_arrays(make_walk(zigzag, spacing_m=10.0), params=CROSSINGS_ONLY)
    assert junctions(pg) == []
    assert pg.graph.number_of_nodes() == 40


def test_a_crossing_exactly_through_poses_is_one_junction_replacing_them():
    # The second pass runs through the pose at (5, 0) of the first one: one junction, 4 ways.
    walk = make_walk([(0, 0), (10, 0), (10, 5), (5, 5), (5, -5)], spacing_m=0.5)
    pg = build_path_graph_from_arrays(walk)
    (junction,) = junctions(pg)
    np.testing.assert_allclose(position(pg, junction), [5.0, 0.0, 0.0], atol=1e-9)
    assert pg.graph.degree(junction) == 4
    assert total_length_m(pg) == pytest.approx(walk_length_m(walk), rel=1e-12)


def test_one_segment_crossed_many_times_is_split_at_every_crossing():
    # A long first leg, then a comb of legs crossing it: 5 crossings of one segment.
    comb = [(0, 0), (20, 0), (20, 2)]
    for k, x in enumerate([18.2, 14.2, 10.2, 6.2, 2.2]):
        comb += [(x, 2), (x, -2)] if k % 2 == 0 else [(x, -2), (x, 2)]
    walk = make_walk(comb, spacing_m=100.0)  # one segment per leg
    pg = build_path_graph_from_arrays(walk, params=CROSSINGS_ONLY)

    xs = sorted(float(position(pg, j)[0]) for j in junctions(pg))
    np.testing.assert_allclose(xs, [2.2, 6.2, 10.2, 14.2, 18.2], atol=1e-9)
    first_leg = nx.shortest_path(pg.graph, 0, 1, weight="length_m")
    assert len(first_leg) == 7  # start, the 5 junctions, the corner
    assert total_length_m(pg) == pytest.approx(walk_length_m(walk), rel=1e-12)


def test_junction_splits_keep_the_total_length_of_the_walk():
    # A pentagram (not closed): every long leg crosses two or three others.
    angles = np.deg2rad(90 + 144 * np.arange(5))
    star = make_walk(np.column_stack([10 * np.cos(angles), 10 * np.sin(angles)]), spacing_m=0.4)
    expected = crossings_brute_force(star[:, [0, 2]])
    assert expected == 3
    for params in (PathGraphParams(), CROSSINGS_ONLY):
        pg = build_path_graph_from_arrays(star, params=params)
        assert len(junctions(pg)) == expected
        assert total_length_m(pg) == pytest.approx(walk_length_m(star), rel=1e-9)


def test_a_junction_takes_the_mean_height_of_the_two_passes():
    walk = np.array([[0, 0.0, 0], [4, 0.0, 0], [4, 0.2, 2], [2, 0.2, 2], [2, 0.2, -2]])
    pg = build_path_graph_from_arrays(walk, params=CROSSINGS_ONLY)
    (junction,) = junctions(pg)
    np.testing.assert_allclose(position(pg, junction), [2.0, 0.1, 0.0], atol=1e-12)


# --------------------------------------------------------------------------- loops and overlaps


def test_a_square_loop_ending_near_its_start_is_closed_without_a_junction():
    walk = make_walk([(0, 0), (10, 0), (10, 10), (0, 10), (0, 0.4)], spacing_m=0.5)
    pg = build_path_graph_from_arrays(walk)

    assert junctions(pg) == []
    assert len(nx.cycle_basis(pg.graph)) == 1
    assert all(degree == 2 for _, degree in pg.graph.degree)
    # The walk (39.6 m) and the 0.4 m link that closes it; the corners are the nodes.
    assert total_length_m(pg) == pytest.approx(40.0)
    assert pg.graph.number_of_nodes() == 4


def test_a_walk_ending_far_from_its_start_is_not_closed():
    walk = make_walk([(0, 0), (10, 0), (10, 10), (0, 10), (0, 3)], spacing_m=0.5)
    pg = build_path_graph_from_arrays(walk)
    assert nx.cycle_basis(pg.graph) == []


@pytest.mark.parametrize("offset_m", [0.0, 0.3, 0.6])
def test_an_out_and_back_along_one_corridor_connects_the_two_passes(offset_m):
    rng = np.random.default_rng(1)
    walk = make_walk([(0, 0), (20, 0), (20, offset_m), (0, offset_m)], spacing_m=0.3)
    walk[1:-1, [0, 2]] += rng.normal(0.0, 0.03, size=(len(walk) - 2, 2))
    pg = build_path_graph_from_arrays(walk)
    assert nx.is_connected(pg.graph)

    # From the way back to the way out at the same place: a step across, not 20 m and back.
    for x in (3.0, 10.0, 16.0):
        assert route_length_m(pg, (x, 0, offset_m), (x, 0, 0)) < 2.0
    # End to end along the corridor: straight, not zig-zagging between the two passes.
    route = nx.shortest_path(
        pg.graph, nearest_node(pg, (0, 0, offset_m)), nearest_node(pg, (20, 0, 0)), "length_m"
    )
    xs = np.array([position(pg, n)[0] for n in route])
    assert np.all(np.diff(xs) > -0.5)  # never doubles back
    assert route_length_m(pg, (0, 0, offset_m), (20, 0, 0)) < 20.0 * 1.03 + offset_m
    assert pg.graph.number_of_nodes() <= 8


def test_a_corridor_walked_three_times_is_one_line():
    walk = make_walk([(0, 0), (30, 0), (30, 0.4), (0, 0.4), (0, 0.2), (30, 0.2)], spacing_m=0.25)
    pg = build_path_graph_from_arrays(walk)
    # Everything after the first pass (but the first metres of each U-turn) was merged into it.
    assert total_length_m(pg) < 30.0 + 6.0
    assert route_length_m(pg, (0, 0, 0.2), (30, 0, 0.2)) == pytest.approx(30.0, abs=1.0)


def test_a_turn_on_the_spot_is_erased_but_a_real_loop_is_kept():
    t = np.linspace(0, 2 * np.pi, 30)
    spin = np.column_stack([10 + 0.3 * np.sin(t), 0.3 - 0.3 * np.cos(t)])  # a 0.6 m circle
    walk = make_walk([(0, 0), (10, 0), *spin.tolist(), (10, 0), (20, 0)], spacing_m=0.25)
    walk[:, 2] += np.linspace(0, 0.05, len(walk))  # so the way on crosses the way in
    assert junctions(build_path_graph_from_arrays(walk)) == []
    assert len(junctions(build_path_graph_from_arrays(walk, params=CROSSINGS_ONLY))) >= 1

    loop = make_walk([(0, 0), (10, 0), (10, 4), (6, 4), (6, -4)], spacing_m=0.25)
    assert len(junctions(build_path_graph_from_arrays(loop))) == 1


# --------------------------------------------------------------------------- floors


def two_floor_walk():
    """Floor 0 (y = 0) → stairs up (6 m run, 3.5 m rise) → floor 1 → elevator down → floor 0."""
    rng = np.random.default_rng(7)
    floor_0 = make_walk([(0, 0, 0), (10, 0, 0)], spacing_m=0.3)
    stairs = make_walk([(10, 0, 0), (16, 3.5, 0)], spacing_m=0.3)[1:]
    floor_1 = make_walk([(16, 3.5, 0), (16, 3.5, 6), (12, 3.5, 6)], spacing_m=0.3)[1:]
    ride = np.column_stack(
        [12 + rng.normal(0, 0.02, 40), np.linspace(3.5, 0.0, 40), 6 + rng.normal(0, 0.02, 40)]
    )
    back = make_walk([(12, 0, 6), (5, 0, 6), (5, 0, -2)], spacing_m=0.3)[1:]  # crosses floor_0
    return np.vstack([floor_0, stairs, floor_1, ride, back])


def test_a_two_floor_walk_has_two_floors_and_tells_stairs_from_elevator():
    pg = build_path_graph_from_arrays(two_floor_walk())
    G = pg.graph

    np.testing.assert_allclose(pg.floor_levels_m, [0.0, 3.5], atol=0.1)
    kinds = {d["kind"] for _, _, d in G.edges(data=True)}
    assert kinds == {WALK, STAIRS, ELEVATOR}
    for u, v, d in G.edges(data=True):
        floors = {G.nodes[u]["floor"], G.nodes[v]["floor"]}
        if d["kind"] == WALK:
            assert len(floors) == 1
            assert d["floor"] in floors
        else:
            assert d["floor"] == 0  # a floor change carries the lower floor
    stairs_x = [position(pg, u)[0] for u, v, d in G.edges(data=True) if d["kind"] == STAIRS]
    elevator_x = [position(pg, u)[0] for u, v, d in G.edges(data=True) if d["kind"] == ELEVATOR]
    assert min(stairs_x) >= 10
    assert max(stairs_x) <= 16
    np.testing.assert_allclose(elevator_x, 12.0, atol=0.1)
    # Both floor changes are whole: floor 0 and floor 1 are joined by each of them alone.
    for avoid in (STAIRS, ELEVATOR):
        H = G.edge_subgraph([(u, v) for u, v, d in G.edges(data=True) if d["kind"] != avoid])
        assert nx.is_connected(H)


def test_the_simulated_two_floor_building_has_stairs_between_its_floors():
    sim = simulate_session(SimulationConfig(num_poses=3000, two_floors=True, seed=2))
    pg = build_path_graph_from_arrays(sim.world_T_phone_true[:, :3, 3])
    G = pg.graph

    np.testing.assert_allclose(pg.floor_levels_m, [1.3, 4.8], atol=0.1)
    assert {G.nodes[n]["floor"] for n in G.nodes} == {0, 1}
    changes = [d["kind"] for u, v, d in G.edges(data=True) if d["kind"] != WALK]
    assert changes
    assert set(changes) == {STAIRS}
    assert nx.is_connected(G)
    assert not nx.is_connected(
        G.edge_subgraph([(u, v) for u, v, d in G.edges(data=True) if d["kind"] == WALK])
    )


def test_a_ramp_on_one_floor_is_walk():
    # Up 0.6 m and down again: within one floor, so no floor change.
    walk = make_walk([(0, 0, 0), (5, 0.6, 0), (10, 0, 0), (20, 0, 0)], spacing_m=0.3)
    pg = build_path_graph_from_arrays(walk)
    assert {d["kind"] for _, _, d in pg.graph.edges(data=True)} == {WALK}
    assert len(pg.floor_levels_m) == 1


# --------------------------------------------------------------------------- simplification


def wiggly_walk():
    """Straight corridors joined by a curve, with 2 cm of noise: (N, 3)."""
    rng = np.random.default_rng(3)
    straight = make_walk([(0, 0), (30, 0)], spacing_m=0.12)
    t = np.linspace(-np.pi / 2, np.pi / 2, 60)[1:]
    curve = np.column_stack([30 + 4 * np.cos(t), np.zeros_like(t), 4 + 4 * np.sin(t)])
    back = make_walk([(30, 8), (5, 8), (5, 20)], spacing_m=0.12)[1:]
    walk = np.vstack([straight, curve, back])
    walk[:, [0, 2]] += rng.normal(0, 0.02, size=(len(walk), 2))
    return walk


@pytest.mark.parametrize("tolerance_m", [0.05, 0.25, 0.5])
def test_simplification_keeps_every_pose_within_tolerance_of_the_path(tolerance_m):
    walk = wiggly_walk()
    pg = build_path_graph_from_arrays(
        walk, params=PathGraphParams(simplify_tolerance_m=tolerance_m)
    )
    assert distance_to_graph_m(pg, walk).max() <= tolerance_m + 1e-9
    assert total_length_m(pg) == pytest.approx(walk_length_m(walk), rel=1e-9)


def test_simplification_greatly_reduces_straight_runs():
    walk = wiggly_walk()
    pg = build_path_graph_from_arrays(walk)
    assert pg.graph.number_of_nodes() < len(walk) / 20
    straight = build_path_graph_from_arrays(make_walk([(0, 0), (50, 0)], spacing_m=0.1))
    assert straight.graph.number_of_nodes() == 2
    L = build_path_graph_from_arrays(make_walk([(0, 0), (20, 0), (20, 20)], spacing_m=0.1))
    assert sorted(L.graph.nodes) == [0, 200, 400]


# --------------------------------------------------------------------------- anchors


def test_tags_and_pois_attach_to_their_nearest_node():
    walk = make_walk([(0, 0), (20, 0)], spacing_m=0.5)
    pg = build_path_graph_from_arrays(
        walk,
        tag_ids=[300, 301],
        tag_positions_m=[[7.3, 1.4, 1.2], [15.9, 1.4, -1.5]],  # on the walls, 1–2 m off
        poi_names=["Room 209"],
        poi_positions_m=[[3.1, 0.0, -0.5]],
    )
    assert set(pg.tags) == {300, 301}
    np.testing.assert_allclose(position(pg, pg.tags[300].node), [7.5, 0, 0])
    np.testing.assert_allclose(position(pg, pg.tags[301].node), [16.0, 0, 0])
    assert pg.tags[300].name == "300"
    assert pg.tags[300].position_m == (7.3, 1.4, 1.2)
    (poi,) = pg.pois
    assert poi.name == "Room 209"
    np.testing.assert_allclose(position(pg, poi.node), [3.0, 0, 0])
    # Anchor nodes survive simplification (the straight walk keeps only them and its ends).
    assert pg.graph.number_of_nodes() == 5


def test_an_anchor_prefers_a_node_on_its_own_floor():
    floor_0 = make_walk([(0, 0, 0), (10, 0, 0), (10, 0, 3)], spacing_m=0.5)
    stairs = make_walk([(10, 0, 3), (16, 3.5, 3)], spacing_m=0.5)[1:]
    floor_1 = make_walk([(16, 3.5, 3), (0, 3.5, 3)], spacing_m=0.5)[1:]
    walk = np.vstack([floor_0, stairs, floor_1])
    # Nearer the floor-0 corridor (2.3 m) than the floor-1 one (2.8 m), but at floor-1 height.
    tag_m = [5.0, 2.2, 0.5]
    pg = build_path_graph_from_arrays(walk, tag_ids=[7], tag_positions_m=[tag_m])
    (anchor,) = pg.tags.values()
    assert anchor.floor == 1
    assert pg.graph.nodes[anchor.node]["floor"] == 1


# --------------------------------------------------------------------------- JSON and GeoJSON


def rich_graph() -> PathGraph:
    return build_path_graph_from_arrays(
        two_floor_walk(),
        tag_ids=[300, 305],
        tag_positions_m=[[4.0, 1.2, -1.0], [14.0, 4.8, 7.2]],
        poi_names=["Room 209", "Exit"],
        poi_positions_m=[[2.0, 0.0, 0.5], [0.5, 0.0, 6.2]],
    )


def test_json_round_trip_is_lossless():
    pg = rich_graph()
    assert junctions(pg)  # the last leg crosses the first
    document = path_graph_to_json(pg)
    text = json.dumps(document, allow_nan=False)
    again = path_graph_from_json(json.loads(text))

    assert path_graph_to_json(again) == document
    assert list(again.graph.nodes(data=True)) == list(pg.graph.nodes(data=True))
    assert list(again.graph.edges(data=True)) == list(pg.graph.edges(data=True))
    assert again.floor_levels_m == pg.floor_levels_m
    assert again.tags == pg.tags
    assert again.pois == pg.pois


def test_json_of_an_empty_walk_round_trips():
    pg = build_path_graph_from_arrays(np.empty((0, 3)))
    assert path_graph_to_json(path_graph_from_json(path_graph_to_json(pg))) == path_graph_to_json(
        pg
    )


@pytest.mark.parametrize(
    "breakage",
    [
        lambda d: d.update(format="something else"),
        lambda d: d.update(format_version=99),
        lambda d: d.pop("nodes"),
        lambda d: d["edges"].append(
            {"from": 0, "to": 10**9, "length_m": 1.0, "kind": "walk", "floor": 0}
        ),
        lambda d: d["edges"][0].update(kind="teleport"),
        lambda d: d["nodes"][0].update(kind="mystery"),
    ],
)
def test_a_malformed_json_document_is_refused(breakage):
    document = json.loads(json.dumps(path_graph_to_json(rich_graph())))
    breakage(document)
    with pytest.raises(MapFormatError):
        path_graph_from_json(document)


def test_geojson_has_the_kinds_and_properties_the_api_promises():
    pg = rich_graph()
    collection = path_graph_to_geojson(pg)
    json.dumps(collection, allow_nan=False)

    assert collection["type"] == "FeatureCollection"
    assert collection["coordinate_system"]["axes"] == ["x", "-z", "y"]
    points = [f for f in collection["features"] if f["geometry"]["type"] == "Point"]
    lines = [f for f in collection["features"] if f["geometry"]["type"] == "LineString"]
    point_kinds = [f["properties"]["kind"] for f in points]
    assert set(point_kinds) == {NODE, JUNCTION, "tag", "poi"}
    assert point_kinds.count("tag") == 2
    assert point_kinds.count("poi") == 2
    assert len(lines) == pg.graph.number_of_edges()
    assert {f["properties"]["kind"] for f in lines} == {WALK, STAIRS, ELEVATOR}
    for f in points:
        assert {"kind", "floor"} <= set(f["properties"])
        assert "id" in f["properties"] or "name" in f["properties"]
    for f in lines:
        assert {"kind", "floor", "length_m"} <= set(f["properties"])
        assert f["properties"]["length_m"] > 0
    # [x, −z, y]: a right-handed east-north-up view of the y-up map frame.
    node = next(f for f in points if f["properties"]["kind"] == NODE)
    x, y, z = pg.graph.nodes[node["properties"]["id"]]["position_m"]
    assert node["geometry"]["coordinates"] == [x, -z, y]
    tag = next(f for f in points if f["properties"]["kind"] == "tag")
    assert tag["properties"]["id"] == 300
    assert tag["properties"]["name"] == "300"
    poi = next(f for f in points if f["properties"]["kind"] == "poi")
    assert poi["properties"]["name"] == "Room 209"
    assert poi["geometry"]["coordinates"] == [2.0, -0.5, 0.0]


# --------------------------------------------------------------------------- parameters


@pytest.mark.parametrize(
    "changes",
    [
        {"simplify_tolerance_m": -0.1},
        {"merge_distance_m": float("nan")},
        {"floor_band_m": 0.0},
        {"merge_distance_m": 1.0, "merge_min_length_m": 1.5},
    ],
)
def test_out_of_range_parameters_are_refused(changes):
    with pytest.raises(ParameterError):
        PathGraphParams(**changes)


def test_anchor_positions_must_match_their_names():
    with pytest.raises(ParameterError):
        build_path_graph_from_arrays(np.zeros((3, 3)), tag_ids=[1, 2], tag_positions_m=[[0, 0, 0]])


def test_degenerate_walks_build():
    assert build_path_graph_from_arrays(np.zeros((1, 3))).graph.number_of_nodes() == 1
    still = build_path_graph_from_arrays(np.zeros((50, 3)))  # a phone that never moved
    assert still.graph.number_of_nodes() == 1
    assert still.graph.number_of_edges() == 0


# --------------------------------------------------------------------------- real sessions


@pytest.fixture(scope="module")
def real_maps():
    return {
        name: optimize_session(load_session(SESSIONS / f"{name}.json"))
        for name in ("floor_2_straight", "occam_room")
    }


@pytest.mark.parametrize("name", ["floor_2_straight", "occam_room"])
def test_real_sessions_build_a_connected_graph_with_plausible_junctions(real_maps, name):
    result = real_maps[name]
    poses = result.world_T_phone.shape[0]
    pg = build_path_graph(result)
    G = pg.graph
    count = len(junctions(pg))
    print(
        f"{name}: {poses} poses → {G.number_of_nodes()} nodes ({count} junctions), "
        f"{G.number_of_edges()} edges, {total_length_m(pg):.1f} m"
    )

    assert nx.is_connected(G)
    assert len(pg.floor_levels_m) == 1
    assert G.number_of_nodes() < poses / 4
    assert count < poses / 20  # the authors' bug: a junction at almost every pose
    if name == "occam_room":
        assert count >= 1  # a room walked round several times does cross itself
    assert set(pg.tags) == {int(t) for t in result.tag_ids}
    # Every pose is near the graph: merged passes ≤ merge distance, plus the simplification.
    positions = result.world_T_phone[:, :3, 3]
    assert np.quantile(distance_to_graph_m(pg, positions), 0.95) < 1.0


def test_app_format_neighbors_come_from_the_path_graph(real_maps):
    result = real_maps["occam_room"]
    pg = build_path_graph(result)
    plain = map_to_app_format(result)
    app = map_to_app_format(result, path_graph=pg)

    n = result.world_T_phone.shape[0]
    vertices = app["odometry_vertices"]
    assert len(vertices) == n + len(junctions(pg))
    ids = {v["poseId"] for v in vertices}
    last_pose_id = int(result.pose_id.max())
    assert [v["poseId"] for v in vertices[n:]] == list(
        range(last_pose_id + 1, last_pose_id + 1 + len(junctions(pg)))
    )
    for v in vertices:
        assert v["neighbors"]
        assert set(v["neighbors"]) <= ids
    # Graph links are symmetric; a pose that is a node lists exactly its graph neighbours.
    by_id = {v["poseId"]: v for v in vertices}
    app_id = {node: int(result.pose_id[node]) for node in pg.graph if node < n}
    app_id |= {
        node: v["poseId"] for node, v in zip(sorted(junctions(pg)), vertices[n:], strict=True)
    }
    for u, w in pg.graph.edges:
        assert app_id[w] in by_id[app_id[u]]["neighbors"]
        assert app_id[u] in by_id[app_id[w]]["neighbors"]
    # Everything else about the vertices is as before.
    for before, after in zip(plain["odometry_vertices"], vertices[:n], strict=True):
        assert {k: v for k, v in before.items() if k != "neighbors"} == {
            k: v for k, v in after.items() if k != "neighbors"
        }
    assert plain["odometry_vertices"][5]["neighbors"] == [
        int(result.pose_id[4]),
        int(result.pose_id[6]),
    ]


# --------------------------------------------------------------------------- scale


def test_a_ten_thousand_pose_two_floor_walk_builds_a_sound_graph():
    # How long it takes is for the README's measurements, not an assertion.
    sim = simulate_session(SimulationConfig(num_poses=10_000, two_floors=True))
    pg = build_path_graph_from_arrays(sim.world_T_phone_true[:, :3, 3])
    assert nx.is_connected(pg.graph)
    assert len(pg.floor_levels_m) == 2
    assert pg.graph.number_of_nodes() < 10_000 / 5  # straight runs simplified


def test_routes_across_the_simulated_floors_take_the_stairs_or_say_why_not():
    sim = simulate_session(SimulationConfig(num_poses=3000, two_floors=True, seed=2))
    positions = sim.world_T_phone_true[:, :3, 3]
    pg = build_path_graph_from_arrays(positions)
    floor_of = {n: pg.graph.nodes[n]["floor"] for n in pg.graph.nodes}
    low = next(n for n in pg.graph.nodes if floor_of[n] == 0)
    high = next(n for n in pg.graph.nodes if floor_of[n] == 1)

    route = plan_guided_route(pg, NodeEnd(low), NodeEnd(high))
    assert route.floors == [0, 1]
    assert any(
        step.kind == "stairs" and "up" in step.instruction and "floor 2" in step.instruction
        for step in route.steps
    )
    with pytest.raises(Unreachable, match="without stairs"):
        plan_walk(pg, NodeEnd(low), NodeEnd(high), avoid=frozenset({STAIRS}))


# --------------------------------------------------------------------------- properties

grid_points = st.lists(
    st.tuples(st.integers(0, 6), st.integers(0, 6)), min_size=2, max_size=25
).map(lambda p: [q for k, q in enumerate(p) if k == 0 or q != p[k - 1]])
float_points = st.lists(
    st.tuples(st.floats(0, 10, width=32), st.floats(0, 10, width=32)), min_size=2, max_size=30
)


def pose_to_other_segments_m(walk) -> float:
    """Smallest distance of a pose to a segment it is not an end of (inf if there is none)."""
    a, b = walk[:-1], walk[1:]
    smallest = math.inf
    for k in range(len(walk)):
        others = [j for j in range(len(a)) if j not in (k - 1, k)]
        if others:
            distance_m = point_segment_distance(walk[k][None], a[others], b[others]).min()
            smallest = min(smallest, float(distance_m))
    return smallest


def as_walk(points_xz):
    p = np.asarray(points_xz, dtype=np.float64).reshape(-1, 2)
    return np.column_stack([p[:, 0], np.zeros(len(p)), p[:, 1]])


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(grid_points)
def test_every_junction_lies_on_two_non_adjacent_segments(points):
    """Grid points give every degenerate case: shared endpoints, touches, collinear overlaps."""
    walk = as_walk(points)
    pg = build_path_graph_from_arrays(walk, params=CROSSINGS_ONLY)
    assert nx.is_connected(pg.graph) or pg.graph.number_of_nodes() <= 1

    a, b = walk[:-1], walk[1:]
    for junction in junctions(pg):
        d = point_segment_distance(position(pg, junction)[None], a, b)[0]
        on = np.flatnonzero(d <= 1e-6)
        # Two segments at least two apart (adjacent ones share an endpoint: never a junction).
        assert len(on) >= 2, (junction, on)
        assert on.max() - on.min() >= 2, (junction, on)
    # A walk that meets itself nowhere (no pose on a non-adjacent segment, no crossing) has none.
    if crossings_brute_force(points) == 0 and pose_to_other_segments_m(walk) > 1e-9:
        assert junctions(pg) == []


@settings(max_examples=200, deadline=None)
@given(float_points)
def test_random_polylines_get_one_junction_per_crossing(points):
    """In general position, junctions are exactly the proper crossings of non-adjacent
    segments, and splitting keeps the total length."""
    walk = as_walk(points)
    walk[:, [0, 2]] += np.random.default_rng(len(points)).normal(0, 1e-3, (len(walk), 2))
    # General position, well above the 1e-6 m at which the builder calls points the same.
    assume(np.linalg.norm(np.diff(walk, axis=0), axis=1).min() > 1e-2)
    crossings = crossing_points_brute_force(walk[:, [0, 2]])
    special = np.array([*crossings, *walk[:, [0, 2]]])
    gaps = np.linalg.norm(special[:, None] - special[None], axis=2)[
        np.triu_indices(len(special), 1)
    ]
    assume(gaps.size == 0 or gaps.min() > 1e-4)
    assume(pose_to_other_segments_m(walk) > 1e-4)  # no pose (almost) on another segment
    pg = build_path_graph_from_arrays(walk, params=CROSSINGS_ONLY)
    assert len(junctions(pg)) == len(crossings)
    assert total_length_m(pg) == pytest.approx(walk_length_m(walk), rel=1e-9)
    assert nx.is_connected(pg.graph)


@settings(max_examples=100, deadline=None)
@given(float_points)
def test_random_polylines_with_default_parameters_give_a_sound_graph(points):
    walk = as_walk(points)
    pg = build_path_graph_from_arrays(walk)
    G = pg.graph
    assert G.number_of_nodes() >= 1
    assert nx.is_connected(G)
    for u, v, d in G.edges(data=True):
        assert u != v
        assert d["kind"] == WALK
        straight_m = float(np.linalg.norm(position(pg, u) - position(pg, v)))
        assert d["length_m"] >= straight_m - 1e-6  # a junction may sit 1e-6 m off a pose
    for node, data in G.nodes(data=True):
        assert (data["kind"] == NODE) == (data["pose_index"] is not None)
        if data["kind"] == NODE:
            assert node == data["pose_index"]
        else:
            assert node >= len(walk)
