"""The report: each walk's share of the joint map, and the map's warnings, in sentences.

:func:`session_parts` gives each walk's :class:`SessionPart` (its rows, tags, noise,
disagreement factor and why it weighs what it does); :func:`joint_warnings` names every walk
rescaled, down-weighted or with tags set apart.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np

from app.domain.frames import FloatArray
from app.domain.mapping.joint.model import SessionPart, WalkFit
from app.domain.mapping.joint.plan import JointInputs, JointPlan
from app.domain.mapping.joint.stairs import StairLink, stair_link_trust, tag_levels
from app.domain.mapping.joint.weights import MAX_DISAGREEMENT_FACTOR, Weighing
from app.domain.mapping.map_result import MapResult
from app.domain.mapping.params import SlamParams
from app.domain.mapping.slam import GraphInputs, Solution, map_result


def joint_warnings(
    joint: JointInputs,
    splits: frozenset[tuple[int, int]],
    reasons: Mapping[tuple[int, int], float],
    disagreement: FloatArray,
    weighing: Weighing,
    scale_drops: Mapping[int, float],
) -> list[str]:
    plan = joint.plan
    warnings = []
    for s, dataset in enumerate(plan.datasets):
        note = _scale_note(s, plan, scale_drops)
        if plan.alignments[s].odometry_scale != 1.0:
            warnings.append(f"{dataset}: {note}")
        if plan.scales[s] != 1.0:
            warnings.append(
                f"{dataset}: camera-to-tag distances scaled by {plan.scales[s]:.3f} (what its "
                f"sightings and odometry support; the tag size the app assumed differs)"
            )
        if disagreement[s] > 1.0:
            warnings.append(f"{dataset}: {_weighting(s, disagreement, weighing)}")
        tags = sorted(t for w, t in splits if w == s)
        if tags:
            listed = ", ".join(
                f"{t} (χ² {reasons.get((s, t), math.nan):.0f} per sighting)" for t in tags
            )
            warnings.append(
                f"{dataset}: its sightings of tags {listed} disagree with the other sessions' "
                f"beyond its noise and do not move the map's (moved or re-printed tags?)"
            )
    return warnings


def _weighting(s: int, disagreement: FloatArray, weighing: Weighing) -> str:
    """Why walk ``s`` weighs what it does, in a sentence."""
    figures = (
        f"its cost grew by {weighing.excess[s]:.1f} on joining, for {weighing.gain[s]:.1f} "
        f"degrees of freedom gained"
    )
    factor = float(disagreement[s])
    if factor <= 1.0:
        return f"weighed by its own noise: {figures}, which that noise explains"
    capped = " (the cap: it barely moves the map)" if factor >= MAX_DISAGREEMENT_FACTOR else ""
    return (
        f"down-weighted: its variances ×{factor:.3g}{capped}, since {figures}, more than its own "
        f"noise explains (its disagreement with the other walks)"
    )


def _scale_note(s: int, plan: JointPlan, scale_drops: Mapping[int, float]) -> str:
    """What became of walk ``s``'s odometry scale, in a sentence ("" when none was tested)."""
    if s not in scale_drops:
        return ""
    candidate = plan.scale_candidates[s]
    drop = scale_drops[s]
    if plan.alignments[s].odometry_scale != 1.0:
        return (
            f"its odometry lengths ×{candidate:.4f} (they ran {abs(1 / candidate - 1):.1%} "
            f"{'long' if candidate < 1 else 'short'} against the other walks'; the map's cost "
            f"fell by {drop:.1f})"
        )
    return (
        f"its odometry scale against the other walks' ({candidate:.4f}) was tested and not "
        f"used: the map's cost {'fell' if drop > 0 else 'rose'} by {abs(drop):.1f}, which a "
        f"drift explains as well"
    )


def report_as_planned(
    joint: JointInputs,
    params: SlamParams,
    solution: Solution,
    weighing: Weighing,
    *,
    build_ms: float,
    optimize_ms: float,
    fits: Sequence[WalkFit | None] | None = None,
) -> tuple[MapResult, tuple[SessionPart, ...]]:
    """The map of ``joint``'s graph as planned (no tag set apart, no walk's variances raised)
    solved at ``solution``, and each walk's part: what the build with the variances as given
    serves, and what the ISAM2 engine's map is served as (``incremental.served_map``).
    ``fits``: as :func:`session_parts`'s."""
    ones = np.ones(len(joint.plan.datasets))
    result = map_result(
        joint.inputs,
        params,
        solution,
        build_ms=build_ms,
        optimize_ms=optimize_ms,
        warnings=joint_warnings(joint, frozenset(), {}, ones, weighing, {}),
    )
    parts = session_parts(joint, joint.inputs, result, frozenset(), ones, weighing, {}, fits=fits)
    return result, parts


