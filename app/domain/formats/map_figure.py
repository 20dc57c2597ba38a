"""What the map page plots, per floor, top-down in the map's x–z plane: raw and optimized
trajectory, tags with their 2σ position ellipses, the path graph, points of interest, and a
route when there is one. The page's script draws it with plotly.js; the same numbers fill the
tables next to each plot.

    figure = map_figure(result, raw_session, path_graph)     # JSON-ready dict
    figure = with_route(figure, route)                       # the route drawn too
    figure = with_path_graph(figure, edited_graph)           # another graph's edges, nodes, POIs

Shape of the figure (positions in m, rounded to mm)::

    {"tag_count": K, "floors": [{"index": 0, "name": "Floor 1", "level_m": 0.0,
        "raw": {"x": [...], "z": [...]}, "optimized": {...},      # None breaks the line
        "walk": {...}, "stairs": {...},                            # path-graph edges
        "nodes": {"x", "z", "id"},                                 # path-graph nodes
        "tags": [{"id", "x", "y", "z", "detections", "ellipse_m": [w, h] | None}],
        "ellipses": {"x", "z"},                                     # outlines, None-separated
        "pois": [{"name", "x", "y", "z"}],
        "route": {"x", "z"} | None}],
     "downsampled": {"poses": N, "shown": n} | None}

A trajectory of more than :data:`MAX_TRAJECTORY_POINTS` poses is drawn through every k-th pose
(and the last, and each session's first and last), so that a page never ships every pose of a
long walk (a 100,000-pose walk drawn whole is megabytes of JSON a browser must plot);
``downsampled`` says so, and the page says it under each plot.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from typing import Any

import numpy as np

from app.domain.frames import FloatArray
from app.domain.mapping.map_result import MapResult
from app.domain.mapping.uncertainty import horizontal_position_ellipse
from app.domain.navigation.floors import assign_floors, find_floor_levels
from app.domain.navigation.path_graph import WALK, PathGraph
from app.domain.navigation.path_graph.app_format import thinned_rows
from app.domain.navigation.routing import Route
from app.domain.upload.session import Session

#: Position ellipses drawn at this many standard deviations.
ELLIPSE_SIGMAS = 2.0
ELLIPSE_POINTS = 24
#: Most poses of one trajectory (raw or optimized) a figure draws.
MAX_TRAJECTORY_POINTS = 5_000


def trajectory_rows(n: int, keep: Iterable[int] = ()) -> list[int]:
    """The rows of an ``n``-pose trajectory that a figure draws: all of them up to
    :data:`MAX_TRAJECTORY_POINTS`, else every k-th and the last, with the rows in ``keep``
    (where a session starts or ends) added."""
    rows = thinned_rows(n, MAX_TRAJECTORY_POINTS)
    if len(rows) == n:
        return rows
    return sorted({*rows, *(int(k) for k in keep if 0 <= int(k) < n)})


def _mm(value: float) -> float | None:
    return round(float(value), 3) if math.isfinite(value) else None


def _line(points_xz: Iterable[Sequence[float] | None]) -> dict[str, list[float | None]]:
    """A polyline as plotly wants it; a None point breaks the line."""
    xs: list[float | None] = []
    zs: list[float | None] = []
    for point in points_xz:
        if point is None:
            xs.append(None)
            zs.append(None)
        else:
            xs.append(_mm(point[0]))
            zs.append(_mm(point[1]))
    return {"x": xs, "z": zs}


def _on_floor(
    xz: FloatArray, floor_of: np.ndarray, floor: int, breaks: Sequence[int] = ()
) -> dict[str, list[float | None]]:
    """The points of one floor, with breaks where the path leaves it (and before each row in
    ``breaks``)."""
    points: list[Sequence[float] | None] = []
    starts = {int(b) for b in breaks if b > 0}
    for k in range(xz.shape[0]):
        if k in starts and points and points[-1] is not None:
            points.append(None)
        if floor_of[k] == floor:
            points.append(xz[k].tolist())
        elif points and points[-1] is not None:
            points.append(None)
    return _line(points)


def map_figure(
    result: MapResult,
    raw_session: Session | None,
    path_graph: PathGraph | None,
    *,
    session_starts: Sequence[int] = (),
    session_names: Sequence[str] = (),
) -> dict[str, Any]:
    """The figure of a map version (``raw_session`` and ``path_graph`` when available).
    ``session_starts``: for a map of several sessions, the first pose row of each; the optimized
    trajectory is broken there (no line joins one walk's end to the next one's start), and each
    floor also has each session's part (``sessions``: name and line), drawn in its own colour.
    ``session_names``: their names (default "Session 1", …)."""
    heights_m = result.world_T_phone[:, 1, 3]
    if path_graph is not None and path_graph.floor_levels_m:
        levels_m = np.asarray(path_graph.floor_levels_m, dtype=np.float64)
    else:
        levels_m = find_floor_levels(heights_m)
    floor_count = max(1, len(levels_m))

    def floor_of(heights: FloatArray) -> np.ndarray:
        if len(levels_m) == 0:
            return np.zeros(len(heights), dtype=np.int64)
        return assign_floors(heights, levels_m)

    n = result.world_T_phone.shape[0]
    starts = [int(s) for s in session_starts]
    shown = np.asarray(trajectory_rows(n, keep=[*starts, *(s - 1 for s in starts)]), dtype=np.int64)
    # the session starts as places in the drawn rows (all rows drawn: the rows themselves)
    shown_starts = [int(np.searchsorted(shown, s)) for s in starts]
    optimized_xz = result.world_T_phone[shown][:, [0, 2], 3]
    optimized_floor = floor_of(heights_m[shown])
    raw_xz = raw_floor = None
    raw_rows = 0
    if raw_session is not None:
        raw_rows = raw_session.world_T_phone.shape[0]
        raw_shown = trajectory_rows(raw_rows)
        raw_xz = raw_session.world_T_phone[raw_shown][:, [0, 2], 3]
        raw_floor = floor_of(raw_session.world_T_phone[raw_shown, 1, 3])
    tag_floor = floor_of(result.world_T_tag[:, 1, 3])
    poi_floor = floor_of(result.world_T_poi[:, 1, 3])

    floors = []
    for floor in range(floor_count):
        level_m = float(levels_m[floor]) if len(levels_m) else 0.0
        tags, outlines = _tags(result, [int(k) for k in np.flatnonzero(tag_floor == floor)])
        floors.append(
            {
                "index": floor,
                "name": f"Floor {floor + 1}",
                "level_m": _mm(level_m),
                "raw": None
                if raw_xz is None or raw_floor is None
                else _on_floor(raw_xz, raw_floor, floor),
                "optimized": _on_floor(optimized_xz, optimized_floor, floor, shown_starts),
                "sessions": _session_lines(
                    optimized_xz, optimized_floor, floor, shown_starts, session_names
                ),
                **_graph(path_graph, floor),
                "tags": tags,
                "ellipses": _line(outlines),
                "pois": [
                    {
                        "name": name,
                        "x": _mm(result.world_T_poi[k, 0, 3]),
                        "y": _mm(result.world_T_poi[k, 1, 3]),
                        "z": _mm(result.world_T_poi[k, 2, 3]),
                    }
                    for k, name in enumerate(result.poi_names)
                    if poi_floor[k] == floor
                ],
                "route": None,
            }
        )
    poses = max(n, raw_rows)
    drawn = max(len(shown), len(raw_xz) if raw_xz is not None else 0)
    return {
        "tag_count": len(result.tag_ids),
        "floors": floors,
        "downsampled": {"poses": poses, "shown": drawn} if drawn < poses else None,
    }


def _session_lines(
    xz: FloatArray,
    optimized_floor: np.ndarray,
    floor: int,
    session_starts: Sequence[int],
    session_names: Sequence[str],
) -> list[dict[str, Any]] | None:
    """Each session's optimized trajectory on ``floor`` (None for a map of one session)."""
    starts = sorted(int(s) for s in session_starts)
    if len(starts) < 2:
        return None
    ends = [*starts[1:], xz.shape[0]]
    names = list(session_names) or [f"Session {k + 1}" for k in range(len(starts))]
    return [
        {"name": name, "line": _on_floor(xz[a:b], optimized_floor[a:b], floor)}
        for name, a, b in zip(names, starts, ends, strict=True)
    ]


