"""A model of how the iPhone app reads a map and plans a route, to check our app-map against.

    report = check_app_map(document)          # the app-map JSON (architecture §7), as downloaded
    report.decode_error                       # None, or why JSONDecoder would refuse the map
    report.isolated_vertices                  # odometry vertices with no edge in the app's graph
    report.crashing_pairs, report.pairs       # (start vertex, destination) pairs that trap

It follows the app's Swift source (occamLab/InvisibleMap, ``InvisibleMap2/.../Map.swift``), which
decides what "works" means, step by step:

1. **Decoding** (``JSONDecoder`` into ``RawMap``): ``tag_vertices``, ``odometry_vertices`` and
   ``waypoints_vertices`` are required arrays; each vertex needs ``id``/``poseId`` (Int; a
   waypoint's ``id`` is a String), ``translation {x, y, z}`` and ``rotation {x, y, z, w}``
   (Float: a finite number within Float's range), and an odometry vertex ``neighbors`` ([Int]).
   A missing or ``null`` key, or a value of another type, fails the whole map. Extra keys are
   ignored.
2. **Dictionaries**: odometry vertices by ``poseId`` with ``Dictionary(uniqueKeysWithValues:)``
   (a duplicate id traps); tags by ``id`` (a duplicate would shadow one: counted as a trap here,
   as the issue states it); waypoints by name (``waypointKeyDictionary[name] = index``: of two
   waypoints with one name, only the last can be chosen; the others are *unreachable waypoints*).
3. **The navigation graph**: for each vertex and each ``neighbor`` in its ``neighbors``, an edge
   is added **only if** ``neighbor < vertex.poseId`` (weight: the 3-D distance), and then used in
   both directions; there ``odometryDict![neighbor]!`` traps on a neighbor that is no vertex. A
   link listed only at its smaller-id end is therefore lost.
4. **A route** to a tag or waypoint: ``endpoint`` = the vertex nearest the destination,
   ``start`` = the vertex nearest the phone *other than* ``endpoint`` (so every vertex but the
   endpoint can be a start); Dijkstra from ``start``; an ``endpoint`` it does not reach
   force-unwraps nil (trap); a map of one vertex has no start (``closestNode`` stays 0: trap, and
   the route of one stop traps on ``0...stops.count-2``).

So a map works when every (start, destination) pair is routed: no isolated vertex, one connected
graph, every link listed at its larger-id end.
"""

from __future__ import annotations

import dataclasses
import heapq
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

#: Largest magnitude a Swift ``Float`` holds; a larger JSON number fails to decode.
FLOAT32_MAX = 3.4028234663852886e38
#: Range of a Swift ``Int`` (64-bit).
INT64_MIN, INT64_MAX = -(2**63), 2**63 - 1
#: How many trap descriptions a report keeps (examples, not a complete list).
MAX_EXAMPLES = 5


class AppDecodeError(ValueError):
    """Raised when the app's ``JSONDecoder`` would refuse the map; ``path`` names the key."""

    def __init__(self, path: str, reason: str) -> None:
        self.path = path
        self.reason = reason
        super().__init__(f"{path}: {reason}")


class AppTrap(RuntimeError):
    """Raised where the app would crash (a force-unwrap of nil, a duplicate dictionary key)."""


@dataclass(frozen=True, slots=True, kw_only=True)
class AppVertex:
    """A decoded odometry vertex: its id, position (x, y, z) and listed neighbors."""

    pose_id: int
    position: tuple[float, float, float]
    neighbors: tuple[int, ...]


@dataclass(frozen=True, slots=True, kw_only=True)
class Destination:
    """A tag or waypoint the app can route to: ``kind`` "tag" or "waypoint", its key, position."""

    kind: str
    key: str
    position: tuple[float, float, float]


@dataclass(frozen=True, slots=True, kw_only=True)
class AppMap:
    """The map as the app holds it after decoding."""

    vertices: tuple[AppVertex, ...]
    tags: tuple[Destination, ...]
    waypoints: tuple[Destination, ...]


