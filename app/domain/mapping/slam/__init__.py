"""Graph SLAM on a mapping session with gtsam (§3). All gtsam calls of the project live here.

    result = optimize_session(session, SlamParams())
    result.noise                   # each noise variance as the walk's own residuals support it

Steps:
 1. screen detections (``screening.py``): the rejected never enter the graph; choose the
    keyframes (``keyframes.py``): the poses a used detection hangs on, and as many others as keep
    consecutive keyframes at most ``keyframe_interval_s`` apart, per pose chain;
 2. build the factor graph over the keyframes ``t < u`` (consecutive)
    2a. a prior on the first phone pose fixes the gauge: its heading and position only (roll and
        pitch are measured by gravity, so holding them too would pull against gravity, and make
        the optimum depend on which pose is first),
    2b. odometry: ``BetweenFactorPose3(X(t), X(u), world_T_phone_t⁻¹ · world_T_phone_u)`` with
        variance growing linearly with the time between the poses,
    2c. gravity: an ``AttitudeFactorPose3`` per keyframe holds the phone's up vector (ARKit's
        world +y, seen in the phone frame) to the map's +y; it carries the gravity of the poses
        between keyframes too (:func:`gravity_variances`), so gravity's total weight does not
        depend on the keyframe interval,
    2d. tags: ``BetweenFactorPose3(X(a), L(b), phone_T_tag)`` per used detection, noise in the
        camera frame (depth the weak axis, growing with distance²), under a Huber kernel whose
        threshold is the χ² quantile of the residual's 6 dimensions (``params.huber_k``);
 3. initial values: raw odometry for the poses, each tag's first used observation;
 4. Levenberg–Marquardt with a COLAMD ordering computed once, stopping when no pose or tag moves
    by more than ``converged_step_m`` / ``converged_step_rad`` in an iteration; with
    ``estimate_noise`` (the default), the odometry and tag variances are estimated from the walk's
    own residuals (``noise.py``: iterated variance-component estimation, one LM solve per round);
    else one or two stages as :func:`optimize_session` says;
 5. the poses between keyframes placed by their interpolated odometry correction; per-factor
    residuals and the marginal covariances of the tag poses.

The stages, a module each; :func:`optimize_session` and :func:`solve`, here, run them in order:

inputs.py        1, 3. ``GraphInputs``: the keyframes, the measurements, the initial values;
                 values by graph key (``values_from``, ``solved_poses``)
factors.py       2. the noise models and the factors (2a–2d), the problem they make, ``chain_graph``
optimizer.py     4. Levenberg–Marquardt and its stopping rule, ``Solution``, ``refine``
noise_rounds.py  4. the noise estimate's rounds (iterated variance-component estimation)
result.py        5. the ``MapResult``: every pose placed, tag marginals, residuals, chain costs
trial.py         a sweep's ``TrialGraph``: one session's graph for many noise settings

:func:`solve` reads ``MAX_NOISE_ESTIMATE_ENTRIES`` and ``levenberg_marquardt`` from this module,
so patching them here changes its first stage and its size check; ``refine``, the noise rounds
and ``TrialGraph`` call ``levenberg_marquardt`` from their own modules.
"""

from __future__ import annotations

import time

import gtsam

from app.domain.frames import FloatArray
from app.domain.mapping.map_result import MapResult
from app.domain.mapping.params import SlamParams
from app.domain.upload.session import Session, require_tags

from .factors import GAUGE_PRIOR_SIGMA_M as GAUGE_PRIOR_SIGMA_M
from .factors import GAUGE_PRIOR_SIGMA_RAD as GAUGE_PRIOR_SIGMA_RAD
from .factors import GAUGE_TILT_INFORMATION as GAUGE_TILT_INFORMATION
from .factors import build_problem as build_problem
from .factors import (
    chain_graph,
    gauge_prior,
    gravity_variances,
    odometry_sigmas,
    pose_sigmas,
    tag_covariance_in_tag_frame,
)
from .inputs import MIN_ODOMETRY_DT_S as MIN_ODOMETRY_DT_S
from .inputs import WORLD_UP as WORLD_UP
from .inputs import GraphInputs, local_landmark_key, prepare_graph_inputs, solved_poses, values_from
from .inputs import to_pose3 as to_pose3
from .noise_rounds import MAX_NOISE_ESTIMATE_ENTRIES as MAX_NOISE_ESTIMATE_ENTRIES
from .noise_rounds import MAX_NOISE_ROUNDS as MAX_NOISE_ROUNDS
from .noise_rounds import NOISE_SCALE_BOUNDS as NOISE_SCALE_BOUNDS
from .noise_rounds import NOISE_TOLERANCE as NOISE_TOLERANCE
from .noise_rounds import ROUGH_MAX_ITERATIONS as ROUGH_MAX_ITERATIONS
from .noise_rounds import ROUGH_STEP_FACTOR as ROUGH_STEP_FACTOR
from .noise_rounds import Hats as Hats
from .noise_rounds import estimate_noise_scales, estimate_size
from .optimizer import LINEAR_SOLVER as LINEAR_SOLVER
from .optimizer import IterationCallback as IterationCallback
from .optimizer import Solution, counting_from, linearize_and_solve_ms, refine
from .optimizer import largest_step as largest_step
from .optimizer import levenberg_marquardt as levenberg_marquardt
from .result import chain_costs, map_result, solution_residuals
from .trial import GRAVITY_NOISE_FIELDS as GRAVITY_NOISE_FIELDS
from .trial import ODOMETRY_NOISE_FIELDS as ODOMETRY_NOISE_FIELDS
from .trial import TAG_NOISE_FIELDS as TAG_NOISE_FIELDS
from .trial import TrialGraph, optimize_tag_poses


