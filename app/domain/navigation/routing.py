"""Routes on a path graph: from a tag, a point of interest, a node or a position to another
(docs/architecture.md §6). The walk only: what a walker hears on it is worded by
:mod:`app.domain.navigation.instructions` (``plan_guided_route``), the one instruction writer
(issue 26 retired the per-leg steps written here).

    route = plan_walk(pg, TagEnd(300), PoiEnd("Room 209"), avoid=frozenset({"stairs"}))
    route.length_m                    # 23.4, m, along the polyline
    route.polyline_m, route.floors    # the way, and the floors it visits
    search_pois(pg, "room")           # exact name first, then prefix matches, then substrings

Frames and units: positions are (x, y, z) in the map frame, metres, y up (ARKit's world:
right-handed, gravity-aligned). Turns are measured in the horizontal x–z plane; a positive
``turn_deg`` is a left turn (counter-clockwise seen from above), e.g. walking along −z then along
−x is +90°.

Design decisions:

- **Where a route starts and ends.** A node endpoint is that node. A tag or point of interest is
  its anchor node: the polyline ends (or starts) there, on the walkable path, never at the thing
  itself (a tag is on a wall); the instructions say on which side it is. A position is
  joined to the graph at the nearest point on a walk edge of its floor (the floor whose height is
  nearest, then the nearest edge in x–z), so the route starts where the person is, not at a node.
- **Shortest path.** networkx's bidirectional Dijkstra on ``length_m``, step for step over each
  node's neighbours listed once per graph and set of avoided kinds
  (:mod:`app.domain.navigation.shortest_path`: the same path on equal-length alternatives; no copy
  of the graph per query). A position on an edge is handled without adding nodes to the shared
  graph: the search starts from the nearer end ``s`` of the edge with all costs shifted by the
  distance to it, and the edge itself costs ``L − 2·d(P, s)`` (≥ 0), which is exactly the shifted
  cost of leaving through the far end; the same holds at the goal. Start and goal on the same edge
  go straight along it.
- **The polyline** is the path as walked: graph node positions plus the snapped start and goal, and
  ``length_m`` is the sum of its segment lengths (3-D, m).
- **Floors for people** are numbered from 1: floor index 0 (the lowest) is "floor 1".

Errors (each ``str(err)`` is one sentence fit for a person):

    RouteError                 anything a route request is refused for (bad avoid, bad position)
    ├── UnknownEndpoint        no such tag, point of interest or node (HTTP 404)
    ├── AmbiguousEndpoint      a point-of-interest name that matches several (HTTP 422)
    └── Unreachable            no route, or none without the avoided stairs/elevators (HTTP 409)
"""

from __future__ import annotations

import itertools
import math
import threading
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any, Literal, TypeAlias

import networkx as nx
import numpy as np
import numpy.typing as npt

from app.domain.errors import InvisibleMapError
from app.domain.navigation.floors import assign_floors
from app.domain.navigation.path_graph import ELEVATOR, JUNCTION, STAIRS, WALK, Anchor, PathGraph
from app.domain.navigation.polyline import xyz_array
from app.domain.navigation.shortest_path import Neighbours, bidirectional_dijkstra, neighbour_lists

Point3: TypeAlias = tuple[float, float, float]
FloatArray: TypeAlias = npt.NDArray[np.float64]

#: Kinds of edge a route may avoid.
AVOIDABLE = frozenset({STAIRS, ELEVATOR})
#: Every set of kinds a route may avoid (the subsets of ``AVOIDABLE``).
AVOID_SETS: tuple[frozenset[str], ...] = (
    frozenset(),
    frozenset({STAIRS}),
    frozenset({ELEVATOR}),
    AVOIDABLE,
)

#: A snapped position within this distance of an edge end, m, is that node.
SNAP_TO_NODE_M = 1e-6

