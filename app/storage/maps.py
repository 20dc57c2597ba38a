"""Maps and their versions: what a worker stores, what the API reads.

A map belongs to one session. Each successful build job adds a *version* (numbered 1, 2, … per
map); the newest version is the map's current one. A version keeps our lossless map document
(``app.domain.formats.map_io.map_to_json``, gzip-compressed), the plot, the parameters, statistics
and metrics as JSON, and one ``map_tag`` row per tag so that tag poses are queryable. The bulk data
(document, plot, path graph) is in content-addressed blobs (``app.storage.blobs``) that a worker
writes before the small transaction that stores the version (:func:`write_version_bulk`); versions
stored before the blobs hold it in their row. The worker also stores what is derived from a version
once (``app.domain.formats.derived_documents``: the app's map file and the dashboard's overview) as
blobs the version refers to (:class:`DerivedDocuments`); older versions have none.

Versions always match their walks (issue 25): every change of what a map's next version is built
from (a session added, taken out or merged in, a rebuild with other parameters or sessions) bumps
the map's *generation* (:func:`bump_generation`, under the map row's lock: :func:`lock_maps`),
a build job carries the generation it was queued for (``job.map_generation``), and
:func:`store_version` is called only while it is still the map's (:func:`generation_for_store`,
which takes the same lock), so the newest version is always one of the map's current sessions
and parameters. Changes of maps lock their rows in ascending id order, so two of them never
deadlock; a build storing locks its map before its job, as a change does.
"""

from __future__ import annotations

import dataclasses
import gzip
import hashlib
import json
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, fields
from datetime import datetime
from typing import Any

from sqlalchemy import Row, delete, func, select, true, update
from sqlalchemy.orm import Session, defer

from app.domain.evaluation.metrics import SHIFT_METRIC_VERSION
from app.domain.evaluation.table import Evaluation
from app.domain.formats.map_io import map_to_json
from app.domain.frames import pose_to_xyz_quat_xyzw
from app.domain.json_values import finite_or_none
from app.domain.mapping.map_result import MapResult
from app.domain.upload.session import display_name_of
from app.storage import blobs, queue
from app.storage.changes import MAP_CHANGES
from app.storage.db import Database
from app.storage.orm import (
    Job,
    JobState,
    MapRow,
    MapSession,
    MapTag,
    MapVersion,
    SessionImage,
    utc_now,
)
from app.storage.rows import info_from_row

#: The job kind that turns a map's sessions into a map version.
BUILD_MAP = "build_map"

#: Load options for a version's metadata without its (large) map document and plot.
_WITHOUT_BLOBS = (
    defer(MapVersion.map_json_gzip),
    defer(MapVersion.plot_png),
    defer(MapVersion.path_graph_gzip),
)


@dataclass(frozen=True, slots=True, kw_only=True)
class DerivedDocuments:
    """What a worker derives from a version once, stored as blobs with it: the app's map file
    (gzip) made by export ``app_map_export``, and the dashboard's overview (gzip JSON)."""

    app_map_gzip: bytes
    app_map_export: int
    overview_gzip: bytes


class MapNotFound(LookupError):
    """Raised when no map (or no such version of it) exists."""

    def __init__(self, map_id: int, number: int | None = None) -> None:
        what = f"map {map_id}" if number is None else f"version {number} of map {map_id}"
        super().__init__(f"{what} not found")
        self.map_id = map_id
        self.number = number


@dataclass(frozen=True, slots=True, kw_only=True)
class VersionInfo:
    """One version of a map, without its (large) map document and plot."""

    id: int
    map_id: int
    number: int
    job_id: int | None
    created_at: datetime
    params: dict[str, Any]
    statistics: dict[str, Any]
    metrics: dict[str, Any]
    tag_count: int
    detections_used: int
    detections_rejected: int
    rejections: list[dict[str, Any]]
    warnings: list[str]
    content_sha256: str
    #: the sessions it was optimized from, in order (the first is the reference frame); empty for
    #: versions made before maps held several sessions (made from the map's ``session_id``)
    session_ids: list[int]
    #: the blobs of its derived documents (:class:`DerivedDocuments`; None: not stored) and the
    #: export that made the stored app-map
    app_map_sha256: str | None = None
    app_map_export: int | None = None
    overview_sha256: str | None = None
    #: the map's generation it was built for (None: stored before generations)
    generation: int | None = None

    @classmethod
    def from_row(cls, row: MapVersion) -> VersionInfo:
        return info_from_row(cls, row, session_ids=list(row.session_ids or []))


