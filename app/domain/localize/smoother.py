"""The update: a fixed-lag smoother over keyframes with the map's tags held fixed."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from typing import Any

import gtsam
import numpy as np
from gtsam.symbol_shorthand import X

from app.domain.frames import FloatArray, se3_inverse
from app.domain.localize.batch import UpdateBatch, validate_update
from app.domain.localize.linalg import adjoint, adjoints, symmetric, yaw_only
from app.domain.localize.params import FALLBACK_PRIOR_SIGMAS, LocalizerParams
from app.domain.localize.result import LocalizationRejection, LocalizationResult
from app.domain.localize.state import Keyframe, LocalizerState, WindowDetection
from app.domain.mapping.params import SlamParams
from app.domain.mapping.screening import screen_detections
from app.domain.mapping.slam import (
    MIN_ODOMETRY_DT_S,
    WORLD_UP,
    pose_sigmas,
    tag_covariance_in_tag_frame,
    to_pose3,
)
from app.domain.upload.session import (
    IntArray,
)

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
            keyframes[-1], drift_to_next=symmetric(keyframes[-1].drift_to_next + drift)
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
        covariance = symmetric(
            tag_covariance_in_tag_frame(batch.detections.camera_T_tag[row], params.slam)
        )
        if map_T_session is None:  # the first usable detection: localize from it
            map_T_session = yaw_only(map_tags[tag_id] @ se3_inverse(session_T_tag))
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
            last_covariance = symmetric(
                adjoint(keyframes[-1].session_T_phone)
                @ phone_covariance
                @ adjoint(keyframes[-1].session_T_phone).T
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
        step_adjoints = adjoints(self.session_T_phone[i + 1 : j + 1])
        drift = np.einsum("n,nij,jk,nlk->il", dt_s, step_adjoints, self.rate, step_adjoints)
        return symmetric(np.asarray(drift, dtype=np.float64))


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
            before, drift_to_next=symmetric(before.drift_to_next - drift)
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
                ad_next = adjoint(se3_inverse(following.session_T_phone))
                graph.add(
                    gtsam.BetweenFactorPose3(
                        X(i),
                        X(i + 1),
                        to_pose3(se3_inverse(keyframe.session_T_phone) @ following.session_T_phone),
                        gtsam.noiseModel.Gaussian.Covariance(
                            symmetric(ad_next @ keyframe.drift_to_next @ ad_next.T)
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
        ad = adjoint(detection.keyframe_T_tag)
        covariance = ad @ (detection.covariance + self.map_tag_covariance) @ ad.T
        noise: gtsam.noiseModel.Base = gtsam.noiseModel.Gaussian.Covariance(symmetric(covariance))
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
        return symmetric(np.asarray(covariance, dtype=np.float64))

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
        return solved.atPose3(X(count)).matrix(), symmetric(covariance)


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
        ad = adjoint(se3_inverse(session_T_phone))
        phone_covariance = ad @ covariance @ ad.T
        map_R_phone = map_T_phone[:3, :3]
        position_covariance_m2 = symmetric(map_R_phone @ phone_covariance[3:, 3:] @ map_R_phone.T)
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