StepKind: TypeAlias = Literal[
    "face", "go", "announce", "turn", "keep", "stairs", "elevator", "arrive"
]
#: The class of a turn by its angle alone (:func:`app.domain.navigation.instructions.turn_class`).
TurnClass: TypeAlias = Literal["straight", "bear", "turn", "sharp", "around"]
#: Where a thing is from the walker: the side of the goal on arrival.
Side: TypeAlias = Literal["ahead", "left", "right", "behind"]


# --------------------------------------------------------------------------- errors


class RouteError(InvisibleMapError):
    """Raised when a route request cannot be served: an invalid ``avoid`` or position, or a path
    graph that contradicts itself; the subclasses name the usual cases."""


class UnknownEndpoint(RouteError):
    """Raised when a tag, point of interest or node is not in the map; ``kind`` is ``"tag"``,
    ``"poi"`` or ``"node"`` and ``value`` what was asked for."""

    def __init__(self, kind: str, value: object, message: str) -> None:
        self.kind = kind
        self.value = value
        super().__init__(message)


class AmbiguousEndpoint(RouteError):
    """Raised when a point-of-interest name matches several places; ``candidates`` are their
    names."""

    def __init__(self, kind: str, value: object, candidates: Sequence[str]) -> None:
        self.kind = kind
        self.value = value
        self.candidates = tuple(candidates)
        names = ", ".join(repr(c) for c in self.candidates)
        super().__init__(f"{value!r} matches several points of interest: {names}")


class Unreachable(RouteError):
    """Raised when the goal cannot be reached from the start (with ``avoid``, or at all);
    ``reason`` is the part of the message after the colon."""

    def __init__(self, start: str, goal: str, avoid: frozenset[str], reason: str) -> None:
        self.start = start
        self.goal = goal
        self.avoid = avoid
        self.reason = reason
        without = f" without {_avoid_phrase(avoid)}" if avoid else ""
        super().__init__(f"no route from {start} to {goal}{without}: {reason}")


# --------------------------------------------------------------------------- endpoints


@dataclass(frozen=True, slots=True)
class TagEnd:
    """A route end at a tag: its anchor node."""

    tag_id: int


@dataclass(frozen=True, slots=True)
class PoiEnd:
    """A route end at a point of interest, by name (exact match first, then case-insensitive)."""

    name: str


@dataclass(frozen=True, slots=True)
class NodeEnd:
    """A route end at a path-graph node."""

    node_id: int


@dataclass(frozen=True, slots=True)
class PositionEnd:
    """A route end at a position (x, y, z), m, map frame (y up), snapped onto the nearest walk edge
    of its floor."""

    position_m: Point3


Endpoint: TypeAlias = TagEnd | PoiEnd | NodeEnd | PositionEnd


# --------------------------------------------------------------------------- results


@dataclass(frozen=True, slots=True, kw_only=True)
class Step:
    """One spoken instruction.

    ``position_m``: where to do it (map frame, m): the start of a stretch to walk, the corner of a
    turn, the foot (or top) of the stairs, the arrival point. ``distance_m``: the stretch's length
    along the path (m; 0 for turns and arrival). ``turn_deg``: signed horizontal turn, + is left
    (face, announce and turn steps; on a keep step, the route's own bend at its fork).
    ``floor``: floor index (0 = lowest) where the step starts. A ``keep`` step ("keep left at
    the fork", :mod:`app.domain.navigation.forks`) is said at a junction the route goes through
    without a turn while another way goes on near straight ahead.

    Written by :mod:`app.domain.navigation.instructions` (the defaults are for steps made by
    hand): ``turn``: the class of ``turn_deg`` (``turn_class``), ``clock``: its clock-face hour
    (12 ahead, 3 right, 9 left), ``steps_count``: ``distance_m`` in the walker's strides (go
    steps), ``landmark``: the tag or point of interest at the step ("Room 210", "tag 305"),
    ``side``: where the goal is on the last walked step and the arrival, and the side to keep
    on a keep step ("ahead" for straight on), ``text``: the step as one plain sentence for a
    screen reader ("Turn right, to 3 o'clock.").
    """

    instruction: str
    position_m: Point3
    kind: StepKind
    distance_m: float
    turn_deg: float | None
    floor: int
    turn: TurnClass | None = None
    clock: int | None = None
    steps_count: int | None = None
    landmark: str | None = None
    side: Side | None = None
    text: str = ""


