"""Routing on the path graph (issue 5, item 2): shortest routes, avoidance and position snapping
in the y-up map frame. What a walker hears is app.domain.navigation.instructions'
(tests/unit/test_instructions.py); the per-leg steps routing once wrote retired (issue 26)."""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence

import networkx as nx
import numpy as np
import numpy.typing as npt
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from app.domain.navigation.path_graph import (
    ELEVATOR,
    JUNCTION,
    NODE,
    STAIRS,
    WALK,
    Anchor,
    PathGraph,
)
from app.domain.navigation.routing import (
    AmbiguousEndpoint,
    Endpoint,
    NodeEnd,
    PoiEnd,
    PositionEnd,
    RouteError,
    TagEnd,
    UnknownEndpoint,
    Unreachable,
    plan_walk,
    search_pois,
    signed_turn_deg,
)

Point = tuple[float, float, float]
STOREY_M = 3.0


# --------------------------------------------------------------------------- builders


def make_graph(
    points: Sequence[Sequence[float]],
    *,
    edges: Sequence[tuple[int, int]] | None = None,
    kinds: Sequence[str] | None = None,
    floors: Sequence[int] | None = None,
    node_kinds: Sequence[str] | None = None,
    floor_levels_m: Sequence[float] = (0.0,),
    tags: dict[int, int] | None = None,
    pois: Sequence[tuple[str, int]] | Sequence[tuple[str, int, Point]] = (),
) -> PathGraph:
    """A PathGraph with node i at points[i]; edges default to the chain 0-1-2-…, all walk.

    ``tags``: tag id → node; ``pois``: (name, node) or (name, node, position of the thing).
    """
    G: nx.Graph[int] = nx.Graph()
    floors = floors if floors is not None else [0] * len(points)
    for i, p in enumerate(points):
        G.add_node(
            i,
            position_m=tuple(float(c) for c in p),
            floor=floors[i],
            kind=node_kinds[i] if node_kinds else NODE,
            pose_index=i,
        )
    edges = edges if edges is not None else [(i, i + 1) for i in range(len(points) - 1)]
    kinds = kinds if kinds is not None else [WALK] * len(edges)
    for (u, v), kind in zip(edges, kinds, strict=True):
        length_m = float(np.linalg.norm(np.subtract(points[u], points[v])))
        G.add_edge(u, v, length_m=length_m, kind=kind, floor=min(floors[u], floors[v]))

    def anchor(name: str, node: int, at: Sequence[float] | None = None) -> Anchor:
        position = p3(at if at is not None else points[node])
        return Anchor(name=name, node=node, position_m=position, floor=floors[node])

    return PathGraph(
        graph=G,
        floor_levels_m=tuple(floor_levels_m),
        tags={tag: anchor(f"tag {tag}", node) for tag, node in (tags or {}).items()},
        pois=tuple(anchor(*poi) for poi in pois),
    )


def p3(values: npt.ArrayLike) -> Point:
    x, y, z = (float(c) for c in np.asarray(values, dtype=np.float64))
    return (x, y, z)


def make_polyline(*corners: npt.ArrayLike, spacing_m: float = 1.0) -> list[Point]:
    """Points every ~spacing_m along straight runs between the corners (x, y, z)."""
    out = [p3(corners[0])]
    for a, b in itertools.pairwise(np.asarray(c, dtype=np.float64) for c in corners):
        n = max(1, math.ceil(np.linalg.norm(b - a) / spacing_m))
        out += [p3(a + k / n * (b - a)) for k in range(1, n + 1)]
    return out


