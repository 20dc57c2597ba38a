"""Ground-truth tag poses: RTAB-Map exports and the ground-truth JSON form.

    poses = load_ground_truth("data/ground_truth/rtabmap_mac_1_2.txt")   # either form, by content
    poses[305]                                   # (4, 4) world_T_tag, app's y-up world frame, m
    ground_truth_to_json(poses)                  # {"poses": [{"tag_id": N, "pose": [x, y, z,
                                                 #             qx, qy, qz, qw]}, ...]}

Two forms are read:

- **RTAB-Map export**, one tag per line: ``rpy TAG_ID x y z roll pitch yaw`` (metres, radians) in
  RTAB-Map's z-up frame. Negative ids are RTAB-Map's own landmarks, not tags, and are skipped; blank
  lines and ``#`` comments are skipped. Converted to the app's y-up world frame and tag-frame
  convention (see :func:`world_T_tag_from_rtabmap`).
- **JSON**: ``{"poses": [{"tag_id": N, "pose": [x, y, z, qx, qy, qz, qw]}, ...]}``, already in the
  app's conventions (the form :func:`ground_truth_to_json` writes).

Every malformed input raises :class:`GroundTruthFormatError` naming where (a line number, a JSON
field such as ``poses[3].pose[5]``, a file) and why.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from app.domain.errors import GroundTruthFormatError
from app.domain.frames import (
    FloatArray,
    make_pose,
    pose_from_xyz_quat_xyzw,
    pose_to_xyz_quat_xyzw,
    rotation_about_x,
    rotation_about_y,
    rotation_about_z,
    rotation_from_quat_xyzw,
)
from app.domain.json_values import gunzip_if_compressed, json_type_name

#: Rotation taking RTAB-Map's z-up axes to the app's y-up world axes: quaternion (x, y, z, w) =
#: (-0.5, 0.5, 0.5, 0.5), i.e. x_app = -y_rtab, y_app = z_rtab, z_app = -x_rtab.
YUP_R_RTABMAP: FloatArray = rotation_from_quat_xyzw([-0.5, 0.5, 0.5, 0.5])

#: Keyword that starts each tag line of an RTAB-Map export.
RTABMAP_KEYWORD = "rpy"

#: Smallest quaternion norm accepted before normalizing.
MIN_QUATERNION_NORM = 1e-6


def world_T_tag_from_rtabmap(
    x_m: float, y_m: float, z_m: float, roll_rad: float, pitch_rad: float, yaw_rad: float
) -> FloatArray:
    """``world_T_tag`` in the app's conventions from one RTAB-Map export line's numbers.

    With A = :data:`YUP_R_RTABMAP` and R_rpy = Rx(roll)·Ry(pitch)·Rz(yaw): position p' = A·p and
    rotation R' = R_rpy·A·A. This is the conversion that reproduces the project's reference file
    ``data/ground_truth/mac_1_2_yup_reference.json`` (to 1e-14 m and 2e-6°).
    """
    R_rpy = rotation_about_x(roll_rad) @ rotation_about_y(pitch_rad) @ rotation_about_z(yaw_rad)
    world_R_tag = R_rpy @ YUP_R_RTABMAP @ YUP_R_RTABMAP
    world_t_tag = YUP_R_RTABMAP @ np.array([x_m, y_m, z_m], dtype=np.float64)
    return make_pose(world_R_tag, world_t_tag)


# --------------------------------------------------------------------------- RTAB-Map export


def parse_rtabmap_export(text: str) -> dict[int, FloatArray]:
    """Tag poses from an RTAB-Map export (lines ``rpy TAG_ID x y z roll pitch yaw``).

    Returns ``{tag_id: world_T_tag}`` (4x4, app's y-up world frame, m). Negative ids are skipped;
    blank lines and lines starting with ``#`` are skipped. Raises :class:`GroundTruthFormatError`
    ("line 7: ...") for any other line that is not a well-formed tag line, for a tag id given twice,
    and for an export with no tag at all.
    """
    poses: dict[int, FloatArray] = {}
    line_of_tag: dict[int, int] = {}
    for line_number, raw_line in enumerate(text.splitlines(), start=1):
        line = raw_line.strip()
        if not line or line.startswith("#"):
            continue
        tag_id, values = _parse_rtabmap_line(line, line_number)
        if tag_id < 0:
            continue
        if tag_id in poses:
            raise GroundTruthFormatError(
                f"line {line_number}: tag {tag_id} already given on line {line_of_tag[tag_id]}"
            )
        poses[tag_id] = world_T_tag_from_rtabmap(*values)
        line_of_tag[tag_id] = line_number
    if not poses:
        raise GroundTruthFormatError("no tag poses (no 'rpy' line with a tag id ≥ 0)")
    return poses


def _parse_rtabmap_line(line: str, line_number: int) -> tuple[int, list[float]]:
    where = f"line {line_number}"
    fields = line.split()
    if fields[0] != RTABMAP_KEYWORD:
        raise GroundTruthFormatError(
            f"{where}: expected 'rpy TAG_ID x y z roll pitch yaw', got {_shorten(line)!r}"
        )
    if len(fields) != 8:
        raise GroundTruthFormatError(
            f"{where}: expected 8 fields 'rpy TAG_ID x y z roll pitch yaw', got {len(fields)}"
        )
    try:
        tag_id = int(fields[1])
    except ValueError:
        raise GroundTruthFormatError(f"{where}: tag id {fields[1]!r} is not an integer") from None
    names = ("x", "y", "z", "roll", "pitch", "yaw")
    values: list[float] = []
    for name, token in zip(names, fields[2:], strict=True):
        try:
            value = float(token)
        except ValueError:
            raise GroundTruthFormatError(f"{where}: {name} {token!r} is not a number") from None
        if not math.isfinite(value):
            raise GroundTruthFormatError(f"{where}: {name} is a non-finite number {token}")
        values.append(value)
    return tag_id, values


# --------------------------------------------------------------------------- JSON form


def parse_ground_truth_json(document: Any) -> dict[int, FloatArray]:
    """Tag poses from the JSON form ``{"poses": [{"tag_id": N, "pose": [x,y,z,qx,qy,qz,qw]}]}``.

    ``document`` is the decoded JSON value. Returns ``{tag_id: world_T_tag}`` (4x4, m); quaternions
    are normalized. Raises :class:`GroundTruthFormatError` naming the field (``poses[2].pose[4]``)
    and the reason: not an object, a missing key, a wrong length, a non-finite number, a negative
    or repeated tag id, a zero quaternion, or no poses at all. Unknown keys are ignored.
    """
    if not isinstance(document, Mapping):
        raise GroundTruthFormatError(f"expected a JSON object, got {json_type_name(document)}")
    if "poses" not in document:
        raise GroundTruthFormatError("poses: missing")
    entries = document["poses"]
    if not isinstance(entries, list):
        raise GroundTruthFormatError(f"poses: expected a list, got {json_type_name(entries)}")
    if not entries:
        raise GroundTruthFormatError("poses: empty, no tag poses")
    poses: dict[int, FloatArray] = {}
    index_of_tag: dict[int, int] = {}
    for i, entry in enumerate(entries):
        where = f"poses[{i}]"
        if not isinstance(entry, Mapping):
            raise GroundTruthFormatError(
                f"{where}: expected an object, got {json_type_name(entry)}"
            )
        tag_id = _json_tag_id(entry, where)
        if tag_id in poses:
            raise GroundTruthFormatError(
                f"{where}.tag_id: tag {tag_id} already given at poses[{index_of_tag[tag_id]}]"
            )
        poses[tag_id] = _json_pose(entry, where)
        index_of_tag[tag_id] = i
    return poses


def _json_tag_id(entry: Mapping[str, Any], where: str) -> int:
    if "tag_id" not in entry:
        raise GroundTruthFormatError(f"{where}.tag_id: missing")
    value = entry["tag_id"]
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise GroundTruthFormatError(
            f"{where}.tag_id: expected an integer, got {json_type_name(value)}"
        )
    if isinstance(value, float) and not value.is_integer():
        raise GroundTruthFormatError(f"{where}.tag_id: expected an integer, got {value}")
    if value < 0:
        raise GroundTruthFormatError(f"{where}.tag_id: must be ≥ 0, got {int(value)}")
    return int(value)


def _json_pose(entry: Mapping[str, Any], where: str) -> FloatArray:
    where = f"{where}.pose"
    if "pose" not in entry:
        raise GroundTruthFormatError(f"{where}: missing")
    value = entry["pose"]
    if not isinstance(value, list):
        raise GroundTruthFormatError(
            f"{where}: expected a list of 7 numbers [x, y, z, qx, qy, qz, qw], "
            f"got {json_type_name(value)}"
        )
    if len(value) != 7:
        raise GroundTruthFormatError(
            f"{where}: expected 7 numbers [x, y, z, qx, qy, qz, qw], got {len(value)}"
        )
    for j, item in enumerate(value):
        if isinstance(item, bool) or not isinstance(item, (int, float)):
            raise GroundTruthFormatError(
                f"{where}[{j}]: expected a number, got {json_type_name(item)}"
            )
        if not math.isfinite(item):
            raise GroundTruthFormatError(f"{where}[{j}]: non-finite number {item}")
    values = np.asarray(value, dtype=np.float64)
    quat_norm = float(np.linalg.norm(values[3:7]))
    if quat_norm < MIN_QUATERNION_NORM:
        raise GroundTruthFormatError(
            f"{where}: quaternion [qx, qy, qz, qw] is zero (norm {quat_norm:.3g})"
        )
    return pose_from_xyz_quat_xyzw(values)


def ground_truth_to_json(poses: Mapping[int, FloatArray]) -> dict[str, Any]:
    """The JSON form of ``{tag_id: world_T_tag}``, sorted by tag id; the inverse of
    :func:`parse_ground_truth_json` (quaternions written with qw ≥ 0)."""
    return {
        "poses": [
            {"tag_id": int(tag_id), "pose": pose_to_xyz_quat_xyzw(np.asarray(poses[tag_id]))}
            for tag_id in sorted(poses)
        ]
    }


# --------------------------------------------------------------------------- files


def load_ground_truth(path: str | Path) -> dict[int, FloatArray]:
    """Read a ground-truth file in either form (told apart by content; may be gzip-compressed).

    A file whose first non-blank character is ``{`` or ``[`` is read as JSON, one whose first
    non-blank, non-comment line starts with ``rpy`` as an RTAB-Map export. Errors name the file:
    ``GroundTruthFormatError("gt.txt: line 3: ...")``.
    """
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as err:
        raise GroundTruthFormatError(f"cannot read {path}: {err.strerror or err}") from err
    try:
        return parse_ground_truth_text(_decode(raw))
    except GroundTruthFormatError as err:
        raise GroundTruthFormatError(f"{path}: {err}") from err


def parse_ground_truth_text(text: str) -> dict[int, FloatArray]:
    """Tag poses from a ground-truth file's text, in either form (see :func:`load_ground_truth`)."""
    stripped = text.lstrip("\ufeff \t\r\n")
    if stripped.startswith(("{", "[")):
        try:
            document = json.loads(stripped)
        except json.JSONDecodeError as err:
            raise GroundTruthFormatError(
                f"not valid JSON: {err.msg} at line {err.lineno} column {err.colno}"
            ) from err
        return parse_ground_truth_json(document)
    first_line = next(
        (
            line.strip()
            for line in stripped.splitlines()
            if line.strip() and not line.strip().startswith("#")
        ),
        "",
    )
    if first_line.split(maxsplit=1)[:1] == [RTABMAP_KEYWORD]:
        return parse_rtabmap_export(text.lstrip("\ufeff"))
    if not first_line:
        raise GroundTruthFormatError("empty: no tag poses")
    raise GroundTruthFormatError(
        'unknown ground-truth form: expected a JSON object {"poses": [...]} or RTAB-Map lines '
        f"'rpy TAG_ID x y z roll pitch yaw', got {_shorten(first_line)!r}"
    )


def _decode(raw: bytes) -> str:
    try:
        raw = gunzip_if_compressed(raw)
    except ValueError as err:
        raise GroundTruthFormatError(f"not valid gzip: {err}") from err
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as err:
        raise GroundTruthFormatError(f"not UTF-8 text: {err.reason}") from err


def _shorten(text: str, limit: int = 60) -> str:
    return text if len(text) <= limit else text[: limit - 1] + "…"