@dataclass(frozen=True, slots=True, kw_only=True)
class Route:
    """A planned route.

    ``polyline_m``: the walked points (map frame, m), from the start (snapped onto the graph) to
    the goal's node or snapped point. ``length_m``: sum of the polyline's 3-D segment lengths.
    ``floors``: floor indices visited, in order, no repeats in a row. ``nodes``: graph nodes passed
    through, in order. ``steps``: turn-by-turn instructions, ending with "arrive at …".
    """

    polyline_m: list[Point3]
    length_m: float
    floors: list[int]
    nodes: list[int]
    steps: list[Step]


# --------------------------------------------------------------------------- public API


def plan_walk(
    pg: PathGraph,
    start: Endpoint,
    goal: Endpoint,
    *,
    avoid: frozenset[str] = frozenset(),
) -> Route:
    """The shortest route on ``pg`` from ``start`` to ``goal`` that uses no edge of a kind in
    ``avoid`` (a subset of ``{"stairs", "elevator"}``): the walk alone (``steps`` is empty;
    :func:`app.domain.navigation.instructions.plan_guided_route` words it).

    Raises :class:`UnknownEndpoint`, :class:`AmbiguousEndpoint`, :class:`Unreachable` or
    :class:`RouteError` (see the module docstring).
    """
    return _planned_walk(pg, start, goal, avoid).route


@dataclass(frozen=True, slots=True, kw_only=True)
class MeasuredWalk:
    """The route of :func:`plan_walk` and what measuring its length made: ``xyz`` (N, 3) its
    polyline (map frame, m), ``segment_lengths_m`` (N − 1) the 3-D length of each segment, m;
    ``lookups``: the graph's :class:`NodeLookups` it was planned with."""

    route: Route
    xyz: FloatArray
    segment_lengths_m: list[float]
    lookups: NodeLookups


def measured_walk(
    pg: PathGraph,
    start: Endpoint,
    goal: Endpoint,
    *,
    avoid: frozenset[str] = frozenset(),
) -> MeasuredWalk:
    """:func:`plan_walk` with its polyline as an array and its segments' lengths, so that a caller
    wording the steps (:mod:`app.domain.navigation.instructions`) need not make them again. Same
    refusals."""
    return _planned_walk(pg, start, goal, avoid)


def _planned_walk(
    pg: PathGraph, start: Endpoint, goal: Endpoint, avoid: frozenset[str]
) -> MeasuredWalk:
    """The walk from ``start`` to ``goal`` (see :func:`plan_walk`), measured."""
    avoid = frozenset(avoid)
    bad = avoid - AVOIDABLE
    if bad:
        raise RouteError(
            f"cannot avoid {', '.join(sorted(bad))}: only stairs and elevator can be avoided"
        )
    a = _resolve(pg, start)
    b = _resolve(pg, goal)
    index = _edge_index(pg)
    walk = _shortest_walk(index, a, b, avoid)
    if walk is None:
        raise _unreachable(index, a, b, avoid)
    points, floors, _, nodes = walk
    xyz = xyz_array(points)
    step_m = np.diff(xyz, axis=0)
    segments_m = np.sqrt(np.add.reduce(step_m * step_m, axis=1))  # np.linalg.norm(…, axis=1)
    route = Route(
        polyline_m=points,
        length_m=float(segments_m.sum()) if len(xyz) > 1 else 0.0,
        floors=_without_repeats(floors),
        nodes=nodes,
        steps=[],
    )
    return MeasuredWalk(
        route=route, xyz=xyz, segment_lengths_m=segments_m.tolist(), lookups=index.lookups
    )


