"""The steps' geometry, made cheap (issue 16), agrees with the straightforward numpy it replaced:
each polyline point matched to the same node (edge kinds, junctions, floors) — on random graphs
with coincident nodes."""

from __future__ import annotations

import itertools

import networkx as nx
import numpy as np
import pytest

from app.domain import instructions
from app.domain.floors import assign_floors
from app.domain.path_graph import ELEVATOR, JUNCTION, NODE, STAIRS, WALK, PathGraph

# --------------------------------------------------------------------------- points → nodes


def reference_segment_kinds(
    pg: PathGraph, xyz: np.ndarray, nodes: list[int]
) -> tuple[list[str], list[bool]]:
    """``_segment_kinds`` as it was written before it was made cheap."""
    adjacency = pg.graph.adj
    positions = {n: tuple(float(c) for c in d["position_m"]) for n, d in pg.graph.nodes.items()}
    junctions = {n for n, d in pg.graph.nodes.items() if d["kind"] == JUNCTION}
    node_m = np.array([positions[n] for n in nodes], dtype=np.float64).reshape(-1, 3)
    node_at = {tuple(p): n for p, n in zip(np.round(node_m, 9).tolist(), nodes, strict=True)}
    at = [node_at.get(tuple(p)) for p in np.round(xyz, 9).tolist()]
    junction = [n is not None and n in junctions for n in at]
    kinds = []
    for a, b in itertools.pairwise(at):
        if a is not None and b is not None and b in adjacency[a]:
            kinds.append(str(adjacency[a][b]["kind"]))
        else:
            kinds.append(WALK)
    return kinds, junction


def graph_with_coincident_nodes(seed: int) -> PathGraph:
    """Nodes on a coarse grid on two floors (so several share a position), random edges of the
    three kinds; some positions differ from a grid point by less than the rounding."""
    rng = np.random.default_rng(seed)
    G: nx.Graph[int] = nx.Graph()
    n = 30
    for i in range(n):
        x, z = (float(v) for v in rng.integers(0, 4, size=2))
        y = 3.0 * float(rng.integers(0, 2))
        if rng.random() < 0.2:
            x += 1e-11
        kind = JUNCTION if rng.random() < 0.3 else NODE
        G.add_node(i, position_m=(x, y, z), floor=int(y > 1), kind=kind, pose_index=i)
    for _ in range(3 * n):
        u, v = (int(i) for i in rng.integers(0, n, size=2))
        if u != v:
            kind = str(rng.choice([WALK, WALK, STAIRS, ELEVATOR]))
            G.add_edge(u, v, length_m=1.0, kind=kind, floor=0)
    return PathGraph(graph=G, floor_levels_m=(0.1, 2.9))


@pytest.mark.parametrize("seed", range(20))
def test_each_point_is_matched_to_the_node_the_straightforward_way_matches(seed):
    pg = graph_with_coincident_nodes(seed)
    G = pg.graph
    rng = np.random.default_rng(seed)
    for _ in range(30):
        nodes = [int(rng.integers(0, len(G)))]
        for _ in range(int(rng.integers(0, 12))):
            around = list(G.adj[nodes[-1]])
            if not around:
                break
            nodes.append(around[int(rng.integers(0, len(around)))])
        points = [tuple(float(c) for c in G.nodes[n]["position_m"]) for n in nodes]
        if rng.random() < 0.5:  # a snapped start, sometimes on a node's position
            x, y, z = points[0]
            points.insert(0, (x + float(rng.choice([0.0, 0.5])), y, z))
        xyz = np.array(points, dtype=np.float64).reshape(-1, 3)
        fast_points = [(x, y, z) for x, y, z in xyz.tolist()]
        want = reference_segment_kinds(pg, xyz, nodes)
        assert instructions._segment_kinds(pg, fast_points, nodes) == want
        floors = assign_floors(xyz[:, 1], np.asarray(pg.floor_levels_m)).tolist()
        assert instructions._point_floors(pg, fast_points) == floors


def test_a_point_shared_by_two_route_nodes_is_the_later_one():
    """Nodes 0 and 2 at one position, 0–1 stairs and 1–2 an elevator: the route 0, 1, 2's first
    point is taken for node 2 (the last route node there), so both segments read "elevator"."""
    G: nx.Graph[int] = nx.Graph()
    for i, p in enumerate([(0.0, 0.0, 0.0), (0.0, 3.0, 0.0), (0.0, 0.0, 0.0)]):
        G.add_node(i, position_m=p, floor=int(p[1] > 1), kind=NODE, pose_index=i)
    G.add_edge(0, 1, length_m=3.0, kind=STAIRS, floor=0)
    G.add_edge(1, 2, length_m=3.0, kind=ELEVATOR, floor=0)
    pg = PathGraph(graph=G, floor_levels_m=(0.0, 3.0))
    points = [(0.0, 0.0, 0.0), (0.0, 3.0, 0.0), (0.0, 0.0, 0.0)]
    want = reference_segment_kinds(pg, np.array(points), [0, 1, 2])
    assert instructions._segment_kinds(pg, points, [0, 1, 2]) == want
    assert want == ([ELEVATOR, ELEVATOR], [False, False, False])
