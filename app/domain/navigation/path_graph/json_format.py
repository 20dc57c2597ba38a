"""The path graph's own lossless JSON document (stored with each map version)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import networkx as nx

from app.domain.errors import MapFormatError
from app.domain.navigation.path_graph.geometry import tuple3
from app.domain.navigation.path_graph.model import EDGE_KINDS, JUNCTION, NODE, Anchor, PathGraph

# =========================================================================== JSON

PATH_GRAPH_FORMAT = "invisible-map/path-graph"
PATH_GRAPH_FORMAT_VERSION = 1


def path_graph_to_json(pg: PathGraph) -> dict[str, Any]:
    """Our lossless document: plain lists, ints, floats, strings and None; see
    :func:`path_graph_from_json`. Nodes and edges keep the graph's order."""
    G = pg.graph
    return {
        "format": PATH_GRAPH_FORMAT,
        "format_version": PATH_GRAPH_FORMAT_VERSION,
        "floor_levels_m": [float(v) for v in pg.floor_levels_m],
        "nodes": [
            {
                "id": int(n),
                "position_m": [float(v) for v in d["position_m"]],
                "floor": int(d["floor"]),
                "kind": str(d["kind"]),
                "pose_index": None if d["pose_index"] is None else int(d["pose_index"]),
            }
            for n, d in G.nodes(data=True)
        ],
        "edges": [
            {
                "from": int(u),
                "to": int(v),
                "length_m": float(d["length_m"]),
                "kind": str(d["kind"]),
                "floor": int(d["floor"]),
            }
            for u, v, d in G.edges(data=True)
        ],
        "tags": [{"tag_id": int(t), **_anchor_to_json(a)} for t, a in pg.tags.items()],
        "pois": [_anchor_to_json(a) for a in pg.pois],
    }


def path_graph_from_json(document: Any) -> PathGraph:
    """Read back a document written by :func:`path_graph_to_json`; MapFormatError if malformed."""
    if not isinstance(document, Mapping) or document.get("format") != PATH_GRAPH_FORMAT:
        raise MapFormatError(f"not an {PATH_GRAPH_FORMAT} document")
    if document.get("format_version") != PATH_GRAPH_FORMAT_VERSION:
        raise MapFormatError(
            f"unsupported path graph format_version {document.get('format_version')!r}, "
            f"this build reads {PATH_GRAPH_FORMAT_VERSION}"
        )
    try:
        G: nx.Graph[int] = nx.Graph()
        for node in document["nodes"]:
            kind = str(node["kind"])
            if kind not in (NODE, JUNCTION):
                raise ValueError(f"node kind {kind!r}")
            pose_index = node["pose_index"]
            G.add_node(
                int(node["id"]),
                position_m=tuple3(node["position_m"]),
                floor=int(node["floor"]),
                kind=kind,
                pose_index=None if pose_index is None else int(pose_index),
            )
        for edge in document["edges"]:
            u, v, kind = int(edge["from"]), int(edge["to"]), str(edge["kind"])
            if kind not in EDGE_KINDS or u not in G or v not in G:
                raise ValueError(f"edge {u}–{v} of kind {kind!r}")
            G.add_edge(u, v, length_m=float(edge["length_m"]), kind=kind, floor=int(edge["floor"]))
        return PathGraph(
            graph=G,
            floor_levels_m=tuple(float(v) for v in document["floor_levels_m"]),
            tags={int(t["tag_id"]): _anchor_from_json(t) for t in document["tags"]},
            pois=tuple(_anchor_from_json(p) for p in document["pois"]),
        )
    except (KeyError, TypeError, ValueError) as err:
        raise MapFormatError(f"path graph document is missing or has a malformed {err}") from err


def _anchor_to_json(anchor: Anchor) -> dict[str, Any]:
    return {
        "name": anchor.name,
        "node": int(anchor.node),
        "position_m": [float(v) for v in anchor.position_m],
        "floor": int(anchor.floor),
    }


def _anchor_from_json(entry: Mapping[str, Any]) -> Anchor:
    return Anchor(
        name=str(entry["name"]),
        node=int(entry["node"]),
        position_m=tuple3(entry["position_m"]),
        floor=int(entry["floor"]),
    )