def make_two_floors() -> PathGraph:
    """Floor 0 corridor and floor 1 corridor (3 m up), joined by short stairs at one end and an
    elevator at the far end.

        floor 1:  B0 (0,3,0) ── B1 (6,3,0)                B2 (0,3,-20) ── B0
                                  │ stairs (5 m)           │ elevator (3 m)
        floor 0:  A0 (0,0,0) ── A1 (2,0,0)                A2 (0,0,-20) ── A0
    Via stairs A0→B0 is 2 + 5 + 6 = 13 m; via the elevator 20 + 3 + 20 = 43 m.
    """
    points = [
        (0.0, 0.0, 0.0),  # 0 A0, tag 300
        (2.0, 0.0, 0.0),  # 1 A1, foot of the stairs
        (0.0, 0.0, -20.0),  # 2 A2, elevator floor 0
        (0.0, 3.0, 0.0),  # 3 B0, Room 209
        (6.0, 3.0, 0.0),  # 4 B1, top of the stairs
        (0.0, 3.0, -20.0),  # 5 B2, elevator floor 1
    ]
    edges = [(0, 1), (0, 2), (3, 4), (3, 5), (1, 4), (2, 5)]
    kinds = [WALK, WALK, WALK, WALK, STAIRS, ELEVATOR]
    return make_graph(
        points,
        edges=edges,
        kinds=kinds,
        floors=[0, 0, 0, 1, 1, 1],
        floor_levels_m=(0.0, STOREY_M),
        tags={300: 0},
        pois=[("Room 209", 3)],
    )


def rot_y(angle_deg: float) -> np.ndarray:
    """Rotation about +y (up) by angle_deg, right-handed: counter-clockwise seen from above."""
    c, s = math.cos(math.radians(angle_deg)), math.sin(math.radians(angle_deg))
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


# --------------------------------------------------------------------------- length ≥ straight line


Case = tuple[PathGraph, Endpoint, Endpoint, frozenset[str]]


@st.composite
def graphs_and_ends(draw: st.DrawFn) -> Case:
    """A random connected graph on one or two floors, two ends (nodes or positions), an avoid."""
    n = draw(st.integers(2, 10))
    coordinate = st.floats(-10, 10, allow_nan=False)
    floors = [draw(st.integers(0, 1)) for _ in range(n)]
    points = [(draw(coordinate), STOREY_M * f, draw(coordinate)) for f in floors]
    edges = {(draw(st.integers(0, i - 1)), i) for i in range(1, n)}  # a spanning tree
    edges |= {
        (min(u, v), max(u, v))
        for u, v in draw(st.lists(st.tuples(st.integers(0, n - 1), st.integers(0, n - 1))))
        if u != v
    }
    edge_list = sorted(edges)
    kinds = [
        WALK if floors[u] == floors[v] else draw(st.sampled_from([STAIRS, ELEVATOR]))
        for u, v in edge_list
    ]
    pg = make_graph(
        points, edges=edge_list, kinds=kinds, floors=floors, floor_levels_m=(0.0, STOREY_M)
    )
    end = st.one_of(
        st.builds(NodeEnd, st.integers(0, n - 1)),
        st.builds(
            PositionEnd,
            st.tuples(coordinate, st.floats(-1.0, 4.0, allow_nan=False), coordinate),
        ),
    )
    avoid = draw(st.sampled_from([frozenset(), frozenset({STAIRS}), frozenset({STAIRS, ELEVATOR})]))
    return pg, draw(end), draw(end), avoid


