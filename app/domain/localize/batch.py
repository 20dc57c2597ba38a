"""One update from the phone: its odometry and tag detections, parsed and checked."""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from app.domain.errors import SessionFormatError
from app.domain.frames import FloatArray, orthonormalized_stack
from app.domain.json_values import json_type_name
from app.domain.localize.params import LocalizationUpdateError
from app.domain.localize.state import LocalizerState
from app.domain.upload.fields import (
    integer_field,
    matrix16_field,
    maybe_not_rigid,
    number_field,
    require_list,
    require_object,
    rigid_pose,
)
from app.domain.upload.session import (
    IntArray,
    TagDetections,
    count_detections,
    detections_from_rows,
    parse_detection_rows,
)

# --------------------------------------------------------------------------- the update batch

#: Most poses one update may hold. A phone sends one update a second with the poses since the last
#: (the app records ~6 a second), so this is minutes of backlog; and the cost of an update grows
#: faster than its size (604 poses and 79 detections: 43 ms; 2,416 and 316: 0.5 s; the 10,872
#: and 1,422 a 4 MiB body holds: 10 s), while an API process computes one update at a time. A
#: larger backlog goes in several updates.
MAX_UPDATE_POSES = 1_000
#: Most tag detections one update may hold (the walks of ``data/sessions`` see ~1 a second).
MAX_UPDATE_DETECTIONS = 200


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class UpdateBatch:
    """One update from the phone, parsed (see :func:`parse_update`).

    pose_id: (N,) the app's pose ids, increasing.
    timestamp_s: (N,) s, non-decreasing.
    session_T_phone: (N, 4, 4) ARKit odometry, the phone's session frame (y up), m.
    detection_pose_id: (M,) the pose each detection was made from: in this batch or a recent one.
    detection_field: (M,) each detection's JSON path in the update (``tag_data[2][0]``).
    detections: the M detections; here ``pose_index`` holds the pose id (a detection may refer to
        a pose of an earlier batch, so no row of this batch's arrays would do).
    """

    pose_id: IntArray
    timestamp_s: FloatArray
    session_T_phone: FloatArray
    detection_pose_id: IntArray
    detection_field: tuple[str, ...]
    detections: TagDetections

    @property
    def num_poses(self) -> int:
        return int(self.pose_id.shape[0])


def parse_update(document: Any) -> UpdateBatch:
    """Parse ``{"poses": [...], "tag_data": [...]}`` into an :class:`UpdateBatch`.

    ``poses[i] = {"id": int, "timestamp": s, "pose": [16 floats, column-major]}`` (ARKit's
    ``session_T_phone``, as the upload's ``pose_data``); ``tag_data`` is a list of frames, each a
    list of detections in the upload's format (§2), or a bare detection. Either list may be
    empty or absent. Raises :class:`LocalizationUpdateError` naming the field and the reason.
    """
    try:
        return _parse_update(document)
    except SessionFormatError as err:  # the session parser's field readers raise these
        raise LocalizationUpdateError(err.field, err.reason) from err