def search_pois(pg: PathGraph, query: str) -> list[Anchor]:
    """Points of interest whose name contains ``query`` (case-insensitive, surrounding spaces
    ignored): exact names first, then names starting with it, then the rest; alphabetical within
    each group. An empty query lists them all."""
    q = query.strip().casefold()
    ranked: list[tuple[int, str, str, int, Anchor]] = []
    for i, poi in enumerate(pg.pois):
        name = poi.name.strip().casefold()
        if q not in name:
            continue
        rank = 0 if name == q else 1 if name.startswith(q) else 2
        ranked.append((rank, name, poi.name, i, poi))
    ranked.sort(key=lambda r: r[:4])
    return [r[4] for r in ranked]


def signed_turn_deg(heading_in: Sequence[float], heading_out: Sequence[float]) -> float:
    """Signed horizontal angle, degrees in (−180, 180], from one walking direction to the next.

    Both are (x, y, z) vectors in the map frame (y up; y is ignored). Positive is a left turn:
    the y component of ``heading_in × heading_out`` is positive when turning counter-clockwise
    seen from above, e.g. from −z (ahead) to −x (left) is +90°.
    """
    ax, az = float(heading_in[0]), float(heading_in[2])
    bx, bz = float(heading_out[0]), float(heading_out[2])
    cross_y = az * bx - ax * bz
    dot = ax * bx + az * bz
    return math.degrees(math.atan2(cross_y, dot))


@dataclass(frozen=True, slots=True, kw_only=True)
class NodeLookups:
    """What the steps of a route look up about the graph's nodes and edges, made once per graph
    (:func:`node_lookups`; a graph must not change once routed on); do not modify them.

    ``point_of_node``: node → ``position_m`` as floats (map frame, m). ``junctions``: the nodes of
    kind ``"junction"``. ``kind_between``: node → {neighbour → the kind of the edge between them}.
    Places: the nodes' positions rounded to ``ROUNDED_DECIMALS`` (``np.round``), numbered;
    ``place_of_rounded``: a rounded position → its place, ``place_of_point``: a node's
    ``position_m`` → its place, ``place_of_node``: node → its place. ``floor_of_height``: a node's
    height (y, m) → the index of the nearest of ``floor_levels_m``
    (:func:`app.domain.navigation.floors.assign_floors`), the levels it was made for.
    """

    point_of_node: dict[int, Point3]
    junctions: frozenset[int]
    kind_between: dict[int, dict[int, str]]
    place_of_rounded: dict[Point3, int]
    place_of_point: dict[Point3, int]
    place_of_node: dict[int, int]
    floor_levels_m: tuple[float, ...]
    floor_of_height: dict[float, int]


#: Decimals a polyline point is rounded to when it is matched to a node (steps), m.
ROUNDED_DECIMALS = 9


def node_lookups(pg: PathGraph) -> NodeLookups:
    """The :class:`NodeLookups` of ``pg``, made once per graph with routing's index."""
    return _edge_index(pg).lookups


# --------------------------------------------------------------------------- endpoints → graph


@dataclass(frozen=True, slots=True, kw_only=True)
class _Terminal:
    """Where a route end meets the graph: a node, or a point on a walk edge ``(u, v)`` at
    ``along_m`` (in ``length_m`` units) from ``u``."""

    label: str  # for messages: "tag 300", "'Room 209'", "node 12", "position (1.0, 0.0, -2.0)"
    name: str  # for "arrive at …"
    position_m: Point3
    floor: int
    node: int | None = None
    edge: tuple[int, int] | None = None
    along_m: float = 0.0
    thing_m: Point3 | None = None  # the tag or POI itself


