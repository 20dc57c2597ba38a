"""The smoother's state between updates, and its JSON form (kept in the database)."""

from __future__ import annotations

import base64
import binascii
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from app.domain.frames import FloatArray, se3_inverse
from app.domain.localize.linalg import UPPER_6, symmetric
from app.domain.localize.params import STATE_VERSION, LocalizerStateError
from app.domain.upload.session import (
    IntArray,
)

# --------------------------------------------------------------------------- the state


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class WindowDetection:
    """A used tag detection in the window.

    keyframe_T_tag: (4, 4) the observed tag in the frame of its keyframe's phone pose, m (the
        detection's own pose carried there by odometry when it was merged into the keyframe).
    covariance: (6, 6) the detection's noise in the tag frame, ``[rot rad, trans m]``.
    """

    tag_id: int
    pose_id: int
    keyframe_T_tag: FloatArray
    covariance: FloatArray


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class Keyframe:
    """A phone pose with tag detections: one variable of the window.

    session_T_phone: (4, 4) the odometry at this pose, session frame, m.
    map_T_phone: (4, 4) the current estimate of this pose in the map, m.
    drift_to_next: (6, 6) covariance of the change of ``map_T_session`` (session-frame tangent,
        ``[rot rad, trans m]``) accumulated by the odometry from this pose to the next keyframe's,
        or to the latest pose for the newest keyframe.
    """

    pose_id: int
    timestamp_s: float
    session_T_phone: FloatArray
    map_T_phone: FloatArray
    drift_to_next: FloatArray
    detections: tuple[WindowDetection, ...]


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class LocalizerState:
    """Everything a navigation session needs between updates; JSON-serializable, immutable.

    keyframes: the window, oldest first (empty until the first usable known-tag detection).
    prior_map_T_phone, prior_covariance: the marginalized past, a Gaussian on the oldest keyframe's
        ``map_T_phone`` ((4, 4); (6, 6) in its phone-frame tangent), or None while nothing was
        marginalized.
    last_keyframe_covariance: (6, 6) marginal covariance of ``map_T_session`` at the newest
        keyframe, session-frame tangent; None before the first keyframe.
    recent_pose_id, recent_timestamp_s, recent_session_T_phone: the last ``recent_poses`` odometry
        poses ((R,), (R,) s, (R, 4, 4) session frame), the latest last.
    num_updates, num_poses, num_detections, num_detections_used: counts over the session.
    num_keyframes_marginalized: keyframes folded into the prior so far.

    Compare states by their ``to_json()`` (the arrays make ``==`` meaningless, so it is identity).
    """

    keyframes: tuple[Keyframe, ...] = ()
    prior_map_T_phone: FloatArray | None = None
    prior_covariance: FloatArray | None = None
    last_keyframe_covariance: FloatArray | None = None
    recent_pose_id: IntArray = field(default_factory=lambda: np.empty(0, dtype=np.int64))
    recent_timestamp_s: FloatArray = field(default_factory=lambda: np.empty(0, dtype=np.float64))
    recent_session_T_phone: FloatArray = field(
        default_factory=lambda: np.empty((0, 4, 4), dtype=np.float64)
    )
    num_updates: int = 0
    num_poses: int = 0
    num_detections: int = 0
    num_detections_used: int = 0
    num_keyframes_marginalized: int = 0

    @classmethod
    def initial(cls) -> LocalizerState:
        """The state of a navigation session that has sent nothing yet."""
        return cls()

    @property
    def localized(self) -> bool:
        return bool(self.keyframes)

    @property
    def last_pose_id(self) -> int | None:
        return int(self.recent_pose_id[-1]) if self.recent_pose_id.size else None

    @property
    def last_timestamp_s(self) -> float | None:
        return float(self.recent_timestamp_s[-1]) if self.recent_timestamp_s.size else None

    def map_T_session(self) -> FloatArray | None:
        """(4, 4) current estimate, or None while not localized."""
        if not self.keyframes:
            return None
        newest = self.keyframes[-1]
        return newest.map_T_phone @ se3_inverse(newest.session_T_phone)

    def map_T_session_covariance(self) -> FloatArray | None:
        """(6, 6) covariance of :meth:`map_T_session` at the latest pose, session-frame tangent."""
        if not self.keyframes or self.last_keyframe_covariance is None:
            return None
        return symmetric(self.last_keyframe_covariance + self.keyframes[-1].drift_to_next)

    def window_tag_ids(self) -> tuple[int, ...]:
        """Distinct tag ids with detections in the window, sorted."""
        return tuple(sorted({d.tag_id for k in self.keyframes for d in k.detections}))

    def to_json(self) -> dict[str, Any]:
        """A JSON-ready dict; ``from_json(to_json())`` gives back an identical state.

        Ids, timestamps and counts are plain JSON; the bulky float arrays are packed
        (:func:`pack_poses`: the top 3×4 of each pose; :func:`pack_covariances`: the upper
        triangle of each 6×6, both as little-endian float64 in base64), which keeps every bit and
        reads and writes several times faster than lists of numbers.
        """
        detections = [d for k in self.keyframes for d in k.detections]
        return {
            "version": STATE_VERSION,
            "keyframes": {
                "pose_id": [k.pose_id for k in self.keyframes],
                "timestamp_s": [k.timestamp_s for k in self.keyframes],
                "detection_count": [len(k.detections) for k in self.keyframes],
                "session_T_phone": pack_poses([k.session_T_phone for k in self.keyframes]),
                "map_T_phone": pack_poses([k.map_T_phone for k in self.keyframes]),
                "drift_to_next": pack_covariances([k.drift_to_next for k in self.keyframes]),
            },
            "detections": {
                "tag_id": [d.tag_id for d in detections],
                "pose_id": [d.pose_id for d in detections],
                "keyframe_T_tag": pack_poses([d.keyframe_T_tag for d in detections]),
                "covariance": pack_covariances([d.covariance for d in detections]),
            },
            "prior": (
                None
                if self.prior_map_T_phone is None or self.prior_covariance is None
                else {
                    "map_T_phone": pack_poses([self.prior_map_T_phone]),
                    "covariance": pack_covariances([self.prior_covariance]),
                }
            ),
            "last_keyframe_covariance": (
                None
                if self.last_keyframe_covariance is None
                else pack_covariances([self.last_keyframe_covariance])
            ),
            "recent_poses": {
                "pose_id": [int(v) for v in self.recent_pose_id],
                "timestamp_s": [float(v) for v in self.recent_timestamp_s],
                "session_T_phone": pack_poses(list(self.recent_session_T_phone)),
            },
            "counts": {
                "updates": self.num_updates,
                "poses": self.num_poses,
                "detections": self.num_detections,
                "detections_used": self.num_detections_used,
                "keyframes_marginalized": self.num_keyframes_marginalized,
            },
        }

    @classmethod
    def from_json(cls, document: Mapping[str, Any]) -> LocalizerState:
        """Inverse of :meth:`to_json`; raises :class:`LocalizerStateError` if it cannot be read."""
        try:
            return cls._from_json(document)
        except LocalizerStateError:
            raise
        except (KeyError, TypeError, ValueError, AttributeError, binascii.Error) as err:
            raise LocalizerStateError(f"unreadable localizer state: {err!r}") from err

    @classmethod
    def _from_json(cls, document: Mapping[str, Any]) -> LocalizerState:
        if document.get("version") != STATE_VERSION:
            raise LocalizerStateError(
                f"localizer state version {document.get('version')!r}, expected {STATE_VERSION}"
            )
        stored = document["keyframes"]
        counts = [int(c) for c in stored["detection_count"]]
        k = len(counts)
        table = document["detections"]
        m = sum(counts)
        keyframe_T_tag = unpack_poses(table["keyframe_T_tag"], m)
        detection_covariance = unpack_covariances(table["covariance"], m)
        detections = [
            WindowDetection(
                tag_id=int(table["tag_id"][row]),
                pose_id=int(table["pose_id"][row]),
                keyframe_T_tag=keyframe_T_tag[row],
                covariance=detection_covariance[row],
            )
            for row in range(m)
        ]
        session_T_phone = unpack_poses(stored["session_T_phone"], k)
        map_T_phone = unpack_poses(stored["map_T_phone"], k)
        drift = unpack_covariances(stored["drift_to_next"], k)
        ends = np.cumsum([0, *counts]).tolist()
        keyframes = tuple(
            Keyframe(
                pose_id=int(stored["pose_id"][i]),
                timestamp_s=float(stored["timestamp_s"][i]),
                session_T_phone=session_T_phone[i],
                map_T_phone=map_T_phone[i],
                drift_to_next=drift[i],
                detections=tuple(detections[ends[i] : ends[i + 1]]),
            )
            for i in range(k)
        )
        prior = document["prior"]
        last_covariance = document["last_keyframe_covariance"]
        recent = document["recent_poses"]
        r = len(recent["pose_id"])
        counters = document["counts"]
        return cls(
            keyframes=keyframes,
            prior_map_T_phone=None if prior is None else unpack_poses(prior["map_T_phone"], 1)[0],
            prior_covariance=(
                None if prior is None else unpack_covariances(prior["covariance"], 1)[0]
            ),
            last_keyframe_covariance=(
                None if last_covariance is None else unpack_covariances(last_covariance, 1)[0]
            ),
            recent_pose_id=np.array([int(v) for v in recent["pose_id"]], dtype=np.int64),
            recent_timestamp_s=np.array(
                [float(v) for v in recent["timestamp_s"]], dtype=np.float64
            ).reshape(r),
            recent_session_T_phone=unpack_poses(recent["session_T_phone"], r),
            num_updates=int(counters["updates"]),
            num_poses=int(counters["poses"]),
            num_detections=int(counters["detections"]),
            num_detections_used=int(counters["detections_used"]),
            num_keyframes_marginalized=int(counters["keyframes_marginalized"]),
        )


