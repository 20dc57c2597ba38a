"""networkx's bidirectional Dijkstra over a path graph's adjacency made once (issue 16).

    neighbours = neighbour_lists(G)                          # once per graph
    path = bidirectional_dijkstra(neighbours, 3, 17, avoid=frozenset({"stairs"}))
    # [3, 4, 9, 17], or None when 17 cannot be reached

It is ``networkx.bidirectional_dijkstra(G, source, target, weight=…)`` (networkx 3.x) step for step
— the same alternation of directions, the same heap entries ``(distance, counter, node)``, the
neighbours in ``G.adj`` order — so on equal-length alternatives it returns the same path. What it
saves is networkx's dispatch and a Python weight call per edge: the weight is the edge's
``length_m``, an edge whose ``kind`` is in ``avoid`` is hidden, and ``changed_costs`` gives the
edges whose cost a route end on them changes (:mod:`app.domain.routing`).
"""

from __future__ import annotations

from collections.abc import Mapping
from heapq import heappop, heappush
from itertools import count
from typing import TypeAlias

import networkx as nx

#: node → its neighbours in ``G.adj`` order, each (neighbour, ``length_m`` as a float, ``kind``).
Neighbours: TypeAlias = dict[int, tuple[tuple[int, float, str], ...]]
#: node → {neighbour → the cost of the edge between them, in place of its ``length_m``}; an edge
#: is listed from both ends.
ChangedCosts: TypeAlias = Mapping[int, Mapping[int, float]]


def neighbour_lists(G: nx.Graph[int]) -> Neighbours:
    """Each node's neighbours in ``G.adj`` order with the edge's length and kind (made once per
    graph: a change to the graph is not seen by lists made before it)."""
    return {
        v: tuple((w, float(data["length_m"]), data["kind"]) for w, data in around.items())
        for v, around in G.adjacency()
    }


def bidirectional_dijkstra(
    neighbours: Neighbours,
    source: int,
    target: int,
    *,
    avoid: frozenset[str] = frozenset(),
    changed_costs: ChangedCosts | None = None,
) -> list[int] | None:
    """The nodes of a shortest path from ``source`` to ``target`` (both in ``neighbours``) that uses
    no edge whose kind is in ``avoid``, as networkx's ``bidirectional_dijkstra`` finds it; None when
    there is none. Raises ValueError on a negative cost, as networkx does."""
    if source == target:
        return [source]
    changed = changed_costs or {}
    dists: tuple[dict[int, float], dict[int, float]] = ({}, {})
    preds: tuple[dict[int, int | None], dict[int, int | None]] = ({source: None}, {target: None})
    seen: tuple[dict[int, float], dict[int, float]] = ({source: 0}, {target: 0})
    fringe: tuple[list[tuple[float, int, int]], list[tuple[float, int, int]]] = ([], [])
    c = count()
    heappush(fringe[0], (0, next(c), source))
    heappush(fringe[1], (0, next(c), target))
    finaldist: float | None = None
    meetnode: int | None = None
    direction = 1
    while fringe[0] and fringe[1]:
        direction = 1 - direction
        dist, _, v = heappop(fringe[direction])
        done, other_done = dists[direction], dists[1 - direction]
        if v in done:
            continue  # the shortest path to v was found already
        done[v] = dist
        if v in other_done:  # v scanned from both sides: the best meeting node is known
            assert meetnode is not None
            return _joined(preds, meetnode)
        reached, other_reached = seen[direction], seen[1 - direction]
        pred = preds[direction]
        changed_here = changed.get(v)
        for w, length_m, kind in neighbours[v]:
            if kind in avoid:
                continue
            cost = length_m
            if changed_here is not None and w in changed_here:
                cost = changed_here[w]
            vw_length = dist + cost
            if w in done:
                if vw_length < done[w]:
                    raise ValueError("Contradictory paths found: negative weights?")
            elif w not in reached or vw_length < reached[w]:
                reached[w] = vw_length
                heappush(fringe[direction], (vw_length, next(c), w))
                pred[w] = v
                if w in other_reached:
                    through_w = vw_length + other_reached[w]
                    if finaldist is None or finaldist > through_w:
                        finaldist, meetnode = through_w, w
    return None


def _joined(preds: tuple[dict[int, int | None], dict[int, int | None]], meetnode: int) -> list[int]:
    """The path source … meetnode … target from both searches' predecessors."""
    forward: list[int] = []
    node: int | None = meetnode
    while node is not None:
        forward.append(node)
        node = preds[0][node]
    forward.reverse()
    node = preds[1][meetnode]
    while node is not None:
        forward.append(node)
        node = preds[1][node]
    return forward