def _tags(
    result: MapResult, rows: Sequence[int]
) -> tuple[list[dict[str, Any]], list[Sequence[float] | None]]:
    tags = []
    outlines: list[Sequence[float] | None] = []
    for k in rows:
        position = result.world_T_tag[k, :3, 3]
        ellipse = horizontal_position_ellipse(
            result.world_T_tag[k, :3, :3], result.tag_covariance[k], sigmas=ELLIPSE_SIGMAS
        )
        if ellipse is not None:
            outline = ellipse.outline_xz(position[[0, 2]], points=ELLIPSE_POINTS)
            outlines.extend([*outline.tolist(), None])
        tags.append(
            {
                "id": int(result.tag_ids[k]),
                "x": _mm(position[0]),
                "y": _mm(position[1]),
                "z": _mm(position[2]),
                "detections": int(result.tag_detection_count[k]),
                "ellipse_m": None
                if ellipse is None
                else [_mm(ellipse.width_m), _mm(ellipse.height_m)],
            }
        )
    return tags, outlines


def _graph(path_graph: PathGraph | None, floor: int) -> dict[str, Any]:
    if path_graph is None:
        return {"walk": None, "stairs": None, "nodes": None}
    graph = path_graph.graph
    walk: list[Sequence[float] | None] = []
    changes: list[Sequence[float] | None] = []
    for u, v, data in graph.edges(data=True):
        if data["floor"] != floor:
            continue
        a = graph.nodes[u]["position_m"]
        b = graph.nodes[v]["position_m"]
        target = walk if data["kind"] == WALK else changes
        target.extend([(a[0], a[2]), (b[0], b[2]), None])
    nodes = [(node, data) for node, data in graph.nodes(data=True) if data["floor"] == floor]
    return {
        "walk": _line(walk),
        "stairs": _line(changes) if changes else None,
        "nodes": {
            "id": [int(node) for node, _ in nodes],
            "x": [_mm(data["position_m"][0]) for _, data in nodes],
            "z": [_mm(data["position_m"][2]) for _, data in nodes],
        },
    }


