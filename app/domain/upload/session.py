"""The app's upload format (docs/architecture.md §2), parsed once into typed arrays.

    session = parse_session(json.loads(text))      # or load_session(path), gzip or plain
    session.world_T_phone                          # (N, 4, 4) ARKit poses, world frame, y up
    session.detections.phone_T_tag                 # (M, 4, 4) one per tag detection
    session.world_T_tag_observed()                 # (M, 4, 4) raw, unoptimized tag poses

Everything downstream reads these arrays; nobody walks the dicts again. Any malformed input raises
:class:`SessionFormatError` naming the field (``tag_data[3][0].tag_pose``) and the reason.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import re
from collections import Counter
from collections.abc import Container, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from app.domain.errors import NoTagsRecorded, SessionFormatError
from app.domain.frames import (
    PHONE_T_CAMERA_CV,
    FloatArray,
    orthonormalized_stack,
)
from app.domain.json_values import gunzip_if_compressed, json_type_name, value_error_reason
from app.domain.upload.earlier_format import (
    EARLIER_FORMAT,
    convert_earlier_format,
    is_earlier_format,
)
from app.domain.upload.fields import (
    integer_field,
    matrix16_field,
    maybe_not_rigid,
    number_field,
    optional_vector_field,
    require_list,
    require_object,
    rigid_pose,
    vector_field,
    within_pixels,
)
from app.domain.upload.json_stream import WINDOW_CHARS, JsonStream

IntArray = npt.NDArray[np.int64]


#: Why a session with no tag detections makes no map (its build job fails with this).
NO_TAGS_REASON = "no tags were recorded: a map needs at least one tag"

#: The app misspelt this key in at least one real upload; both spellings are read.
LOCATION_KEYS = ("location_data", "location_ data")


@dataclass(frozen=True, slots=True, kw_only=True)
class TagDetections:
    """All tag detections of a session, one row each (M rows), in upload order.

    tag_id: (M,) AprilTag 36h11 ids.
    pose_index: (M,) row in the session's pose arrays of the phone pose the tag was seen from.
    frame_index: (M,) index of the ``tag_data`` frame the detection came from.
    frame_size: (M,) number of detections in that frame (the shift metric uses single ones).
    timestamp_s: (M,) s, the app's clock.
    camera_T_tag: (M, 4, 4) OpenCV camera convention (x right, y down, z forward), m.
    phone_T_tag: (M, 4, 4) ARKit phone frame (x right, y up, −z forward), m.
    intrinsics: (M, 4) fx, fy, cx, cy in px.
    corners_px: (M, 4, 2) detected corner pixels (u, v), tag-frame corners 0..3 in order.
    position_variance_m2: (M, 3) the app's tag position variance (NaN where absent).
    orientation_variance: (M, 4) the app's quaternion variance (NaN where absent).
    joint_covariance: (M, 7, 7) the app's (t, q) covariance from 1-px corner noise (NaN if absent).
    """

    tag_id: IntArray
    pose_index: IntArray
    frame_index: IntArray
    frame_size: IntArray
    timestamp_s: FloatArray
    camera_T_tag: FloatArray
    phone_T_tag: FloatArray
    intrinsics: FloatArray
    corners_px: FloatArray
    position_variance_m2: FloatArray
    orientation_variance: FloatArray
    joint_covariance: FloatArray

    def __len__(self) -> int:
        return int(self.tag_id.shape[0])


@dataclass(frozen=True, slots=True, kw_only=True)
class PointOfInterest:
    """A place named while mapping; ``phone_T_poi`` is relative to pose ``pose_index``."""

    name: str
    pose_index: int
    timestamp_s: float
    phone_T_poi: FloatArray


@dataclass(frozen=True, slots=True, kw_only=True)
class Session:
    """A parsed mapping session.

    pose_id: (N,) the app's pose ids, increasing.
    timestamp_s: (N,) s, non-decreasing.
    world_T_phone: (N, 4, 4) ARKit odometry, world frame y up, m.
    """

    map_id: str
    pose_id: IntArray
    timestamp_s: FloatArray
    world_T_phone: FloatArray
    detections: TagDetections
    pois: tuple[PointOfInterest, ...] = ()
    warnings: tuple[str, ...] = field(default=())

    @property
    def num_poses(self) -> int:
        return int(self.pose_id.shape[0])

    @property
    def tag_ids(self) -> list[int]:
        """Distinct tag ids, sorted."""
        return sorted({int(t) for t in self.detections.tag_id})

    def world_T_tag_observed(self) -> FloatArray:
        """(M, 4, 4) each detection's tag pose in the world, from raw odometry."""
        return self.world_T_phone[self.detections.pose_index] @ self.detections.phone_T_tag

    def path_length_m(self) -> float:
        """Distance walked along the raw odometry, m."""
        steps = np.diff(self.world_T_phone[:, :3, 3], axis=0)
        return float(np.linalg.norm(steps, axis=1).sum())

    def __str__(self) -> str:
        return (
            f"{self.map_id}: {self.num_poses} poses, {self.path_length_m():.1f} m walked, "
            f"{len(self.detections)} detections of {len(self.tag_ids)} tags"
        )