@dataclass(slots=True)
class AppGraph:
    """The app's navigation graph: vertex id → position, and undirected weighted adjacency."""

    position: dict[int, tuple[float, float, float]] = field(default_factory=dict)
    adjacency: dict[int, dict[int, float]] = field(default_factory=dict)

    def nearest(self, point: Sequence[float], *, ignoring: int | None = None) -> int | None:
        """``getClosestGraphNode``: the vertex nearest ``point`` other than ``ignoring``
        (ties: the smallest id; the app's order is a dictionary's), None if there is none."""
        best: tuple[float, int] | None = None
        for vertex_id, p in self.position.items():
            if vertex_id == ignoring:
                continue
            candidate = (math.dist(p, point), vertex_id)
            if best is None or candidate < best:
                best = candidate
        return None if best is None else best[1]

    def shortest_path(self, start: int, end: int) -> list[int]:
        """Dijkstra's route from ``start`` to ``end`` as the stops' ids; AppTrap where the app
        would crash (``end`` unreachable, or a route of one stop)."""
        distance = {start: 0.0}
        previous: dict[int, int] = {}
        heap = [(0.0, start)]
        while heap:
            d, u = heapq.heappop(heap)
            if d > distance[u]:
                continue
            if u == end:
                break
            for v, w in self.adjacency[u].items():
                if d + w < distance.get(v, math.inf):
                    distance[v] = d + w
                    previous[v] = u
                    heapq.heappush(heap, (d + w, v))
        if end not in distance:
            raise AppTrap(f"vertex {end} is unreachable from vertex {start}")
        stops = [end]
        while stops[-1] != start:
            stops.append(previous[stops[-1]])
        if len(stops) < 2:
            raise AppTrap(f"a route of one stop (vertex {start})")
        return stops[::-1]

    def components(self) -> dict[int, int]:
        """Vertex id → the smallest id of its connected component."""
        label: dict[int, int] = {}
        for root in sorted(self.position):
            if root in label:
                continue
            label[root] = root
            stack = [root]
            while stack:
                for v in self.adjacency[stack.pop()]:
                    if v not in label:
                        label[v] = root
                        stack.append(v)
        return label


@dataclass(frozen=True, slots=True, kw_only=True)
class ConformanceReport:
    """How the app would fare on one map.

    pairs: (start vertex, destination) pairs a person can ask for (per destination, every vertex
    but the one nearest it); crashing_pairs: those that trap. ``traps`` holds a few examples.
    """

    decode_error: str | None = None
    vertices: int = 0
    tags: int = 0
    waypoints: int = 0
    isolated_vertices: tuple[int, ...] = ()
    components: int = 0
    pairs: int = 0
    crashing_pairs: int = 0
    unreachable_waypoints: tuple[str, ...] = ()
    traps: tuple[str, ...] = ()

    @property
    def ok(self) -> bool:
        """Decodes, builds, and every pair routes."""
        return (
            self.decode_error is None
            and not self.traps
            and self.crashing_pairs == 0
            and not self.isolated_vertices
            and not self.unreachable_waypoints
        )

    def __str__(self) -> str:
        if self.decode_error is not None:
            return f"does not decode: {self.decode_error}"
        return (
            f"{self.vertices} vertices, {self.tags} tags, {self.waypoints} waypoints: "
            f"{len(self.isolated_vertices)} isolated, {self.components} component(s), "
            f"{self.crashing_pairs}/{self.pairs} crashing pairs"
            + (f", traps: {'; '.join(self.traps)}" if self.traps else "")
        )


# --------------------------------------------------------------------------- 1. decoding


def decode_app_map(document: Any) -> AppMap:
    """What ``JSONDecoder().decode(RawMap.self, …)`` accepts; AppDecodeError otherwise."""
    root = _object(document, "$")
    vertices = []
    for where, v in _entries(root, "odometry_vertices"):
        pose_id = _int(_key(v, "poseId", where), f"{where}.poseId")
        position = _pose(v, where)
        listed = _array(_key(v, "neighbors", where), f"{where}.neighbors")
        neighbors = tuple(_int(n, f"{where}.neighbors[{j}]") for j, n in enumerate(listed))
        vertices.append(AppVertex(pose_id=pose_id, position=position, neighbors=neighbors))
    tags = []
    for where, t in _entries(root, "tag_vertices"):
        tag_id = _int(_key(t, "id", where), f"{where}.id")
        tags.append(Destination(kind="tag", key=str(tag_id), position=_pose(t, where)))
    waypoints = []
    for where, w in _entries(root, "waypoints_vertices"):
        name = _string(_key(w, "id", where), f"{where}.id")
        waypoints.append(Destination(kind="waypoint", key=name, position=_pose(w, where)))
    return AppMap(vertices=tuple(vertices), tags=tuple(tags), waypoints=tuple(waypoints))


def _pose(vertex: Mapping[str, Any], where: str) -> tuple[float, float, float]:
    """The vertex's translation, after checking its rotation decodes too."""
    rotation = _object(_key(vertex, "rotation", where), f"{where}.rotation")
    for k in "xyzw":
        _float(_key(rotation, k, f"{where}.rotation"), f"{where}.rotation.{k}")
    return _vector3(_key(vertex, "translation", where), f"{where}.translation")


def _entries(root: Mapping[str, Any], key: str) -> list[tuple[str, Mapping[str, Any]]]:
    items = _array(_key(root, key, "$"), key)
    return [(f"{key}[{i}]", _object(item, f"{key}[{i}]")) for i, item in enumerate(items)]


def _key(obj: Mapping[str, Any], key: str, where: str) -> Any:
    if key not in obj or obj[key] is None:
        raise AppDecodeError(f"{where}.{key}", "missing (keyNotFound / valueNotFound)")
    return obj[key]


def _object(value: Any, where: str) -> Mapping[str, Any]:
    if not isinstance(value, Mapping):
        raise AppDecodeError(where, f"expected an object, got {type(value).__name__}")
    return value


def _array(value: Any, where: str) -> list[Any]:
    if not isinstance(value, list):
        raise AppDecodeError(where, f"expected an array, got {type(value).__name__}")
    return value


