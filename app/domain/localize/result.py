"""What an update answers: the phone in the map, with its uncertainty, and what was rejected."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np

from app.domain.frames import FloatArray
from app.domain.localize.params import Status

# --------------------------------------------------------------------------- the result


@dataclass(frozen=True, slots=True, kw_only=True)
class LocalizationRejection:
    """A detection of a known tag left out; ``reason`` is ``reprojection``, ``view_angle``,
    ``distance`` (the mapping screen's tests) or ``before_window`` (a late detection on a pose
    older than the window's marginalized past)."""

    tag_id: int
    pose_id: int
    reason: str
    detail: str


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class LocalizationResult:
    """The answer to one update.

    status: ``not_localized`` until the first usable known-tag detection, then ``localized``.
    pose_id, timestamp_s: the latest odometry pose (None before any pose arrived).
    map_T_phone: (4, 4) the phone at the latest pose, map frame (y up), m.
    map_T_session: (4, 4) the session-to-map transform.
    covariance: (6, 6) of ``map_T_session``, ``[rot rad, trans m]``, session-frame tangent.
    position_covariance_m2: (3, 3) of the phone's position, map frame, m².
    position_sigma_m: √trace of ``position_covariance_m2``, m (the RMS 3-D position error).
    tags_used: distinct tag ids whose detections entered this update.
    window_tag_ids: distinct tag ids in the optimized window.
    detections_used: detections of this update that entered the window.
    rejections: detections of this update left out, with the reason.
    window_keyframes: keyframes in the window after the update (bounded).
    iterations: Levenberg–Marquardt iterations run (0 when no new detection arrived).
    """

    status: Status
    pose_id: int | None
    timestamp_s: float | None
    map_T_phone: FloatArray | None
    map_T_session: FloatArray | None
    covariance: FloatArray | None
    position_covariance_m2: FloatArray | None
    position_sigma_m: float | None
    tags_used: tuple[int, ...]
    window_tag_ids: tuple[int, ...]
    detections_used: int
    rejections: tuple[LocalizationRejection, ...]
    window_keyframes: int
    iterations: int

    def to_json(self) -> dict[str, Any]:
        """A JSON-ready dict; 4×4 and 6×6 matrices as nested row lists."""

        def rows(matrix: FloatArray | None) -> list[list[float]] | None:
            # (tolist: the same Python floats as float() of each entry, at once)
            return None if matrix is None else np.asarray(matrix, dtype=np.float64).tolist()

        return {
            "status": self.status,
            "pose_id": self.pose_id,
            "timestamp_s": self.timestamp_s,
            "map_T_phone": rows(self.map_T_phone),
            "map_T_session": rows(self.map_T_session),
            "covariance": rows(self.covariance),
            "position_covariance_m2": rows(self.position_covariance_m2),
            "position_sigma_m": self.position_sigma_m,
            "tags_used": list(self.tags_used),
            "window_tag_ids": list(self.window_tag_ids),
            "detections_used": self.detections_used,
            "rejections": [dataclasses.asdict(r) for r in self.rejections],
            "window_keyframes": self.window_keyframes,
            "iterations": self.iterations,
        }
