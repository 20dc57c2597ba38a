"""The path graph: where a pedestrian can walk in a map — the walked path, with junctions where it
crosses itself, floors, and stairs/elevators where it changes floor.

Data model (``model.py``; built in ``build.py``, exported by ``json_format.py``, ``geojson.py``
and ``app_format.py``):

- ``graph``: an undirected ``networkx.Graph`` with integer node ids.
  Node attributes: ``position_m`` (x, y, z) in the map frame (y up), ``floor`` (int, 0 = lowest),
  ``kind`` (``"node"`` for a kept pose, ``"junction"`` for a crossing), ``pose_index`` (int, the
  row of the pose in the map's trajectory; None for junctions).
  Edge attributes: ``length_m`` (3-D length, m), ``kind`` (``"walk"``, ``"stairs"`` or
  ``"elevator"``), ``floor`` (the floor of a walk edge; for a floor change, the lower floor).
- ``floor_levels_m``: height of each floor, m, lowest first (``app.domain.navigation.floors``).
- ``tags``: tag id → :class:`Anchor` (the node the tag is reached from).
- ``pois``: the points of interest, each an :class:`Anchor` with its name.

Building, storing and exporting it:

    pg = build_path_graph(result)                       # from an optimized MapResult
    pg = build_path_graph_from_arrays(positions_m, tag_ids=…, tag_positions_m=…)
    document = path_graph_to_json(pg)                   # lossless, JSON-safe
    pg = path_graph_from_json(document)
    feature_collection = path_graph_to_geojson(pg)      # nodes, junctions, tags, POIs, edges
    map_to_app_format(result, path_graph=pg)            # app.domain.formats.map_io, links from
                                                        # app_format.app_links

Node ids: a pose node's id is its row in the trajectory (``pose_index``, 0 … N−1); junctions get
ids from N up, in the order they were made. Ids are not contiguous: poses simplified away, merged
into an earlier pass or erased with a small loop, and junctions merged into a knot, leave gaps.
"""

from __future__ import annotations

from app.domain.navigation.path_graph.app_format import (
    AppLinks,
    ExtraVertex,
    app_links,
    chain_links,
    unique_waypoint_names,
)
from app.domain.navigation.path_graph.build import (
    COINCIDENT_M,
    DEFAULT_PATH_GRAPH_PARAMS,
    MIN_STEP_M,
    PathGraphParams,
    build_path_graph,
    build_path_graph_from_arrays,
)
from app.domain.navigation.path_graph.geojson import (
    GEOJSON_COORDINATE_SYSTEM,
    path_graph_to_geojson,
)
from app.domain.navigation.path_graph.json_format import (
    PATH_GRAPH_FORMAT,
    PATH_GRAPH_FORMAT_VERSION,
    path_graph_from_json,
    path_graph_to_json,
)
from app.domain.navigation.path_graph.model import (
    EDGE_KINDS,
    ELEVATOR,
    JUNCTION,
    NODE,
    STAIRS,
    WALK,
    Anchor,
    PathGraph,
)

__all__ = [
    "COINCIDENT_M",
    "DEFAULT_PATH_GRAPH_PARAMS",
    "EDGE_KINDS",
    "ELEVATOR",
    "GEOJSON_COORDINATE_SYSTEM",
    "JUNCTION",
    "MIN_STEP_M",
    "NODE",
    "PATH_GRAPH_FORMAT",
    "PATH_GRAPH_FORMAT_VERSION",
    "STAIRS",
    "WALK",
    "Anchor",
    "AppLinks",
    "ExtraVertex",
    "PathGraph",
    "PathGraphParams",
    "app_links",
    "build_path_graph",
    "build_path_graph_from_arrays",
    "chain_links",
    "path_graph_from_json",
    "path_graph_to_geojson",
    "path_graph_to_json",
    "unique_waypoint_names",
]
