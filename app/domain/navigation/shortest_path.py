"""networkx's bidirectional Dijkstra over a path graph's adjacency made once (issue 16).

    no_stairs = neighbour_lists(G, avoid=frozenset({"stairs"}))   # once per graph
    path = bidirectional_dijkstra(no_stairs, 3, 17)
    # [3, 4, 9, 17], or None when 17 cannot be reached

It is ``networkx.bidirectional_dijkstra(G, source, target, weight=…)`` (networkx 3.x) step for step
— the same alternation of directions, the same heap entries ``(distance, counter, node)``, the
neighbours in ``G.adj`` order — so on equal-length alternatives it returns the same path. What it
saves is networkx's dispatch and a Python weight call per edge: the weight is the edge's
``length_m``, the edges of an avoided kind are left out of the lists, and ``changed_costs`` gives
the edges whose cost a route end on them changes (:mod:`app.domain.navigation.routing`).
"""

from __future__ import annotations

from collections.abc import Mapping
from heapq import heappop, heappush
from itertools import count
from typing import TypeAlias

import networkx as nx

#: node → its neighbours in ``G.adj`` order, each (neighbour, the edge's ``length_m`` as a float).
Neighbours: TypeAlias = dict[int, tuple[tuple[int, float], ...]]
#: node → {neighbour → the cost of the edge between them, in place of its ``length_m``}; an edge
#: is listed from both ends.
ChangedCosts: TypeAlias = Mapping[int, Mapping[int, float]]


def neighbour_lists(G: nx.Graph[int], *, avoid: frozenset[str] = frozenset()) -> Neighbours:
    """Each node's neighbours in ``G.adj`` order with the edge's length, but for edges whose
    ``kind`` is in ``avoid`` (made once per graph: a change to the graph is not seen by lists made
    before it)."""
    return {
        v: tuple(
            (w, float(data["length_m"])) for w, data in around.items() if data["kind"] not in avoid
        )
        for v, around in G.adjacency()
    }


def bidirectional_dijkstra(
    neighbours: Neighbours,
    source: int,
    target: int,
    *,
    changed_costs: ChangedCosts | None = None,
) -> list[int] | None:
    """The nodes of a shortest path from ``source`` to ``target`` (both in ``neighbours``) along
    the listed edges, as networkx's ``bidirectional_dijkstra`` finds it; None when there is none.
    Raises ValueError on a negative cost, as networkx does."""
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
        heap = fringe[direction]
        dist, _, v = heappop(heap)
        done = dists[direction]
        if v in done:
            continue  # the shortest path to v was found already
        done[v] = dist
        if v in dists[1 - direction]:  # v scanned from both sides: the best meeting node is known
            assert meetnode is not None
            return _joined(preds, meetnode)
        reached, other_reached = seen[direction], seen[1 - direction]
        pred = preds[direction]
        changed_here = changed.get(v)
        for w, length_m in neighbours[v]:
            if changed_here is not None and w in changed_here:
                vw_length = dist + changed_here[w]
            else:
                vw_length = dist + length_m
            if w in done:
                if vw_length < done[w]:
                    raise ValueError("Contradictory paths found: negative weights?")
                continue
            reached_w = reached.get(w)
            if reached_w is None or vw_length < reached_w:
                reached[w] = vw_length
                heappush(heap, (vw_length, next(c), w))
                pred[w] = v
                other_w = other_reached.get(w)
                if other_w is not None:
                    through_w = vw_length + other_w
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
