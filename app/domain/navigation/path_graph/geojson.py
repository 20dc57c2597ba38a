"""The path graph as GeoJSON, in a local metric frame (not WGS84)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from app.domain.navigation.path_graph.model import PathGraph

# =========================================================================== GeoJSON

#: The GeoJSON coordinate system: a local frame, not WGS84 (see :func:`path_graph_to_geojson`).
GEOJSON_COORDINATE_SYSTEM: dict[str, Any] = {
    "name": "invisible-map local",
    "units": "m",
    "axes": ["x", "-z", "y"],
    "description": (
        "not WGS84: a local frame in metres. Each position is [x, -z, y] of the map frame "
        "(ARKit world, y up): easting x, northing -z, altitude y, so a plot seen from above keeps "
        "the map's handedness (left turns look left)."
    ),
}


def path_graph_to_geojson(pg: PathGraph) -> dict[str, Any]:
    """The path graph as a GeoJSON FeatureCollection (RFC 7946 structure, local coordinates).

    Coordinates are ``[x, −z, y]`` of the map frame in metres: x east, −z north, y the height. The
    map frame is right-handed with y up, so (x, −z, y) is right-handed east-north-up and a plot of
    the first two coordinates shows the walk as seen from above without mirroring. It is a local
    frame, not WGS84 longitude/latitude; the top-level foreign member ``coordinate_system`` says
    so, and ``floor_levels_m`` gives the floor heights.

    Point features, ``properties.kind``:
        ``node``      a path node: ``id``, ``floor``, ``pose_index``.
        ``junction``  a crossing: ``id``, ``floor``, ``pose_index`` None.
        ``tag``       a tag: ``id`` (the tag id), ``name``, ``floor``, ``node`` (its anchor).
        ``poi``       a point of interest: ``name``, ``floor``, ``node``.
    LineString features (edges), ``properties.kind`` ``walk``, ``stairs`` or ``elevator``, with
    ``floor`` (the lower one for a floor change), ``length_m``, ``from`` and ``to`` (node ids).
    """
    G = pg.graph
    features: list[dict[str, Any]] = []
    for n, d in G.nodes(data=True):
        features.append(
            _point_feature(
                d["position_m"],
                {
                    "kind": d["kind"],
                    "id": int(n),
                    "floor": int(d["floor"]),
                    "pose_index": d["pose_index"],
                },
            )
        )
    for tag_id, anchor in pg.tags.items():
        features.append(
            _point_feature(
                anchor.position_m,
                {
                    "kind": "tag",
                    "id": int(tag_id),
                    "name": anchor.name,
                    "floor": anchor.floor,
                    "node": anchor.node,
                },
            )
        )
    for anchor in pg.pois:
        features.append(
            _point_feature(
                anchor.position_m,
                {"kind": "poi", "name": anchor.name, "floor": anchor.floor, "node": anchor.node},
            )
        )
    for u, v, d in G.edges(data=True):
        features.append(
            {
                "type": "Feature",
                "geometry": {
                    "type": "LineString",
                    "coordinates": [
                        _geojson_position(G.nodes[u]["position_m"]),
                        _geojson_position(G.nodes[v]["position_m"]),
                    ],
                },
                "properties": {
                    "kind": d["kind"],
                    "floor": int(d["floor"]),
                    "length_m": float(d["length_m"]),
                    "from": int(u),
                    "to": int(v),
                },
            }
        )
    return {
        "type": "FeatureCollection",
        "coordinate_system": dict(GEOJSON_COORDINATE_SYSTEM),
        "floor_levels_m": [float(v) for v in pg.floor_levels_m],
        "features": features,
    }


def _geojson_position(position_m: Sequence[float]) -> list[float]:
    x, y, z = (float(v) for v in position_m)
    return [x, -z, y]


def _point_feature(position_m: Sequence[float], properties: dict[str, Any]) -> dict[str, Any]:
    return {
        "type": "Feature",
        "geometry": {"type": "Point", "coordinates": _geojson_position(position_m)},
        "properties": properties,
    }