def optimize_session(
    session: Session,
    params: SlamParams | None = None,
    *,
    on_iteration: IterationCallback | None = None,
    initial_world_T_phone: FloatArray | None = None,
) -> MapResult:
    """Optimize ``session`` into a map. Raises ``NoTagsRecorded`` for a session with no tag
    detection (``session.require_tags``); never raises on any other session the parser accepted.

    With ``params.estimate_noise`` (the default) the walk's odometry and tag variances are
    estimated from its own residuals, starting from (and, where its data cannot tell, kept near)
    ``params``' (``noise.py``; ``result.noise`` says what was found). Without it, a map whose
    noise variances are the defaults is one Levenberg–Marquardt run from the initial values; any
    other setting is optimized in two stages: first with the default variances
    (``params.with_default_variances()``), then with its own, starting from that optimum
    (``stats.start_iterations`` counts the first stage's iterations). From raw odometry, LM at
    stiff settings crawls along directions where the error is nearly flat (a heading free between
    tag sightings): on floor_2_straight one setting took 284 iterations, and stopped at 100 with
    a map worse than the first observations. From the defaults' optimum it converges in a few.
    A sweep's trials start there too (``tuning.TuningTarget``), so a converged trial *is* the
    map this function makes with its setting, bit for bit.

    ``initial_world_T_phone`` ((N, 4, 4), optional) starts LM from another trajectory than the raw
    odometry (a warm start); tags then start from their first observation on it.
    """
    params = params or SlamParams()
    require_tags(session)
    if initial_world_T_phone is not None and initial_world_T_phone.shape != (
        session.num_poses,
        4,
        4,
    ):
        raise ValueError(
            f"initial_world_T_phone must have shape ({session.num_poses}, 4, 4), "
            f"got {initial_world_T_phone.shape}"
        )
    started = time.perf_counter()
    inputs = GraphInputs(session, params, initial_world_T_phone)
    return optimize_graph_inputs(inputs, params, on_iteration=on_iteration, started=started)


def solve(
    inputs: GraphInputs,
    params: SlamParams,
    *,
    on_iteration: IterationCallback | None = None,
    start: gtsam.Values | None = None,
) -> Solution:
    """Optimize the graph of ``inputs`` (see :func:`optimize_session` for the stages).

    ``start``: values to start LM from instead of ``inputs.initial`` (a warm start: every key of
    the graph)."""
    initial = inputs.initial if start is None else start
    problem = build_problem(inputs, params)
    initial_error = float(problem.graph.error(initial))
    # every setting gives the same graph structure, so one ordering serves every stage
    ordering = gtsam.Ordering.ColamdNonlinearFactorGraph(problem.graph)
    start_iterations = 0
    if params.estimate_noise:
        values = initial
        if not params.has_default_variances and start is None:
            first = params.with_default_variances()
            values, start_iterations, _ = levenberg_marquardt(
                build_problem(inputs, first).graph, initial, first, on_iteration, ordering=ordering
            )
        chains = list(range(inputs.num_chains))
        if estimate_size(inputs) > MAX_NOISE_ESTIMATE_ENTRIES:
            chains = []  # too large to estimate: the configured variances, said so below
        values, iterations, estimates = estimate_noise_scales(
            inputs,
            params,
            values,
            chains,
            counting_from(start_iterations, on_iteration),
            ordering,
        )
        problem = build_problem(inputs, params)
        return Solution(
            values=values,
            problem=problem,
            start_iterations=start_iterations,
            iterations=iterations,
            final_error=float(problem.graph.error(values)),
            initial_error=initial_error,
            noise=estimates,
        )
    start_params = params.with_default_variances()
    if params.has_default_variances:
        values, iterations, final_error = levenberg_marquardt(
            problem.graph, initial, params, on_iteration, ordering=ordering
        )
    else:
        start_problem = build_problem(inputs, start_params)
        first_values, start_iterations, _ = levenberg_marquardt(
            start_problem.graph, initial, start_params, on_iteration, ordering=ordering
        )
        values, iterations, final_error = levenberg_marquardt(
            problem.graph,
            first_values,
            params,
            counting_from(start_iterations, on_iteration),
            ordering=ordering,
        )
    return Solution(
        values=values,
        problem=problem,
        start_iterations=start_iterations,
        iterations=iterations,
        final_error=final_error,
        initial_error=initial_error,
        noise=None,
    )


def optimize_graph_inputs(
    inputs: GraphInputs,
    params: SlamParams,
    *,
    on_iteration: IterationCallback | None = None,
    started: float | None = None,
    start: gtsam.Values | None = None,
) -> MapResult:
    """:func:`optimize_session` from prepared inputs, as a :class:`MapResult`. ``started``:
    ``time.perf_counter()`` when preparing them began (build time). The other arguments are
    :func:`solve`'s."""
    started = time.perf_counter() if started is None else started
    build_ms = (time.perf_counter() - started) * 1e3
    started = time.perf_counter()
    solution = solve(inputs, params, on_iteration=on_iteration, start=start)
    optimize_ms = (time.perf_counter() - started) * 1e3
    return map_result(inputs, params, solution, build_ms=build_ms, optimize_ms=optimize_ms)


__all__ = [
    "GraphInputs",
    "Solution",
    "TrialGraph",
    "chain_costs",
    "chain_graph",
    "gauge_prior",
    "gravity_variances",
    "linearize_and_solve_ms",
    "local_landmark_key",
    "map_result",
    "odometry_sigmas",
    "optimize_graph_inputs",
    "optimize_session",
    "optimize_tag_poses",
    "pose_sigmas",
    "prepare_graph_inputs",
    "refine",
    "solution_residuals",
    "solve",
    "solved_poses",
    "tag_covariance_in_tag_frame",
    "values_from",
]
