"""What is derived from a map version once, by the worker that stores it (issue 19, finding 3):
the app's map file and the dashboard's overview of the version. The API then serves them as
stored instead of decoding the whole map document (16 MiB of JSON for a 100,000-pose walk) per
process and request.

    app_map = app_map_bytes(document, path_graph_document)     # compact JSON bytes
    app_map = app_map_of(map_from_json(document), path_graph)  # the same, read back already
    overview = overview_document(result, raw_session, path_graph, sessions=contributions)
    figure = figure_of_overview(overview)                      # None: another format
    app_map_gz, overview_gz = packed_documents(result, raw_session, path_graph, sessions=…)

Each has a format number stored with it: a version whose stored file was made by another
export is served by building the file again, as before the files were stored.
"""

from __future__ import annotations

import gzip
import json
from collections.abc import Sequence
from typing import Any

from app.domain.formats.map_figure import map_figure
from app.domain.formats.map_io import map_from_json, map_to_app_format
from app.domain.mapping.map_result import MapResult
from app.domain.navigation.path_graph import PathGraph, path_graph_from_json
from app.domain.upload.session import Session

#: The version of what :func:`app_map_bytes` makes of a stored version. It is part of the
#: app-map's ETag: raise it whenever the export changes, so that a phone holding a file made by
#: the older export downloads the new one instead of a 304 (and stored files of the older export
#: are no longer served). 2: links at both ends, one connected part, unique waypoint names,
#: ``notes``. 3: at most 5,000 poses besides the graph's nodes.
APP_MAP_EXPORT = 3
#: The version of :func:`overview_document`'s shape (the dashboard's figure of a version).
OVERVIEW_FORMAT = 1
#: gzip level of the stored and cached app-map and overview: made once per version, so the
#: smaller file wins.
DERIVED_GZIP_LEVEL = 6


def app_map_bytes(document: dict[str, Any], path_graph_document: dict[str, Any] | None) -> bytes:
    """The app's map file (docs/architecture.md §7) of a stored version, compact JSON bytes:
    from its map document (``app.domain.formats.map_io`` format) and its path graph document
    (``path_graph_to_json``; None for a version built before path graphs)."""
    return app_map_of(
        map_from_json(document),
        None if path_graph_document is None else path_graph_from_json(path_graph_document),
    )


def app_map_of(stored: MapResult, path_graph: PathGraph | None) -> bytes:
    """:func:`app_map_bytes` of the version read back already (``map_from_json`` of its
    document, ``path_graph_from_json`` of its path graph)."""
    app_map = map_to_app_format(stored, path_graph=path_graph)
    return json.dumps(app_map, separators=(",", ":"), allow_nan=False).encode()


def overview_document(
    result: MapResult,
    raw_session: Session | None,
    path_graph: PathGraph | None,
    *,
    sessions: Sequence[dict[str, Any]] = (),
) -> dict[str, Any]:
    """The dashboard's overview of a version: the figure its map page draws (downsampled
    trajectories, tags, path graph, points of interest; ``app.domain.formats.map_figure``),
    JSON-ready. ``result``: the version as stored (``map_from_json`` of its document);
    ``raw_session``: the upload of a map of one session (a map of several has no raw line: each
    session's raw odometry is in its own frame); ``sessions``: ``statistics["sessions"]``."""
    several = len(sessions) >= 2
    figure = map_figure(
        result,
        None if several else raw_session,
        path_graph,
        session_starts=[int(c["first_pose_row"]) for c in sessions],
        session_names=[f"Session {c['session_id']}" for c in sessions],
    )
    return {"format": OVERVIEW_FORMAT, "figure": figure}


def packed_documents(
    result: MapResult,
    raw_session: Session | None,
    path_graph: PathGraph | None,
    *,
    sessions: Sequence[dict[str, Any]] = (),
) -> tuple[bytes, bytes]:
    """The app-map (:func:`app_map_of`) and the overview (:func:`overview_document`, compact
    JSON) as stored: each gzip at :data:`DERIVED_GZIP_LEVEL` with no timestamp, so that the same
    version always gives the same bytes (the worker's and a backup import's blobs agree)."""
    overview = overview_document(result, raw_session, path_graph, sessions=sessions)
    overview_json = json.dumps(overview, separators=(",", ":"), allow_nan=False).encode()
    return (
        gzip.compress(app_map_of(result, path_graph), compresslevel=DERIVED_GZIP_LEVEL, mtime=0),
        gzip.compress(overview_json, compresslevel=DERIVED_GZIP_LEVEL, mtime=0),
    )


def figure_of_overview(overview: Any) -> dict[str, Any] | None:
    """The figure of a stored overview; None if it was made in another format."""
    if not isinstance(overview, dict) or overview.get("format") != OVERVIEW_FORMAT:
        return None
    figure = overview.get("figure")
    return figure if isinstance(figure, dict) else None