@dataclass(frozen=True, slots=True, kw_only=True)
class MapInfo:
    """A map with its current version (None until the first build succeeds).

    name: the upload's ``map_id``; display_name: the name people see (set by an admin, else the
    name typed in the app: ``app.domain.upload.session.display_name_of(name)``); image_sha256: of
    the session's picture, None without one.
    """

    id: int
    name: str
    session_id: int
    created_at: datetime
    version_count: int
    current: VersionInfo | None
    display_name: str = ""
    image_sha256: str | None = None
    #: the sessions it is made of now, in order (the next build uses them)
    session_ids: list[int]
    #: bumped by every change of its sessions or a rebuild's parameters (module docstring)
    generation: int = 0
    #: the queued or running build of this generation (None: none is under way); read for one
    #: map (:func:`get_map`), not for a page of them (:func:`list_maps`: always None), so not
    #: compared (a map is the same map either way)
    pending_job_id: int | None = field(default=None, compare=False)
    #: grows with every corridor edit added or deleted (``app.storage.corridor_edits``)
    corridor_edits_revision: int = 0

    @property
    def up_to_date(self) -> bool:
        """Whether the current version was built from the map's current sessions and parameters
        (its generation; a version stored before generations: its sessions)."""
        current = self.current
        if current is None:
            return False
        if current.generation is not None:
            return current.generation == self.generation
        return (current.session_ids or [self.session_id]) == self.session_ids


@dataclass(frozen=True, slots=True, kw_only=True)
class TagPose:
    """A tag in a map version: position (m) and orientation (quaternion x, y, z, w), map frame."""

    tag_id: int
    position_m: tuple[float, float, float]
    quat_xyzw: tuple[float, float, float, float]
    detection_count: int
    covariance: list[float] | None


# --------------------------------------------------------------------------- writing


def create_map(
    db_session: Session, *, name: str, session_id: int, display_name: str | None = None
) -> int:
    now = utc_now()
    row = MapRow(name=name, display_name=display_name, session_id=session_id, created_at=now)
    db_session.add(row)
    db_session.flush()
    db_session.add(MapSession(map_id=row.id, session_id=session_id, added_at=now))
    db_session.flush()
    MAP_CHANGES.note(db_session, row.id)
    return row.id


def set_display_name(db_session: Session, map_id: int, display_name: str) -> MapInfo:
    """Change the name people see; MapNotFound if there is no such map."""
    row = db_session.get(MapRow, map_id)
    if row is None:
        raise MapNotFound(map_id)
    row.display_name = display_name
    db_session.flush()
    MAP_CHANGES.note(db_session, map_id)
    return _map_info(db_session, row)


# --------------------------------------------------------------------------- sessions of a map


