"""The app's upload format (docs/architecture.md §2), parsed once into typed arrays.

    session = parse_session(json.loads(text))      # or load_session(path), gzip or plain
    session.world_T_phone                          # (N, 4, 4) ARKit poses, world frame, y up
    session.detections.phone_T_tag                 # (M, 4, 4) one per tag detection
    session.world_T_tag_observed()                 # (M, 4, 4) raw, unoptimized tag poses

Everything downstream reads these arrays; nobody walks the dicts again. Any malformed input raises
:class:`SessionFormatError` naming the field (``tag_data[3][0].tag_pose``) and the reason.
"""

from __future__ import annotations

import json
import math
from collections.abc import Container, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from app.domain.errors import SessionFormatError
from app.domain.frames import (
    PHONE_T_CAMERA_CV,
    FloatArray,
    orthonormalized,
    rigidity_defect,
)
from app.domain.json_values import gunzip_if_compressed, json_type_name

IntArray = npt.NDArray[np.int64]

#: Largest id accepted: integers a JSON number can hold exactly (2^53).
MAX_ID = 2**53
#: Farthest a pose (of the phone, or of a tag from the camera) may be from its frame's origin, m:
#: a walk through a building stays within kilometres; beyond this the arithmetic of a map would
#: lose its precision (or overflow), so the upload is refused instead.
MAX_TRANSLATION_M = 1e5
#: Largest focal length, principal point or corner coordinate accepted, px.
MAX_PIXELS = 1e5

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


# --------------------------------------------------------------------------- parsing


def parse_session(document: Any, *, correct_poi_pose_id: bool = True) -> Session:
    """Parse the app's upload (a decoded JSON object) into a :class:`Session`.

    ``correct_poi_pose_id``: the app writes a point of interest's ``pose_id`` one too high (it
    points to the next pose); when True (the default) it is moved back by one.
    """
    if not isinstance(document, Mapping):
        raise SessionFormatError("", f"expected a JSON object, got {json_type_name(document)}")
    map_id = document.get("map_id")
    if not isinstance(map_id, str) or not map_id.strip():
        raise SessionFormatError("map_id", "missing or not a non-empty string")

    pose_id, timestamp_s, world_T_phone = _parse_poses(document.get("pose_data"))
    index_of_pose_id = {int(pid): i for i, pid in enumerate(pose_id)}
    detections = _parse_tag_data(document.get("tag_data", []), index_of_pose_id)

    location_key = next((k for k in LOCATION_KEYS if k in document), LOCATION_KEYS[0])
    pois = _parse_locations(
        document.get(location_key, []), location_key, index_of_pose_id, correct_poi_pose_id
    )
    warnings = []
    if len(detections) == 0:
        warnings.append("session has no tag detections: the map holds the walked path alone")
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
    if pose_data is None:
        raise SessionFormatError("pose_data", "missing")
    _require_list(pose_data, "pose_data")
    if len(pose_data) == 0:
        raise SessionFormatError("pose_data", "empty session: no poses")
    n = len(pose_data)
    pose_id = np.empty(n, dtype=np.int64)
    timestamp_s = np.empty(n, dtype=np.float64)
    world_T_phone = np.empty((n, 4, 4), dtype=np.float64)
    for i, entry in enumerate(pose_data):
        where = f"pose_data[{i}]"
        _require_object(entry, where)
        pose_id[i] = _integer(entry, "id", where)
        timestamp_s[i] = _number(entry, "timestamp", where)
        matrix = _matrix16(entry, "pose", where).reshape(4, 4).T  # column-major
        world_T_phone[i] = _rigid(matrix, f"{where}.pose")
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
    return pose_id, timestamp_s, world_T_phone


def _parse_tag_data(tag_data: Any, index_of_pose_id: Mapping[int, int]) -> TagDetections:
    rows = parse_detection_rows(tag_data, known_pose_ids=index_of_pose_id)
    return detections_from_rows(rows, [index_of_pose_id[r["pose_id"]] for r in rows])


