"""The search over adjacency lists finds the path networkx's bidirectional Dijkstra finds, ties
included (issue 16: routes must not change when the search is made cheaper)."""

from __future__ import annotations

import itertools
from typing import Any

import networkx as nx
import numpy as np
import pytest

from app.domain.navigation.path_graph import ELEVATOR, STAIRS, WALK
from app.domain.navigation.shortest_path import bidirectional_dijkstra, neighbour_lists

AVOIDS = [frozenset(), frozenset({STAIRS}), frozenset({ELEVATOR}), frozenset({STAIRS, ELEVATOR})]


def random_graph(seed: int) -> nx.Graph[int]:
    """A sparse random graph whose edges have small whole lengths (so many equal-length paths),
    some zero, of all three kinds, with node ids out of order and gaps among them."""
    rng = np.random.default_rng(seed)
    n = int(rng.integers(2, 40))
    ids = [int(i) for i in rng.permutation(3 * n)[:n]]
    G: nx.Graph[int] = nx.Graph()
    G.add_nodes_from(ids)
    for _ in range(int(rng.integers(n - 1, 3 * n))):
        u, v = (ids[int(i)] for i in rng.integers(0, n, size=2))
        if u != v:
            kind = str(rng.choice([WALK, WALK, WALK, STAIRS, ELEVATOR]))
            G.add_edge(u, v, length_m=float(rng.integers(0, 4)), kind=kind)
    return G


def networkx_path(
    G: nx.Graph[int],
    source: int,
    target: int,
    avoid: frozenset[str],
    changed: dict[tuple[int, int], float],
) -> list[int] | None:
    def weight(u: int, v: int, data: dict[str, Any]) -> float | None:
        if data["kind"] in avoid:
            return None
        return changed.get((u, v), float(data["length_m"]))

    try:
        return list(nx.bidirectional_dijkstra(G, source, target, weight=weight)[1])
    except nx.NetworkXNoPath:
        return None


@pytest.mark.parametrize("seed", range(60))
def test_every_path_is_the_one_networkx_finds(seed):
    G = random_graph(seed)
    for avoid in AVOIDS:
        neighbours = neighbour_lists(G, avoid=avoid)
        for source, target in itertools.product(list(G)[:12], repeat=2):
            want = networkx_path(G, source, target, avoid, {})
            got = bidirectional_dijkstra(neighbours, source, target)
            assert got == want, (seed, source, target, avoid)


@pytest.mark.parametrize("seed", range(30))
def test_changed_edge_costs_are_the_ones_networkx_would_use(seed):
    G = random_graph(seed)
    edges = list(G.edges)
    rng = np.random.default_rng(seed)
    for _ in range(40):
        changed: dict[tuple[int, int], float] = {}
        costs: dict[int, dict[int, float]] = {}
        for k in rng.integers(0, len(edges), size=min(2, len(edges))) if edges else []:
            u, v = edges[int(k)]
            cost = float(rng.integers(0, 3)) / 2
            changed[u, v] = changed[v, u] = cost
            costs.setdefault(u, {})[v] = cost
            costs.setdefault(v, {})[u] = cost
        source, target = (list(G)[int(i)] for i in rng.integers(0, len(G), size=2))
        avoid = AVOIDS[int(rng.integers(0, len(AVOIDS)))]
        want = networkx_path(G, source, target, avoid, changed)
        neighbours = neighbour_lists(G, avoid=avoid)
        got = bidirectional_dijkstra(neighbours, source, target, changed_costs=costs)
        assert got == want, (seed, source, target, avoid, changed)


def test_a_square_with_two_equal_ways_goes_the_way_networkx_goes():
    """0-1-2 and 0-3-2 are both 2 m; networkx expands 0's neighbours in insertion order."""
    G: nx.Graph[int] = nx.Graph()
    for u, v in [(0, 1), (1, 2), (0, 3), (3, 2)]:
        G.add_edge(u, v, length_m=1.0, kind=WALK)
    assert bidirectional_dijkstra(neighbour_lists(G), 0, 2) == networkx_path(
        G, 0, 2, frozenset(), {}
    )
    assert bidirectional_dijkstra(neighbour_lists(G), 0, 0) == [0]


def test_an_avoided_kind_is_never_used_and_can_leave_no_path():
    G: nx.Graph[int] = nx.Graph()
    G.add_edge(0, 1, length_m=1.0, kind=WALK)
    G.add_edge(1, 2, length_m=4.0, kind=STAIRS)
    assert bidirectional_dijkstra(neighbour_lists(G), 0, 2) == [0, 1, 2]
    assert bidirectional_dijkstra(neighbour_lists(G, avoid=frozenset({STAIRS})), 0, 2) is None


def outcome(search: Any) -> object:
    try:
        return search()
    except ValueError as err:
        return ("ValueError", str(err))


@pytest.mark.parametrize("seed", range(20))
def test_a_negative_cost_is_refused_where_networkx_refuses_it(seed):
    G = random_graph(seed)
    rng = np.random.default_rng(seed)
    for u, v in G.edges:
        G.edges[u, v]["length_m"] -= float(rng.integers(0, 2))
    neighbours = neighbour_lists(G)
    outcomes = []
    for source, target in itertools.product(list(G)[:10], repeat=2):
        want = outcome(lambda s=source, t=target: networkx_path(G, s, t, frozenset(), {}))
        got = outcome(lambda s=source, t=target: bidirectional_dijkstra(neighbours, s, t))
        assert got == want, (seed, source, target)
        outcomes.append(got)
    if seed == 0:
        assert ("ValueError", "Contradictory paths found: negative weights?") in outcomes
