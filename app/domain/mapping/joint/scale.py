"""Step 3, odometry scale: each walk's candidate scale kept only if the joint map's cost says so.

ARKit's scale drifts by a percent or two, which the odometry's random-walk noise does not
describe. A walk whose odometry is off significantly against the others'
(``placing.odometry_scale_candidates``) is rescaled only if that lowers the joint map's cost
beyond χ²₁(0.999) (drift can look like scale on the shared tags; a real scale error lowers the
cost of the whole graph), in maps of ≥ 3 walks, for walks mostly inside the overlap
(``MIN_SCALE_COVERAGE``): :func:`tested_scales`.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from dataclasses import dataclass

from app.domain.frames import FloatArray
from app.domain.mapping.joint.model import JointMap
from app.domain.mapping.joint.plan import JointInputs, JointPlan, joint_inputs
from app.domain.mapping.noise import chi2_quantile
from app.domain.mapping.params import SlamParams
from app.domain.mapping.slam import refine, solved_poses, values_from

#: … and when it lowers the joint map's cost by more than this quantile of χ²(1) allows …
SCALE_TEST_QUANTILE = 0.999


#: … for a walk at least this fraction of whose tags other walks share (its scale is measured
#: where they overlap; chosen on straight_209_occam, whose two floors share 6 of 19 tags: its
#: floor 2 measures 0.7% short, and scaling all of it took its floor-1 tags 35% further from
#: the ground truth; docs/multi-session.md).
MIN_SCALE_COVERAGE = 0.5


#: A joint solution's keyframe poses ((K, 4, 4)) and tags by id: where the next solve starts.
Solved = tuple[FloatArray, dict[int, FloatArray]]


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class ScaleTests:
    """What :func:`tested_scales` decided: the plan with the kept scales, each tested walk's
    drop of the joint cost, and, when the plan is the one tested unscaled, its joint inputs, its
    optimum and the time that first solve took (the build's own first solve, s)."""

    plan: JointPlan
    drops: dict[int, float]
    solved: Solved | None = None
    joint: JointInputs | None = None
    first_solve_s: float = 0.0


def tested_scales(
    plan: JointPlan,
    params: SlamParams,
    variance_scales: Mapping[str, tuple[float, float]] | None,
    initial: JointMap | None,
) -> ScaleTests:
    """The plan with the odometry scales the joint map's cost supports: each walk's candidate
    (:func:`odometry_scale_candidates`) on its own, against none, by how much it lowers the joint
    map's cost (one parameter: kept when the drop is beyond ``SCALE_TEST_QUANTILE`` of χ²(1)).
    Only a walk whose tags the others share for the most part (``MIN_SCALE_COVERAGE``) is tested:
    its scale is measured where they overlap, and ARKit's scale drifts along a walk.
    A random walk's drift can look like a scale error on the shared tags; a real scale error
    lowers the cost of the whole graph, drift does not (on simulated walks the cost rose by 48
    for a drifting walk and fell by 59–88 for one whose odometry was 2% long). When the plan's
    scales stay as they are, the unscaled solve is the build's first: its inputs and optimum are
    returned for the build to go on from."""
    candidates = [
        s
        for s, k in enumerate(plan.scale_candidates)
        if k != 1.0
        and len(plan.alignments[s].shared_tags)
        >= MIN_SCALE_COVERAGE * len(plan.fits[s].alone.tag_ids)
    ]
    if not candidates:
        return ScaleTests(plan=plan, drops={})
    n = len(plan.datasets)

    def solved(trial: JointPlan, start: Solved | None = None) -> tuple[float, Solved, JointInputs]:
        joint = joint_inputs(trial, params, variance_scales, initial)
        begin = start or (joint.start_T_keyframe, joint.start_T_tag)
        solution = refine(joint.inputs, params, values_from(joint.inputs, *begin))
        world_T_keyframe, world_T_tag, _ = solved_poses(joint.inputs, solution.values)
        return 2.0 * solution.final_error, (world_T_keyframe, world_T_tag), joint

    started = time.perf_counter()
    unscaled, unscaled_poses, unscaled_joint = solved(plan)
    unscaled_s = time.perf_counter() - started
    drops = {}
    for s in sorted(candidates, key=lambda s: plan.datasets[s]):
        scales = [1.0] * n
        scales[s] = plan.scale_candidates[s]
        # from the unscaled optimum: one walk's lengths change by a percent or two
        drops[s] = unscaled - solved(plan.with_odometry_scales(scales), unscaled_poses)[0]
    limit = chi2_quantile(SCALE_TEST_QUANTILE, 1)
    kept = [plan.scale_candidates[s] if drops.get(s, 0.0) > limit else 1.0 for s in range(n)]
    if all(k == 1.0 for k in kept):
        return ScaleTests(
            plan=plan,
            drops=drops,
            solved=unscaled_poses,
            joint=unscaled_joint,
            first_solve_s=unscaled_s,
        )
    return ScaleTests(plan=plan.with_odometry_scales(kept), drops=drops)