# --------------------------------------------------------------------------- loading


def load_session(path: str | Path, *, correct_poi_pose_id: bool = True) -> Session:
    """Read and parse a session file, plain JSON or gzip-compressed JSON."""
    return parse_session(read_json_document(path), correct_poi_pose_id=correct_poi_pose_id)


def read_json_document(path: str | Path) -> Any:
    """The JSON value in a file that may be gzip-compressed; errors name the file and the reason."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as err:
        raise SessionFormatError("", f"cannot read {path}: {err.strerror or err}") from err
    return decode_json_bytes(raw, source=str(path))


def decode_json_bytes(raw: bytes, *, source: str = "upload") -> Any:
    """Decode (gunzipping if needed) and parse JSON bytes."""
    try:
        raw = gunzip_if_compressed(raw)
    except ValueError as err:
        raise SessionFormatError("", f"{source} is not valid gzip: {err}") from err
    try:
        return json.loads(raw)
    except RecursionError as err:
        raise SessionFormatError("", f"{source} is nested too deeply to be a session") from err
    except UnicodeDecodeError as err:
        raise SessionFormatError("", f"{source} is not UTF-8 text: {err.reason}") from err
    except json.JSONDecodeError as err:
        raise SessionFormatError(
            "", f"{source} is not valid JSON: {err.msg} at line {err.lineno} column {err.colno}"
        ) from err
    except ValueError as err:  # an integer of more digits than Python converts
        raise SessionFormatError(
            "", f"{source} is not valid JSON: {value_error_reason(err)}"
        ) from err


# --------------------------------------------------------------------------- parsing


def parse_session(document: Any, *, correct_poi_pose_id: bool = True) -> Session:
    """Parse the app's upload (a decoded JSON object) into a :class:`Session`.

    ``correct_poi_pose_id``: the app writes a point of interest's ``pose_id`` one too high (it
    points to the next pose); when True (the default) it is moved back by one.
    """
    if not isinstance(document, Mapping):
        raise SessionFormatError("", f"expected a JSON object, got {json_type_name(document)}")
    warnings: list[str] = []
    if is_earlier_format(document):
        try:
            document, notes = convert_earlier_format(document)
            return _parse_current(document, correct_poi_pose_id, list(notes))
        except SessionFormatError as err:
            raise SessionFormatError(err.field, f"{err.reason} ({EARLIER_FORMAT})") from err
    return _parse_current(document, correct_poi_pose_id, warnings)


def parse_session_stream(
    chunks: Iterable[bytes],
    *,
    max_poses: int,
    max_poses_name: str = "max_poses",
    source: str = "upload",
    correct_poi_pose_id: bool = True,
    window_chars: int = WINDOW_CHARS,
) -> Session:
    """Parse the app's upload from its JSON bytes as they come (``chunks``: UTF-8 in pieces of
    any size), the same as ``parse_session(decode_json_bytes(...))`` but without holding the
    document or its object graph: ``pose_data`` entries are checked and written into arrays one
    at a time, ``tag_data`` frames likewise, keys the parser does not read are passed over.

    A ``pose_data`` longer than ``max_poses`` is refused (SessionFormatError ``pose_data``,
    naming ``max_poses_name``) as soon as entry ``max_poses`` + 1 is reached, before the rest is
    read; so is a ``tag_data`` of more than ``max_poses`` detections. Faults are reported as the
    dict parser reports them, in the same order (``map_id``,
    then ``pose_data``, ``tag_data``, points of interest), except that this limit comes first.
    Rows in the app's earlier format, or sections in an order the app does not write
    (``tag_data`` before ``pose_data``), are decoded whole and parsed as before.
    ``window_chars``: the text held ahead of the reading position (:class:`JsonStream`)."""
    stream = JsonStream(chunks, source=source, window_chars=window_chars)
    if stream.peek() == "[":  # no session: passed over an element at a time, then refused
        stream.skip_value()
        stream.end()
        return parse_session([], correct_poi_pose_id=correct_poi_pose_id)
    if stream.peek() != "{":
        document = stream.value()
        stream.end()
        return parse_session(document, correct_poi_pose_id=correct_poi_pose_id)
    sections: dict[str, Any] = {}
    for key in stream.object_keys():
        if key == "pose_data" and isinstance(sections.get("tag_data"), _DetectionColumns):
            raise SessionFormatError("pose_data", "given twice, the second after tag_data")
        if key == "pose_data" and stream.peek() == "[":
            sections[key] = _stream_poses(stream, max_poses, max_poses_name)
        elif key == "tag_data" and stream.peek() == "[" and "pose_data" in sections:
            sections[key] = _stream_detections(
                stream, sections["pose_data"], max_poses, max_poses_name
            )
        elif key in _KEYS_READ:
            sections[key] = stream.value()
        else:
            stream.skip_value()
    stream.end()
    as_dicts = {
        key: ([value.first_entry] if value.count else [])
        if isinstance(value, _PoseColumns)
        else value
        for key, value in sections.items()
    }
    if isinstance(tags := sections.get("tag_data"), _DetectionColumns):
        as_dicts["tag_data"] = [tags.first_frame] if tags.count else []
    if is_earlier_format(as_dicts):
        # the streamed sections hold an entry that is no row: converting stops at it, as it
        # would have stopped at the same entry of the whole list
        return parse_session(as_dicts, correct_poi_pose_id=correct_poi_pose_id)
    return _parse_current(sections, correct_poi_pose_id, [])


#: Rows of pose columns made at once when streaming (grown by doubling past it).
_STREAM_CAPACITY = 1 << 17
#: The top-level keys the parser reads (others are passed over when streaming).
_KEYS_READ = frozenset({"map_id", "pose_data", "tag_data", "camera_intrinsics", *LOCATION_KEYS})


def _stream_poses(stream: JsonStream, max_poses: int, max_poses_name: str) -> Any:
    """``pose_data`` read from ``stream``: :class:`_PoseColumns`, or the entries as a list when
    entry 0 is no object (rows of the earlier format, or a fault the dict parser reports)."""
    # np.empty pages cost memory only once written; past _STREAM_CAPACITY the columns grow
    columns = _PoseColumns(capacity=min(max_poses, _STREAM_CAPACITY))
    entries: list[Any] | None = None
    for i, entry in enumerate(stream.array_items()):
        if i == max_poses:
            raise SessionFormatError(
                "pose_data",
                f"more than {max_poses} poses; a session may have at most {max_poses} "
                f"({max_poses_name})",
            )
        if i == 0 and not isinstance(entry, Mapping):
            entries = []
        if entries is not None:
            entries.append(entry)
        else:
            columns.add(entry)
    return columns if entries is None else entries


def _stream_detections(
    stream: JsonStream, poses: Any, max_detections: int, max_poses_name: str
) -> Any:
    """``tag_data`` read from ``stream`` after ``pose_data``: :class:`_DetectionColumns` when the
    poses were streamed, else the frames as a list. More than ``max_detections`` detections (the
    pose limit: the app records at most a few per pose) are refused as soon as they are reached."""
    if not isinstance(poses, _PoseColumns):
        return stream.value()
    try:
        pose_index: PoseIndex | None = PoseIndex(poses.finish()[0])
    except SessionFormatError:
        pose_index = None  # the poses' fault is reported; the frames are only passed over
    columns = _DetectionColumns(pose_index)
    detections = 0
    for f, frame in enumerate(stream.array_items()):
        detections += len(frame) if isinstance(frame, list) else 1
        if detections > max_detections:
            raise SessionFormatError(
                "tag_data",
                f"more than {max_detections} detections; a session may have at most as many "
                f"detections as poses ({max_detections}, {max_poses_name})",
            )
        columns.add_frame(f, frame)
    return columns


def _parse_current(
    document: Mapping[str, Any], correct_poi_pose_id: bool, warnings: list[str]
) -> Session:
    map_id = document.get("map_id")
    if map_id is None:
        raise SessionFormatError("map_id", "missing")
    if not isinstance(map_id, str):
        raise SessionFormatError("map_id", f"expected a string, got {json_type_name(map_id)}")

    pose_id, timestamp_s, world_T_phone = _parse_poses(document.get("pose_data"))
    index_of_pose_id = PoseIndex(pose_id)
    detections = _parse_tag_data(document.get("tag_data", []), index_of_pose_id)

    location_key = next((k for k in LOCATION_KEYS if k in document), LOCATION_KEYS[0])
    pois = _parse_locations(
        document.get(location_key, []), location_key, index_of_pose_id, correct_poi_pose_id
    )
    if not map_id.strip():
        map_id = derived_map_id(timestamp_s, world_T_phone)
        warnings.append(f"map_id was empty: named {map_id!r} from the upload's poses")
    pois = _name_unnamed_pois(pois, location_key, warnings)
    if len(detections) == 0:
        warnings.append(NO_TAGS_REASON)
    return Session(
        map_id=map_id,
        pose_id=pose_id,
        timestamp_s=timestamp_s,
        world_T_phone=world_T_phone,
        detections=detections,
        pois=tuple(pois),
        warnings=tuple(warnings),
    )


def _parse_poses(pose_data: Any) -> tuple[IntArray, FloatArray, FloatArray]:
    if isinstance(pose_data, _PoseColumns):  # read from a stream already
        return pose_data.finish()
    if pose_data is None:
        raise SessionFormatError("pose_data", "missing")
    require_list(pose_data, "pose_data")
    columns = _PoseColumns(capacity=len(pose_data))
    for entry in pose_data:
        columns.add(entry)
        if columns.error is not None:
            raise columns.error
    return columns.finish()


class _PoseColumns:
    """``pose_data`` entries checked and written into arrays one at a time, so that the
    entries themselves need not be kept. The first fault is kept in ``error`` (later entries are
    only counted); ``first_entry`` is entry 0 as it was (for :func:`is_earlier_format`)."""

    def __init__(self, *, capacity: int) -> None:
        # np.empty of a large capacity costs only the pages written
        capacity = max(capacity, 1)
        self.pose_id = np.empty(capacity, dtype=np.int64)
        self.timestamp_s = np.empty(capacity, dtype=np.float64)
        self.world_T_phone = np.empty((capacity, 4, 4), dtype=np.float64)
        self.count = 0
        self._checked = 0  # poses before this one are checked for rigidity
        self.error: SessionFormatError | None = None
        self.first_entry: Any = None

    def add(self, entry: Any) -> None:
        i = self.count
        self.count += 1
        if i == 0:
            self.first_entry = entry
        if self.error is not None:
            return
        if i == self.pose_id.shape[0]:
            self._grow()
        where = f"pose_data[{i}]"
        try:
            require_object(entry, where)
            self.pose_id[i] = integer_field(entry, "id", where)
            self.timestamp_s[i] = number_field(entry, "timestamp", where)
            # column-major; checked for rigidity a block at a time (_check_rigid)
            self.world_T_phone[i] = matrix16_field(entry, "pose", where).reshape(4, 4).T
        except SessionFormatError as err:
            self._check_rigid(i)  # a fault in an earlier pose comes first
            if self.error is None:
                self.error = err
            return
        if i + 1 - self._checked >= _RIGIDITY_BLOCK:
            self._check_rigid(i + 1)

    def _check_rigid(self, end: int) -> None:
        """Check the poses from the last checked up to ``end`` for rigidity, as
        :func:`rigid_pose` does each, and orthonormalize them. The test runs on the whole block
        with a margin; a pose it flags gets :func:`rigid_pose` itself, so the first fault is
        reported with its own words. Sets ``error`` (and raises nothing)."""
        start = self._checked
        if end <= start or self.error is not None:
            return
        block = self.world_T_phone[start:end]
        flagged = np.flatnonzero(maybe_not_rigid(block))
        for k in flagged:
            i = start + int(k)
            try:
                rigid_pose(block[k], f"pose_data[{i}].pose")
            except SessionFormatError as err:
                self.error = err
                self._checked = i
                return
        self.world_T_phone[start:end] = orthonormalized_stack(block)
        self._checked = end

    def _grow(self) -> None:
        capacity = 2 * self.pose_id.shape[0]
        self.pose_id = np.resize(self.pose_id, capacity)
        self.timestamp_s = np.resize(self.timestamp_s, capacity)
        self.world_T_phone = np.resize(self.world_T_phone, (capacity, 4, 4))

    def finish(self) -> tuple[IntArray, FloatArray, FloatArray]:
        """The arrays (N rows); SessionFormatError for the first fault."""
        self._check_rigid(self.count)
        if self.error is not None:
            raise self.error
        n = self.count
        if n == 0:
            raise SessionFormatError("pose_data", "empty session: no poses")
        pose_id, timestamp_s = self.pose_id[:n], self.timestamp_s[:n]
        decreasing = np.flatnonzero(np.diff(pose_id) <= 0)
        if decreasing.size:
            i = int(decreasing[0]) + 1
            raise SessionFormatError(
                f"pose_data[{i}].id", f"ids must increase: {pose_id[i]} follows {pose_id[i - 1]}"
            )
        backwards = np.flatnonzero(np.diff(timestamp_s) < 0)
        if backwards.size:
            i = int(backwards[0]) + 1
            raise SessionFormatError(
                f"pose_data[{i}].timestamp",
                f"time goes backwards: {timestamp_s[i]} s after {timestamp_s[i - 1]} s",
            )
        return pose_id, timestamp_s, self.world_T_phone[:n]


#: Poses checked for rigidity at once by :class:`_PoseColumns`.
_RIGIDITY_BLOCK = 4096


class PoseIndex:
    """The row of each pose id (ids increasing, as the parser checks): ``pose_id in index``,
    ``index[pose_id]``; a search in the id array instead of a dict of every pose."""

    def __init__(self, pose_id: IntArray) -> None:
        self._pose_id = pose_id

    def row(self, pose_id: object) -> int | None:
        """The row of ``pose_id``, or None."""
        if isinstance(pose_id, bool) or not isinstance(pose_id, int):
            return None
        if not int(self._pose_id[0]) <= pose_id <= int(self._pose_id[-1]):
            return None
        row = int(np.searchsorted(self._pose_id, pose_id))
        return row if int(self._pose_id[row]) == pose_id else None

    def __contains__(self, pose_id: object) -> bool:
        return self.row(pose_id) is not None

    def __getitem__(self, pose_id: int) -> int:
        row = self.row(pose_id)
        if row is None:
            raise KeyError(pose_id)
        return row


def _parse_tag_data(tag_data: Any, index_of_pose_id: PoseIndex) -> TagDetections:
    if isinstance(tag_data, _DetectionColumns):  # read from a stream already
        return tag_data.finish()
    require_list(tag_data, "tag_data")
    columns = _DetectionColumns(index_of_pose_id)
    for f, frame in enumerate(tag_data):
        columns.add_frame(f, frame)
        if columns.error is not None:
            raise columns.error
    return columns.finish()


def parse_detection_rows(
    tag_data: Any, *, known_pose_ids: Container[int] | None = None
) -> list[dict[str, Any]]:
    """The detections of a ``tag_data`` list (frames of detections; a bare detection where a
    frame was expected is taken as a frame of one), each as :func:`parse_detection_fields` reads
    it plus ``where``, its JSON path. Used for uploads and for localization updates."""
    require_list(tag_data, "tag_data")
    rows: list[dict[str, Any]] = []
    for f, frame in enumerate(tag_data):
        rows += _frame_rows(f, frame, known_pose_ids)
    return rows


def count_detections(tag_data: Any) -> int:
    """How many detections :func:`parse_detection_rows` reads from ``tag_data``, counted without
    reading them; 0 for what it refuses anyway."""
    if not isinstance(tag_data, list):
        return 0
    return sum(len(frame) for frame in map(_as_frame, tag_data) if isinstance(frame, list))


def _as_frame(frame: Any) -> Any:
    """A bare detection where a frame was expected is taken as a frame of one."""
    return [frame] if isinstance(frame, Mapping) else frame


def _frame_rows(f: int, frame: Any, known_pose_ids: Container[int] | None) -> list[dict[str, Any]]:
    where_frame = f"tag_data[{f}]"
    frame = _as_frame(frame)
    require_list(frame, where_frame)
    rows = []
    for d, detection in enumerate(frame):
        where = f"{where_frame}[{d}]"
        require_object(detection, where)
        row = parse_detection_fields(
            detection,
            where,
            frame_index=f,
            frame_size=len(frame),
            known_pose_ids=known_pose_ids,
        )
        row["where"] = where
        rows.append(row)
    return rows


class _DetectionColumns:
    """``tag_data`` frames checked one at a time and kept as arrays in blocks of
    :data:`_DETECTION_BLOCK` detections, not as one dict per detection. The first fault is kept
    in ``error`` (later frames are passed over); ``first_frame`` is frame 0 as it was."""

    def __init__(self, pose_index: PoseIndex | None) -> None:
        self._pose_index = pose_index
        self._rows: list[dict[str, Any]] = []
        self._blocks: list[dict[str, npt.NDArray[Any]]] = []
        self.count = 0
        self.error: SessionFormatError | None = None
        self.first_frame: Any = None

    def add_frame(self, f: int, frame: Any) -> None:
        self.count += 1
        if f == 0:
            self.first_frame = frame
        if self.error is not None:
            return
        if self._pose_index is None:  # the poses are faulty: their error comes first
            return
        try:
            self._rows += _frame_rows(f, frame, self._pose_index)
        except SessionFormatError as err:
            self.error = err
            return
        if len(self._rows) >= _DETECTION_BLOCK:
            self._end_block()

    def _end_block(self) -> None:
        if self._rows and self._pose_index is not None:
            pose_index = [self._pose_index[r["pose_id"]] for r in self._rows]
            block = detections_from_rows(self._rows, pose_index)
            self._blocks.append({name: getattr(block, name) for name in _DETECTION_FIELDS})
        self._rows = []

    def finish(self) -> TagDetections:
        if self.error is not None:
            raise self.error
        self._end_block()
        if not self._blocks:
            return _empty_detections()
        # field by field, each block's part let go once joined: never two copies of all
        return TagDetections(
            **{
                name: np.concatenate([block.pop(name) for block in self._blocks])
                for name in _DETECTION_FIELDS
            }
        )


#: Detections per block of :class:`_DetectionColumns`.
_DETECTION_BLOCK = 256
_DETECTION_FIELDS = tuple(field.name for field in dataclasses.fields(TagDetections))


def detections_from_rows(
    rows: Sequence[Mapping[str, Any]], pose_index: Sequence[int]
) -> TagDetections:
    """:class:`TagDetections` of rows from :func:`parse_detection_rows`; ``pose_index`` is each
    detection's pose (a row of the session's poses; localization keeps the pose id there)."""
    if not rows:
        return _empty_detections()
    return TagDetections(
        tag_id=np.array([r["tag_id"] for r in rows], dtype=np.int64),
        pose_index=np.array(pose_index, dtype=np.int64),
        frame_index=np.array([r["frame_index"] for r in rows], dtype=np.int64),
        frame_size=np.array([r["frame_size"] for r in rows], dtype=np.int64),
        timestamp_s=np.array([r["timestamp_s"] for r in rows], dtype=np.float64),
        camera_T_tag=np.stack([r["camera_T_tag"] for r in rows]),
        phone_T_tag=np.stack([PHONE_T_CAMERA_CV @ r["camera_T_tag"] for r in rows]),
        intrinsics=np.stack([r["intrinsics"] for r in rows]),
        corners_px=np.stack([r["corners_px"] for r in rows]),
        position_variance_m2=np.stack([r["position_variance"] for r in rows]),
        orientation_variance=np.stack([r["orientation_variance"] for r in rows]),
        joint_covariance=np.stack([r["joint_covariance"] for r in rows]),
    )


def parse_detection_fields(
    detection: Mapping[str, Any],
    where: str,
    *,
    frame_index: int,
    frame_size: int,
    known_pose_ids: Container[int] | None = None,
) -> dict[str, Any]:
    """One detection of the upload's ``tag_data`` (§2) as checked values, its ``pose_id``
    as written (checked against ``known_pose_ids`` when given; else the caller resolves it). Also
    used for localization updates, whose detections have the same format. Fields are checked in
    order (tag_id, pose_id, tag_pose, …); the first fault raises :class:`SessionFormatError`
    naming ``where`` and the field."""
    tag_id = integer_field(detection, "tag_id", where)
    if tag_id < 0:
        raise SessionFormatError(f"{where}.tag_id", f"must be ≥ 0, got {tag_id}")
    pose_id = integer_field(detection, "pose_id", where)
    if known_pose_ids is not None and pose_id not in known_pose_ids:
        raise SessionFormatError(f"{where}.pose_id", f"no pose with id {pose_id} in pose_data")
    camera_T_tag = rigid_pose(
        matrix16_field(detection, "tag_pose", where).reshape(4, 4), f"{where}.tag_pose"
    )
    intrinsics = vector_field(detection, "camera_intrinsics", where, 4)
    if intrinsics[0] <= 0 or intrinsics[1] <= 0:
        raise SessionFormatError(
            f"{where}.camera_intrinsics", "focal lengths fx, fy must be positive"
        )
    within_pixels(intrinsics, f"{where}.camera_intrinsics")
    corners = vector_field(detection, "tag_corners_pixel_coordinates", where, 8)
    within_pixels(corners, f"{where}.tag_corners_pixel_coordinates")
    corners = corners.reshape(4, 2)
    timestamp = (
        number_field(detection, "timestamp", where) if "timestamp" in detection else math.nan
    )
    return {
        "tag_id": tag_id,
        "pose_id": pose_id,
        "frame_index": frame_index,
        "frame_size": frame_size,
        "timestamp_s": timestamp,
        "camera_T_tag": camera_T_tag,
        "intrinsics": intrinsics,
        "corners_px": corners,
        "position_variance": optional_vector_field(detection, "tag_position_variance", where, 3),
        "orientation_variance": optional_vector_field(
            detection, "tag_orientation_variance", where, 4
        ),
        "joint_covariance": optional_vector_field(detection, "joint_covar", where, 49).reshape(
            7, 7
        ),
    }


def _parse_locations(
    location_data: Any,
    key: str,
    index_of_pose_id: PoseIndex,
    correct_poi_pose_id: bool,
) -> list[PointOfInterest]:
    if location_data is None:
        return []
    require_list(location_data, key)
    pois = []
    for i, entry in enumerate(location_data):
        where = f"{key}[{i}]"
        require_object(entry, where)
        name = entry.get("name")
        if name is None:
            raise SessionFormatError(f"{where}.name", "missing")
        if not isinstance(name, str):
            raise SessionFormatError(
                f"{where}.name", f"expected a string, got {json_type_name(name)}"
            )
        pose_id = integer_field(entry, "pose_id", where)
        corrected = pose_id - 1 if correct_poi_pose_id else pose_id
        if corrected not in index_of_pose_id:
            raise SessionFormatError(
                f"{where}.pose_id",
                f"no pose with id {corrected} in pose_data"
                + (" (after the app's off-by-one correction)" if correct_poi_pose_id else ""),
            )
        timestamp = number_field(entry, "timestamp", where) if "timestamp" in entry else math.nan
        phone_T_poi = rigid_pose(
            matrix16_field(entry, "transform", where).reshape(4, 4), f"{where}.transform"
        )
        pois.append(
            PointOfInterest(
                name=name.strip(),
                pose_index=index_of_pose_id[corrected],
                timestamp_s=timestamp,
                phone_T_poi=phone_T_poi,
            )
        )
    return pois


def derived_map_id(timestamp_s: FloatArray, world_T_phone: FloatArray) -> str:
    """A stable name for a session sent with an empty ``map_id`` (the app sets it to the name the
    person typed, which may be empty): ``unnamed-`` and a digest of its poses' times and places,
    so the same walk always gets the same name."""
    digest = hashlib.sha256(timestamp_s.tobytes() + world_T_phone[:, :3, 3].tobytes())
    return f"unnamed-{digest.hexdigest()[:10]}"


#: A run of digits the app appends to the typed name (a timestamp: 6 digits or more) or puts
#: before it (``963934784127833-Test``), with the separator.
_TRAILING_DIGITS = re.compile(r"[\s_-]*\d{6,}$")
_LEADING_DIGITS = re.compile(r"^\d{6,}[\s_-]+")


def require_tags(session: Session) -> None:
    """Raise :class:`NoTagsRecorded` for a session with no tag detection: it is a valid upload
    (kept as it is), but a map needs at least one tag."""
    if len(session.detections) == 0:
        raise NoTagsRecorded(NO_TAGS_REASON)


def display_name_of(map_id: str) -> str:
    """The name a person typed, from the ``map_id`` the app made of it: the timestamp digits it
    adds are dropped (``"Lab 1700000000"`` → ``"Lab"``, ``"963934784127833-Test"`` → ``"Test"``);
    a map id that is nothing but digits is kept as it is."""
    name = _LEADING_DIGITS.sub("", _TRAILING_DIGITS.sub("", map_id.strip())).strip()
    return name or map_id.strip()


def _name_unnamed_pois(
    pois: list[PointOfInterest], key: str, warnings: list[str]
) -> list[PointOfInterest]:
    """Points of interest with an empty name (the app's "add location" button accepts one) are
    named ``Point <k>`` after their place in ``location_data`` (1-based), so the name is the same
    whenever the upload is read; a name already taken gets `` (2)``, `` (3)``…. Repeated names are
    kept as sent (the app-map says how it tells them apart); both are reported in ``warnings``."""
    taken = {poi.name for poi in pois if poi.name}
    named = []
    for k, poi in enumerate(pois):
        if not poi.name:
            name = candidate = f"Point {k + 1}"
            suffix = 2
            while name in taken:
                name = f"{candidate} ({suffix})"
                suffix += 1
            taken.add(name)
            warnings.append(f"{key}[{k}].name was empty: named {name!r}")
            poi = dataclasses.replace(poi, name=name)
        named.append(poi)
    counts = Counter(poi.name for poi in named)
    for name, count in sorted(counts.items()):
        if count > 1:
            warnings.append(f"{count} points of interest are named {name!r}")
    return named


def _empty_detections() -> TagDetections:
    return TagDetections(
        tag_id=np.empty(0, dtype=np.int64),
        pose_index=np.empty(0, dtype=np.int64),
        frame_index=np.empty(0, dtype=np.int64),
        frame_size=np.empty(0, dtype=np.int64),
        timestamp_s=np.empty(0),
        camera_T_tag=np.empty((0, 4, 4)),
        phone_T_tag=np.empty((0, 4, 4)),
        intrinsics=np.empty((0, 4)),
        corners_px=np.empty((0, 4, 2)),
        position_variance_m2=np.empty((0, 3)),
        orientation_variance=np.empty((0, 4)),
        joint_covariance=np.empty((0, 7, 7)),
    )


def first_observation_tag_poses(session: Session) -> dict[int, FloatArray]:
    """The "pre-optimized" map: each tag's ``world_T_tag`` from its first raw detection."""
    world_T_tag = session.world_T_tag_observed()
    poses: dict[int, FloatArray] = {}
    for row, tag_id in enumerate(session.detections.tag_id):
        poses.setdefault(int(tag_id), world_T_tag[row])
    return poses