def _resolve(pg: PathGraph, end: Endpoint) -> _Terminal:
    G = pg.graph
    match end:
        case NodeEnd(node_id=node):
            if node not in G:
                raise UnknownEndpoint("node", node, f"unknown node {node}")
            return _at_node(G, node, label=f"node {node}", name=f"node {node}")
        case TagEnd(tag_id=tag_id):
            anchor = pg.tags.get(tag_id)
            if anchor is None:
                raise UnknownEndpoint("tag", tag_id, f"unknown tag {tag_id}")
            return _at_anchor(G, anchor, label=f"tag {tag_id}", name=f"tag {tag_id}")
        case PoiEnd(name=name):
            poi = _find_poi(pg, name)
            return _at_anchor(G, poi, label=repr(poi.name), name=poi.name)
        case PositionEnd(position_m=position_m):
            return _snap(pg, position_m)
    raise RouteError(f"not a route endpoint: {end!r}")  # pragma: no cover


def _at_node(G: nx.Graph[int], node: int, *, label: str, name: str) -> _Terminal:
    data = G.nodes[node]
    return _Terminal(
        label=label,
        name=name,
        position_m=_point(data["position_m"]),
        floor=int(data["floor"]),
        node=node,
    )


def _at_anchor(G: nx.Graph[int], anchor: Anchor, *, label: str, name: str) -> _Terminal:
    if anchor.node not in G:
        raise RouteError(f"{label} is anchored to node {anchor.node}, which is not in the map")
    data = G.nodes[anchor.node]
    return _Terminal(
        label=label,
        name=name,
        position_m=_point(data["position_m"]),
        floor=int(data["floor"]),
        node=anchor.node,
        thing_m=_point(anchor.position_m),
    )


def _find_poi(pg: PathGraph, name: str) -> Anchor:
    exact = [p for p in pg.pois if p.name == name]
    folded = name.strip().casefold()
    for matches in (exact, [p for p in pg.pois if p.name.strip().casefold() == folded]):
        if len({p.node for p in matches}) == 1:
            return matches[0]  # duplicates of one place are one place
        if matches:
            raise AmbiguousEndpoint("poi", name, [p.name for p in matches])
    near = [p.name for p in search_pois(pg, name)[:3]] if folded else []
    hint = f"; did you mean {' or '.join(repr(n) for n in near)}?" if near else ""
    raise UnknownEndpoint("poi", name, f"no point of interest named {name!r}{hint}")


@dataclass(frozen=True, slots=True, kw_only=True)
class _EdgeIndex:
    """Walk edges and nodes as arrays, for snapping positions; each node's position and floor as
    Python values, for the polyline of a route; each node's neighbours, for the search (built once
    per graph)."""

    graph: nx.Graph[int]
    n_nodes: int
    n_neighbours: int  # :func:`_neighbour_count`: changes when an edge is added or removed
    edge_u: npt.NDArray[np.int64]  # (E,)
    edge_v: npt.NDArray[np.int64]  # (E,)
    edge_a_m: FloatArray  # (E, 3) position of u, map frame
    edge_b_m: FloatArray  # (E, 3) position of v, map frame
    edge_floor: npt.NDArray[np.int64]  # (E,)
    node_ids: npt.NDArray[np.int64]  # (N,)
    node_m: FloatArray  # (N, 3)
    node_floor: npt.NDArray[np.int64]  # (N,)
    floors: npt.NDArray[np.int64]  # (F,) floor indices that have nodes
    floor_height_m: FloatArray  # (F,) their heights, m
    floor_of_node: dict[int, int]  # node → floor
    neighbours: dict[frozenset[str], Neighbours]  # for the search, per set in AVOID_SETS
    lookups: NodeLookups  # node positions, junctions, edge kinds (for the polyline and steps)


_INDEX_CACHE: dict[int, _EdgeIndex] = {}
_INDEX_CACHE_SIZE = 8
_INDEX_LOCK = threading.Lock()


