"""Live localization against a map with its tags held fixed (§6, the paper's formulation).

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

The package: ``params`` (settings and errors), ``batch`` (the phone's update document),
``state`` (the smoother's state and its JSON), ``smoother`` (the update), ``result``,
``replay`` (a recorded session replayed as updates: tests and benchmarks), ``linalg``.
"""

from __future__ import annotations

from app.domain.localize.batch import (
    MAX_UPDATE_DETECTIONS,
    MAX_UPDATE_POSES,
    UpdateBatch,
    parse_update,
    validate_update,
)
from app.domain.localize.params import (
    LocalizationUpdateError,
    LocalizerParams,
    LocalizerStateError,
)
from app.domain.localize.replay import (
    ReplayStep,
    TagPrediction,
    median_and_p90,
    prediction_errors_m,
    replay_session,
    session_update_documents,
)
from app.domain.localize.result import LocalizationRejection, LocalizationResult
from app.domain.localize.smoother import update
from app.domain.localize.state import (
    LocalizerState,
)

__all__ = [
    "MAX_UPDATE_DETECTIONS",
    "MAX_UPDATE_POSES",
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