def _int(value: Any, where: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise AppDecodeError(where, f"expected an Int, got {value!r}")
    if not INT64_MIN <= value <= INT64_MAX:
        raise AppDecodeError(where, f"{value} does not fit an Int")
    return value


def _float(value: Any, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise AppDecodeError(where, f"expected a Float, got {value!r}")
    if not math.isfinite(value) or abs(value) > FLOAT32_MAX:
        raise AppDecodeError(where, f"{value} does not fit a Float")
    return float(value)


def _string(value: Any, where: str) -> str:
    if not isinstance(value, str):
        raise AppDecodeError(where, f"expected a String, got {value!r}")
    return value


def _vector3(value: Any, where: str) -> tuple[float, float, float]:
    obj = _object(value, where)
    x, y, z = (_float(_key(obj, k, where), f"{where}.{k}") for k in "xyz")
    return (x, y, z)


# --------------------------------------------------------------------------- 2–3. the graph


def build_app_graph(app_map: AppMap) -> AppGraph:
    """``renderGraphPath``: the navigation graph under the smaller-id rule; AppTrap on a
    duplicate ``poseId`` or a listed smaller neighbor that is no vertex."""
    graph = AppGraph()
    for vertex in app_map.vertices:
        if vertex.pose_id in graph.position:
            raise AppTrap(f"duplicate poseId {vertex.pose_id} (Dictionary(uniqueKeysWithValues:))")
        graph.position[vertex.pose_id] = vertex.position
        graph.adjacency[vertex.pose_id] = {}
    for vertex in app_map.vertices:
        for neighbor in vertex.neighbors:
            if neighbor < vertex.pose_id:
                if neighbor not in graph.position:
                    raise AppTrap(f"vertex {vertex.pose_id} lists neighbor {neighbor}: no vertex")
                weight = math.dist(vertex.position, graph.position[neighbor])
                graph.adjacency[vertex.pose_id][neighbor] = weight
                graph.adjacency[neighbor][vertex.pose_id] = weight
    return graph


# --------------------------------------------------------------------------- 4. routes


def plan_app_route(
    graph: AppGraph, phone: Sequence[float], destination: Sequence[float]
) -> list[int]:
    """``planPath``: the stops from the vertex nearest the phone to the vertex nearest the
    destination; AppTrap where the app would crash."""
    endpoint = graph.nearest(destination)
    if endpoint is None:
        raise AppTrap("the map has no odometry vertex")
    start = graph.nearest(phone, ignoring=endpoint)
    if start is None:
        raise AppTrap(f"a route of one stop: vertex {endpoint} is the map's only vertex")
    return graph.shortest_path(start, endpoint)


def check_app_map(document: Any) -> ConformanceReport:
    """Decode ``document`` as the app does, build its graph, and try every (start vertex,
    destination) pair; a report, never an exception."""
    try:
        app_map = decode_app_map(document)
    except AppDecodeError as err:
        return ConformanceReport(decode_error=str(err))
    counts = ConformanceReport(
        vertices=len(app_map.vertices), tags=len(app_map.tags), waypoints=len(app_map.waypoints)
    )
    traps: list[str] = []
    tag_ids = [tag.key for tag in app_map.tags]
    if len(set(tag_ids)) < len(tag_ids):
        duplicates = sorted({t for t in tag_ids if tag_ids.count(t) > 1})
        traps.append(f"duplicate tag id(s) {', '.join(duplicates)}")
    last_index = {w.key: i for i, w in enumerate(app_map.waypoints)}
    unreachable = tuple(w.key for i, w in enumerate(app_map.waypoints) if last_index[w.key] != i)
    try:
        graph = build_app_graph(app_map)
    except AppTrap as err:
        return dataclasses.replace(counts, traps=(*traps, str(err)))
    component = graph.components()
    members: dict[int, int] = {}
    for label in component.values():
        members[label] = members.get(label, 0) + 1
    isolated = tuple(v for v in sorted(graph.position) if not graph.adjacency[v])
    pairs = crashing = 0
    destinations = [*app_map.tags, *(app_map.waypoints[i] for i in last_index.values())]
    for destination in destinations:
        endpoint = graph.nearest(destination.position)
        if endpoint is None or len(graph.position) < 2:
            traps.append(f"{destination.kind} {destination.key}: the map has < 2 vertices")
            crashing += 1
            pairs += 1
            continue
        starts = len(graph.position) - 1
        reached = members[component[endpoint]] - 1
        pairs += starts
        crashing += starts - reached
        if starts > reached and len(traps) < MAX_EXAMPLES:
            stranded = next(
                v for v in sorted(graph.position) if component[v] != component[endpoint]
            )
            traps.append(
                f"{destination.kind} {destination.key}: its vertex {endpoint} is unreachable "
                f"from {starts - reached} start(s), e.g. vertex {stranded}"
            )
    return dataclasses.replace(
        counts,
        isolated_vertices=isolated,
        components=len(members),
        pairs=pairs,
        crashing_pairs=crashing,
        unreachable_waypoints=unreachable,
        traps=tuple(traps),
    )
