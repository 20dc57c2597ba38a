"""What an optimization produces: the map, how it was made, and what was left out.

result = optimize_session(session, params)        # app.domain.mapping.slam
result.world_T_tag[result.tag_index(305)]         # optimized pose of tag 305, (4, 4)
result.tag_covariance[k]                          # (6, 6) [rot rad, trans m], tag frame
result.rejections                                 # why each left-out detection was left out
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from app.domain.frames import FloatArray
from app.domain.mapping.noise import NoiseEstimate
from app.domain.mapping.params import SlamParams

IntArray = npt.NDArray[np.int64]


@dataclass(frozen=True, slots=True, kw_only=True)
class Rejection:
    """A detection left out of the graph.

    reason: a short code, one of ``reprojection``, ``view_angle``, ``distance``.
    value: the measured quantity (px, deg or m), ``limit`` the threshold it broke.
    """

    detection_index: int
    tag_id: int
    pose_index: int
    reason: str
    value: float
    limit: float

    @property
    def detail(self) -> str:
        units = {"reprojection": "px", "view_angle": "°", "distance": "m"}
        unit = units.get(self.reason, "")
        return f"{self.reason} {self.value:.3g} {unit} > {self.limit:.3g} {unit}".replace(" °", "°")


@dataclass(frozen=True, slots=True, kw_only=True)
class FactorResiduals:
    """Per-factor residuals at the solution; chi² is the whitened squared error (‖r‖²_Σ).

    keyframe_index: (K,) the phone poses in the graph (``SlamParams.keyframe_interval_s``), sorted;
        all N when every pose is.
    odometry_chi2: (K−1,) between consecutive keyframes; 0 where none joins them (the last pose of
        one session and the first of the next, in a map of several sessions).
    gravity_chi2: (K,) one attitude factor per keyframe.
    tag_chi2: (U,) one per used detection, in ``detection_index`` order (before any robust kernel).
    tag_detection_index: (U,) which detection each tag factor came from.
    tag_pose_index: (U,) the phone pose each tag factor hangs on.
    tag_translation_m: (U,) translation part of the tag factor's error, m.
    tag_rotation_rad: (U,) rotation part of the tag factor's error, rad.
    """

    keyframe_index: IntArray
    odometry_chi2: FloatArray
    gravity_chi2: FloatArray
    tag_chi2: FloatArray
    tag_detection_index: IntArray
    tag_pose_index: IntArray
    tag_translation_m: FloatArray
    tag_rotation_rad: FloatArray


@dataclass(frozen=True, slots=True, kw_only=True)
class OptimizationStats:
    """How the optimization went. Errors are gtsam's graph error (½ Σ chi², robust-weighted).

    iterations: LM's iterations with the map's parameters; start_iterations: those of the first
    stage, with the default noise variances (0 when the map's variances are the defaults).
    """

    iterations: int
    start_iterations: int = 0
    initial_error: float
    final_error: float
    build_ms: float
    optimize_ms: float
    marginals_ms: float
    num_factors: int
    num_variables: int


@dataclass(frozen=True, slots=True, kw_only=True)
class MapResult:
    """An optimized map of one session.

    pose_id: (N,) the app's pose ids.
    timestamp_s: (N,) s.
    world_T_phone: (N, 4, 4) optimized trajectory, map frame (y up), m.
    tag_ids: (K,) the tags in the map, sorted.
    world_T_tag: (K, 4, 4) optimized tag poses, m.
    world_T_tag_pre: (K, 4, 4) the "pre-optimized" baseline: each tag's first observation on raw
        odometry.
    tag_covariance: (K, 6, 6) marginal covariance of each tag pose in its own frame, ordered
        [rotation (rad), translation (m)] as gtsam's Pose3 tangent; NaN when not computed.
    tag_detection_count: (K,) detections of each tag used in the graph.
    poi_names: (P,) names of the points of interest.
    world_T_poi: (P, 4, 4) points of interest on the optimized trajectory.
    noise: the walk's noise as its own residuals support it (``params.estimate_noise``; None
        when the variances were used as given, and for a map of several walks, whose
        ``JointMap.parts`` carry one each).
    """

    map_id: str
    params: SlamParams
    pose_id: IntArray
    timestamp_s: FloatArray
    world_T_phone: FloatArray
    tag_ids: IntArray
    world_T_tag: FloatArray
    world_T_tag_pre: FloatArray
    tag_covariance: FloatArray
    tag_detection_count: IntArray
    detections_used: int
    rejections: tuple[Rejection, ...]
    residuals: FactorResiduals
    stats: OptimizationStats
    poi_names: tuple[str, ...] = ()
    world_T_poi: FloatArray = field(default_factory=lambda: np.empty((0, 4, 4)))
    warnings: tuple[str, ...] = field(default=())
    noise: NoiseEstimate | None = None

    def tag_index(self, tag_id: int) -> int:
        """Row of ``tag_id`` in the tag arrays; KeyError if the tag is not in the map."""
        rows = np.flatnonzero(self.tag_ids == tag_id)
        if rows.size == 0:
            raise KeyError(f"tag {tag_id} is not in map {self.map_id!r}")
        return int(rows[0])

    def tag_poses(self) -> dict[int, FloatArray]:
        """Optimized ``world_T_tag`` by tag id."""
        return {int(t): self.world_T_tag[k] for k, t in enumerate(self.tag_ids)}

    def tag_poses_pre(self) -> dict[int, FloatArray]:
        """Pre-optimized (first observation) ``world_T_tag`` by tag id."""
        return {int(t): self.world_T_tag_pre[k] for k, t in enumerate(self.tag_ids)}

    def rejection_counts(self) -> Mapping[str, int]:
        counts: dict[str, int] = {}
        for rejection in self.rejections:
            counts[rejection.reason] = counts.get(rejection.reason, 0) + 1
        return counts