def distance_to_segment(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    ab = b - a
    length2 = float(ab @ ab)
    t = 0.0 if length2 == 0.0 else float(np.clip((p - a) @ ab / length2, 0.0, 1.0))
    return float(np.linalg.norm(p - (a + t * ab)))


def nearest_walk_distance_xz(pg: PathGraph, position: npt.ArrayLike) -> tuple[float, int]:
    """Brute force: the floor a position belongs to and its x–z distance to that floor's path."""
    G = pg.graph
    xyz = np.asarray(position, dtype=np.float64)
    present = sorted({d["floor"] for _, d in G.nodes(data=True)})
    floor = min(present, key=lambda f: abs(pg.floor_levels_m[f] - xyz[1]))
    p = xyz[[0, 2]]
    walk = [(u, v) for u, v, d in G.edges(data=True) if d["kind"] == WALK and d["floor"] == floor]
    if walk:
        best = min(
            distance_to_segment(
                p,
                np.array(G.nodes[u]["position_m"])[[0, 2]],
                np.array(G.nodes[v]["position_m"])[[0, 2]],
            )
            for u, v in walk
        )
    else:
        best = min(
            float(np.linalg.norm(np.array(d["position_m"])[[0, 2]] - p))
            for _, d in G.nodes(data=True)
            if d["floor"] == floor
        )
    return best, floor


Join = tuple[str, int, int]  # ("edge", u, v) or ("node", n, n)


def joins(pg: PathGraph, end: Endpoint, at: np.ndarray) -> list[Join]:
    """Every way the route end at ``at`` may be joined to the graph (several when edges overlap)."""
    G = pg.graph
    if isinstance(end, NodeEnd):
        return [("node", end.node_id, end.node_id)]
    floor = nearest_walk_distance_xz(pg, at)[1]
    position = {n: np.array(d["position_m"]) for n, d in G.nodes(data=True)}
    on_edges: list[Join] = [
        ("edge", u, v)
        for u, v, d in G.edges(data=True)
        if d["kind"] == WALK
        and d["floor"] == floor
        and distance_to_segment(at, position[u], position[v]) < 1e-6
    ]
    return on_edges or [("node", n, n) for n in G if np.linalg.norm(position[n] - at) < 1e-6]


def oracle_length(
    pg: PathGraph, ends: Sequence[tuple[Join, np.ndarray]], avoid: frozenset[str]
) -> float | None:
    """Shortest length between two points joined to the graph as given, on a copy of the graph
    with both inserted as nodes, by networkx's plain Dijkstra; None when unreachable."""
    H: nx.Graph[object] = nx.Graph()
    H.add_nodes_from(pg.graph.nodes)
    for n1, n2, d in pg.graph.edges(data=True):
        if d["kind"] not in avoid:
            H.add_edge(n1, n2, length_m=d["length_m"])
    position: dict[object, np.ndarray] = {
        n: np.array(d["position_m"]) for n, d in pg.graph.nodes(data=True)
    }
    for name, ((how, node_u, node_v), p) in zip(("start", "goal"), ends, strict=True):
        position[name] = p
        if how == "node":
            H.add_edge(name, node_u, length_m=0.0)
            continue
        u: object = node_u
        v: object = node_v
        if not H.has_edge(u, v):  # already split by the start: find its half
            u, v = next(
                (a, b)
                for a, b in (("start", v), (u, "start"))
                if H.has_edge(a, b) and distance_to_segment(p, position[a], position[b]) < 1e-6
            )
        H.remove_edge(u, v)
        H.add_edge(u, name, length_m=float(np.linalg.norm(position[u] - p)))
        H.add_edge(name, v, length_m=float(np.linalg.norm(position[v] - p)))
    try:
        return float(nx.dijkstra_path_length(H, "start", "goal", weight="length_m"))
    except nx.NetworkXNoPath:
        return None


@settings(max_examples=300, deadline=None)
@given(graphs_and_ends())
def test_route_is_shortest_and_not_shorter_than_the_straight_line(case: Case) -> None:
    pg, start, goal, avoid = case
    try:
        route = plan_walk(pg, start, goal, avoid=avoid)
    except Unreachable:
        return  # when that is right: test_unreachable_only_when_no_route_exists
    polyline = np.array(route.polyline_m)
    first, last = polyline[0], polyline[-1]
    for end, at in ((start, first), (goal, last)):
        if isinstance(end, NodeEnd):
            np.testing.assert_allclose(at, pg.graph.nodes[end.node_id]["position_m"], atol=1e-9)
        else:
            assert isinstance(end, PositionEnd)
            best_m, floor = nearest_walk_distance_xz(pg, end.position_m)
            xz_m = float(np.linalg.norm((at - np.array(end.position_m))[[0, 2]]))
            assert xz_m == pytest.approx(best_m, abs=1e-6)
            assert abs(at[1] - STOREY_M * floor) < 1e-6  # on the position's floor
    segments = np.linalg.norm(np.diff(polyline, axis=0), axis=1)
    assert route.length_m == pytest.approx(float(segments.sum()), abs=1e-9)
    assert route.length_m >= float(np.linalg.norm(last - first)) - 1e-9
    # As short as the shortest path with both ends inserted into the graph (one of the ways to
    # insert them, when the nearest point lies on several edges).
    options = [
        oracle_length(pg, [(j, first), (k, last)], avoid)
        for j in joins(pg, start, first)
        for k in joins(pg, goal, last)
    ]
    assert any(o is not None and route.length_m == pytest.approx(o, abs=1e-6) for o in options)


@settings(max_examples=150, deadline=None)
@given(graphs_and_ends())
def test_unreachable_only_when_no_route_exists(case: Case) -> None:
    pg, start, goal, avoid = case
    if not (isinstance(start, NodeEnd) and isinstance(goal, NodeEnd)):
        return
    a = np.array(pg.graph.nodes[start.node_id]["position_m"])
    b = np.array(pg.graph.nodes[goal.node_id]["position_m"])
    expected = oracle_length(
        pg, [(("node", start.node_id, 0), a), (("node", goal.node_id, 0), b)], avoid
    )
    if expected is None:
        message = f"no route from node {start.node_id} to node {goal.node_id}"
        with pytest.raises(Unreachable, match=f"^{message}"):
            plan_walk(pg, start, goal, avoid=avoid)
    else:
        route = plan_walk(pg, start, goal, avoid=avoid)
        assert route.length_m == pytest.approx(expected, abs=1e-6)


# --------------------------------------------------------------------------- handedness


@pytest.mark.parametrize("angle_deg", [-170.0, -90.0, -30.0, 0.0, 25.0, 90.0, 179.0])
@pytest.mark.parametrize("heading", [(0.0, 0.0, -1.0), (1.0, 0.0, 0.0), (0.6, 0.0, 0.8)])
def test_signed_turn_is_the_rotation_about_y_up(heading: Point, angle_deg: float) -> None:
    """Rotating the heading by +θ about +y (counter-clockwise from above) is a turn of +θ (left)."""
    turned = rot_y(angle_deg) @ np.array(heading)
    assert signed_turn_deg(heading, turned) == pytest.approx(angle_deg, abs=1e-9)


def test_walking_minus_z_then_minus_x_is_a_left_turn() -> None:
    # Facing −z, x is to the right, so −x is to the left.
    assert signed_turn_deg((0, 0, -1), (-1, 0, 0)) == pytest.approx(90.0)
    assert signed_turn_deg((0, 0, -1), (1, 0, 0)) == pytest.approx(-90.0)


# --------------------------------------------------------------------------- thresholds


# --------------------------------------------------------------------------- noise, corridors


def make_out_and_back(
    length_m: float = 20.0, spacing_m: float = 1.0, gap_m: float = 0.12
) -> PathGraph:
    """One corridor walked out along −z and back: two nearly coincident passes, joined by junction
    nodes where the noisy passes cross, each junction linked to the four segment ends around it.

    Nodes 0..n-1: the way out (x ≈ +gap/2 ± noise), n..2n-1: the way back (x ≈ −gap/2),
    then the junctions. "Exit" is the far end (node n, where the way back starts).
    """
    rng = np.random.default_rng(3)
    zs = -np.arange(0.0, length_m + 1e-9, spacing_m)
    n = len(zs)
    out = [(gap_m / 2 + rng.normal(0, 0.03), 0.0, float(z)) for z in zs]
    back = [(-gap_m / 2 + rng.normal(0, 0.03), 0.0, float(z)) for z in zs[::-1]]
    points: list[Point] = [*out, *back]
    edges = [(i, i + 1) for i in range(n - 1)] + [(n + i, n + i + 1) for i in range(n - 1)]
    node_kinds = [NODE] * (2 * n)
    for i in range(0, n - 1, 2):  # a crossing between out[i]–out[i+1] and the matching back pass
        j = 2 * n - 1 - i  # back node at the same z as out[i]
        a, b = np.array(out[i]), np.array(out[i + 1])
        c, d = np.array(points[j]), np.array(points[j - 1])
        junction = len(points)
        points.append(p3((a + b + c + d) / 4))
        node_kinds.append(JUNCTION)
        edges += [(i, junction), (i + 1, junction), (j, junction), (j - 1, junction)]
    return make_graph(points, edges=edges, node_kinds=node_kinds, pois=[("Exit", n)])


def test_out_and_back_corridor_route_does_not_zigzag() -> None:
    pg = make_out_and_back()
    route = plan_walk(pg, PositionEnd((0.0, 1.2, 0.2)), PoiEnd("Exit"))
    z = np.array(route.polyline_m)[:, 2]
    assert np.all(np.diff(z) <= 1e-9)  # monotone progress along −z
    assert route.length_m < 20.5
    # Either direction.
    back = plan_walk(pg, PoiEnd("Exit"), NodeEnd(0))
    assert np.all(np.diff(np.array(back.polyline_m)[:, 2]) >= -1e-9)


# --------------------------------------------------------------------------- floors, avoid


def test_default_route_takes_the_shorter_stairs() -> None:
    route = plan_walk(make_two_floors(), TagEnd(300), PoiEnd("Room 209"))
    assert route.length_m == pytest.approx(13.0)
    assert route.floors == [0, 1]
    assert route.nodes == [0, 1, 4, 3]
    assert route.steps == []  # the walk alone: plan_guided_route words it


def test_avoid_stairs_takes_the_elevator() -> None:
    route = plan_walk(
        make_two_floors(), TagEnd(300), PoiEnd("Room 209"), avoid=frozenset({"stairs"})
    )
    assert route.length_m == pytest.approx(43.0)
    assert route.nodes == [0, 2, 5, 3]
    down = plan_walk(
        make_two_floors(), PoiEnd("Room 209"), TagEnd(300), avoid=frozenset({"stairs"})
    )
    assert down.nodes == [3, 5, 2, 0]
    assert down.floors == [1, 0]


def test_avoid_stairs_and_elevator_explains_why_it_fails() -> None:
    with pytest.raises(Unreachable) as caught:
        plan_walk(
            make_two_floors(),
            TagEnd(300),
            PoiEnd("Room 209"),
            avoid=frozenset({"stairs", "elevator"}),
        )
    assert str(caught.value) == (
        "no route from tag 300 to 'Room 209' without stairs or elevators: "
        "the goal is on floor 2 and every way there uses stairs or an elevator"
    )
    assert caught.value.avoid == {"stairs", "elevator"}


def test_avoid_elevator_when_only_an_elevator_goes_there() -> None:
    pg = make_two_floors()
    pg.graph.remove_edge(1, 4)  # no stairs any more
    with pytest.raises(
        Unreachable,
        match=r"without elevators: the goal is on floor 2 and every way there uses an elevator$",
    ):
        plan_walk(pg, TagEnd(300), PoiEnd("Room 209"), avoid=frozenset({"elevator"}))


def test_avoid_explains_a_detour_through_another_floor() -> None:
    # Two halves of floor 0 joined only by going up the stairs and down again.
    points = [(0, 0, 0), (5, 0, 0), (5, 3, 0), (10, 3, 0), (10, 0, 0), (15, 0, 0)]
    pg = make_graph(
        points,
        kinds=[WALK, STAIRS, WALK, STAIRS, WALK],
        floors=[0, 0, 1, 1, 0, 0],
        floor_levels_m=(0.0, 3.0),
    )
    assert plan_walk(pg, NodeEnd(0), NodeEnd(5)).floors == [0, 1, 0]
    with pytest.raises(
        Unreachable,
        match="the goal is on floor 1 like the start, but every way there uses stairs",
    ):
        plan_walk(pg, NodeEnd(0), NodeEnd(5), avoid=frozenset({"stairs"}))


def test_disconnected_goal_is_unreachable_whatever_is_avoided() -> None:
    pg = make_graph([(0, 0, 0), (1, 0, 0), (5, 0, 0), (6, 0, 0)], edges=[(0, 1), (2, 3)])
    for avoid in (frozenset(), frozenset({"stairs"})):
        with pytest.raises(Unreachable, match="parts of the map that are not connected"):
            plan_walk(pg, NodeEnd(0), NodeEnd(3), avoid=avoid)


def test_only_stairs_and_elevator_can_be_avoided() -> None:
    with pytest.raises(RouteError, match="cannot avoid walk"):
        plan_walk(make_two_floors(), NodeEnd(0), NodeEnd(1), avoid=frozenset({"walk"}))


# --------------------------------------------------------------------------- endpoints


@pytest.mark.parametrize(
    ("end", "kind", "message"),
    [
        (TagEnd(999), "tag", "unknown tag 999"),
        (NodeEnd(42), "node", "unknown node 42"),
        (PoiEnd("Cafeteria"), "poi", "no point of interest named 'Cafeteria'"),
    ],
)
def test_unknown_endpoints_name_the_value(end: Endpoint, kind: str, message: str) -> None:
    for start, goal in ((end, TagEnd(300)), (TagEnd(300), end)):
        with pytest.raises(UnknownEndpoint) as caught:
            plan_walk(make_two_floors(), start, goal)
        assert caught.value.kind == kind
        assert str(caught.value) == message


def test_unknown_poi_suggests_near_names() -> None:
    with pytest.raises(UnknownEndpoint, match=r"'Room 20'; did you mean 'Room 209'\?"):
        plan_walk(make_two_floors(), TagEnd(300), PoiEnd("Room 20"))


def test_poi_names_match_exactly_then_case_insensitively() -> None:
    pois = [("Room 209", 0), ("ROOM 209", 2), ("Lobby", 1), ("Restroom", 2), ("restroom", 2)]
    pg = make_graph([(0, 0, 0), (5, 0, 0), (10, 0, 0)], pois=pois)
    assert plan_walk(pg, NodeEnd(1), PoiEnd("Room 209")).nodes[-1] == 0
    assert plan_walk(pg, NodeEnd(1), PoiEnd("ROOM 209")).nodes[-1] == 2
    assert plan_walk(pg, NodeEnd(0), PoiEnd("lobby")).nodes[-1] == 1
    # Two entries at one place are one place.
    assert plan_walk(pg, NodeEnd(0), PoiEnd("RESTROOM")).nodes[-1] == 2
    with pytest.raises(AmbiguousEndpoint) as caught:
        plan_walk(pg, NodeEnd(1), PoiEnd("room 209"))
    assert (
        str(caught.value) == "'room 209' matches several points of interest: 'Room 209', 'ROOM 209'"
    )
    assert caught.value.candidates == ("Room 209", "ROOM 209")


def test_position_snaps_to_the_nearest_edge_point_on_its_floor() -> None:
    pg = make_two_floors()
    # Above the floor-0 corridor A0–A2 but at the height of floor 1: joins B0–B2 at z = −7.
    route = plan_walk(pg, PositionEnd((0.4, 2.6, -7.0)), PoiEnd("Room 209"))
    np.testing.assert_allclose(route.polyline_m[0], (0.0, 3.0, -7.0), atol=1e-9)
    assert route.length_m == pytest.approx(7.0)
    assert route.floors == [1]
    assert route.nodes == [3]
    # Same x–z at floor-0 height: joins A0–A2, and the stairs are the way up.
    low = plan_walk(pg, PositionEnd((0.4, 0.3, -7.0)), PoiEnd("Room 209"))
    np.testing.assert_allclose(low.polyline_m[0], (0.0, 0.0, -7.0), atol=1e-9)
    assert low.length_m == pytest.approx(7.0 + 13.0)
    assert low.floors == [0, 1]


def test_position_on_an_edge_leaves_by_whichever_end_is_shorter() -> None:
    # 0 ── 1 ── 2 along −z, 10 m each; the person is 4 m from node 0, nearer to it than to 1.
    pg = make_graph([(0, 0, 0), (0, 0, -10), (0, 0, -20)])
    route = plan_walk(pg, PositionEnd((0.5, 0.0, -4.0)), NodeEnd(2))
    assert route.length_m == pytest.approx(16.0)
    assert route.nodes == [1, 2]
    np.testing.assert_allclose(route.polyline_m, [(0, 0, -4), (0, 0, -10), (0, 0, -20)], atol=1e-9)
    to_zero = plan_walk(pg, PositionEnd((0.5, 0.0, -4.0)), NodeEnd(0))
    assert to_zero.length_m == pytest.approx(4.0)
    # Both ends on edges, different edges; and both on one edge.
    both = plan_walk(pg, PositionEnd((0, 0, -4.0)), PositionEnd((0, 0, -17.0)))
    assert both.length_m == pytest.approx(13.0)
    assert both.nodes == [1]
    same = plan_walk(pg, PositionEnd((0, 0, -16.0)), PositionEnd((0, 0, -12.0)))
    assert same.length_m == pytest.approx(4.0)
    assert same.nodes == []
    np.testing.assert_allclose(same.polyline_m, [(0, 0, -16), (0, 0, -12)], atol=1e-9)


def test_position_beside_a_node_joins_it() -> None:
    pg = make_graph([(0, 0, 0), (0, 0, -10), (-10, 0, -10)])
    route = plan_walk(pg, PositionEnd((1.0, 0.0, -11.0)), NodeEnd(2))
    np.testing.assert_allclose(route.polyline_m[0], (0, 0, -10), atol=1e-9)
    assert route.nodes == [1, 2]


def test_position_must_be_finite() -> None:
    with pytest.raises(RouteError, match="3 finite numbers"):
        plan_walk(make_two_floors(), PositionEnd((0.0, math.nan, 0.0)), NodeEnd(0))


@pytest.mark.parametrize(
    "end", [NodeEnd(4), TagEnd(300), PoiEnd("Room 209"), PositionEnd((3.0, 3.0, -1.0))]
)
def test_route_to_itself_is_a_single_point(end: Endpoint) -> None:
    route = plan_walk(make_two_floors(), end, end)
    assert route.length_m == 0.0
    assert len(route.polyline_m) == 1


def test_routing_does_not_change_the_graph() -> None:
    pg = make_two_floors()
    before = (sorted(pg.graph.nodes(data=True)), sorted(pg.graph.edges(data=True)))
    plan_walk(pg, PositionEnd((0.5, 0.0, -3.0)), PositionEnd((0.0, 3.0, -5.0)))
    assert (sorted(pg.graph.nodes(data=True)), sorted(pg.graph.edges(data=True))) == before


# --------------------------------------------------------------------------- search


def test_search_pois_ranks_exact_then_prefix_then_substring() -> None:
    names = ["Classroom 2", "Room 209", "Restroom", "room", "Room 101", "Lobby"]
    pg = make_graph([(0, 0, 0)], pois=[(name, 0) for name in names])
    assert [p.name for p in search_pois(pg, "ROOM")] == [
        "room",
        "Room 101",
        "Room 209",
        "Classroom 2",
        "Restroom",
    ]
    assert [p.name for p in search_pois(pg, " lob ")] == ["Lobby"]
    assert search_pois(pg, "cafeteria") == []
    assert len(search_pois(pg, "")) == len(names)