class MapMembershipError(ValueError):
    """A change of a map's sessions that cannot be made. ``code``: ``already_in_map``,
    ``not_in_map``, ``last_session``, ``same_map``."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(message)
        self.code = code


def lock_maps(db_session: Session, map_ids: Sequence[int], *, for_delete: bool = False) -> None:
    """Lock the rows of maps ``map_ids`` to the end of the transaction, in ascending id order
    (so that two changes of the same maps never deadlock): PostgreSQL's ``FOR NO KEY UPDATE``,
    which holds back other changes of these maps and builds storing into them but not uploads
    or localizations that merely refer to them; ``for_delete``: ``FOR UPDATE``, for a map about
    to be deleted. Missing maps are skipped (the caller's read then says MapNotFound). SQLite's
    writers run one at a time anyway (``BEGIN IMMEDIATE``)."""
    db_session.execute(
        select(MapRow.id)
        .where(MapRow.id.in_(sorted(set(map_ids))))
        .order_by(MapRow.id)
        .with_for_update(key_share=not for_delete)
    ).all()


def bump_generation(db_session: Session, map_id: int) -> int:
    """Advance map ``map_id``'s generation (the caller holds its lock: :func:`lock_maps`): what
    is being built for the old one will not be stored. Returns the new one. Raises
    MapNotFound."""
    generation = db_session.scalar(
        update(MapRow)
        .where(MapRow.id == map_id)
        .values(generation=MapRow.generation + 1)
        .returning(MapRow.generation)
    )
    if generation is None:
        raise MapNotFound(map_id)
    MAP_CHANGES.note(db_session, map_id)
    return int(generation)


def map_generation(db_session: Session, map_id: int) -> int | None:
    """Map ``map_id``'s generation now (no lock); None if the map is gone."""
    generation = db_session.scalar(select(MapRow.generation).where(MapRow.id == map_id))
    return None if generation is None else int(generation)


def generation_for_store(db_session: Session, map_id: int) -> int | None:
    """Lock map ``map_id`` (as :func:`lock_maps`) and read its generation, in the transaction
    that will store a version of it: the version may be stored only if this is the generation
    its build was queued for. None if the map is gone."""
    generation = db_session.scalar(
        select(MapRow.generation).where(MapRow.id == map_id).with_for_update(key_share=True)
    )
    return None if generation is None else int(generation)


def map_session_ids(db_session: Session, map_id: int) -> list[int]:
    """The sessions map ``map_id`` is made of, in order (the first is the reference frame).
    Raises MapNotFound."""
    row = db_session.get(MapRow, map_id)
    if row is None:
        raise MapNotFound(map_id)
    return _session_ids(db_session, row)


def _session_ids(db_session: Session, row: MapRow) -> list[int]:
    ids = list(
        db_session.scalars(
            select(MapSession.session_id).where(MapSession.map_id == row.id).order_by(MapSession.id)
        )
    )
    return ids or [row.session_id]  # a map restored from an archive made before map_session


def add_session(db_session: Session, map_id: int, session_id: int) -> list[int]:
    """Add a session to a map (last in the order); the map's sessions after. Raises MapNotFound,
    MapMembershipError ``already_in_map`` (the session must exist: the caller checks). Locks the
    map first (:func:`lock_maps`): two adds of one session are one add and a 409."""
    lock_maps(db_session, [map_id])
    ids = map_session_ids(db_session, map_id)
    if session_id in ids:
        raise MapMembershipError(
            "already_in_map", f"session {session_id} is already in map {map_id}"
        )
    _ensure_rows(db_session, map_id, ids)
    MAP_CHANGES.note(db_session, map_id)
    db_session.add(MapSession(map_id=map_id, session_id=session_id, added_at=utc_now()))
    db_session.flush()
    return [*ids, session_id]


def remove_session(db_session: Session, map_id: int, session_id: int) -> list[int]:
    """Take a session out of a map (its upload and other maps stay); the map's sessions after.
    The first remaining session becomes the map's reference. Raises MapNotFound,
    MapMembershipError ``not_in_map`` or ``last_session``. Locks the map first
    (:func:`lock_maps`): of two removes racing each other, the second sees the first's result,
    so a map never loses its last session."""
    lock_maps(db_session, [map_id])
    ids = map_session_ids(db_session, map_id)
    if session_id not in ids:
        raise MapMembershipError("not_in_map", f"session {session_id} is not in map {map_id}")
    if len(ids) == 1:
        raise MapMembershipError(
            "last_session",
            f"session {session_id} is the only session of map {map_id}: a map needs one; "
            f"delete the map instead",
        )
    _ensure_rows(db_session, map_id, ids)
    MAP_CHANGES.note(db_session, map_id)
    db_session.execute(
        delete(MapSession).where(MapSession.map_id == map_id, MapSession.session_id == session_id)
    )
    remaining = [i for i in ids if i != session_id]
    row = db_session.get(MapRow, map_id)
    assert row is not None
    row.session_id = remaining[0]
    db_session.flush()
    return remaining


def set_sessions(db_session: Session, map_id: int, session_ids: list[int]) -> None:
    """Make ``session_ids`` (distinct, existing: the caller checks) the map's sessions, in this
    order; the first becomes its reference. Raises MapNotFound. Locks the map first."""
    lock_maps(db_session, [map_id])
    row = db_session.get(MapRow, map_id)
    if row is None:
        raise MapNotFound(map_id)
    if _session_ids(db_session, row) == session_ids:
        return
    MAP_CHANGES.note(db_session, map_id)
    db_session.execute(delete(MapSession).where(MapSession.map_id == map_id))
    now = utc_now()
    for session_id in session_ids:
        db_session.add(MapSession(map_id=map_id, session_id=session_id, added_at=now))
    row.session_id = session_ids[0]
    db_session.flush()


def _ensure_rows(db_session: Session, map_id: int, ids: list[int]) -> None:
    """Write the membership rows of a map that has none yet (restored from an old archive)."""
    present = db_session.scalar(
        select(func.count()).select_from(MapSession).where(MapSession.map_id == map_id)
    )
    if not present:
        for session_id in ids:
            db_session.add(MapSession(map_id=map_id, session_id=session_id, added_at=utc_now()))
        db_session.flush()


def maps_sharing_tags(
    db_session: Session, tag_ids: list[int], *, exclude_map_id: int | None = None
) -> list[tuple[int, str, list[int]]]:
    """Maps whose current version holds any of ``tag_ids``: (map id, name, the shared tag ids),
    most shared first."""
    if not tag_ids:
        return []
    newest = (
        select(MapVersion.map_id, func.max(MapVersion.number).label("number"))
        .group_by(MapVersion.map_id)
        .subquery()
    )
    rows = db_session.execute(
        select(MapRow.id, MapRow.name, MapTag.tag_id)
        .join(MapVersion, MapVersion.map_id == MapRow.id)
        .join(
            newest,
            (newest.c.map_id == MapVersion.map_id) & (newest.c.number == MapVersion.number),
        )
        .join(MapTag, MapTag.map_version_id == MapVersion.id)
        .where(MapTag.tag_id.in_(sorted(set(tag_ids))))
        .order_by(MapRow.id, MapTag.tag_id)
    ).all()
    shared: dict[int, tuple[str, list[int]]] = {}
    for map_id, name, tag_id in rows:
        if map_id != exclude_map_id:
            shared.setdefault(map_id, (name, []))[1].append(int(tag_id))
    return sorted(
        ((map_id, name, tags) for map_id, (name, tags) in shared.items()),
        key=lambda item: (-len(item[2]), item[0]),
    )


@dataclass(frozen=True, slots=True, kw_only=True)
class VersionBulk:
    """A version's bulk data, stored as blobs (``app.storage.blobs``) before the version:
    what :func:`store_version` needs to refer to it, and the document's small parts."""

    #: SHA-256 of the map document's JSON (the version's ``content_sha256``)
    content_sha256: str
    #: the blobs: the map document (gzip), the plot (None: no plot), the path graph (gzip)
    map_json_sha256: str
    plot_png_sha256: str | None
    path_graph_sha256: str | None
    #: the document's ``rejections`` (a column of the version)
    rejections: list[dict[str, Any]]
    #: the derived documents' blobs (None: none stored) and the app-map's export
    app_map_sha256: str | None = None
    app_map_export: int | None = None
    overview_sha256: str | None = None


def write_version_bulk(
    db: Database,
    *,
    result: MapResult,
    plot_png: bytes | None,
    path_graph: dict[str, Any] | None = None,
    derived: DerivedDocuments | None = None,
    document: dict[str, Any] | None = None,
) -> VersionBulk:
    """Store a version's map document, plot and path graph (and ``derived``, what the worker
    derived from it) as blobs, each chunk in a small transaction of its own (never in the
    transaction that stores the version: issue 19, finding 4); then :func:`store_version` with
    ``bulk=`` makes the version visible. ``document``: ``map_to_json(result)``, if the caller
    has made it already (it takes seconds for a long walk)."""
    bulk = _version_bulk(
        lambda data: blobs.put_blob(db, data),
        result=result,
        plot_png=plot_png,
        path_graph=path_graph,
        document=document,
    )
    if derived is None:
        return bulk
    return dataclasses.replace(
        bulk,
        app_map_sha256=blobs.put_blob(db, derived.app_map_gzip),
        app_map_export=derived.app_map_export,
        overview_sha256=blobs.put_blob(db, derived.overview_gzip),
    )


def _version_bulk(
    put: Callable[[bytes], str],
    *,
    result: MapResult,
    plot_png: bytes | None,
    path_graph: dict[str, Any] | None,
    document: dict[str, Any] | None = None,
) -> VersionBulk:
    if document is None:
        document = map_to_json(result)
    encoded = json.dumps(document, separators=(",", ":"), allow_nan=False).encode()
    return VersionBulk(
        content_sha256=hashlib.sha256(encoded).hexdigest(),
        map_json_sha256=put(gzip.compress(encoded, compresslevel=6, mtime=0)),
        plot_png_sha256=None if plot_png is None else put(plot_png),
        path_graph_sha256=None if path_graph is None else put(_gzip_json(path_graph)),
        rejections=document["rejections"],
    )


def store_version(
    db_session: Session,
    *,
    map_id: int,
    job_id: int | None,
    result: MapResult,
    evaluation: Evaluation,
    path_length_m: float,
    plot_png: bytes | None = None,
    path_graph: dict[str, Any] | None = None,
    session_ids: list[int] | None = None,
    sessions: list[dict[str, Any]] | None = None,
    bulk: VersionBulk | None = None,
    generation: int | None = None,
) -> VersionInfo:
    """Add the next version of ``map_id`` in the caller's transaction. Its bulk data is
    ``bulk``, written beforehand by :func:`write_version_bulk` (the worker: this transaction
    then writes only small rows), or else ``plot_png`` and ``path_graph``
    (``app.domain.navigation.path_graph.path_graph_to_json`` of it), written here as blobs in this
    transaction. ``session_ids``: the sessions it was made from, in order; ``sessions``: what
    each contributed (``statistics["sessions"]``); ``generation``: the map's generation it was
    built for (the worker checks it with :func:`generation_for_store` first). Two builds of
    one map storing at once take their numbers in turn (the map row's lock, held to the commit;
    PostgreSQL's ``FOR NO KEY UPDATE`` does not hold back uploads that refer to the map).
    Raises ``blobs.BlobMissing`` if a blob of ``bulk`` is gone (the caller writes it again)."""
    if bulk is None:
        bulk = _version_bulk(
            lambda data: blobs.put_blob_in(db_session, data),
            result=result,
            plot_png=plot_png,
            path_graph=path_graph,
        )
    elif plot_png is not None or path_graph is not None:
        raise ValueError("store_version: give the bulk data as bulk= or as plot_png/path_graph")
    blobs.require_blobs(
        db_session,
        [
            sha256
            for sha256 in (
                bulk.map_json_sha256,
                bulk.plot_png_sha256,
                bulk.path_graph_sha256,
                bulk.app_map_sha256,
                bulk.overview_sha256,
            )
            if sha256 is not None
        ],
    )
    db_session.execute(select(MapRow.id).where(MapRow.id == map_id).with_for_update(key_share=True))
    number = 1 + (
        db_session.scalar(select(func.max(MapVersion.number)).where(MapVersion.map_id == map_id))
        or 0
    )
    metrics = {
        "shift_pre": finite_or_none(evaluation.shift_pre),
        "shift_opt": finite_or_none(evaluation.shift_opt),
        "shift_metric_version": SHIFT_METRIC_VERSION,
    }
    if evaluation.tags_with_ground_truth:  # the build had ground truth (a rebuild's)
        metrics |= {
            "gt_metric_pre": finite_or_none(evaluation.gt_metric_pre),
            "gt_metric_opt": finite_or_none(evaluation.gt_metric_opt),
            "tag_rmse_pre_m": finite_or_none(evaluation.tag_rmse_pre_m),
            "tag_rmse_opt_m": finite_or_none(evaluation.tag_rmse_opt_m),
            "tags_with_ground_truth": evaluation.tags_with_ground_truth,
        }
    statistics = {
        "poses": int(result.pose_id.shape[0]),
        "path_length_m": path_length_m,
        "tags": len(result.tag_ids),
        "points_of_interest": len(result.poi_names),
        "detections_used": result.detections_used,
        "detections_rejected": len(result.rejections),
        "rejection_counts": dict(result.rejection_counts()),
        "iterations": result.stats.iterations,
        "start_iterations": result.stats.start_iterations,
        "initial_error": result.stats.initial_error,
        "final_error": result.stats.final_error,
        "build_ms": result.stats.build_ms,
        "optimize_ms": result.stats.optimize_ms,
        "marginals_ms": result.stats.marginals_ms,
    }
    if sessions is not None:
        statistics["sessions"] = sessions
    row = MapVersion(
        map_id=map_id,
        number=number,
        job_id=job_id,
        created_at=utc_now(),
        params=result.params.to_dict(),
        statistics=statistics,
        metrics=metrics,
        shift_metric=metrics["shift_opt"],
        tag_count=len(result.tag_ids),
        detections_used=result.detections_used,
        detections_rejected=len(result.rejections),
        rejections=bulk.rejections,
        warnings=list(result.warnings),
        map_json_gzip=None,
        plot_png=None,
        content_sha256=bulk.content_sha256,
        path_graph_gzip=None,
        map_json_sha256=bulk.map_json_sha256,
        plot_png_sha256=bulk.plot_png_sha256,
        path_graph_sha256=bulk.path_graph_sha256,
        app_map_sha256=bulk.app_map_sha256,
        app_map_export=bulk.app_map_export,
        overview_sha256=bulk.overview_sha256,
        session_ids=session_ids,
        generation=generation,
    )
    db_session.add(row)
    db_session.flush()
    for k, tag_id in enumerate(result.tag_ids):
        x, y, z, qx, qy, qz, qw = pose_to_xyz_quat_xyzw(result.world_T_tag[k])
        covariance = result.tag_covariance[k]
        db_session.add(
            MapTag(
                map_version_id=row.id,
                tag_id=int(tag_id),
                x_m=x,
                y_m=y,
                z_m=z,
                qx=qx,
                qy=qy,
                qz=qz,
                qw=qw,
                detection_count=int(result.tag_detection_count[k]),
                covariance=None
                if not bool(math.isfinite(covariance.sum()))
                else [float(v) for v in covariance.ravel()],
            )
        )
    db_session.flush()
    return VersionInfo.from_row(row)


def _gzip_json(document: Any) -> bytes:
    encoded = json.dumps(document, separators=(",", ":"), allow_nan=False).encode()
    return gzip.compress(encoded, compresslevel=6, mtime=0)


def delete_map(db_session: Session, map_id: int) -> None:
    """Delete a map and its versions (the session and its raw upload stay, and so do its jobs,
    with no map)."""
    lock_maps(db_session, [map_id], for_delete=True)
    if db_session.get(MapRow, map_id) is None:
        raise MapNotFound(map_id)
    MAP_CHANGES.note(db_session, map_id)
    queue.keep_jobs_of_deleted_map(db_session, map_id)  # not deleted with it
    db_session.execute(delete(MapRow).where(MapRow.id == map_id))


# --------------------------------------------------------------------------- reading


def get_map(db_session: Session, map_id: int) -> MapInfo:
    row = db_session.get(MapRow, map_id)
    if row is None:
        raise MapNotFound(map_id)
    return _map_info(db_session, row)


def list_maps(
    db_session: Session, *, limit: int = 50, offset: int = 0, tag_id: int | None = None
) -> tuple[list[MapInfo], int]:
    """Maps, newest first, and how many there are; with ``tag_id``, only maps whose current
    version contains that tag."""
    query = select(MapRow.id)
    if tag_id is not None:
        query = query.where(MapRow.id.in_(_maps_with_tag_in_current_version(tag_id)))
    total = db_session.scalar(select(func.count()).select_from(query.subquery())) or 0
    page = (
        select(
            MapRow.id,
            MapRow.name,
            MapRow.session_id,
            MapRow.created_at,
            MapRow.display_name,
            MapRow.generation,
            MapRow.corridor_edits_revision,
        )
        .where(MapRow.id.in_(query.scalar_subquery()) if tag_id is not None else true())
        .order_by(MapRow.id.desc())
        .limit(limit)
        .offset(offset)
    )
    return _map_infos(db_session, db_session.execute(page).all()), total


#: The columns of a version that :class:`VersionInfo` holds (no blobs, no ORM objects).
_VERSION_COLUMNS = tuple(getattr(MapVersion, f.name) for f in fields(VersionInfo))


def _map_infos(
    db_session: Session, rows: Sequence[Row[int, str, int, datetime, str | None, int, int]]
) -> list[MapInfo]:
    """:func:`_map_info` of a page of maps (rows of their columns) in four queries, however
    long the page (not three or four per map: a list of 50 maps made 150 round trips), reading
    columns, not ORM objects."""
    map_ids = [row.id for row in rows]
    if not map_ids:
        return []
    per_map = (
        select(
            MapVersion.map_id,
            func.max(MapVersion.number).label("number"),
            func.count().label("count"),
        )
        .where(MapVersion.map_id.in_(map_ids))
        .group_by(MapVersion.map_id)
        .subquery()
    )
    counts = {map_id: count for map_id, _, count in db_session.execute(select(per_map)).all()}
    newest = db_session.execute(
        select(*_VERSION_COLUMNS).join(
            per_map,
            (per_map.c.map_id == MapVersion.map_id) & (per_map.c.number == MapVersion.number),
        )
    )
    current = {
        version.map_id: info_from_row(
            VersionInfo, version, session_ids=list(version.session_ids or [])
        )
        for version in newest
    }
    pictures = db_session.execute(
        select(SessionImage.session_id, SessionImage.sha256).where(
            SessionImage.session_id.in_([row.session_id for row in rows])
        )
    )
    image_sha256: dict[int, str] = dict(pictures.all())
    members: dict[int, list[int]] = {}
    for map_id, session_id in db_session.execute(
        select(MapSession.map_id, MapSession.session_id)
        .where(MapSession.map_id.in_(map_ids))
        .order_by(MapSession.id)
    ).all():
        members.setdefault(map_id, []).append(session_id)
    return [
        MapInfo(
            id=row.id,
            name=row.name,
            session_id=row.session_id,
            created_at=row.created_at,
            version_count=counts.get(row.id, 0),
            current=current.get(row.id),
            display_name=row.display_name or display_name_of(row.name),
            image_sha256=image_sha256.get(row.session_id),
            session_ids=members.get(row.id) or [row.session_id],
            generation=row.generation,
            corridor_edits_revision=row.corridor_edits_revision,
        )
        for row in rows
    ]


def _pending_builds(db_session: Session, generations: dict[int, int]) -> dict[int, int]:
    """Per map (id → its generation): the newest queued or running build of that generation."""
    pending: dict[int, int] = {}
    if not generations:
        return pending
    for job_id, map_id, generation in db_session.execute(
        select(Job.id, Job.map_id, Job.map_generation)
        .where(
            Job.map_id.in_(list(generations)),
            Job.kind == BUILD_MAP,
            Job.state.in_([JobState.QUEUED.value, JobState.RUNNING.value]),
        )
        .order_by(Job.id)
    ).all():
        if map_id is not None and (generation or 0) == generations[map_id]:
            pending[map_id] = job_id
    return pending


def list_versions(db_session: Session, map_id: int) -> list[VersionInfo]:
    if db_session.get(MapRow, map_id) is None:
        raise MapNotFound(map_id)
    rows = db_session.scalars(
        select(MapVersion)
        .options(*_WITHOUT_BLOBS)
        .where(MapVersion.map_id == map_id)
        .order_by(MapVersion.number)
    )
    return [VersionInfo.from_row(row) for row in rows]


def get_version(db_session: Session, map_id: int, number: int | None = None) -> VersionInfo:
    """A version of a map; the current one when ``number`` is None. Raises MapNotFound."""
    return VersionInfo.from_row(_version_row(db_session, map_id, number, blobs=False))


def map_document(db_session: Session, map_id: int, number: int | None = None) -> dict[str, Any]:
    """The version's map document (``app.domain.formats.map_io`` format)."""
    row = _version_row(db_session, map_id, number)
    packed = version_bytes(db_session, row.map_json_gzip, row.map_json_sha256)
    if packed is None:  # the column was NOT NULL before the blobs; nothing stores none
        raise LookupError(f"version {row.id} of map {map_id} has no map document")
    document: dict[str, Any] = json.loads(gzip.decompress(packed))
    return document


def derived_bytes(db_session: Session, sha256: str | None) -> bytes | None:
    """A stored derived document of a version (``VersionInfo.app_map_sha256``,
    ``overview_sha256``), as stored (gzip); None when the version has none."""
    return None if sha256 is None else blobs.read_blob(db_session, sha256)


def plot_png(db_session: Session, map_id: int, number: int | None = None) -> bytes | None:
    row = _version_row(db_session, map_id, number)
    return version_bytes(db_session, row.plot_png, row.plot_png_sha256)


def version_bytes(db_session: Session, inline: bytes | None, sha256: str | None) -> bytes | None:
    """A version's bulk data: in its row (versions stored before the ``blob`` table, and
    restored ones), else in the blob its row names; None when it has none."""
    if inline is not None:
        return bytes(inline)
    if sha256 is None:
        return None
    return blobs.read_blob(db_session, sha256)


def tag_poses(db_session: Session, version_id: int) -> list[TagPose]:
    rows = db_session.scalars(
        select(MapTag).where(MapTag.map_version_id == version_id).order_by(MapTag.tag_id)
    )
    return [
        TagPose(
            tag_id=row.tag_id,
            position_m=(row.x_m, row.y_m, row.z_m),
            quat_xyzw=(row.qx, row.qy, row.qz, row.qw),
            detection_count=row.detection_count,
            covariance=row.covariance,
        )
        for row in rows
    ]


def _version_row(
    db_session: Session, map_id: int, number: int | None, *, blobs: bool = True
) -> MapVersion:
    if db_session.get(MapRow, map_id) is None:
        raise MapNotFound(map_id)
    query = select(MapVersion).where(MapVersion.map_id == map_id)
    if not blobs:
        query = query.options(*_WITHOUT_BLOBS)
    if number is None:
        query = query.order_by(MapVersion.number.desc()).limit(1)
    else:
        query = query.where(MapVersion.number == number)
    row = db_session.scalar(query)
    if row is None:
        raise MapNotFound(map_id, number)
    return row


def _map_info(db_session: Session, row: MapRow) -> MapInfo:
    """The map of ``row`` (one map; a page of them: :func:`_map_infos`)."""
    count = db_session.scalar(
        select(func.count()).select_from(MapVersion).where(MapVersion.map_id == row.id)
    )
    current = db_session.scalar(
        select(MapVersion)
        .options(*_WITHOUT_BLOBS)
        .where(MapVersion.map_id == row.id)
        .order_by(MapVersion.number.desc())
        .limit(1)
    )
    image_sha256 = db_session.scalar(
        select(SessionImage.sha256).where(SessionImage.session_id == row.session_id)
    )
    return MapInfo(
        id=row.id,
        name=row.name,
        session_id=row.session_id,
        created_at=row.created_at,
        version_count=count or 0,
        current=VersionInfo.from_row(current) if current is not None else None,
        display_name=row.display_name or display_name_of(row.name),
        image_sha256=image_sha256,
        session_ids=_session_ids(db_session, row),
        generation=row.generation,
        pending_job_id=_pending_builds(db_session, {row.id: row.generation}).get(row.id),
        corridor_edits_revision=row.corridor_edits_revision,
    )


def _maps_with_tag_in_current_version(tag_id: int) -> Any:
    newest = (
        select(MapVersion.map_id, func.max(MapVersion.number).label("number"))
        .group_by(MapVersion.map_id)
        .subquery()
    )
    return (
        select(MapVersion.map_id)
        .join(
            newest,
            (newest.c.map_id == MapVersion.map_id) & (newest.c.number == MapVersion.number),
        )
        .join(MapTag, MapTag.map_version_id == MapVersion.id)
        .where(MapTag.tag_id == tag_id)
    )