def _edge_index(pg: PathGraph) -> _EdgeIndex:
    """The (cached) snapping index of ``pg.graph``; a graph must not change once routed on."""
    G = pg.graph
    with _INDEX_LOCK:
        index = _INDEX_CACHE.get(id(G))
    if (
        index is not None
        and index.graph is G
        and index.n_nodes == G.number_of_nodes()
        and index.n_neighbours == _neighbour_count(G)
    ):
        return index
    index = _build_edge_index(pg)
    with _INDEX_LOCK:
        _INDEX_CACHE[id(G)] = index
        while len(_INDEX_CACHE) > _INDEX_CACHE_SIZE:
            del _INDEX_CACHE[next(iter(_INDEX_CACHE))]
    return index


def _neighbour_count(G: nx.Graph[int]) -> int:
    """The sum of the nodes' neighbour counts (twice the edges, self-loops once): an edge added
    or removed changes it, and it costs a third of ``G.number_of_edges()`` (degree views)."""
    return sum(len(neighbours) for _, neighbours in G.adjacency())


def _build_edge_index(pg: PathGraph) -> _EdgeIndex:
    G = pg.graph
    nodes = list(G.nodes.items())
    row = {n: i for i, (n, _) in enumerate(nodes)}
    node_ids = np.array([n for n, _ in nodes], dtype=np.int64)
    node_m = np.array([d["position_m"] for _, d in nodes], dtype=np.float64).reshape(-1, 3)
    node_floor = np.array([d["floor"] for _, d in nodes], dtype=np.int64)
    walk = [(u, v, d["floor"]) for u, v, d in G.edges(data=True) if d["kind"] == WALK]
    rows_u = np.array([row[u] for u, _, _ in walk], dtype=np.int64)
    rows_v = np.array([row[v] for _, v, _ in walk], dtype=np.int64)
    floors = np.unique(node_floor)
    levels = pg.floor_levels_m
    floor_height_m = np.array(
        [
            levels[f] if 0 <= f < len(levels) else float(np.median(node_m[node_floor == f, 1]))
            for f in floors
        ],
        dtype=np.float64,
    )
    return _EdgeIndex(
        graph=G,
        floor_of_node={n: int(d["floor"]) for n, d in nodes},
        neighbours={avoid: neighbour_lists(G, avoid=avoid) for avoid in AVOID_SETS},
        lookups=_node_lookups(pg, nodes),
        n_nodes=G.number_of_nodes(),
        n_neighbours=_neighbour_count(G),
        edge_u=node_ids[rows_u],
        edge_v=node_ids[rows_v],
        edge_a_m=node_m[rows_u],
        edge_b_m=node_m[rows_v],
        edge_floor=np.array([f for _, _, f in walk], dtype=np.int64),
        node_ids=node_ids,
        node_m=node_m,
        node_floor=node_floor,
        floors=floors,
        floor_height_m=floor_height_m,
    )


def _node_lookups(pg: PathGraph, nodes: list[tuple[int, dict[str, Any]]]) -> NodeLookups:
    points = [_point(d["position_m"]) for _, d in nodes]
    xyz = np.array(points, dtype=np.float64).reshape(-1, 3)
    rounded = [_point(r) for r in np.round(xyz, ROUNDED_DECIMALS).tolist()]
    place_of_rounded: dict[Point3, int] = {}
    for r in rounded:
        place_of_rounded.setdefault(r, len(place_of_rounded))
    places = [place_of_rounded[r] for r in rounded]
    levels_m = tuple(pg.floor_levels_m)
    floors = assign_floors(xyz[:, 1], np.asarray(levels_m, dtype=np.float64)).tolist()
    return NodeLookups(
        point_of_node={n: p for (n, _), p in zip(nodes, points, strict=True)},
        junctions=frozenset(n for n, d in nodes if d.get("kind") == JUNCTION),
        kind_between={
            v: {w: str(d["kind"]) for w, d in around.items()} for v, around in pg.graph.adjacency()
        },
        place_of_rounded=place_of_rounded,
        place_of_point=dict(zip(points, places, strict=True)),
        place_of_node={n: place for (n, _), place in zip(nodes, places, strict=True)},
        floor_levels_m=levels_m,
        floor_of_height={p[1]: int(f) for p, f in zip(points, floors, strict=True)},
    )


