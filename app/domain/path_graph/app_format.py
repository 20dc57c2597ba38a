"""The app's navigation links (``neighbors``) from a path graph (docs/architecture.md §7)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from app.domain.errors import MapFormatError
from app.domain.floors import assign_floors
from app.domain.path_graph.geometry import project_to_segments, tuple3
from app.domain.path_graph.model import PathGraph

# =========================================================================== the app's format


#: Poses per block when finding the nearest edge of poses that are not nodes.
_APP_CHUNK = 256


@dataclass(frozen=True, slots=True, kw_only=True)
class AppVertex:
    """An extra odometry vertex of the app's format (architecture §7): a path-graph node that is
    no pose (a junction, or any node of a corridor skeleton).

    pose_id: the id it is given, above every pose id of the map; position_m: map frame, m.
    neighbors: the pose ids it links to.
    """

    pose_id: int
    position_m: tuple[float, float, float]
    neighbors: list[int]


def app_neighbors(
    pg: PathGraph, *, pose_id: npt.ArrayLike, positions_m: npt.ArrayLike
) -> tuple[list[list[int]], list[AppVertex]]:
    """The app format's ``neighbors`` from a path graph: per pose row, and the junction vertices.

    pose_id: (N,) the app's pose ids; positions_m: (N, 3) the poses' positions, map frame, m.

    - A pose that is a graph node links to its graph neighbours.
    - A node that is no pose (a junction; every node of a corridor skeleton), ``k`` = 0, 1, … in
      node-id order, becomes an extra vertex with pose id ``max(pose_id) + 1 + k``, linking to
      its graph neighbours.
    - A pose that is not a node (simplified away, or a later pass merged into an earlier one)
      links to the two ends of the nearest edge of its floor, and they list it back (the app adds
      an edge only from the vertex with the larger id, and a corridor skeleton's nodes are all
      extra vertices with ids above every pose), so every pose reaches the graph in the app.
    """
    ids = np.asarray(pose_id, dtype=np.int64).reshape(-1)
    world_p_phone = np.asarray(positions_m, dtype=np.float64).reshape(-1, 3)
    n = ids.shape[0]
    G = pg.graph
    junctions = sorted(node for node in G.nodes if G.nodes[node]["pose_index"] is None)
    base = int(ids.max()) + 1 if n else 0
    app_id = {node: base + k for k, node in enumerate(junctions)}
    pose_nodes: dict[int, int] = {}
    for node in G.nodes:
        row = G.nodes[node]["pose_index"]
        if row is not None:
            if not 0 <= row < n:
                raise MapFormatError(f"path graph node {node} is pose {row}, not in this map")
            app_id[node] = int(ids[row])
            pose_nodes[int(row)] = node

    neighbors: list[list[int]] = [[] for _ in range(n)]
    back: dict[int, list[int]] = {}  # node → the loose poses that link to it
    for row, node in pose_nodes.items():
        neighbors[row] = [app_id[m] for m in G.neighbors(node)]
    loose = [row for row in range(n) if row not in pose_nodes]
    if loose and G.number_of_edges() > 0:
        edge_list: list[tuple[int, int]] = list(G.edges)
        a = np.array([G.nodes[u]["position_m"] for u, _ in edge_list], dtype=np.float64)
        b = np.array([G.nodes[v]["position_m"] for _, v in edge_list], dtype=np.float64)
        edge_floor = np.array([G.edges[e]["floor"] for e in edge_list], dtype=np.int64)
        levels = np.asarray(pg.floor_levels_m, dtype=np.float64)
        pose_floor = assign_floors(world_p_phone[loose, 1], levels)
        for start in range(0, len(loose), _APP_CHUNK):
            rows = loose[start : start + _APP_CHUNK]
            distance_m = project_to_segments(world_p_phone[rows][:, None, :], a[None], b[None])[1]
            other_floor = edge_floor[None, :] != pose_floor[start : start + _APP_CHUNK, None]
            penalty = np.where(other_floor & ~other_floor.all(axis=1)[:, None], np.inf, 0.0)
            nearest = np.argmin(distance_m + penalty, axis=1).tolist()
            for row, e in zip(rows, nearest, strict=True):
                u, v = edge_list[e]
                neighbors[row] = [app_id[u], app_id[v]]
                for node in (u, v):
                    back.setdefault(node, []).append(int(ids[row]))
    elif loose and G.number_of_nodes() > 0:
        first = next(iter(G.nodes))
        for row in loose:
            neighbors[row] = [app_id[first]]
            back.setdefault(first, []).append(int(ids[row]))
    for row, node in pose_nodes.items():
        neighbors[row] += back.get(node, [])

    vertices = [
        AppVertex(
            pose_id=app_id[node],
            position_m=tuple3(G.nodes[node]["position_m"]),
            neighbors=[app_id[m] for m in G.neighbors(node)] + back.get(node, []),
        )
        for node in junctions
    ]
    return neighbors, vertices
