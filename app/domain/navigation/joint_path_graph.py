"""The path graph of a map of several sessions (issue 15): one graph over every walk.

    pg = build_joint_path_graph(result, session_starts)    # result: a joint map (joint.py)

Each session's optimized walk becomes its own path graph (``build_path_graph_from_arrays``: its
passes merged, loops closed, floors and stairs found), so no edge ever joins the end of one walk
to the start of the next. The graphs are then put together in the map frame:

1. floors are the map's (levels found over every session's heights), each session's floors
   mapped to the nearest of them;
2. junctions where walks of different sessions cross (the same step as within one walk);
3. *side by side*: two walks along one corridor are a few decimetres apart and need not cross, so
   each node of a later session within ``merge_distance_m`` (horizontal, same floor) of an earlier
   session's node is linked to the nearest one;
4. what is still apart is joined by its nearest pair of nodes on one floor within
   ``JOIN_WITHIN_M``, closest first, so the app gets one connected graph where the walks allow;
5. tags and points of interest (of every session) are attached to their nearest node.

Pose node ids are rows of the joint trajectory (session after session); junctions come after.
This is the builder for several walks until the corridor skeleton (docs/architecture.md §8)
replaces both: a corridor walked in several sessions is linked, not yet merged into one line.
"""

from __future__ import annotations

from collections.abc import Sequence

import networkx as nx
import numpy as np

from app.domain.mapping.map_result import MapResult
from app.domain.navigation.floors import find_floor_levels
from app.domain.navigation.path_graph import (
    DEFAULT_PATH_GRAPH_PARAMS,
    PathGraph,
    PathGraphParams,
    build_path_graph,
    build_path_graph_from_arrays,
)
from app.domain.navigation.path_graph.build import (
    attach_anchors,
    contract_junctions,
    insert_crossings,
)
from app.domain.navigation.path_graph.model import NODE, WALK

#: Farthest apart two walks' nearest nodes may be to join them when nothing else does, m.
JOIN_WITHIN_M = 3.0


def build_joint_path_graph(
    result: MapResult,
    session_starts: Sequence[int],
    *,
    params: PathGraphParams = DEFAULT_PATH_GRAPH_PARAMS,
) -> PathGraph:
    """The path graph of a joint map whose sessions' poses start at rows ``session_starts``
    (see the module docstring); one session: :func:`build_path_graph`'s."""
    starts = sorted({int(s) for s in session_starts} | {0})
    if len(starts) == 1:
        return build_path_graph(result, params=params)
    positions_m = result.world_T_phone[:, :3, 3]
    total = positions_m.shape[0]
    levels_m = find_floor_levels(positions_m[:, 1])
    G: nx.Graph[int] = nx.Graph()
    next_id = total
    session_of: dict[int, int] = {}
    for s, (start, end) in enumerate(zip(starts, [*starts[1:], total], strict=True)):
        if end <= start:
            continue
        part = build_path_graph_from_arrays(positions_m[start:end], params=params)
        floor_of = [int(np.argmin(np.abs(levels_m - h))) for h in part.floor_levels_m]
        renamed: dict[int, int] = {}
        for node, data in part.graph.nodes(data=True):
            if data["kind"] == NODE:
                renamed[node] = start + int(data["pose_index"])
                pose_index: int | None = start + int(data["pose_index"])
            else:
                renamed[node] = next_id
                next_id += 1
                pose_index = None
            G.add_node(
                renamed[node],
                position_m=data["position_m"],
                floor=floor_of[int(data["floor"])],
                kind=data["kind"],
                pose_index=pose_index,
            )
            session_of[renamed[node]] = s
        for u, v, data in part.graph.edges(data=True):
            G.add_edge(
                renamed[u],
                renamed[v],
                length_m=float(data["length_m"]),
                kind=data["kind"],
                floor=floor_of[int(data["floor"])],
            )
    insert_crossings(G, first_junction_id=next_id)
    _link_side_by_side(G, session_of, params.merge_distance_m)
    contract_junctions(G, params.contract_junctions_within_m)
    _join_components(G, JOIN_WITHIN_M)
    tag_ids = [int(t) for t in result.tag_ids]
    tags = attach_anchors(
        G, [str(t) for t in tag_ids], result.world_T_tag[:, :3, 3], levels_m, params
    )
    pois = attach_anchors(G, list(result.poi_names), result.world_T_poi[:, :3, 3], levels_m, params)
    return PathGraph(
        graph=G,
        floor_levels_m=tuple(float(v) for v in levels_m),
        tags=dict(zip(tag_ids, tags, strict=True)),
        pois=tuple(pois),
    )


def _positions(G: nx.Graph[int], nodes: list[int]) -> np.ndarray:
    return np.array([G.nodes[n]["position_m"] for n in nodes], dtype=np.float64).reshape(-1, 3)


def _link_side_by_side(G: nx.Graph[int], session_of: dict[int, int], within_m: float) -> None:
    """Step 3: each node of a later session to the nearest earlier-session node of its floor
    within ``within_m`` (horizontal)."""
    nodes = [n for n in G.nodes if G.nodes[n]["kind"] == NODE and n in session_of]
    if not nodes or within_m <= 0:
        return
    xyz = _positions(G, nodes)
    session = np.array([session_of[n] for n in nodes])
    floor = np.array([G.nodes[n]["floor"] for n in nodes])
    for k, node in enumerate(nodes):
        earlier = (session < session[k]) & (floor == floor[k])
        if not earlier.any():
            continue
        candidates = np.flatnonzero(earlier)
        horizontal_m = np.hypot(xyz[candidates, 0] - xyz[k, 0], xyz[candidates, 2] - xyz[k, 2])
        best = int(np.argmin(horizontal_m))
        if horizontal_m[best] <= within_m:
            other = nodes[int(candidates[best])]
            _add_walk_edge(G, node, other)


def _join_components(G: nx.Graph[int], within_m: float) -> None:
    """Step 4: join the graph's components by their nearest same-floor nodes, closest first,
    while any two are within ``within_m`` (3-D)."""
    while nx.number_connected_components(G) > 1:
        components = [sorted(c) for c in nx.connected_components(G)]
        best: tuple[float, int, int] | None = None
        for i, a in enumerate(components):
            a_xyz = _positions(G, a)
            a_floor = np.array([G.nodes[n]["floor"] for n in a])
            for b in components[i + 1 :]:
                b_xyz = _positions(G, b)
                b_floor = np.array([G.nodes[n]["floor"] for n in b])
                distance_m = np.linalg.norm(a_xyz[:, None, :] - b_xyz[None, :, :], axis=2)
                distance_m[a_floor[:, None] != b_floor[None, :]] = np.inf
                k = int(np.argmin(distance_m))
                d = float(distance_m.flat[k])
                if d <= within_m and (best is None or d < best[0]):
                    best = (d, a[k // len(b)], b[k % len(b)])
        if best is None:
            return
        _add_walk_edge(G, best[1], best[2])


def _add_walk_edge(G: nx.Graph[int], u: int, v: int) -> None:
    if u == v or G.has_edge(u, v):
        return
    length_m = float(np.linalg.norm(_positions(G, [u])[0] - _positions(G, [v])[0]))
    G.add_edge(u, v, length_m=length_m, kind=WALK, floor=int(G.nodes[u]["floor"]))


__all__ = ["JOIN_WITHIN_M", "build_joint_path_graph"]