def _snap(pg: PathGraph, position_m: Sequence[float]) -> _Terminal:
    """A position joined to the graph: the nearest floor by height, then the nearest point (in
    x–z) on a walk edge of that floor, or the nearest node if the floor has no walk edge."""
    p = np.asarray(position_m, dtype=np.float64)
    if p.shape != (3,) or not np.all(np.isfinite(p)):
        raise RouteError(f"a position must be 3 finite numbers (x, y, z) in metres, not {p}")
    label = "position ({:.2f}, {:.2f}, {:.2f})".format(*p)
    name = "your destination"
    index = _edge_index(pg)
    if len(index.node_ids) == 0:
        raise RouteError(f"the map has no path to join {label} to")
    floor = int(index.floors[np.argmin(np.abs(index.floor_height_m - p[1]))])
    on_floor = np.flatnonzero(index.edge_floor == floor)
    if len(on_floor) == 0:
        nodes = np.flatnonzero(index.node_floor == floor)
        dxz = index.node_m[nodes][:, [0, 2]] - p[[0, 2]]
        node = int(index.node_ids[nodes[np.argmin(np.einsum("ij,ij->i", dxz, dxz))]])
        return _at_node(pg.graph, node, label=label, name=name)
    a = index.edge_a_m[on_floor]
    b = index.edge_b_m[on_floor]
    t = _projection_xz(p[[0, 2]], a[:, [0, 2]], b[:, [0, 2]])
    closest = a + t[:, None] * (b - a)
    dxz = closest[:, [0, 2]] - p[[0, 2]]
    best = int(np.argmin(np.einsum("ij,ij->i", dxz, dxz)))
    e = on_floor[best]
    u, v = int(index.edge_u[e]), int(index.edge_v[e])
    point = closest[best]
    geometric_m = float(np.linalg.norm(b[best] - a[best]))
    if float(np.linalg.norm(point - a[best])) <= SNAP_TO_NODE_M:
        return _at_node(pg.graph, u, label=label, name=name)
    if float(np.linalg.norm(point - b[best])) <= SNAP_TO_NODE_M or geometric_m == 0.0:
        return _at_node(pg.graph, v, label=label, name=name)
    edge_length = float(pg.graph.edges[u, v]["length_m"])
    return _Terminal(
        label=label,
        name=name,
        position_m=_point(point),
        floor=floor,
        edge=(u, v),
        along_m=float(t[best]) * edge_length,
    )


def _projection_xz(p: FloatArray, a: FloatArray, b: FloatArray) -> FloatArray:
    """(E,) parameter in [0, 1] of the point of each segment a→b (E, 2) nearest p (2,)."""
    ab = b - a
    denominator = np.einsum("ij,ij->i", ab, ab)
    numerator = np.einsum("ij,ij->i", p - a, ab)
    t = np.divide(numerator, denominator, out=np.zeros_like(numerator), where=denominator > 0)
    return np.asarray(np.clip(t, 0.0, 1.0), dtype=np.float64)


# --------------------------------------------------------------------------- search

_Walk: TypeAlias = tuple[list[Point3], list[int], list[str], list[int]]


