"""A route cut into its walked stretches and its stairs and elevators: the kind of each polyline
segment and the node, junction and floor at each point (:func:`walk_stretches`)."""

from __future__ import annotations

import itertools
from collections.abc import Sequence

import numpy as np

from app.domain.frames import FloatArray
from app.domain.navigation.floors import assign_floors
from app.domain.navigation.path_graph import WALK, PathGraph
from app.domain.navigation.routing import ROUNDED_DECIMALS, NodeLookups, Point3, Route, node_lookups


def walk_stretches(pg: PathGraph, route: Route) -> list[tuple[FloatArray, list[bool]]]:
    """The walked stretches of ``route`` between its stairs and elevators: each (points (K, 3),
    whether each point is a junction)."""
    xyz = np.asarray(route.polyline_m, dtype=np.float64).reshape(-1, 3)
    kinds, junction, _ = segment_kinds(node_lookups(pg), as_points(xyz), route.nodes)
    return [
        (xyz[i : j + 2], junction[i : j + 2]) for kind, i, j in kind_runs(kinds) if kind == WALK
    ]


def kind_runs(kinds: Sequence[str]) -> list[tuple[str, int, int]]:
    """(kind, first, last) of each run of segments of one kind, in order."""
    runs = []
    first = 0
    for kind, run in itertools.groupby(kinds):
        last = first + len(list(run)) - 1
        runs.append((kind, first, last))
        first = last + 1
    return runs


def segment_kinds(
    lookups: NodeLookups, points: Sequence[Point3], nodes: Sequence[int]
) -> tuple[list[str], list[bool], list[int | None]]:
    """(kind of each polyline segment, whether each point is a junction, the node at each point
    or None): a point is the route node at its position (rounded to ``ROUNDED_DECIMALS``; the
    last such node if several)."""
    place_of_node, place_of_point = lookups.place_of_node, lookups.place_of_point
    node_at = {place_of_node[n]: n for n in nodes}
    places = [place_of_point.get(p, -1) for p in points]  # -1: no node there
    for i, place in enumerate(places):
        if place < 0:  # not a node's position (a position on an edge): rounded, maybe one
            places[i] = lookups.place_of_rounded.get(_rounded(points[i]), -1)
    at = [node_at.get(place) for place in places]
    junctions = lookups.junctions
    junction = [n in junctions for n in at]
    kind_between = lookups.kind_between
    kinds = [
        WALK if a is None or b is None else kind_between[a].get(b, WALK)
        for a, b in itertools.pairwise(at)
    ]
    return kinds, junction, at


def _rounded(point: Point3) -> Point3:
    """``point`` rounded as :class:`app.domain.navigation.routing.NodeLookups` rounds the nodes'
    positions."""
    x, y, z = np.round(np.asarray(point, dtype=np.float64), ROUNDED_DECIMALS).tolist()
    return (x, y, z)


def point_floors(pg: PathGraph, lookups: NodeLookups, points: Sequence[Point3]) -> list[int]:
    """The floor of each polyline point: the level nearest its height."""
    if not pg.floor_levels_m:
        return [0] * len(points)
    if lookups.floor_levels_m != pg.floor_levels_m:
        return _floors_of_heights(pg, [p[1] for p in points])
    known = lookups.floor_of_height
    floors = [known.get(p[1], -1) for p in points]
    if -1 in floors:  # a point off the graph's nodes (a position on an edge)
        return _floors_of_heights(pg, [p[1] for p in points])
    return floors


def _floors_of_heights(pg: PathGraph, heights_m: list[float]) -> list[int]:
    levels = np.asarray(pg.floor_levels_m, dtype=np.float64)
    return [int(f) for f in assign_floors(np.asarray(heights_m, dtype=np.float64), levels)]


def as_points(xyz: FloatArray) -> list[Point3]:
    """(N, 3) points as N (x, y, z) tuples of floats."""
    return [(x, y, z) for x, y, z in xyz.tolist()]
