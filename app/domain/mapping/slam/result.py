"""What a solution gives (step 5 of ``slam``): the :class:`MapResult` (every pose placed, the
tags), the tag poses' marginal covariances, each factor's residual and each pose chain's cost."""

from __future__ import annotations

import time
from collections.abc import Sequence

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, X

from app.domain.frames import FloatArray
from app.domain.mapping.keyframes import interpolate_poses
from app.domain.mapping.map_result import FactorResiduals, MapResult, OptimizationStats
from app.domain.mapping.params import SlamParams
from app.domain.upload.session import first_observation_tag_poses

from .factors import Problem, build_problem
from .inputs import GraphInputs
from .optimizer import Solution


def chain_costs(inputs: GraphInputs, params: SlamParams, values: gtsam.Values) -> FloatArray:
    """(S,) each pose chain's cost at ``values`` with ``inputs.noise_scales``: its odometry
    factors' chi² plus its tag factors' robust cost (2 × gtsam's error under the Huber kernel);
    gravity left out (the odometry's own tilt)."""
    problem = build_problem(inputs, params)
    costs = np.zeros(inputs.num_chains)
    linked = np.flatnonzero(inputs.odometry_linked)
    odometry = np.array([2.0 * f.error(values) for f in problem.odometry_factors])
    np.add.at(costs, inputs.keyframe_chain[linked], odometry)
    tags = np.array([2.0 * f.error(values) for f in problem.tag_factors])
    np.add.at(costs, inputs.detection_chain, tags)
    return costs


def solution_residuals(inputs: GraphInputs, solution: Solution) -> FactorResiduals:
    """Each factor's residual at ``solution`` (as ``MapResult.residuals``)."""
    return _residuals(inputs, solution.problem, solution.values)


def map_result(
    inputs: GraphInputs,
    params: SlamParams,
    solution: Solution,
    *,
    build_ms: float,
    optimize_ms: float,
    warnings: Sequence[str] = (),
) -> MapResult:
    """The :class:`MapResult` of a solution: every pose placed, the tags, residuals, marginals."""
    session, screening, values = inputs.session, inputs.screening, solution.values
    world_T_keyframe = np.stack([values.atPose3(X(int(i))).matrix() for i in inputs.keyframes])
    world_T_phone = interpolate_poses(
        session.world_T_phone, session.timestamp_s, inputs.keyframes, world_T_keyframe
    )
    tag_ids = np.array(sorted(inputs.tag_rows), dtype=np.int64)
    world_T_tag = (
        np.stack([values.atPose3(L(int(t))).matrix() for t in tag_ids])
        if tag_ids.size
        else np.empty((0, 4, 4))
    )

    started = time.perf_counter()
    tag_covariance = _tag_marginals(solution.problem.graph, values, tag_ids, params)
    marginals_ms = (time.perf_counter() - started) * 1e3

    pre = first_observation_tag_poses(session)
    all_warnings = [*session.warnings, *screening.warnings, *warnings]
    dropped = sorted(set(pre) - set(inputs.tag_rows))
    if dropped:
        all_warnings.append(
            f"tags {dropped} are not in the map: every detection of them was rejected"
        )
    for estimate in solution.noise or ():
        if estimate.note:
            all_warnings.append(f"noise estimate: {estimate.note}")
    return MapResult(
        map_id=session.map_id,
        params=params,
        pose_id=session.pose_id,
        timestamp_s=session.timestamp_s,
        world_T_phone=world_T_phone,
        tag_ids=tag_ids,
        world_T_tag=world_T_tag,
        world_T_tag_pre=(
            np.stack([pre[int(t)] for t in tag_ids]) if tag_ids.size else np.empty((0, 4, 4))
        ),
        tag_covariance=tag_covariance,
        tag_detection_count=np.array(
            [len(inputs.tag_rows[int(t)]) for t in tag_ids], dtype=np.int64
        ),
        detections_used=int(screening.used.sum()),
        rejections=screening.rejections,
        residuals=_residuals(inputs, solution.problem, values),
        stats=OptimizationStats(
            iterations=solution.iterations,
            start_iterations=solution.start_iterations,
            initial_error=solution.initial_error,
            final_error=solution.final_error,
            build_ms=build_ms,
            optimize_ms=optimize_ms,
            marginals_ms=marginals_ms,
            num_factors=int(solution.problem.graph.size()),
            num_variables=int(values.size()),
        ),
        poi_names=tuple(poi.name for poi in session.pois),
        world_T_poi=(
            np.stack([world_T_phone[poi.pose_index] @ poi.phone_T_poi for poi in session.pois])
            if session.pois
            else np.empty((0, 4, 4))
        ),
        warnings=tuple(all_warnings),
        noise=(
            solution.noise[0] if solution.noise is not None and len(solution.noise) == 1 else None
        ),
    )


def _tag_marginals(
    graph: gtsam.NonlinearFactorGraph,
    values: gtsam.Values,
    tag_ids: np.ndarray,
    params: SlamParams,
) -> FloatArray:
    """Marginal covariances of the tag poses, (K, 6, 6), from ``gtsam.Marginals``.

    Cheap at real-session and 10k-pose sizes (≈0.1 s at 10k); at 100k poses with hundreds of tags
    it takes tens of seconds (see the benchmark), so ``compute_marginals=False`` skips it.
    """
    covariance = np.full((tag_ids.size, 6, 6), np.nan)
    if not params.compute_marginals or tag_ids.size == 0:
        return covariance
    try:
        marginals = gtsam.Marginals(graph, values)
        for k, tag_id in enumerate(tag_ids):
            covariance[k] = marginals.marginalCovariance(L(int(tag_id)))
    except RuntimeError:  # an indeterminate system: leave NaN rather than fail the map
        return np.full((tag_ids.size, 6, 6), np.nan)
    return covariance


def _residuals(inputs: GraphInputs, problem: Problem, values: gtsam.Values) -> FactorResiduals:
    # (K−1,) one per pair of consecutive keyframes; 0 where no odometry joins them (two chains)
    odometry_chi2 = np.zeros(inputs.odometry_linked.shape[0])
    odometry_chi2[inputs.odometry_linked] = [
        2.0 * factor.error(values) for factor in problem.odometry_factors
    ]
    gravity_chi2 = np.array([2.0 * factor.error(values) for factor in problem.gravity_factors])
    tag_errors = (
        np.stack([factor.unwhitenedError(values) for factor in problem.tag_factors])
        if problem.tag_factors
        else np.empty((0, 6))
    )
    tag_chi2 = np.array(
        [
            float(e @ np.linalg.solve(cov, e))
            for e, cov in zip(tag_errors, problem.tag_covariances, strict=True)
        ]
    )
    return FactorResiduals(
        keyframe_index=inputs.keyframes.copy(),
        odometry_chi2=odometry_chi2.reshape(-1),
        gravity_chi2=gravity_chi2.reshape(-1),
        tag_chi2=tag_chi2.reshape(-1),
        tag_detection_index=np.array(inputs.tag_detection_rows, dtype=np.int64),
        tag_pose_index=np.array(inputs.tag_pose_indices, dtype=np.int64),
        tag_translation_m=np.linalg.norm(tag_errors[:, 3:], axis=1),
        tag_rotation_rad=np.linalg.norm(tag_errors[:, :3], axis=1),
    )
