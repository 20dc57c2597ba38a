"""The building map the ISAM2 engine serves, as the batch build's :class:`JointMap` (issue 38).

    joint = served_joint_map(building, served, params)   # str: why the batch build must decide

The later stages of a build (evaluation, the corridor skeleton, the documents) read a
``JointMap``: the map with its residuals and tag covariances, and per walk a ``SessionPart``
saying how it was placed and why it weighs what it does. Here the engine's optimum is read
through the batch build's own code (``joint.plan.joint_inputs_at``,
``joint.report.report_as_planned``), so the served figures are the ones the batch build would
compute at the same optimum; no solve is run.

The engine's graph is the batch build's step 4 only. Before serving, the batch build's later
steps are asked at the engine's optimum whether they would change a walk's factors; if one
would, the version is the batch build's (the reason returned, for the job's log):

- step 3, a walk's odometry scale: where a walk's candidate (``placing.odometry_scale_candidates``,
  from the walks' own tag maps kept in the state) is not 1 and the batch build would test it,
  the test is made in the tree (``IsamBuilding.odometry_scale_drop``: the walk's factors
  swapped for scaled ones and back) and must not keep it (the walk that holds the gauge is
  left to the batch build);
- step 5, a tag one walk disagrees on (``weights.worst_split``): none;
- step 6, a walk its noise does not explain (``weights.weigh_walks``): every factor 1.

A walk kept from the stored state has no fit alone in this process, so its part has no noise
estimate and no map alone (``SessionPart.alone`` None: the report compares only the walks fitted
in this build).
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from app.domain.mapping.joint.model import JointMap
from app.domain.mapping.joint.placing import odometry_scale_candidates, placed_alignments
from app.domain.mapping.joint.plan import JointPlan, joint_inputs_at
from app.domain.mapping.joint.report import report_as_planned
from app.domain.mapping.joint.scale import MIN_SCALE_COVERAGE, SCALE_TEST_QUANTILE
from app.domain.mapping.joint.stairs import stairs_on
from app.domain.mapping.joint.weights import factors_changed, weigh_walks, worst_split
from app.domain.mapping.noise import chi2_quantile
from app.domain.mapping.params import SlamParams
from app.domain.mapping.slam import Solution, build_problem, values_from

from .isam import IsamBuilding
from .updates import IncrementalMap


def served_joint_map(
    building: IsamBuilding, served: IncrementalMap, params: SlamParams
) -> JointMap | str:
    """``served`` (``building``'s map after its last change) as the ``JointMap`` the later
    stages read, or why the batch build must make this version instead (the module
    docstring)."""
    started_s = time.perf_counter()
    walks = building.walks
    if len(walks) < 2:
        return "a map of one walk"
    if stairs_on(params) or not params.estimate_noise:
        return "parameters the engine's graph does not model (the stairs rule, variances as given)"
    datasets = tuple(w.walk_id for w in walks)
    alone_tags = [w.alone_tags for w in walks]
    alignments = placed_alignments(
        datasets, alone_tags, {s: building.map_T_world(w) for s, w in enumerate(walks)}
    )
    candidates = odometry_scale_candidates(datasets, alone_tags)
    limit = chi2_quantile(SCALE_TEST_QUANTILE, 1)
    tested = False
    tests_s = time.perf_counter()
    for s, scale in enumerate(candidates):
        if scale == 1.0 or len(alignments[s].shared_tags) < MIN_SCALE_COVERAGE * len(alone_tags[s]):
            continue
        drop = building.odometry_scale_drop(datasets[s], scale)
        tested = True
        if drop is None:
            return f"{datasets[s]}'s odometry scale ×{scale:.3f} is the scale test's to decide"
        if drop > limit:
            return (
                f"{datasets[s]}'s odometry would be rescaled ×{scale:.3f} "
                f"(the map's χ² drops by {drop:.1f})"
            )
    if tested:  # the tree settled again after each test: serve where it is now
        served = dataclasses.replace(
            building.served(updates=served.rounds),
            timings_ms={**served.timings_ms, "scale_tests": (time.perf_counter() - tests_s) * 1e3},
        )
    plan = JointPlan(
        datasets=datasets,
        sessions=tuple(w.session for w in walks),
        screenings=tuple(w.screening for w in walks),
        scales=tuple(w.depth_scale for w in walks),
        alignments=alignments,
        fits=(),
        scale_candidates=candidates,
    )
    joint = joint_inputs_at(
        plan,
        params,
        np.stack([w.noise_scales for w in walks]),
        np.array([w.cost_alone for w in walks]),
        np.concatenate(served.world_T_phone),
        served.tag_poses(),
    )
    fixed = dataclasses.replace(params, estimate_noise=False)
    inputs = joint.inputs
    values = values_from(inputs, joint.start_T_keyframe, joint.start_T_tag)
    problem = build_problem(inputs, fixed)
    error = float(problem.graph.error(values))
    solution = Solution(
        values=values,
        problem=problem,
        start_iterations=0,
        iterations=served.rounds,
        final_error=error,
        initial_error=error,
        noise=None,
    )
    split = worst_split(joint, inputs, solution, frozenset())
    if split is not None:
        (s, tag), chi2 = split
        return f"{datasets[s]}'s sightings of tag {tag} disagree with the map (mean χ² {chi2:.1f})"
    ones = np.ones(len(walks))
    weighing = weigh_walks(joint, inputs, fixed, solution, ones, frozenset())
    if factors_changed(weighing.factors, ones):
        s = int(np.argmax(weighing.factors))
        return f"{datasets[s]} would be down-weighted ×{weighing.factors[s]:.2f}"
    checked_s = time.perf_counter()
    result, parts = report_as_planned(
        joint,
        params,
        solution,
        weighing,
        build_ms=0.0,
        optimize_ms=sum(served.timings_ms.values()),
        fits=[w.fit for w in walks],
    )
    done_s = time.perf_counter()
    return JointMap(
        map=result,
        parts=parts,
        combined=joint.combined,
        sessions=plan.sessions,
        detection_mask=joint.screening.used,
        rounds=1,
        timings_ms={
            **served.timings_ms,
            "checks": (checked_s - started_s) * 1e3,
            "marginals": result.stats.marginals_ms,
            "report": (done_s - checked_s) * 1e3 - result.stats.marginals_ms,
        },
    )


__all__ = ["served_joint_map"]
