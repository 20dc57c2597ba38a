"""What routing keeps per path graph (node positions, floors, junctions, walk edges as arrays) is
made again when the graph gains or loses a node or an edge (issue 16)."""

from __future__ import annotations

import math

import networkx as nx
import pytest

from app.domain.navigation.instructions import plan_guided_route
from app.domain.navigation.path_graph import JUNCTION, NODE, WALK, PathGraph
from app.domain.navigation.routing import NodeEnd, PositionEnd, Unreachable, node_lookups


def square() -> PathGraph:
    """A 10 m square 0-1-2-3-0 on one floor; node 0 is a junction (a stub 0-4 leaves it)."""
    corners = [(0.0, 0.0, 0.0), (10.0, 0.0, 0.0), (10.0, 0.0, -10.0), (0.0, 0.0, -10.0)]
    G: nx.Graph[int] = nx.Graph()
    for i, p in enumerate([*corners, (-3.0, 0.0, 0.0)]):
        G.add_node(i, position_m=p, floor=0, kind=JUNCTION if i == 0 else NODE, pose_index=i)
    for u, v in [(0, 1), (1, 2), (2, 3), (3, 0), (0, 4)]:
        length_m = math.dist(G.nodes[u]["position_m"], G.nodes[v]["position_m"])
        G.add_edge(u, v, length_m=length_m, kind=WALK, floor=0)
    return PathGraph(graph=G, floor_levels_m=(0.0,))


def test_the_table_holds_each_node_and_the_junctions():
    pg = square()
    lookups = node_lookups(pg)
    points, junctions = lookups.point_of_node, lookups.junctions
    assert points[2] == (10.0, 0.0, -10.0)
    assert junctions == {0}
    assert node_lookups(pg).point_of_node is points  # made once


def test_a_removed_edge_is_not_walked_on_or_snapped_onto_on_the_next_route():
    pg = square()
    assert plan_guided_route(pg, NodeEnd(1), NodeEnd(0)).nodes == [1, 0]
    beside_0_1 = PositionEnd((5.0, 0.0, 0.5))
    assert plan_guided_route(pg, beside_0_1, NodeEnd(3)).polyline_m[0] == (5.0, 0.0, 0.0)
    pg.graph.remove_edge(0, 1)
    assert plan_guided_route(pg, NodeEnd(1), NodeEnd(0)).nodes == [1, 2, 3, 0]
    assert plan_guided_route(pg, beside_0_1, NodeEnd(3)).polyline_m[0] != (5.0, 0.0, 0.0)
    pg.graph.remove_edge(2, 3)
    with pytest.raises(Unreachable):
        plan_guided_route(pg, NodeEnd(1), NodeEnd(0))


def test_an_added_edge_between_known_nodes_is_snapped_onto():
    pg = square()
    on_the_diagonal = PositionEnd((5.0, 0.0, -5.0))
    assert plan_guided_route(pg, on_the_diagonal, NodeEnd(0)).polyline_m[0] != (5.0, 0.0, -5.0)
    pg.graph.add_edge(1, 3, length_m=math.hypot(10.0, 10.0), kind=WALK, floor=0)
    assert plan_guided_route(pg, on_the_diagonal, NodeEnd(0)).polyline_m[0] == (5.0, 0.0, -5.0)


def test_an_added_node_and_edge_are_routed_to_and_snapped_onto():
    pg = square()
    plan_guided_route(pg, NodeEnd(1), NodeEnd(3))
    pg.graph.add_node(5, position_m=(10.0, 0.0, 6.0), floor=0, kind=NODE, pose_index=None)
    pg.graph.add_edge(1, 5, length_m=6.0, kind=WALK, floor=0)
    route = plan_guided_route(pg, NodeEnd(0), NodeEnd(5))
    assert route.nodes == [0, 1, 5]
    assert route.polyline_m[-1] == (10.0, 0.0, 6.0)
    assert route.length_m == pytest.approx(16.0)
    snapped = plan_guided_route(pg, PositionEnd((10.5, 0.0, 4.0)), NodeEnd(0))
    assert snapped.polyline_m[0] == pytest.approx((10.0, 0.0, 4.0))