def parse_detection_rows(
    tag_data: Any, *, known_pose_ids: Container[int] | None = None
) -> list[dict[str, Any]]:
    """The detections of a ``tag_data`` list (frames of detections; a bare detection where a
    frame was expected is taken as a frame of one), each as :func:`parse_detection_fields` reads
    it plus ``where``, its JSON path. Used for uploads and for localization updates."""
    _require_list(tag_data, "tag_data")
    rows: list[dict[str, Any]] = []
    for f, frame in enumerate(tag_data):
        where_frame = f"tag_data[{f}]"
        if isinstance(frame, Mapping):  # a bare detection where a frame was expected
            frame = [frame]
        _require_list(frame, where_frame)
        for d, detection in enumerate(frame):
            where = f"{where_frame}[{d}]"
            _require_object(detection, where)
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
    tag_id = _integer(detection, "tag_id", where)
    if tag_id < 0:
        raise SessionFormatError(f"{where}.tag_id", f"must be ≥ 0, got {tag_id}")
    pose_id = _integer(detection, "pose_id", where)
    if known_pose_ids is not None and pose_id not in known_pose_ids:
        raise SessionFormatError(f"{where}.pose_id", f"no pose with id {pose_id} in pose_data")
    camera_T_tag = _rigid(
        _matrix16(detection, "tag_pose", where).reshape(4, 4), f"{where}.tag_pose"
    )
    intrinsics = _vector(detection, "camera_intrinsics", where, 4)
    if intrinsics[0] <= 0 or intrinsics[1] <= 0:
        raise SessionFormatError(
            f"{where}.camera_intrinsics", "focal lengths fx, fy must be positive"
        )
    _within_pixels(intrinsics, f"{where}.camera_intrinsics")
    corners = _vector(detection, "tag_corners_pixel_coordinates", where, 8)
    _within_pixels(corners, f"{where}.tag_corners_pixel_coordinates")
    corners = corners.reshape(4, 2)
    timestamp = _number(detection, "timestamp", where) if "timestamp" in detection else math.nan
    return {
        "tag_id": tag_id,
        "pose_id": pose_id,
        "frame_index": frame_index,
        "frame_size": frame_size,
        "timestamp_s": timestamp,
        "camera_T_tag": camera_T_tag,
        "intrinsics": intrinsics,
        "corners_px": corners,
        "position_variance": _optional_vector(detection, "tag_position_variance", where, 3),
        "orientation_variance": _optional_vector(detection, "tag_orientation_variance", where, 4),
        "joint_covariance": _optional_vector(detection, "joint_covar", where, 49).reshape(7, 7),
    }


