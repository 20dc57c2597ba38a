"""Live localization against a map with its tags held fixed (DESIGN §6, the paper's formulation).

    state = LocalizerState.initial()
    batch = parse_update({"poses": [...], "tag_data": [...]})   # JSON from the phone
    state, result = update(state, batch, map_tags, LocalizerParams())
    result.map_T_phone, result.map_T_session, result.position_sigma_m
    stored = state.to_json()                   # kept in the database between requests
    state = LocalizerState.from_json(stored)   # in any API process, after any restart

The phone navigates with its own ARKit session frame (y up, origin and heading arbitrary) and sends,
in batches, its odometry ``session_T_phone`` and the AprilTags it detects. The map holds
``map_T_tag`` for its tags (fixed, not estimated). We estimate ``map_T_session`` and with it the
phone in the map, ``map_T_phone = map_T_session · session_T_phone``.

Method: a fixed-lag smoother over *keyframes*. A keyframe is a phone pose with tag detections
(detections less than ``keyframe_merge_s`` apart share one). Its variable is the phone pose
``X(k) = map_T_phone`` at that pose; the factors are the paper's, with the tags fixed:

- tag: a ``PriorFactorPose3`` on ``X(k)`` at ``map_T_tag · keyframe_T_tag⁻¹``, its covariance the
  detection's (``slam.tag_covariance_in_tag_frame``: camera-frame noise growing with distance²) plus
  the map's own tag uncertainty, carried from the tag frame into the phone frame by the adjoint;
  under a Huber kernel. It is ``BetweenFactorPose3(X(k), L(tag), keyframe_T_tag)`` with ``L(tag)``
  held at the map's pose, written without the constant variable;
- odometry between consecutive keyframes: ``BetweenFactorPose3`` with the composed odometry. Its
  covariance sums the per-pose random walk of ``slam.odometry_sigmas`` (variance ∝ Δt) over every
  pose in between, each step's noise moved to a common frame by the adjoint, so a heading error
  swings later positions about the place where it happened, as it does on the phone;
- gravity: an ``AttitudeFactorPose3`` per keyframe. Both the map and the session frame are
  gravity-aligned (y up), so ``map_T_session`` is a yaw and a translation; the factors hold roll and
  pitch, and a new keyframe starts from a yaw-only ``map_T_session``.

Cost per update does not grow with the session: the window holds at most ``window_keyframes``
keyframes of at most ``max_detections_per_keyframe`` detections, and when it overflows the oldest
keyframes are marginalized into a Gaussian prior on the oldest kept one. The keyframes form a chain,
so marginalizing the oldest leaves a factor on its neighbour alone: the prior is exact up to
linearization (it is the optimum and marginal covariance of the dropped part's own graph). Odometry
between keyframes is kept as one 6×6 covariance in the session frame (additive over steps, so a
late detection can split it), and only the last ``recent_poses`` poses are kept, for detections
that arrive a batch late. Between keyframes the estimate does not move: ``map_T_session`` keeps its
mean and its covariance grows with the odometry walked since the last keyframe.

Covariances are in gtsam's tangent order ``[rotation (rad), translation (m)]`` with the
perturbation on the right: ``map_T_session · Exp(ξ)``, ξ in the session frame.
"""

from __future__ import annotations

import base64
import binascii
import dataclasses
import math
import statistics
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import gtsam
import numpy as np
import numpy.typing as npt
from gtsam.symbol_shorthand import X

from app.domain.errors import InvisibleMapError, ParameterError, SessionFormatError
from app.domain.frames import FloatArray, se3_inverse, skew
from app.domain.json_values import json_type_name
from app.domain.params import SlamParams
from app.domain.screening import screen_detections
from app.domain.session import (
    IntArray,
    Session,
    TagDetections,
    _integer,
    _matrix16,
    _number,
    _require_list,
    _require_object,
    _rigid,
    detections_from_rows,
    parse_detection_rows,
)
from app.domain.slam import (
    MIN_ODOMETRY_DT_S,
    WORLD_UP,
    pose_sigmas,
    tag_covariance_in_tag_frame,
    to_pose3,
)

#: Version of :meth:`LocalizerState.to_json`'s layout; ``from_json`` refuses others.
STATE_VERSION = 1

#: σ of a marginalized prior whose covariance gtsam could not compute (an indeterminate system,
#: which the window's factors should never make): [rot rad, trans m], so wide it barely counts.
FALLBACK_PRIOR_SIGMAS = pose_sigmas(rot_rad=math.pi, trans_m=100.0)