def session_parts(
    joint: JointInputs,
    inputs: GraphInputs,
    result: MapResult,
    splits: frozenset[tuple[int, int]],
    disagreement: FloatArray,
    weighing: Weighing,
    scale_drops: Mapping[int, float],
    fits: Sequence[WalkFit | None] | None = None,
) -> tuple[SessionPart, ...]:
    """Each walk's share of the map ``result``. ``fits``: the walks' fits alone (default the
    plan's); None for a walk whose fit is not at hand (an incremental map's walks kept from the
    stored state: their part has no noise estimate and no map alone)."""
    plan = joint.plan
    ends = [*joint.starts[1:], joint.combined.num_poses]
    detection_ends = [*joint.detection_starts[1:], len(joint.combined.detections)]
    tag_chi2_by_row = dict(
        zip(
            result.residuals.tag_detection_index.tolist(),
            result.residuals.tag_chi2.tolist(),
            strict=True,
        )
    )
    kept = set(result.tag_ids.tolist())
    links = stair_link_trust(
        plan.sessions,
        [
            joint.screening.used[a:b]
            for a, b in zip(joint.detection_starts, detection_ends, strict=True)
        ],
        tag_levels(result.tag_poses()),
        joint.climbs,
        result.params,
        inputs.noise_scales[:, 1],
    )
    parts = []
    for s, dataset in enumerate(plan.datasets):
        rows = slice(joint.detection_starts[s], detection_ends[s])
        used = joint.screening.used[rows]
        session_chi2 = [
            tag_chi2_by_row[r] for r in range(rows.start, rows.stop) if r in tag_chi2_by_row
        ]
        local = tuple(sorted(t for w, t in splits if w == s))
        fit = plan.fits[s] if fits is None else fits[s]
        parts.append(
            SessionPart(
                dataset=dataset,
                alignment=plan.alignments[s],
                pose_rows=slice(joint.starts[s], ends[s]),
                detection_rows=rows,
                tag_ids=tuple(
                    sorted(
                        {int(t) for t in plan.sessions[s].detections.tag_id[used]} - set(local)
                        & kept
                    )
                ),
                tag_depth_scale=plan.scales[s],
                odometry_variance_scale=float(inputs.noise_scales[s, 0]),
                local_tags=local,
                detections_used=int(used.sum()),
                detections_rejected=int((~used).sum()),
                tag_chi2_mean=float(np.mean(session_chi2)) if session_chi2 else math.nan,
                noise=None if fit is None else fit.noise,
                noise_scales=inputs.noise_scales[s].copy(),
                disagreement_factor=float(disagreement[s]),
                cost_alone=float(joint.cost_alone[s]),
                cost_joint=float(weighing.cost_joint[s]),
                redundancy_gain=float(weighing.gain[s]),
                weighting="; ".join(
                    note
                    for note in (
                        _weighting(s, disagreement, weighing),
                        _scale_note(s, plan, scale_drops),
                        _stairs_note(links[s], result.params.stairs_yaw_var_rad2_per_m > 0),
                    )
                    if note
                ),
                stair_links=tuple(links[s]),
                alone=None if fit is None else fit.alone,
                fit=fit,
            )
        )
    return tuple(parts)


def _stairs_note(links: list[StairLink], stairs_on: bool) -> str:
    """How much a walk's links between levels decide where the levels sit, in a sentence: for
    each two levels that other walks join too ("" if none)."""
    sentences = []
    for pair in sorted({link.levels for link in links}):
        mine = [link for link in links if link.levels == pair]
        if sum(link.share_by_time for link in mine) > 1.0 - 1e-9:
            continue  # no other walk joins these two levels: nothing to weigh it against
        climbed_m = sum(link.climbed_m for link in mine)
        sigmas = ", ".join(f"{math.degrees(link.sigma_yaw_rad):.1f}°" for link in mine)
        share = sum(link.share for link in mine)
        if stairs_on:
            how = f"heading σ {sigmas} with the stairs' variance, {share:.0%} of the heading "
            how += f"between them ({sum(link.share_by_time for link in mine):.0%} by time alone)"
        else:
            how = f"heading σ {sigmas} by time alone, {share:.0%} of the heading between them"
        times = {1: "once", 2: "twice"}.get(len(mine), f"{len(mine)} times")
        sentences.append(
            f"its odometry alone joins levels {pair[0]} and {pair[1]} {times} "
            f"({climbed_m:.1f} m climbed): {how}"
        )
    return "; ".join(sentences)
