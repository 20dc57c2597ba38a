"""The joint solve: the steps in order (the package docstring), one graph solved until no tag is
set apart and no walk's weight changes.

:func:`optimize_sessions` plans the walks (steps 1 and 2), tests their odometry scales (step 3),
then solves the one graph (step 4) from the walks' own optima placed (or from the last version's
optimum), splitting off a tag a walk disagrees on (step 5) and down-weighting a walk its noise
does not explain (step 6), to convergence in metres and radians, at most ``MAX_JOINT_ROUNDS``
times.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Mapping, Sequence

import numpy as np

from app.domain.frames import FloatArray
from app.domain.mapping.joint.alignment import MIN_SHARED_TAGS
from app.domain.mapping.joint.model import JointMap, SessionPart, WalkFit
from app.domain.mapping.joint.plan import (
    JointInputs,
    JointPlan,
    ProgressCallback,
    joint_inputs,
    plan_sessions,
)
from app.domain.mapping.joint.report import joint_warnings, report_as_planned, session_parts
from app.domain.mapping.joint.scale import tested_scales
from app.domain.mapping.joint.weights import Weighing, factors_changed, weigh_walks, worst_split
from app.domain.mapping.params import SlamParams
from app.domain.mapping.slam import (
    GraphInputs,
    Solution,
    local_landmark_key,
    map_result,
    refine,
    solve,
    solved_poses,
    values_from,
)
from app.domain.upload.session import Session

#: Most times the joint map is solved (each after a change of weights or a split tag).
MAX_JOINT_ROUNDS = 12


def optimize_sessions(
    sessions: Sequence[Session],
    params: SlamParams | None = None,
    *,
    names: Sequence[str] | None = None,
    scale_depths: bool = True,
    depth_scales: Mapping[str, float] | None = None,
    variance_scales: Mapping[str, tuple[float, float]] | None = None,
    reweight: bool = True,
    min_shared_tags: int = MIN_SHARED_TAGS,
    initial: JointMap | None = None,
    fits: Sequence[WalkFit] = (),
    on_progress: ProgressCallback | None = None,
) -> JointMap:
    """Optimize ``sessions`` into one map (see the package docstring). One session gives the map
    :func:`app.domain.mapping.slam.optimize_session` gives (with its depth scale applied).

    ``reweight``: down-weight a walk whose disagreement its own noise does not explain (step 6;
    off when ``variance_scales`` gives factors on top of each walk's noise). ``initial``: a
    previous version's map of some of these walks (a warm start): the walks it holds are not
    optimized alone again, and LM starts from its optimum; the result is the map a cold build
    makes, to within the convergence tolerance. ``fits``: walks already optimized alone
    (:func:`fit_walk`, e.g. ``part.fit`` of another map), reused when their parameters are
    these. ``on_progress(step, fraction)`` as it goes."""
    params = params or SlamParams()
    started = time.perf_counter()
    plan = plan_sessions(
        sessions,
        params,
        names=names,
        scale_depths=scale_depths,
        depth_scales=depth_scales,
        min_shared_tags=min_shared_tags,
        initial=initial,
        fits=fits,
        on_progress=on_progress,
    )
    if len(plan.datasets) == 1:
        return _single_walk_map(plan, time.perf_counter() - started)
    if not params.estimate_noise:
        return _as_given_map(plan, params, variance_scales, initial, started)
    fixed = dataclasses.replace(params, estimate_noise=False)
    solved = time.perf_counter()
    tests = tested_scales(plan, fixed, variance_scales, initial)
    plan, scale_drops = tests.plan, tests.drops
    joint = tests.joint or joint_inputs(plan, params, variance_scales, initial)
    if tests.solved is not None:
        joint.start_T_keyframe, joint.start_T_tag = tests.solved
    scaled = time.perf_counter()
    disagreement = joint.start_disagreement.copy()
    splits: frozenset[tuple[int, int]] = frozenset()
    inputs = joint.inputs  # no split yet: the graph as prepared, each walk × its factor
    inputs.noise_scales = joint.base_scales * disagreement[:, None]
    start_T_keyframe, start_T_tag = joint.start_T_keyframe, dict(joint.start_T_tag)
    start_T_local: dict[tuple[int, int], FloatArray] = {}
    reasons: dict[tuple[int, int], float] = {}
    rounds = 0
    settled: Weighing | None = None  # the last round's weighing, when it changed nothing
    while True:
        rounds += 1
        start = values_from(
            inputs,
            start_T_keyframe,
            start_T_tag,
            _local_starts(joint, splits, start_T_local, start_T_tag),
        )
        solution = refine(inputs, fixed, start)
        start_T_keyframe, start_T_tag, start_T_local = _solved_poses(
            joint, inputs, splits, solution
        )
        if on_progress is not None:
            on_progress("joint", min(1.0, rounds / 4))
        if rounds >= MAX_JOINT_ROUNDS:
            break
        # a tag one walk disagrees on is an outlier, not that walk's noise: split it off first
        split = worst_split(joint, inputs, solution, splits)
        if split is not None:
            reasons[split[0]] = split[1]
            splits = splits | {split[0]}
            inputs = joint.graph_inputs(fixed, splits, disagreement)
            continue
        if reweight and not variance_scales:
            weighing = weigh_walks(joint, inputs, fixed, solution, disagreement, splits)
            if factors_changed(weighing.factors, disagreement):
                disagreement = weighing.factors
                inputs.noise_scales = joint.base_scales * disagreement[:, None]
                continue
            settled = weighing
        break
    optimized = time.perf_counter()
    if settled is not None:
        weighing = settled
    else:
        weighing = weigh_walks(joint, inputs, fixed, solution, disagreement, splits)
    result = map_result(
        inputs,
        params,
        solution,
        build_ms=plan.timings_ms.get("walks_alone", 0.0) + plan.timings_ms.get("placing", 0.0),
        optimize_ms=(optimized - solved) * 1e3,
        warnings=joint_warnings(joint, splits, reasons, disagreement, weighing, scale_drops),
    )
    parts = session_parts(joint, inputs, result, splits, disagreement, weighing, scale_drops)
    done = time.perf_counter()
    timings = {
        **plan.timings_ms,
        "scale_tests": (scaled - solved - tests.first_solve_s) * 1e3,
        "joint_optimize": (optimized - scaled + tests.first_solve_s) * 1e3,
        "marginals": result.stats.marginals_ms,
        # the last weighing, residuals and each walk's statistics (its report)
        "report": (done - optimized) * 1e3 - result.stats.marginals_ms,
        "total": (done - started) * 1e3,
    }
    return JointMap(
        map=result,
        parts=parts,
        combined=joint.combined,
        sessions=plan.sessions,
        detection_mask=joint.screening.used,
        rounds=rounds,
        timings_ms=timings,
        pair_alignments=plan.pair_alignments,
    )


def _as_given_map(
    plan: JointPlan,
    params: SlamParams,
    variance_scales: Mapping[str, tuple[float, float]] | None,
    initial: JointMap | None,
    started: float,
) -> JointMap:
    """The joint map with the variances as given for every walk (``estimate_noise`` off, as a
    sweep's trial and ``apply`` use them): no noise estimate, no odometry rescaling, no tag set
    apart, no walk down-weighted, since each of those weighs a walk's disagreement against its
    noise, and these variances are not its noise. The graph is solved as a single walk's with
    these variances is (``slam.solve``: from the default variances' optimum), which is what
    ``tuning.TuningTarget.prepare_joint``'s trials do."""
    joint = joint_inputs(plan, params, variance_scales, initial)
    solved = time.perf_counter()
    solution = solve(
        joint.inputs,
        params,
        start=values_from(joint.inputs, joint.start_T_keyframe, joint.start_T_tag),
    )
    optimized = time.perf_counter()
    ones = np.ones(len(plan.datasets))
    weighing = weigh_walks(joint, joint.inputs, params, solution, ones, frozenset())
    weighing = dataclasses.replace(weighing, factors=ones, significant=np.zeros_like(ones, bool))
    result, parts = report_as_planned(
        joint,
        params,
        solution,
        weighing,
        build_ms=plan.timings_ms.get("walks_alone", 0.0) + plan.timings_ms.get("placing", 0.0),
        optimize_ms=(optimized - solved) * 1e3,
    )
    parts = tuple(
        dataclasses.replace(part, weighting="the variances as given (no noise estimate)")
        for part in parts
    )
    return JointMap(
        map=result,
        parts=parts,
        combined=joint.combined,
        sessions=plan.sessions,
        detection_mask=joint.screening.used,
        rounds=1,
        timings_ms={
            **plan.timings_ms,
            "joint_optimize": (optimized - solved) * 1e3,
            "marginals": result.stats.marginals_ms,
            "total": (time.perf_counter() - started) * 1e3,
        },
        pair_alignments=plan.pair_alignments,
    )


def _single_walk_map(plan: JointPlan, elapsed_s: float) -> JointMap:
    """A map of one walk: its own map (what ``optimize_session`` makes)."""
    fit, session, screening = plan.fits[0], plan.sessions[0], plan.screenings[0]
    result = fit.alone
    if plan.scales[0] != 1.0:
        result = dataclasses.replace(
            result,
            warnings=(
                *result.warnings,
                f"{plan.datasets[0]}: camera-to-tag distances scaled by {plan.scales[0]:.3f} "
                f"(what its sightings and odometry support; the tag size the app assumed differs)",
            ),
        )
    tag_chi2 = result.residuals.tag_chi2
    part = SessionPart(
        dataset=plan.datasets[0],
        alignment=plan.alignments[0],
        pose_rows=slice(0, session.num_poses),
        detection_rows=slice(0, len(session.detections)),
        tag_ids=tuple(int(t) for t in result.tag_ids),
        tag_depth_scale=plan.scales[0],
        odometry_variance_scale=float(fit.noise_scales[0]),
        local_tags=(),
        detections_used=int(screening.used.sum()),
        detections_rejected=int((~screening.used).sum()),
        tag_chi2_mean=float(np.mean(tag_chi2)) if tag_chi2.size else math.nan,
        noise=fit.noise,
        noise_scales=fit.noise_scales.copy(),
        cost_alone=fit.cost,
        cost_joint=fit.cost,
        alone=fit.alone,
        fit=fit,
    )
    return JointMap(
        map=result,
        parts=(part,),
        combined=session,
        sessions=plan.sessions,
        detection_mask=screening.used,
        rounds=0,
        timings_ms={**plan.timings_ms, "total": elapsed_s * 1e3},
    )


def _local_starts(
    joint: JointInputs,
    splits: frozenset[tuple[int, int]],
    start_T_local: Mapping[tuple[int, int], FloatArray],
    start_T_tag: Mapping[int, FloatArray],
) -> dict[int, FloatArray]:
    """Start poses of the split landmarks by graph key: where they were solved last, or (new
    ones) where the map's tag was."""
    out = {}
    for landmark, (s, t) in enumerate(_ordered_splits(joint, splits)):
        pose = start_T_local.get((s, t), start_T_tag.get(t))
        if pose is not None:
            out[local_landmark_key(landmark)] = pose
    return out


def _ordered_splits(
    joint: JointInputs, splits: frozenset[tuple[int, int]]
) -> list[tuple[int, int]]:
    """The split (walk, tag) pairs in the order their landmarks are numbered: by walk name."""
    return sorted(splits, key=lambda st: (joint.plan.datasets[st[0]], st[1]))


def _solved_poses(
    joint: JointInputs,
    inputs: GraphInputs,
    splits: frozenset[tuple[int, int]],
    solution: Solution,
) -> tuple[FloatArray, dict[int, FloatArray], dict[tuple[int, int], FloatArray]]:
    """The solution's keyframes ((K, 4, 4)), tags by id and split landmarks by (walk, tag)."""
    world_T_keyframe, world_T_tag, world_T_local = solved_poses(inputs, solution.values)
    by_pair = {
        st: world_T_local[local_landmark_key(landmark)]
        for landmark, st in enumerate(_ordered_splits(joint, splits))
    }
    return world_T_keyframe, world_T_tag, by_pair