def _parse_update(document: Any) -> UpdateBatch:
    if not isinstance(document, Mapping):
        raise LocalizationUpdateError("", f"expected a JSON object, got {json_type_name(document)}")
    poses = document.get("poses", [])
    require_list(poses, "poses")
    n = len(poses)
    if n > MAX_UPDATE_POSES:
        raise LocalizationUpdateError(
            "poses", f"{n} poses in one update, at most {MAX_UPDATE_POSES}: send them in several"
        )
    tag_data = document.get("tag_data", [])
    detections = count_detections(tag_data)
    if detections > MAX_UPDATE_DETECTIONS:
        raise LocalizationUpdateError(
            "tag_data",
            f"{detections} detections in one update, at most {MAX_UPDATE_DETECTIONS}: "
            "send them in several",
        )
    pose_id = np.empty(n, dtype=np.int64)
    timestamp_s = np.empty(n, dtype=np.float64)
    matrices = np.empty((n, 4, 4), dtype=np.float64)
    for i, entry in enumerate(poses):
        where = f"poses[{i}]"
        try:
            require_object(entry, where)
            pose_id[i] = integer_field(entry, "id", where)
            timestamp_s[i] = number_field(entry, "timestamp", where)
            matrices[i] = matrix16_field(entry, "pose", where).reshape(4, 4).T
        except SessionFormatError:
            _check_rigid(matrices[:i], range(i))  # an earlier pose's error comes first
            raise
        if i > 0 and pose_id[i] <= pose_id[i - 1]:
            _check_rigid(matrices[: i + 1], range(i + 1))
            raise LocalizationUpdateError(
                f"{where}.id", f"ids must increase: {pose_id[i]} follows {pose_id[i - 1]}"
            )
        if i > 0 and timestamp_s[i] < timestamp_s[i - 1]:
            _check_rigid(matrices[: i + 1], range(i + 1))
            raise LocalizationUpdateError(
                f"{where}.timestamp",
                f"time goes backwards: {timestamp_s[i]} s after {timestamp_s[i - 1]} s",
            )
    _check_rigid(matrices, np.flatnonzero(maybe_not_rigid(matrices)))
    session_T_phone = orthonormalized_stack(matrices)

    rows = parse_detection_rows(tag_data)
    return UpdateBatch(
        pose_id=pose_id,
        timestamp_s=timestamp_s,
        session_T_phone=session_T_phone,
        detection_pose_id=np.array([r["pose_id"] for r in rows], dtype=np.int64),
        detection_field=tuple(r["where"] for r in rows),
        detections=detections_from_rows(rows, [r["pose_id"] for r in rows]),
    )


def _check_rigid(matrices: FloatArray, indices: Iterable[int]) -> None:
    """Raise ``rigid_pose``'s error for the first of ``indices`` whose matrix is no rigid
    transform (``poses[i].pose``)."""
    for i in indices:
        rigid_pose(matrices[i], f"poses[{i}].pose")


# --------------------------------------------------------------------------- validation


def validate_update(
    state: LocalizerState, batch: UpdateBatch, map_tags: Mapping[int, FloatArray]
) -> None:
    """Check that ``batch`` follows ``state`` and that every detection is of a tag in the map.

    Raises :class:`LocalizationUpdateError` naming the field: a pose id not above the state's last
    one, a timestamp before the state's last one, a detection whose ``pose_id`` is neither in this
    batch nor among the state's recent poses, a tag id the map does not have.
    """
    last_pose_id, last_timestamp_s = state.last_pose_id, state.last_timestamp_s
    if batch.num_poses and last_pose_id is not None and batch.pose_id[0] <= last_pose_id:
        raise LocalizationUpdateError(
            "poses[0].id",
            f"ids must increase: {batch.pose_id[0]} follows {last_pose_id} from the last update",
        )
    if batch.num_poses and last_timestamp_s is not None and batch.timestamp_s[0] < last_timestamp_s:
        raise LocalizationUpdateError(
            "poses[0].timestamp",
            f"time goes backwards: {batch.timestamp_s[0]} s after {last_timestamp_s} s "
            "from the last update",
        )
    known_pose_ids = {int(p) for p in state.recent_pose_id} | {int(p) for p in batch.pose_id}
    for row, where in enumerate(batch.detection_field):
        tag_id = int(batch.detections.tag_id[row])
        if tag_id not in map_tags:
            raise LocalizationUpdateError(
                f"{where}.tag_id", f"tag {tag_id} is not in this map ({_known_tags(map_tags)})"
            )
        pose_id = int(batch.detection_pose_id[row])
        if pose_id not in known_pose_ids:
            raise LocalizationUpdateError(
                f"{where}.pose_id",
                f"no pose with id {pose_id} in this update or the last "
                f"{state.recent_pose_id.size} poses of the session",
            )


def _known_tags(map_tags: Mapping[int, FloatArray]) -> str:
    ids = sorted(map_tags)
    if not ids:
        return "the map has no tags"
    if len(ids) > 12:
        return f"known: {len(ids)} tags, {ids[0]}–{ids[-1]}"
    return "known: " + ", ".join(str(t) for t in ids)
