"""A recorded mapping session replayed as localization updates (tests, benchmarks, samples)."""

from __future__ import annotations

import math
import statistics
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from app.domain.frames import FloatArray
from app.domain.localize.batch import parse_update
from app.domain.localize.params import LocalizerParams
from app.domain.localize.result import LocalizationResult
from app.domain.localize.smoother import update
from app.domain.localize.state import LocalizerState
from app.domain.upload.session import (
    Session,
)

# --------------------------------------------------------------------------- replaying a session


@dataclass(frozen=True, slots=True, kw_only=True)
class TagPrediction:
    """Where the estimate before an update put a detected tag, against the map.

    error_m: distance between the map's tag position and ``map_T_session_pred · session_T_phone ·
        phone_T_tag``'s, m, the estimate taken *before* the update that carries the detection.
    first_of_sighting: the first detection of this tag after detections of another tag (the
        "next tag" a navigating user walks to); later ones repeat a tag just used.
    """

    tag_id: int
    pose_id: int
    error_m: float
    first_of_sighting: bool


@dataclass(frozen=True, slots=True, kw_only=True)
class ReplayStep:
    """One update of a replay: its result, the predictions made before it, its wall time (ms)."""

    result: LocalizationResult
    predictions: tuple[TagPrediction, ...]
    update_ms: float


def session_update_documents(
    session: Session, batch_size: int, *, tag_ids: Sequence[int] | None = None
) -> list[dict[str, Any]]:
    """The updates a phone would send while walking ``session``: JSON-ready documents of
    ``batch_size`` consecutive poses each, with the detections made from those poses (only of
    ``tag_ids`` when given). The same documents serve :func:`parse_update` and the HTTP API."""
    if batch_size < 1:
        raise ValueError(f"batch_size must be ≥ 1, got {batch_size}")
    detections = session.detections
    keep = (
        np.isin(detections.tag_id, np.asarray(list(tag_ids), dtype=np.int64))
        if tag_ids is not None
        else np.ones(len(detections), dtype=bool)
    )
    documents = []
    for start in range(0, session.num_poses, batch_size):
        stop = min(start + batch_size, session.num_poses)
        poses = [
            {
                "id": int(session.pose_id[i]),
                "timestamp": float(session.timestamp_s[i]),
                "pose": [float(v) for v in session.world_T_phone[i].T.reshape(16)],
            }
            for i in range(start, stop)
        ]
        rows = np.flatnonzero(
            keep & (detections.pose_index >= start) & (detections.pose_index < stop)
        )
        frames: dict[int, list[dict[str, Any]]] = {}
        for row in rows.tolist():
            frames.setdefault(int(detections.frame_index[row]), []).append(
                _detection_document(session, row)
            )
        documents.append({"poses": poses, "tag_data": [frames[f] for f in sorted(frames)]})
    return documents


def _detection_document(session: Session, row: int) -> dict[str, Any]:
    detections = session.detections
    document: dict[str, Any] = {
        "tag_id": int(detections.tag_id[row]),
        "pose_id": int(session.pose_id[detections.pose_index[row]]),
        "tag_pose": [float(v) for v in detections.camera_T_tag[row].reshape(16)],
        "camera_intrinsics": [float(v) for v in detections.intrinsics[row]],
        "tag_corners_pixel_coordinates": [float(v) for v in detections.corners_px[row].reshape(8)],
    }
    if math.isfinite(float(detections.timestamp_s[row])):
        document["timestamp"] = float(detections.timestamp_s[row])
    return document


def replay_session(
    map_tags: Mapping[int, FloatArray],
    session: Session,
    batch_size: int = 10,
    params: LocalizerParams | None = None,
) -> list[ReplayStep]:
    """Walk ``session`` through the localizer against ``map_tags`` in batches of ``batch_size``
    poses, as a navigating phone would, predicting each detected tag before the update that
    carries it. Detections of tags not in the map are left out (the API would refuse them)."""
    params = params or LocalizerParams()
    state = LocalizerState.initial()
    steps = []
    previous_tag: int | None = None
    for document in session_update_documents(session, batch_size, tag_ids=sorted(map_tags)):
        batch = parse_update(document)
        map_T_session = state.map_T_session()
        predictions = []
        for row in range(len(batch.detections)):
            tag_id = int(batch.detections.tag_id[row])
            first = tag_id != previous_tag
            previous_tag = tag_id
            if map_T_session is None:
                continue
            pose_id = int(batch.detection_pose_id[row])
            session_T_phone = batch.session_T_phone[int(np.searchsorted(batch.pose_id, pose_id))]
            map_t_tag_pred = (map_T_session @ session_T_phone @ batch.detections.phone_T_tag[row])[
                :3, 3
            ]
            predictions.append(
                TagPrediction(
                    tag_id=tag_id,
                    pose_id=pose_id,
                    error_m=float(np.linalg.norm(map_t_tag_pred - map_tags[tag_id][:3, 3])),
                    first_of_sighting=first,
                )
            )
        started = time.perf_counter()
        state, result = update(state, batch, map_tags, params)
        update_ms = (time.perf_counter() - started) * 1e3
        steps.append(ReplayStep(result=result, predictions=tuple(predictions), update_ms=update_ms))
    return steps


def prediction_errors_m(
    steps: Sequence[ReplayStep], *, first_of_sighting_only: bool = False
) -> FloatArray:
    """(P,) the tag prediction errors of a replay, m, in order."""
    return np.array(
        [
            p.error_m
            for step in steps
            for p in step.predictions
            if p.first_of_sighting or not first_of_sighting_only
        ],
        dtype=np.float64,
    )


def median_and_p90(values: npt.ArrayLike) -> tuple[float, float]:
    """(median, 90th percentile) of ``values``; NaN for none."""
    array = np.asarray(values, dtype=np.float64)
    if array.size == 0:
        return math.nan, math.nan
    return float(statistics.median(array.tolist())), float(np.percentile(array, 90))