Status = Literal["not_localized", "localized"]


# --------------------------------------------------------------------------- errors


class LocalizationUpdateError(InvisibleMapError):
    """Raised when a localization update is malformed or does not fit the session's state.

    ``field`` names where (``poses[3].timestamp``, ``tag_data[0][1].tag_id``); the state passed to
    :func:`update` is never changed (the function is pure).
    """

    def __init__(self, field: str, reason: str) -> None:
        self.field = field
        self.reason = reason
        super().__init__(f"{field}: {reason}" if field else reason)


class LocalizerStateError(InvisibleMapError):
    """Raised when a stored :class:`LocalizerState` cannot be read back (a server-side fault)."""


# --------------------------------------------------------------------------- parameters


@dataclass(frozen=True, slots=True, kw_only=True)
class LocalizerParams:
    """How the localizer weighs and windows its measurements. All keyword-only.

    slam                        the map's SLAM parameters: the detection noise model
                                (``tag_position_var_m2``, ``tag_depth_var_ratio``,
                                ``tag_orientation_var_rad2``), the odometry random-walk rates, the
                                gravity variance and the detection screening thresholds.
    map_tag_position_var_m2     variance of each map tag's position per axis, m²: the map is not
                                perfect, and a tag "fixed" at a slightly wrong place must not
                                pull harder than the map deserves.
    map_tag_orientation_var_rad2  variance of each map tag's orientation per axis, rad².
    huber_k                     Huber threshold on the whitened 6-D tag residual (σ units); 0 = off.
    window_keyframes            keyframes kept in the optimized window (≥ 2); older ones are
                                marginalized into a prior.
    max_detections_per_keyframe detections one keyframe takes before a new keyframe starts.
    keyframe_merge_s            detections on poses less than this apart share a keyframe, s.
    recent_poses                odometry poses kept for detections that arrive late (≥ 1).
    max_iterations              Levenberg–Marquardt iteration cap per update.

    Out-of-range values raise :class:`ParameterError`.
    """

    slam: SlamParams = field(default_factory=SlamParams)
    map_tag_position_var_m2: float = 0.05**2
    map_tag_orientation_var_rad2: float = 0.05**2
    huber_k: float = 1.345
    window_keyframes: int = 8
    max_detections_per_keyframe: int = 4
    keyframe_merge_s: float = 1.0
    recent_poses: int = 20
    max_iterations: int = 20

    def __post_init__(self) -> None:
        for name in ("map_tag_position_var_m2", "map_tag_orientation_var_rad2", "keyframe_merge_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ParameterError(f"{name} must be finite and ≥ 0")
        if not (math.isfinite(self.huber_k) and self.huber_k >= 0):
            raise ParameterError("huber_k must be finite and ≥ 0 (0 = off)")
        if self.window_keyframes < 2:
            raise ParameterError("window_keyframes must be ≥ 2")
        if self.max_detections_per_keyframe < 1:
            raise ParameterError("max_detections_per_keyframe must be ≥ 1")
        if self.recent_poses < 1:
            raise ParameterError("recent_poses must be ≥ 1")
        if self.max_iterations < 1:
            raise ParameterError("max_iterations must be ≥ 1")


# --------------------------------------------------------------------------- the update batch


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
    list of detections in the upload's format (DESIGN §2), or a bare detection. Either list may be
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
    _require_list(poses, "poses")
    n = len(poses)
    pose_id = np.empty(n, dtype=np.int64)
    timestamp_s = np.empty(n, dtype=np.float64)
    session_T_phone = np.empty((n, 4, 4), dtype=np.float64)
    for i, entry in enumerate(poses):
        where = f"poses[{i}]"
        _require_object(entry, where)
        pose_id[i] = _integer(entry, "id", where)
        timestamp_s[i] = _number(entry, "timestamp", where)
        session_T_phone[i] = _rigid(
            _matrix16(entry, "pose", where).reshape(4, 4).T, f"{where}.pose"
        )
        if i > 0 and pose_id[i] <= pose_id[i - 1]:
            raise LocalizationUpdateError(
                f"{where}.id", f"ids must increase: {pose_id[i]} follows {pose_id[i - 1]}"
            )
        if i > 0 and timestamp_s[i] < timestamp_s[i - 1]:
            raise LocalizationUpdateError(
                f"{where}.timestamp",
                f"time goes backwards: {timestamp_s[i]} s after {timestamp_s[i - 1]} s",
            )

    rows = parse_detection_rows(document.get("tag_data", []))
    return UpdateBatch(
        pose_id=pose_id,
        timestamp_s=timestamp_s,
        session_T_phone=session_T_phone,
        detection_pose_id=np.array([r["pose_id"] for r in rows], dtype=np.int64),
        detection_field=tuple(r["where"] for r in rows),
        detections=detections_from_rows(rows, [r["pose_id"] for r in rows]),
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
        return _symmetric(self.last_keyframe_covariance + self.keyframes[-1].drift_to_next)

    def window_tag_ids(self) -> tuple[int, ...]:
        """Distinct tag ids with detections in the window, sorted."""
        return tuple(sorted({d.tag_id for k in self.keyframes for d in k.detections}))

    def to_json(self) -> dict[str, Any]:
        """A JSON-ready dict; ``from_json(to_json())`` gives back an identical state.

        Ids, timestamps and counts are plain JSON; the bulky float arrays are packed
        (:func:`_pack_poses`: the top 3×4 of each pose; :func:`_pack_covariances`: the upper
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
                "session_T_phone": _pack_poses([k.session_T_phone for k in self.keyframes]),
                "map_T_phone": _pack_poses([k.map_T_phone for k in self.keyframes]),
                "drift_to_next": _pack_covariances([k.drift_to_next for k in self.keyframes]),
            },
            "detections": {
                "tag_id": [d.tag_id for d in detections],
                "pose_id": [d.pose_id for d in detections],
                "keyframe_T_tag": _pack_poses([d.keyframe_T_tag for d in detections]),
                "covariance": _pack_covariances([d.covariance for d in detections]),
            },
            "prior": (
                None
                if self.prior_map_T_phone is None or self.prior_covariance is None
                else {
                    "map_T_phone": _pack_poses([self.prior_map_T_phone]),
                    "covariance": _pack_covariances([self.prior_covariance]),
                }
            ),
            "last_keyframe_covariance": (
                None
                if self.last_keyframe_covariance is None
                else _pack_covariances([self.last_keyframe_covariance])
            ),
            "recent_poses": {
                "pose_id": [int(v) for v in self.recent_pose_id],
                "timestamp_s": [float(v) for v in self.recent_timestamp_s],
                "session_T_phone": _pack_poses(list(self.recent_session_T_phone)),
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
        keyframe_T_tag = _unpack_poses(table["keyframe_T_tag"], m)
        detection_covariance = _unpack_covariances(table["covariance"], m)
        detections = [
            WindowDetection(
                tag_id=int(table["tag_id"][row]),
                pose_id=int(table["pose_id"][row]),
                keyframe_T_tag=keyframe_T_tag[row],
                covariance=detection_covariance[row],
            )
            for row in range(m)
        ]
        session_T_phone = _unpack_poses(stored["session_T_phone"], k)
        map_T_phone = _unpack_poses(stored["map_T_phone"], k)
        drift = _unpack_covariances(stored["drift_to_next"], k)
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
            prior_map_T_phone=None if prior is None else _unpack_poses(prior["map_T_phone"], 1)[0],
            prior_covariance=(
                None if prior is None else _unpack_covariances(prior["covariance"], 1)[0]
            ),
            last_keyframe_covariance=(
                None if last_covariance is None else _unpack_covariances(last_covariance, 1)[0]
            ),
            recent_pose_id=np.array([int(v) for v in recent["pose_id"]], dtype=np.int64),
            recent_timestamp_s=np.array(
                [float(v) for v in recent["timestamp_s"]], dtype=np.float64
            ).reshape(r),
            recent_session_T_phone=_unpack_poses(recent["session_T_phone"], r),
            num_updates=int(counters["updates"]),
            num_poses=int(counters["poses"]),
            num_detections=int(counters["detections"]),
            num_detections_used=int(counters["detections_used"]),
            num_keyframes_marginalized=int(counters["keyframes_marginalized"]),
        )


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
            return None if matrix is None else [[float(v) for v in row] for row in matrix]

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


# --------------------------------------------------------------------------- the update


def update(
    state: LocalizerState,
    batch: UpdateBatch,
    map_tags: Mapping[int, FloatArray],
    params: LocalizerParams | None = None,
) -> tuple[LocalizerState, LocalizationResult]:
    """Fold one batch into the navigation session: ``(new_state, result)``. Pure: ``state`` is
    never changed, and on :class:`LocalizationUpdateError` no new state exists.

    ``map_tags``: tag id → ``map_T_tag`` (4, 4), the map's tags, held fixed. Raises
    :class:`LocalizationUpdateError` (see :func:`validate_update`) before doing any work.

    Steps: 1. the new poses extend the odometry since the newest keyframe; 2. detections that pass
    the mapping screen (``screening.screen_detections``) join keyframes (the very first one sets
    ``map_T_session``, yaw only); 3. when any did, Levenberg–Marquardt on the window from the last
    solution (warm start), the newest keyframe's marginal covariance, and the marginalization of
    the keyframes beyond ``window_keyframes``. Without new detections only step 1 runs.
    """
    params = params or LocalizerParams()
    validate_update(state, batch, map_tags)

    # 1. odometry: the new poses join the recent buffer and the newest keyframe's drift
    pose_id = np.concatenate([state.recent_pose_id, batch.pose_id])
    timestamp_s = np.concatenate([state.recent_timestamp_s, batch.timestamp_s])
    session_T_phone = np.concatenate([state.recent_session_T_phone, batch.session_T_phone])
    buffer = _PoseBuffer(pose_id, timestamp_s, session_T_phone, params.slam)
    keyframes = list(state.keyframes)
    if keyframes and batch.num_poses:
        start = int(state.recent_pose_id[-1])
        drift = buffer.drift(start, int(pose_id[-1]))
        keyframes[-1] = dataclasses.replace(
            keyframes[-1], drift_to_next=_symmetric(keyframes[-1].drift_to_next + drift)
        )

    # 2. detections: screened, then merged into keyframes (new ones split the odometry chain)
    screening = screen_detections(batch.detections, params.slam)
    rejections = [
        LocalizationRejection(
            tag_id=r.tag_id, pose_id=r.pose_index, reason=r.reason, detail=r.detail
        )
        for r in screening.rejections
    ]
    order = sorted(
        np.flatnonzero(screening.used).tolist(), key=lambda row: int(batch.detection_pose_id[row])
    )
    used_tags: set[int] = set()
    used_count = 0
    map_T_session = state.map_T_session()
    for row in order:
        det_pose_id = int(batch.detection_pose_id[row])
        tag_id = int(batch.detections.tag_id[row])
        session_T_tag = buffer.pose(det_pose_id) @ batch.detections.phone_T_tag[row]
        covariance = _symmetric(
            tag_covariance_in_tag_frame(batch.detections.camera_T_tag[row], params.slam)
        )
        if map_T_session is None:  # the first usable detection: localize from it
            map_T_session = _yaw_only(map_tags[tag_id] @ se3_inverse(session_T_tag))
        inserted = _insert_detection(
            keyframes,
            buffer,
            params,
            tag_id=tag_id,
            pose_id=det_pose_id,
            session_T_tag=session_T_tag,
            covariance=covariance,
            map_T_session=map_T_session,
            may_precede_first=state.prior_map_T_phone is None,
        )
        if inserted is None:
            rejections.append(
                LocalizationRejection(
                    tag_id=tag_id,
                    pose_id=det_pose_id,
                    reason="before_window",
                    detail=f"pose {det_pose_id} precedes the window (from pose "
                    f"{keyframes[0].pose_id}), whose past is marginalized",
                )
            )
            continue
        keyframes = inserted
        used_tags.add(tag_id)
        used_count += 1

    # 3. optimize the window, marginalize what overflows, and take the newest keyframe's marginal
    prior_map_T_phone, prior_covariance = state.prior_map_T_phone, state.prior_covariance
    last_covariance = state.last_keyframe_covariance
    iterations = 0
    marginalized = 0
    if used_tags:
        window = _Window(keyframes, prior_map_T_phone, prior_covariance, map_tags, params)
        values, iterations = window.optimize()
        keyframes = [
            dataclasses.replace(k, map_T_phone=values.atPose3(X(i)).matrix())
            for i, k in enumerate(keyframes)
        ]
        newest = len(keyframes) - 1
        phone_covariance = window.marginal_covariance(values, newest)
        if phone_covariance is not None:
            last_covariance = _symmetric(
                _adjoint(keyframes[-1].session_T_phone)
                @ phone_covariance
                @ _adjoint(keyframes[-1].session_T_phone).T
            )
        marginalized = max(0, len(keyframes) - params.window_keyframes)
        if marginalized:
            prior_map_T_phone, prior_covariance = window.marginalize_oldest(values, marginalized)
            keyframes = keyframes[marginalized:]

    keep = params.recent_poses
    new_state = LocalizerState(
        keyframes=tuple(keyframes),
        prior_map_T_phone=prior_map_T_phone,
        prior_covariance=prior_covariance,
        last_keyframe_covariance=last_covariance,
        recent_pose_id=pose_id[-keep:].copy(),
        recent_timestamp_s=timestamp_s[-keep:].copy(),
        recent_session_T_phone=session_T_phone[-keep:].copy(),
        num_updates=state.num_updates + 1,
        num_poses=state.num_poses + batch.num_poses,
        num_detections=state.num_detections + len(batch.detections),
        num_detections_used=state.num_detections_used + used_count,
        num_keyframes_marginalized=state.num_keyframes_marginalized + marginalized,
    )
    return new_state, _result(new_state, iterations, used_tags, rejections, used_count)


# --------------------------------------------------------------------------- odometry


class _PoseBuffer:
    """The recent odometry poses of an update (the state's and the batch's), by pose id."""

    def __init__(
        self,
        pose_id: IntArray,
        timestamp_s: FloatArray,
        session_T_phone: FloatArray,
        slam: SlamParams,
    ) -> None:
        self.row_of = {int(p): i for i, p in enumerate(pose_id)}
        self.pose_id = pose_id
        self.timestamp_s = timestamp_s
        self.session_T_phone = session_T_phone
        #: (6, 6) odometry noise per second, phone frame, [rot rad²/s, trans m²/s].
        self.rate = np.diag(
            pose_sigmas(
                rot_rad=math.sqrt(slam.odom_angular_var_rad2_per_s),
                trans_m=math.sqrt(slam.odom_linear_var_m2_per_s),
            )
            ** 2
        )

    @property
    def last_pose_id(self) -> int:
        return int(self.pose_id[-1])

    def pose(self, pose_id: int) -> FloatArray:
        """(4, 4) ``session_T_phone`` of ``pose_id``."""
        return np.asarray(self.session_T_phone[self.row_of[pose_id]], dtype=np.float64)

    def timestamp(self, pose_id: int) -> float:
        return float(self.timestamp_s[self.row_of[pose_id]])

    def drift(self, from_pose_id: int, to_pose_id: int) -> FloatArray:
        """(6, 6) covariance of the change of ``map_T_session`` (session-frame tangent) from the
        odometry between two poses: Σ over steps of ``Δt · Ad(session_T_phone) · rate · Adᵀ``.

        A step's noise m (phone frame, variance ∝ Δt as ``slam.odometry_sigmas``) moves the session
        frame in the map by ``Exp(Ad(session_T_phone) · m)``, so a rotation error swings the
        session about the phone's position at the time.
        """
        i, j = self.row_of[from_pose_id], self.row_of[to_pose_id]
        if j <= i:
            return np.zeros((6, 6))
        dt_s = np.maximum(np.diff(self.timestamp_s[i : j + 1]), MIN_ODOMETRY_DT_S)
        adjoints = _adjoints(self.session_T_phone[i + 1 : j + 1])
        drift = np.einsum("n,nij,jk,nlk->il", dt_s, adjoints, self.rate, adjoints)
        return _symmetric(np.asarray(drift, dtype=np.float64))


def _insert_detection(
    keyframes: list[Keyframe],
    buffer: _PoseBuffer,
    params: LocalizerParams,
    *,
    tag_id: int,
    pose_id: int,
    session_T_tag: FloatArray,
    covariance: FloatArray,
    map_T_session: FloatArray,
    may_precede_first: bool,
) -> list[Keyframe] | None:
    """``keyframes`` with the detection merged into a nearby keyframe or in a new one; None when
    it would need a new keyframe before the first one and ``may_precede_first`` is False (the
    first keyframe carries the marginalized past, which a new variable before it would not
    see)."""
    keyframes = list(keyframes)
    timestamp_s = buffer.timestamp(pose_id)
    best, best_gap_s = -1, math.inf
    for i, keyframe in enumerate(keyframes):
        gap_s = abs(keyframe.timestamp_s - timestamp_s)
        has_room = len(keyframe.detections) < params.max_detections_per_keyframe
        if keyframe.pose_id == pose_id or (
            gap_s <= params.keyframe_merge_s and has_room and gap_s < best_gap_s
        ):
            best, best_gap_s = i, (-1.0 if keyframe.pose_id == pose_id else gap_s)
    if best >= 0:
        keyframe = keyframes[best]
        detection = WindowDetection(
            tag_id=tag_id,
            pose_id=pose_id,
            keyframe_T_tag=se3_inverse(keyframe.session_T_phone) @ session_T_tag,
            covariance=covariance,
        )
        keyframes[best] = dataclasses.replace(
            keyframe, detections=(*keyframe.detections, detection)
        )
        return keyframes

    # A new keyframe splits the odometry chain: the drift from it to the next keyframe (or the
    # latest pose) moves from its predecessor to it. Drift is additive in the session frame.
    position = sum(1 for k in keyframes if k.pose_id < pose_id)
    if position == 0 and keyframes and not may_precede_first:
        return None
    end_pose_id = keyframes[position].pose_id if position < len(keyframes) else buffer.last_pose_id
    drift = buffer.drift(pose_id, end_pose_id)
    if position > 0:
        before = keyframes[position - 1]
        keyframes[position - 1] = dataclasses.replace(
            before, drift_to_next=_symmetric(before.drift_to_next - drift)
        )
    session_T_phone = buffer.pose(pose_id)
    keyframes.insert(
        position,
        Keyframe(
            pose_id=pose_id,
            timestamp_s=timestamp_s,
            session_T_phone=session_T_phone,
            map_T_phone=map_T_session @ session_T_phone,
            drift_to_next=drift,
            detections=(
                WindowDetection(
                    tag_id=tag_id,
                    pose_id=pose_id,
                    keyframe_T_tag=se3_inverse(session_T_phone) @ session_T_tag,
                    covariance=covariance,
                ),
            ),
        ),
    )
    return keyframes


# --------------------------------------------------------------------------- the window graph


class _Window:
    """The factor graph of the window: variables ``X(i) = map_T_phone`` of keyframe i."""

    def __init__(
        self,
        keyframes: Sequence[Keyframe],
        prior_map_T_phone: FloatArray | None,
        prior_covariance: FloatArray | None,
        map_tags: Mapping[int, FloatArray],
        params: LocalizerParams,
    ) -> None:
        self.keyframes = keyframes
        self.prior_map_T_phone = prior_map_T_phone
        self.prior_covariance = prior_covariance
        self.map_tags = map_tags
        self.params = params
        self.gravity_noise = gtsam.noiseModel.Isotropic.Sigma(
            2, math.sqrt(params.slam.gravity_var_rad2)
        )
        self.map_tag_covariance = np.diag(
            pose_sigmas(
                rot_rad=math.sqrt(params.map_tag_orientation_var_rad2),
                trans_m=math.sqrt(params.map_tag_position_var_m2),
            )
            ** 2
        )
        self.huber = (
            gtsam.noiseModel.mEstimator.Huber.Create(params.huber_k) if params.huber_k > 0 else None
        )
        self.graph = self.factors(len(keyframes), unary_on_last=True)

    def factors(self, count: int, *, unary_on_last: bool) -> gtsam.NonlinearFactorGraph:
        """The graph over keyframes ``0..count-1``; without the last one's own (tag, gravity)
        factors when ``unary_on_last`` is False (the marginalization's boundary)."""
        graph = gtsam.NonlinearFactorGraph()
        if self.prior_map_T_phone is not None and self.prior_covariance is not None:
            graph.add(
                gtsam.PriorFactorPose3(
                    X(0),
                    to_pose3(self.prior_map_T_phone),
                    gtsam.noiseModel.Gaussian.Covariance(self.prior_covariance),
                )
            )
        map_up = gtsam.Unit3(WORLD_UP)
        for i, keyframe in enumerate(self.keyframes[:count]):
            if i + 1 < count:  # odometry to the next keyframe, noise in the next phone's frame
                following = self.keyframes[i + 1]
                ad_next = _adjoint(se3_inverse(following.session_T_phone))
                graph.add(
                    gtsam.BetweenFactorPose3(
                        X(i),
                        X(i + 1),
                        to_pose3(se3_inverse(keyframe.session_T_phone) @ following.session_T_phone),
                        gtsam.noiseModel.Gaussian.Covariance(
                            _symmetric(ad_next @ keyframe.drift_to_next @ ad_next.T)
                        ),
                    )
                )
            if i == count - 1 and not unary_on_last:
                continue
            phone_up = keyframe.session_T_phone[:3, :3].T @ WORLD_UP
            graph.add(
                gtsam.AttitudeFactorPose3(X(i), map_up, self.gravity_noise, gtsam.Unit3(phone_up))
            )
            for detection in keyframe.detections:
                graph.add(self._tag_factor(i, detection))
        return graph

    def _tag_factor(self, i: int, detection: WindowDetection) -> gtsam.NonlinearFactor:
        """``X(i)`` at ``map_T_tag · keyframe_T_tag⁻¹``; tag-frame noise (detection + map) carried
        to the phone frame by ``Ad(keyframe_T_tag)``."""
        map_T_phone = self.map_tags[detection.tag_id] @ se3_inverse(detection.keyframe_T_tag)
        ad = _adjoint(detection.keyframe_T_tag)
        covariance = ad @ (detection.covariance + self.map_tag_covariance) @ ad.T
        noise: gtsam.noiseModel.Base = gtsam.noiseModel.Gaussian.Covariance(_symmetric(covariance))
        if self.huber is not None:
            noise = gtsam.noiseModel.Robust.Create(self.huber, noise)
        return gtsam.PriorFactorPose3(X(i), to_pose3(map_T_phone), noise)

    def initial_values(self, count: int) -> gtsam.Values:
        values = gtsam.Values()
        for i, keyframe in enumerate(self.keyframes[:count]):
            values.insert(X(i), to_pose3(keyframe.map_T_phone))
        return values

    def optimize(self) -> tuple[gtsam.Values, int]:
        return _levenberg_marquardt(
            self.graph, self.initial_values(len(self.keyframes)), self.params.max_iterations
        )

    def marginal_covariance(self, values: gtsam.Values, i: int) -> FloatArray | None:
        """(6, 6) marginal covariance of ``X(i)`` in its phone-frame tangent, or None."""
        try:
            covariance = gtsam.Marginals(self.graph, values).marginalCovariance(X(i))
        except RuntimeError:  # an indeterminate system; keep the previous covariance
            return None
        return _symmetric(np.asarray(covariance, dtype=np.float64))

    def marginalize_oldest(self, values: gtsam.Values, count: int) -> tuple[FloatArray, FloatArray]:
        """The prior on keyframe ``count`` left by the ``count`` oldest keyframes: the optimum
        and marginal covariance of the graph made of their factors alone (a chain, so they touch
        the kept keyframes only through that one)."""
        graph = self.factors(count + 1, unary_on_last=False)
        start = gtsam.Values()
        for i in range(count + 1):
            start.insert(X(i), values.atPose3(X(i)))
        solved, _ = _levenberg_marquardt(graph, start, self.params.max_iterations)
        try:
            covariance = np.asarray(
                gtsam.Marginals(graph, solved).marginalCovariance(X(count)), dtype=np.float64
            )
        except RuntimeError:  # an indeterminate system: keep the mean, forget its weight
            covariance = np.diag(FALLBACK_PRIOR_SIGMAS**2)
        return solved.atPose3(X(count)).matrix(), _symmetric(covariance)


def _levenberg_marquardt(
    graph: gtsam.NonlinearFactorGraph, initial: gtsam.Values, max_iterations: int
) -> tuple[gtsam.Values, int]:
    lm_params = gtsam.LevenbergMarquardtParams()
    lm_params.setMaxIterations(max_iterations)
    lm_params.setRelativeErrorTol(1e-5)
    lm_params.setAbsoluteErrorTol(1e-9)
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, initial, lm_params)
    values = optimizer.optimize()
    return values, int(optimizer.iterations())


# --------------------------------------------------------------------------- the result


def _result(
    state: LocalizerState,
    iterations: int,
    used_tags: set[int],
    rejections: Sequence[LocalizationRejection],
    used_count: int,
) -> LocalizationResult:
    common: dict[str, Any] = {
        "pose_id": state.last_pose_id,
        "timestamp_s": state.last_timestamp_s,
        "tags_used": tuple(sorted(used_tags)),
        "window_tag_ids": state.window_tag_ids(),
        "detections_used": used_count,
        "rejections": tuple(rejections),
        "window_keyframes": len(state.keyframes),
        "iterations": iterations,
    }
    map_T_session = state.map_T_session()
    if map_T_session is None:
        return LocalizationResult(
            status="not_localized",
            map_T_phone=None,
            map_T_session=None,
            covariance=None,
            position_covariance_m2=None,
            position_sigma_m=None,
            **common,
        )
    session_T_phone = state.recent_session_T_phone[-1]
    map_T_phone = map_T_session @ session_T_phone
    covariance = state.map_T_session_covariance()
    position_covariance_m2: FloatArray | None = None
    position_sigma_m: float | None = None
    if covariance is not None:
        ad = _adjoint(se3_inverse(session_T_phone))
        phone_covariance = ad @ covariance @ ad.T
        map_R_phone = map_T_phone[:3, :3]
        position_covariance_m2 = _symmetric(map_R_phone @ phone_covariance[3:, 3:] @ map_R_phone.T)
        position_sigma_m = math.sqrt(max(0.0, float(np.trace(position_covariance_m2))))
    return LocalizationResult(
        status="localized",
        map_T_phone=map_T_phone,
        map_T_session=map_T_session,
        covariance=covariance,
        position_covariance_m2=position_covariance_m2,
        position_sigma_m=position_sigma_m,
        **common,
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


# --------------------------------------------------------------------------- small helpers


def _adjoints(A_T_B: FloatArray) -> FloatArray:
    """(..., 6, 6) adjoint maps of (..., 4, 4) poses in gtsam's ``[rot, trans]`` order:
    ``A_T_B · Exp(ξ_B) · A_T_B⁻¹ = Exp(Ad · ξ_B)``."""
    R = A_T_B[..., :3, :3]
    out = np.zeros((*A_T_B.shape[:-2], 6, 6))
    out[..., :3, :3] = R
    out[..., 3:, 3:] = R
    out[..., 3:, :3] = skew(A_T_B[..., :3, 3]) @ R
    return out


def _adjoint(A_T_B: FloatArray) -> FloatArray:
    return _adjoints(A_T_B)


def _symmetric(M: FloatArray) -> FloatArray:
    return np.asarray(0.5 * (M + M.T), dtype=np.float64)


def _yaw_only(A_T_B: FloatArray) -> FloatArray:
    """``A_T_B`` with its rotation replaced by the nearest rotation about +y (gravity)."""
    R = A_T_B[:3, :3]
    yaw_rad = math.atan2(R[0, 2] - R[2, 0], R[0, 0] + R[2, 2])
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    out = A_T_B.copy()
    out[:3, :3] = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    return out


#: Upper-triangle indices of a 6×6 covariance (21 entries), row by row.
_UPPER_6 = np.triu_indices(6)


def _pack(values: FloatArray) -> str:
    return base64.b64encode(np.ascontiguousarray(values, dtype="<f8").tobytes()).decode("ascii")


def _unpack(text: str, count: int) -> FloatArray:
    values = np.frombuffer(base64.b64decode(text, validate=True), dtype="<f8")
    if values.size != count:
        raise ValueError(f"expected {count} packed numbers, got {values.size}")
    if not np.all(np.isfinite(values)):
        raise ValueError("packed numbers include a non-finite one")
    return values.astype(np.float64)


def _pack_poses(poses: Sequence[FloatArray]) -> str:
    """Poses (4, 4) as their top 3×4 rows (the last row is always [0, 0, 0, 1]), base64."""
    stacked = np.stack(poses) if len(poses) else np.empty((0, 4, 4))
    return _pack(stacked[:, :3, :])


def _unpack_poses(text: str, count: int) -> FloatArray:
    """(count, 4, 4) poses from :func:`_pack_poses`."""
    poses = np.zeros((count, 4, 4))
    poses[:, :3, :] = _unpack(text, count * 12).reshape(count, 3, 4)
    poses[:, 3, 3] = 1.0
    return poses


def _pack_covariances(covariances: Sequence[FloatArray]) -> str:
    """Symmetric (6, 6) matrices as their 21 upper-triangle entries, base64."""
    stacked = np.stack(covariances) if len(covariances) else np.empty((0, 6, 6))
    return _pack(stacked[:, _UPPER_6[0], _UPPER_6[1]])


def _unpack_covariances(text: str, count: int) -> FloatArray:
    """(count, 6, 6) symmetric matrices from :func:`_pack_covariances`."""
    upper = _unpack(text, count * 21).reshape(count, 21)
    out = np.zeros((count, 6, 6))
    out[:, _UPPER_6[0], _UPPER_6[1]] = upper
    out[:, _UPPER_6[1], _UPPER_6[0]] = upper
    return out


__all__ = [
    "LocalizationRejection",
    "LocalizationResult",
    "LocalizationUpdateError",
    "LocalizerParams",
    "LocalizerState",
    "LocalizerStateError",
    "ReplayStep",
    "TagPrediction",
    "UpdateBatch",
    "median_and_p90",
    "parse_update",
    "prediction_errors_m",
    "replay_session",
    "session_update_documents",
    "update",
    "validate_update",
]