def _shortest_walk(
    index: _EdgeIndex, a: _Terminal, b: _Terminal, avoid: frozenset[str]
) -> _Walk | None:
    """(points, floor of each point, kind of each segment, nodes) of the shortest route, or None.

    An end on an edge is searched from its nearer node ``s`` with costs shifted by ``d(P, s)``:
    the edge then costs ``L − 2·d(P, s)`` ≥ 0, the shifted cost of leaving by its far end.
    """
    G = index.graph
    if a.edge is not None and b.edge is not None and set(a.edge) == set(b.edge):
        if a.position_m == b.position_m:
            return [a.position_m], [a.floor], [], []
        return [a.position_m, b.position_m], [a.floor, b.floor], [WALK], []
    source, source_edge = _search_end(G, a)
    target, target_edge = _search_end(G, b)
    changed_costs: dict[int, dict[int, float]] = {}
    for changed in (source_edge, target_edge):  # two different edges (one is handled above)
        if changed is not None:
            u, v, cost = changed
            changed_costs.setdefault(u, {})[v] = cost
            changed_costs.setdefault(v, {})[u] = cost
    nodes = bidirectional_dijkstra(
        index.neighbours[avoid], source, target, changed_costs=changed_costs
    )
    if nodes is None:
        return None
    points: list[Point3] = []
    floors: list[int] = []
    kinds: list[str] = []
    if a.edge is not None:
        points.append(a.position_m)
        floors.append(a.floor)
        if len(nodes) > 1 and set(nodes[:2]) == set(a.edge):
            nodes = nodes[1:]  # left by the far end: the near end is not passed
        kinds.append(WALK)
    if b.edge is not None and len(nodes) > 1 and set(nodes[-2:]) == set(b.edge):
        nodes = nodes[:-1]  # came in by the far end
    point_of_node, floor_of_node = index.lookups.point_of_node, index.floor_of_node
    kind_between = index.lookups.kind_between
    points += [point_of_node[n] for n in nodes]
    floors += [floor_of_node[n] for n in nodes]
    kinds += [kind_between[u][v] for u, v in itertools.pairwise(nodes)]
    if b.edge is not None:
        points.append(b.position_m)
        floors.append(b.floor)
        kinds.append(WALK)
    return points, floors, kinds, nodes


def _search_end(G: nx.Graph[int], end: _Terminal) -> tuple[int, tuple[int, int, float] | None]:
    """(node to search from/to, (u, v, changed cost) of the edge the end is on, if it is on one)."""
    if end.edge is None:
        assert end.node is not None
        return end.node, None
    u, v = end.edge
    length = float(G.edges[u, v]["length_m"])
    near, to_near = (u, end.along_m) if end.along_m <= length / 2 else (v, length - end.along_m)
    return near, (u, v, max(length - 2.0 * to_near, 0.0))


def _unreachable(
    index: _EdgeIndex, a: _Terminal, b: _Terminal, avoid: frozenset[str]
) -> Unreachable:
    """Why there is no route: the avoided kinds (if a route exists without them) or the map."""
    if avoid and _shortest_walk(index, a, b, frozenset()) is not None:
        avoided = [kind for kind in _KIND_ORDER if kind in avoid]
        needed = avoided  # which of them are needed, when more than one is avoided
        if len(avoided) > 1:
            needed = [k for k in avoided if _shortest_walk(index, a, b, avoid - {k}) is not None]
        uses = " or ".join(_KIND_USED[k] for k in (needed or avoided))
        where = f"floor {b.floor + 1}"
        if a.floor == b.floor:
            reason = f"the goal is on {where} like the start, but every way there uses {uses}"
        else:
            reason = f"the goal is on {where} and every way there uses {uses}"
        return Unreachable(a.label, b.label, avoid, reason)
    return Unreachable(
        a.label, b.label, avoid, "they are on parts of the map that are not connected"
    )


_KIND_ORDER = (STAIRS, ELEVATOR)
_KIND_USED = {STAIRS: "stairs", ELEVATOR: "an elevator"}


def _avoid_phrase(avoid: Iterable[str]) -> str:
    """ "stairs", "elevators" or "stairs or elevators"."""
    avoided = set(avoid)
    plural = {STAIRS: "stairs", ELEVATOR: "elevators"}
    return " or ".join(plural[k] for k in _KIND_ORDER if k in avoided)


# --------------------------------------------------------------------------- small helpers


def _point(values: Iterable[float]) -> Point3:
    x, y, z = (float(c) for c in values)
    return (x, y, z)


def _without_repeats(values: Iterable[int]) -> list[int]:
    return [v for v, _ in itertools.groupby(values)]