def pack_floats(values: FloatArray) -> str:
    return base64.b64encode(np.ascontiguousarray(values, dtype="<f8").tobytes()).decode("ascii")


def unpack_floats(text: str, count: int) -> FloatArray:
    values = np.frombuffer(base64.b64decode(text, validate=True), dtype="<f8")
    if values.size != count:
        raise ValueError(f"expected {count} packed numbers, got {values.size}")
    if not np.all(np.isfinite(values)):
        raise ValueError("packed numbers include a non-finite one")
    return values.astype(np.float64)


def pack_poses(poses: Sequence[FloatArray]) -> str:
    """Poses (4, 4) as their top 3×4 rows (the last row is always [0, 0, 0, 1]), base64."""
    stacked = np.stack(poses) if len(poses) else np.empty((0, 4, 4))
    return pack_floats(stacked[:, :3, :])


def unpack_poses(text: str, count: int) -> FloatArray:
    """(count, 4, 4) poses from :func:`pack_poses`."""
    poses = np.zeros((count, 4, 4))
    poses[:, :3, :] = unpack_floats(text, count * 12).reshape(count, 3, 4)
    poses[:, 3, 3] = 1.0
    return poses


def pack_covariances(covariances: Sequence[FloatArray]) -> str:
    """Symmetric (6, 6) matrices as their 21 upper-triangle entries, base64."""
    stacked = np.stack(covariances) if len(covariances) else np.empty((0, 6, 6))
    return pack_floats(stacked[:, UPPER_6[0], UPPER_6[1]])


def unpack_covariances(text: str, count: int) -> FloatArray:
    """(count, 6, 6) symmetric matrices from :func:`pack_covariances`."""
    upper = unpack_floats(text, count * 21).reshape(count, 21)
    out = np.zeros((count, 6, 6))
    out[:, UPPER_6[0], UPPER_6[1]] = upper
    out[:, UPPER_6[1], UPPER_6[0]] = upper
    return out
