"""The app's earlier upload format (2020–2021), converted into the current one
(docs/architecture.md §2).

    if is_earlier_format(document):
        document, notes = convert_earlier_format(document)   # then parse_session as usual

What the early app wrote (three real sessions in ``data/archive/``):

- ``camera_intrinsics`` once, at the top level, as a CSV string ``fx,fy,cx,cy,1,width,height``;
- ``pose_data`` rows as a CSV string or a bare array: 16 pose numbers, the timestamp (s) and,
  in later builds, the pose id (without it, the row's index is the id);
- ``tag_data`` rows as ``"TAG,<id>,<16 numbers>,<timestamp>"`` or a bare array
  ``[id, 16 numbers, timestamp]``, later ``[…, pose id]``; no corners, no variances.

How the frames were pinned down from the data (none of it is documented by the old app):

- **Poses are column-major ``world_T_phone``**, as today: read column-major, every matrix of the
  three sessions is rigid with bottom row (0, 0, 0, 1) (to 2e-7) and the translation at indices
  12–14; read row-major the bottom row holds metres (up to 41 m). World +y is up: the phone's
  x axis points down in every session (x·up ≈ −0.93, a phone held upright in portrait), as ARKit
  reports its camera frame.
- **Tag poses are row-major ``camera_T_tag`` in the OpenCV camera convention**, as today: the
  bottom row is (0, 0, 0, 1) only row-major; with ``phone_T_tag = diag(1, −1, −1, 1) @ tag_pose``
  every detection lies in front of the phone and faces it (tag +z toward the camera), and tags
  seen in consecutive frames agree best (median 0.09–0.11 m between consecutive detections of a
  tag, against ≥ 0.13 m for the inverse, the transpose or the ARKit camera convention), and each
  tag's up axis is the same in all three sessions (tag 18's −x, tag 19's −y: tags stuck on at
  those angles).
- **A detection belongs to the pose nearest in time** (the rows have no pose id, or a pose id
  that is that pose): at most 17 ms apart in the archive. A detection more than
  :data:`MAX_POSE_GAP_S` from every pose is refused.
- **Corners**: the format has none, so they are projected from ``tag_pose`` with the intrinsics
  and the app's printed tag side (0.173 m): the reprojection check passes by construction and
  the map says so.

When a session does not fit these facts (a pose not rigid column-major, most tags behind the
camera, no intrinsics), it is refused with a :class:`SessionFormatError` naming the format.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from app.domain.errors import SessionFormatError
from app.domain.frames import FloatArray, project_pinhole_px, tag_corners_in_camera
from app.domain.json_values import json_type_name

#: How the format is named in messages.
EARLIER_FORMAT = (
    "the app's earlier format: CSV-string or bare-array rows, camera_intrinsics at the top level"
)
#: Side of the app's printed tags, m (the corners are projected with it).
PRINTED_TAG_SIZE_M = 0.173
#: Farthest a detection may be in time from its nearest pose, s.
MAX_POSE_GAP_S = 0.1
#: Least share of detections that must lie in front of the camera for the frames to hold.
MIN_IN_FRONT_SHARE = 0.9
#: Largest deviation of a pose's bottom row from (0, 0, 0, 1) read column-major.
MAX_BOTTOM_ROW_DEFECT = 1e-3


def is_earlier_format(document: Any) -> bool:
    """Whether ``document`` is in the earlier format: ``camera_intrinsics`` at the top level, or
    ``pose_data``/``tag_data`` rows that are strings or bare arrays of numbers."""
    if not isinstance(document, Mapping):
        return False
    if "camera_intrinsics" in document:
        return True
    for key in ("pose_data", "tag_data"):
        rows = document.get(key)
        if isinstance(rows, list) and rows and _is_row(rows[0]):
            return True
    return False


def _is_row(value: Any) -> bool:
    if isinstance(value, str):
        return True
    return (
        isinstance(value, list)
        and len(value) >= 17
        and all(isinstance(v, int | float) and not isinstance(v, bool) for v in value)
    )


def convert_earlier_format(document: Mapping[str, Any]) -> tuple[dict[str, Any], list[str]]:
    """The same session in the current format, and notes for the session's warnings.

    Keys other than the three converted ones are kept as they are (``map_id`` included)."""
    intrinsics = _intrinsics(document.get("camera_intrinsics"))
    pose_rows = _rows(document.get("pose_data"), "pose_data", prefix=None)
    poses: list[dict[str, Any]] = []
    for i, row in enumerate(pose_rows):
        where = f"pose_data[{i}]"
        if len(row) not in (17, 18):
            raise SessionFormatError(
                where, f"expected 16 pose numbers, a timestamp and maybe an id, got {len(row)}"
            )
        matrix = np.asarray(row[:16], dtype=np.float64).reshape(4, 4).T
        defect = float(np.max(np.abs(matrix[3] - (0.0, 0.0, 0.0, 1.0))))
        if not defect <= MAX_BOTTOM_ROW_DEFECT:
            raise SessionFormatError(
                where,
                "read column-major its bottom row is not (0, 0, 0, 1): the pose's frame cannot "
                "be pinned down",
            )
        poses.append(
            {"id": int(row[17]) if len(row) == 18 else i, "timestamp": row[16], "pose": row[:16]}
        )
    if not poses:
        raise SessionFormatError("pose_data", "empty session: no poses")
    pose_time_s = np.array([p["timestamp"] for p in poses], dtype=np.float64)
    pose_ids = {p["id"] for p in poses}

    tag_rows = _rows(document.get("tag_data", []), "tag_data", prefix="TAG")
    frames = []
    camera_T_tag = np.empty((len(tag_rows), 4, 4))
    for k, row in enumerate(tag_rows):
        where = f"tag_data[{k}]"
        if len(row) not in (18, 19):
            raise SessionFormatError(
                where,
                f"expected an id, 16 pose numbers, a timestamp and maybe a pose id, got {len(row)}",
            )
        camera_T_tag[k] = np.asarray(row[1:17], dtype=np.float64).reshape(4, 4)
        timestamp_s = row[17]
        pose_id = int(row[18]) if len(row) == 19 and int(row[18]) in pose_ids else None
        if pose_id is None:
            nearest = int(np.argmin(np.abs(pose_time_s - timestamp_s)))
            if not abs(pose_time_s[nearest] - timestamp_s) <= MAX_POSE_GAP_S:
                raise SessionFormatError(
                    f"{where}.timestamp",
                    f"no pose within {MAX_POSE_GAP_S} s of {timestamp_s} s to attach it to",
                )
            pose_id = poses[nearest]["id"]
        frames.append(
            [
                {
                    "tag_id": _tag_id(row[0], where),
                    "pose_id": pose_id,
                    "timestamp": timestamp_s,
                    "tag_pose": row[1:17],
                    "camera_intrinsics": intrinsics,
                }
            ]
        )
    notes = [f"read from {EARLIER_FORMAT}"]
    if frames:
        in_front = float(np.mean(camera_T_tag[:, 2, 3] > 0))
        if in_front < MIN_IN_FRONT_SHARE:
            raise SessionFormatError(
                "tag_data",
                f"only {in_front:.0%} of the detections are in front of the camera read as "
                "OpenCV camera_T_tag: the tags' frame cannot be pinned down",
            )
        corners_px = _projected_corners(camera_T_tag, intrinsics)
        for frame, corners in zip(frames, corners_px, strict=True):
            frame[0]["tag_corners_pixel_coordinates"] = corners.reshape(8).tolist()
        notes.append(
            "tag corners projected from tag_pose (the earlier format has none): the "
            "reprojection check cannot reject a detection"
        )
    converted = {k: v for k, v in document.items() if k != "camera_intrinsics"}
    converted.update(pose_data=poses, tag_data=frames)
    return converted, notes


def _projected_corners(camera_T_tag: FloatArray, intrinsics: Sequence[float]) -> FloatArray:
    corners_camera = tag_corners_in_camera(camera_T_tag, PRINTED_TAG_SIZE_M)
    # a tag behind the camera (refused later by the parser's checks) must not divide by 0
    corners_camera[..., 2] = np.where(
        np.abs(corners_camera[..., 2]) < 1e-9, 1e-9, corners_camera[..., 2]
    )
    return np.clip(project_pinhole_px(corners_camera, intrinsics), -9e4, 9e4)


def _intrinsics(value: Any) -> list[float]:
    if value is None:
        raise SessionFormatError(
            "camera_intrinsics", "missing: the earlier format keeps them at the top level"
        )
    numbers = _row(value, "camera_intrinsics", prefix=None)
    if len(numbers) < 4:
        raise SessionFormatError(
            "camera_intrinsics", f"expected fx, fy, cx, cy, …, got {len(numbers)} numbers"
        )
    return numbers[:4]


def _rows(value: Any, key: str, *, prefix: str | None) -> list[list[float]]:
    if value is None:
        raise SessionFormatError(key, "missing")
    if not isinstance(value, list):
        raise SessionFormatError(key, f"expected a list, got {json_type_name(value)}")
    return [_row(row, f"{key}[{i}]", prefix=prefix) for i, row in enumerate(value)]


def _row(value: Any, where: str, *, prefix: str | None) -> list[float]:
    """A CSV string (its ``prefix`` field dropped) or a bare array, as finite numbers."""
    if isinstance(value, str):
        fields = [f.strip() for f in value.split(",")]
        if prefix is not None and fields and fields[0] == prefix:
            fields = fields[1:]
        try:
            numbers = [float(f) for f in fields]
        except ValueError as err:
            raise SessionFormatError(where, f"not a row of numbers: {err}") from err
    elif isinstance(value, list):
        if not all(isinstance(v, int | float) and not isinstance(v, bool) for v in value):
            raise SessionFormatError(where, "expected a row of numbers")
        numbers = [float(v) for v in value]
    else:
        raise SessionFormatError(
            where, f"expected a CSV string or an array of numbers, got {json_type_name(value)}"
        )
    if not all(np.isfinite(numbers)):
        raise SessionFormatError(where, "non-finite number")
    return numbers


def _tag_id(value: float, where: str) -> int:
    if not float(value).is_integer() or value < 0:
        raise SessionFormatError(f"{where}.tag_id", f"expected an id ≥ 0, got {value}")
    return int(value)
