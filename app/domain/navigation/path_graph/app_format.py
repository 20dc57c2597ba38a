"""The app's navigation links (``neighbors``) from a path graph (docs/architecture.md §7), made
so the app cannot crash on them.

    links = app_links(pg.graph, floor_levels_m=pg.floor_levels_m, pose_id=…, positions_m=…)
    links.neighbors[row]          # pose row → the ids it links to (None: the pose is left out)
    links.extra                   # graph nodes that are not poses, as extra odometry vertices
    links.notes                   # what the map file should say (a disconnected walk)
    names, notes = unique_waypoint_names(["Desk", "Desk"])   # ["Desk", "Desk (2)"]

The app (``app.domain.formats.app_model`` models it) adds an edge only from the vertex whose
neighbor id is smaller than its own, traps on a listed neighbor that is no vertex, and traps when a
route's end cannot be reached. So, whatever the path graph is (the walked line, or a corridor
skeleton whose nodes are no poses at all):

- **every link is listed at both ends**;
- **one connected graph**: the path graph's largest connected part (by length, then by nodes) is
  kept; a walk that really falls apart is said so in ``notes``, and the poses and nodes of the
  other parts are left out of the file (the app would otherwise route from them into a crash);
- **every pose is attached**: a graph node that is a pose (``pose_index``) is that pose's vertex;
  any other node becomes an extra vertex numbered after the last pose id; a pose that is no node
  links to both ends of the nearest edge of the kept part (of its floor where there is one), and
  they link back to it. A route therefore starts next to the phone and never jumps between
  floors except along the graph's stairs and elevator edges;
- a graph with no edge (a walk too short to make one) is linked as the chain of its poses;
- **a long walk is thinned**: of more than :data:`MAX_APP_POSES` poses, only every k-th (and the
  last) is listed (:func:`thinned_rows`, ``pose_rows``), graph nodes that are poses all the same,
  so that the file stays far under the app's 10 MiB cap (a vertex is about 280 bytes: a
  100,000-pose walk listed whole would be 27 MiB).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import networkx as nx
import numpy as np
import numpy.typing as npt

from app.domain.navigation.floors import assign_floors
from app.domain.navigation.path_graph.geometry import project_to_segments, tuple3

#: Poses per block when finding the nearest edge of poses that are not nodes.
_CHUNK = 256
#: Most poses the app's file lists (graph nodes that are poses aside): about 1.4 MiB of vertices.
MAX_APP_POSES = 5_000


@dataclass(frozen=True, slots=True, kw_only=True)
class ExtraVertex:
    """A path-graph node that is no pose: ``pose_id`` above every pose id, map-frame position."""

    pose_id: int
    position_m: tuple[float, float, float]
    neighbors: list[int]


@dataclass(frozen=True, slots=True, kw_only=True)
class AppLinks:
    """Per pose row its neighbors' ids (None where the pose is left out), the extra vertices,
    and notes for the map file."""

    neighbors: list[list[int] | None]
    extra: list[ExtraVertex] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)


def chain_links(pose_id: Sequence[int], *, pose_rows: Sequence[int] | None = None) -> AppLinks:
    """The poses as one chain, each linked to the previous and the next (both ends listed);
    with ``pose_rows``, the chain of those rows only (the others are left out: None)."""
    ids = [int(p) for p in pose_id]
    rows = list(range(len(ids))) if pose_rows is None else [int(r) for r in pose_rows]
    neighbors: list[list[int] | None] = [None] * len(ids)
    for k, row in enumerate(rows):
        neighbors[row] = [ids[rows[j]] for j in (k - 1, k + 1) if 0 <= j < len(rows)]
    return AppLinks(neighbors=neighbors)


def thinned_rows(n: int, max_rows: int = MAX_APP_POSES) -> list[int]:
    """Rows 0, k, 2k, … and the last of ``n`` poses, k the smallest stride that leaves at most
    ``max_rows`` (all rows when there are no more than that)."""
    if n <= max_rows:
        return list(range(n))
    stride = -(-(n - 1) // max(max_rows - 2, 1))  # ceil: the last row comes on top
    rows = list(range(0, n, stride))
    if rows[-1] != n - 1:
        rows.append(n - 1)
    return rows


def thinning_note(n: int, listed: int) -> list[str]:
    """What the map file says when a walk's poses were thinned for the app (empty if not)."""
    if listed >= n:
        return []
    return [
        f"the walk's {n} poses are thinned to {listed} for the app (at most {MAX_APP_POSES} "
        "poses besides the path graph's nodes), so the file stays small"
    ]