def with_path_graph(figure: dict[str, Any], path_graph: PathGraph) -> dict[str, Any]:
    """``figure`` with the path graph, its nodes and its points of interest taken from
    ``path_graph`` instead (a copy): the version's graph with its map's corridor edits applied,
    so that the plot shows what routes use (a point of interest added in the corridor editor is
    drawn and listed; one removed or renamed is not shown as it was)."""
    floors: list[dict[str, Any]] = []
    for floor in figure["floors"]:
        index = int(floor["index"])
        floors.append(
            {
                **floor,
                **_graph(path_graph, index),
                "pois": [
                    {
                        "name": poi.name,
                        "x": _mm(poi.position_m[0]),
                        "y": _mm(poi.position_m[1]),
                        "z": _mm(poi.position_m[2]),
                    }
                    for poi in path_graph.pois
                    if poi.floor == index
                ],
            }
        )
    return {**figure, "floors": floors}


def with_route(figure: dict[str, Any], route: Route) -> dict[str, Any]:
    """``figure`` with ``route``'s polyline drawn on the floors it passes (a copy)."""
    floors: list[dict[str, Any]] = [dict(floor) for floor in figure["floors"]]
    levels = [floor["level_m"] or 0.0 for floor in floors]
    by_floor: dict[int, list[Sequence[float] | None]] = {f["index"]: [] for f in floors}
    previous: int | None = None
    for x, y, z in route.polyline_m:
        index = int(np.argmin([abs(y - level) for level in levels])) if levels else 0
        if previous is not None and previous != index and by_floor[previous]:
            by_floor[previous].append((x, z))  # finish the segment that leaves the floor
            by_floor[previous].append(None)
        by_floor.setdefault(index, []).append((x, z))
        previous = index
    for entry in floors:
        points = by_floor.get(entry["index"], [])
        entry["route"] = _line(points) if points else None
    return {**figure, "floors": floors}