def _parse_locations(
    location_data: Any,
    key: str,
    index_of_pose_id: Mapping[int, int],
    correct_poi_pose_id: bool,
) -> list[PointOfInterest]:
    if location_data is None:
        return []
    _require_list(location_data, key)
    pois = []
    for i, entry in enumerate(location_data):
        where = f"{key}[{i}]"
        _require_object(entry, where)
        name = entry.get("name")
        if not isinstance(name, str) or not name.strip():
            raise SessionFormatError(f"{where}.name", "missing or not a non-empty string")
        pose_id = _integer(entry, "pose_id", where)
        corrected = pose_id - 1 if correct_poi_pose_id else pose_id
        if corrected not in index_of_pose_id:
            raise SessionFormatError(
                f"{where}.pose_id",
                f"no pose with id {corrected} in pose_data"
                + (" (after the app's off-by-one correction)" if correct_poi_pose_id else ""),
            )
        timestamp = _number(entry, "timestamp", where) if "timestamp" in entry else math.nan
        phone_T_poi = _rigid(
            _matrix16(entry, "transform", where).reshape(4, 4), f"{where}.transform"
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


# --------------------------------------------------------------------------- field readers


def _require_list(value: Any, where: str) -> None:
    if not isinstance(value, list):
        raise SessionFormatError(where, f"expected a list, got {json_type_name(value)}")


def _require_object(value: Any, where: str) -> None:
    if not isinstance(value, Mapping):
        raise SessionFormatError(where, f"expected an object, got {json_type_name(value)}")


def _field(entry: Mapping[str, Any], key: str, where: str) -> Any:
    if key not in entry:
        raise SessionFormatError(f"{where}.{key}", "missing")
    return entry[key]


def _integer(entry: Mapping[str, Any], key: str, where: str) -> int:
    value = _field(entry, key, where)
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise SessionFormatError(
            f"{where}.{key}", f"expected an integer, got {json_type_name(value)}"
        )
    if isinstance(value, float) and not value.is_integer():
        raise SessionFormatError(f"{where}.{key}", f"expected an integer, got {value}")
    if not -MAX_ID <= value <= MAX_ID:
        raise SessionFormatError(
            f"{where}.{key}", f"integer out of range (|value| > 2^53): {value}"
        )
    return int(value)


def _number(entry: Mapping[str, Any], key: str, where: str) -> float:
    value = _field(entry, key, where)
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise SessionFormatError(
            f"{where}.{key}", f"expected a number, got {json_type_name(value)}"
        )
    if not math.isfinite(value):
        raise SessionFormatError(f"{where}.{key}", f"non-finite number {value}")
    return float(value)


def _vector(entry: Mapping[str, Any], key: str, where: str, length: int) -> FloatArray:
    value = _field(entry, key, where)
    return _numbers(value, f"{where}.{key}", length)


def _optional_vector(entry: Mapping[str, Any], key: str, where: str, length: int) -> FloatArray:
    if key not in entry or entry[key] is None:
        return np.full(length, np.nan)
    return _numbers(entry[key], f"{where}.{key}", length)


def _matrix16(entry: Mapping[str, Any], key: str, where: str) -> FloatArray:
    value = _field(entry, key, where)
    if isinstance(value, list) and len(value) == 4 and all(isinstance(r, list) for r in value):
        raise SessionFormatError(f"{where}.{key}", "expected 16 numbers in a flat list, got 4 rows")
    return _numbers(value, f"{where}.{key}", 16)


def _numbers(value: Any, where: str, length: int) -> FloatArray:
    if not isinstance(value, list):
        raise SessionFormatError(
            where, f"expected a list of {length} numbers, got {json_type_name(value)}"
        )
    if len(value) != length:
        raise SessionFormatError(where, f"expected {length} numbers, got {len(value)}")
    for j, item in enumerate(value):
        if isinstance(item, bool) or not isinstance(item, (int, float)):
            raise SessionFormatError(
                f"{where}[{j}]", f"expected a number, got {json_type_name(item)}"
            )
        if not math.isfinite(item):
            raise SessionFormatError(f"{where}[{j}]", f"non-finite number {item}")
    return np.asarray(value, dtype=np.float64)


def _rigid(matrix: FloatArray, where: str) -> FloatArray:
    defect = rigidity_defect(matrix)
    if defect is not None:
        raise SessionFormatError(where, defect)
    distance_m = float(np.max(np.abs(matrix[:3, 3])))
    if distance_m > MAX_TRANSLATION_M:
        raise SessionFormatError(
            where, f"translation {distance_m:.3g} m is beyond {MAX_TRANSLATION_M:.0f} m"
        )
    return orthonormalized(matrix)


def _within_pixels(values: FloatArray, where: str) -> None:
    worst = int(np.argmax(np.abs(values)))
    if abs(values[worst]) > MAX_PIXELS:
        raise SessionFormatError(
            f"{where}[{worst}]", f"{values[worst]:.3g} px is beyond {MAX_PIXELS:.0f} px"
        )


def first_observation_tag_poses(session: Session) -> dict[int, FloatArray]:
    """The "pre-optimized" map: each tag's ``world_T_tag`` from its first raw detection."""
    world_T_tag = session.world_T_tag_observed()
    poses: dict[int, FloatArray] = {}
    for row, tag_id in enumerate(session.detections.tag_id):
        poses.setdefault(int(tag_id), world_T_tag[row])
    return poses