def app_links(
    graph: nx.Graph[int],
    *,
    floor_levels_m: Sequence[float],
    pose_id: npt.ArrayLike,
    positions_m: npt.ArrayLike,
    pose_rows: Sequence[int] | None = None,
) -> AppLinks:
    """The links of the app's file from a path graph (see the module docstring).

    graph: node attributes ``position_m`` (x, y, z, map frame, m) and optionally ``pose_index``
    (row of the pose it is, or None); edge attribute ``floor`` (optional, for attaching poses).
    pose_id: (N,) the app's pose ids, increasing; positions_m: (N, 3) the poses, map frame, m.
    pose_rows: the rows of the poses to list (default: all); a pose that is a graph node is
    listed whatever this says, the others are left out (None).
    """
    ids = np.asarray(pose_id, dtype=np.int64).reshape(-1)
    world_p_phone = np.asarray(positions_m, dtype=np.float64).reshape(-1, 3)
    n = ids.shape[0]
    if graph.number_of_edges() == 0:
        return chain_links(ids.tolist(), pose_rows=pose_rows)

    # parts with an edge; a node with none (a lone pose) is attached like any other pose
    parts = sorted(
        (sorted(part) for part in nx.connected_components(graph) if len(part) > 1),
        key=lambda part: (-_length_m(graph, part), -len(part), part[0]),
    )
    kept = parts[0]
    kept_set = set(kept)
    notes = []

    # vertex ids: a node that is a pose keeps its id; any other node gets one after the last pose
    app_id: dict[int, int] = {}
    node_of_row: dict[int, int] = {}
    for node in kept:
        row = graph.nodes[node].get("pose_index")
        if row is not None and 0 <= int(row) < n and int(row) not in node_of_row:
            node_of_row[int(row)] = node
            app_id[node] = int(ids[row])
    next_id = int(ids.max()) + 1 if n else 0
    extra_nodes = [node for node in kept if node not in app_id]
    for k, node in enumerate(extra_nodes):
        app_id[node] = next_id + k

    links: dict[int, set[int]] = {app_id[node]: set() for node in kept}
    for u, v in graph.subgraph(kept).edges:
        links[app_id[u]].add(app_id[v])
        links[app_id[v]].add(app_id[u])

    # poses that are no node of the kept part: attach to the nearest edge, or leave out
    listed = range(n) if pose_rows is None else pose_rows
    loose = [int(row) for row in listed if int(row) not in node_of_row]
    left_out: list[int] = []
    if loose:
        edges = list(graph.edges)
        a = np.array([graph.nodes[u]["position_m"] for u, _ in edges], dtype=np.float64)
        b = np.array([graph.nodes[v]["position_m"] for _, v in edges], dtype=np.float64)
        edge_kept = np.array([u in kept_set for u, _ in edges])
        edge_floor = np.array([int(graph.edges[e].get("floor", 0)) for e in edges])
        levels = np.asarray(floor_levels_m, dtype=np.float64)
        pose_floor = (
            assign_floors(world_p_phone[loose, 1], levels)
            if levels.size
            else np.zeros(len(loose), dtype=np.int64)
        )
        for start in range(0, len(loose), _CHUNK):
            rows = loose[start : start + _CHUNK]
            distance_m = project_to_segments(world_p_phone[rows][:, None, :], a[None], b[None])[1]
            # the nearest edge over the whole graph decides the part the pose belongs to
            nearest_any = np.argmin(distance_m, axis=1)
            other_floor = edge_floor[None, :] != pose_floor[start : start + _CHUNK, None]
            candidates = edge_kept[None, :] & ~other_floor
            candidates |= edge_kept[None, :] & ~candidates.any(axis=1)[:, None]
            nearest_kept = np.argmin(np.where(candidates, distance_m, np.inf), axis=1)
            for row, any_e, e in zip(rows, nearest_any, nearest_kept, strict=True):
                if not edge_kept[any_e]:
                    left_out.append(row)
                    continue
                pid = int(ids[row])
                u, v = edges[int(e)]
                links[pid] = {app_id[u], app_id[v]}
                links[app_id[u]].add(pid)
                links[app_id[v]].add(pid)
    if len(parts) > 1:
        dropped_nodes = sum(len(part) for part in parts[1:])
        notes.append(
            f"the walk falls apart into {len(parts)} unconnected parts: only the largest "
            f"({_length_m(graph, kept):.0f} m of path) is navigable; {dropped_nodes} graph "
            f"node(s) and {len(left_out)} pose(s) of the others are left out"
        )

    neighbors: list[list[int] | None] = [
        sorted(links[int(ids[row])]) if int(ids[row]) in links else None for row in range(n)
    ]
    extra = [
        ExtraVertex(
            pose_id=app_id[node],
            position_m=tuple3(graph.nodes[node]["position_m"]),
            neighbors=sorted(links[app_id[node]]),
        )
        for node in extra_nodes
    ]
    return AppLinks(neighbors=neighbors, extra=extra, notes=notes)


def unique_waypoint_names(names: Sequence[str]) -> tuple[list[str], list[str]]:
    """Names made unique (the app keys waypoints by name: of two with one name it can only ever
    choose the last): the second "Desk" becomes "Desk (2)", and so on, skipping names taken.
    Returns the names and a note per renamed waypoint."""
    taken = set(names)
    seen: set[str] = set()
    unique, notes = [], []
    for name in names:
        if name not in seen:
            seen.add(name)
            unique.append(name)
            continue
        suffix = 2
        while f"{name} ({suffix})" in taken:
            suffix += 1
        renamed = f"{name} ({suffix})"
        taken.add(renamed)
        seen.add(renamed)
        unique.append(renamed)
        notes.append(f"two points of interest are named {name!r}: the later is {renamed!r}")
    return unique, notes


def _length_m(graph: nx.Graph[int], nodes: Sequence[int]) -> float:
    return float(
        sum(float(d.get("length_m", 0.0)) for _, _, d in graph.subgraph(nodes).edges(data=True))
    )
