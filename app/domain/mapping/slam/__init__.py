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
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, X

from app.domain.frames import FloatArray, se3_inverse
from app.domain.mapping.keyframes import interpolate_poses, select_keyframes
from app.domain.mapping.map_result import FactorResiduals, MapResult, OptimizationStats
from app.domain.mapping.noise import COMPONENTS, NoiseEstimate, updated_scales
from app.domain.mapping.params import SlamParams
from app.domain.mapping.screening import Screening, burst_variance_scale, screen_detections
from app.domain.upload.session import (
    IntArray,
    Session,
    TagDetections,
    first_observation_tag_poses,
    require_tags,
)

#: σ of the gauge prior on the first pose's heading (rad) and position (m).
GAUGE_PRIOR_SIGMA_RAD = 1e-6
GAUGE_PRIOR_SIGMA_M = 1e-6
#: Information of the gauge prior on the first pose's roll and pitch, 1/rad²: next to nothing
#: (gravity measures them, ~1e4 per keyframe), but positive, so the prior's Cholesky exists.
GAUGE_TILT_INFORMATION = 1.0
#: Shortest time credited to an odometry step, s (repeated timestamps would give zero noise).
MIN_ODOMETRY_DT_S = 1e-3
#: The map's up direction, in the world frame (y up).
WORLD_UP = np.array([0.0, 1.0, 0.0])

#: Sparse solver: sequential Cholesky measured ~10% faster than multifrontal on 10k-pose walks.
LINEAR_SOLVER = "SEQUENTIAL_CHOLESKY"

#: Most optimizations one noise estimate may take (each one LM solve and one pass over the
#: factors' marginal covariances).
MAX_NOISE_ROUNDS = 12
#: The estimate has converged when no variance changed by more than this fraction in a round.
NOISE_TOLERANCE = 0.05
#: The rounds of a noise estimate before its last stop LM at steps this many times larger, or
#: after this many iterations (a walk whose odometry fits badly crawls for dozens; the residuals
#: a round reads barely change meanwhile).
ROUGH_STEP_FACTOR = 100.0
ROUGH_MAX_ITERATIONS = 6
#: Largest keyframe–landmark block a noise estimate holds, entries (8 bytes each, five arrays
#: of it at the peak: 200 MB); beyond it (a 40,000-pose walk with 59 tags: 12.7 million, 760 MB
#: and 12 s) the configured variances are used, and the map says so.
MAX_NOISE_ESTIMATE_ENTRIES = 5_000_000
#: No variance is estimated more than this factor away from the configured one (either way).
NOISE_SCALE_BOUNDS = (1e-4, 1e4)

#: Called with (iteration, error) after each LM iteration.
IterationCallback = Callable[[int, float], None]


def pose_sigmas(*, rot_rad: FloatArray | float, trans_m: FloatArray | float) -> FloatArray:
    """Pose3 sigma vector in gtsam's tangent order ``[rot(3) rad, trans(3) m]``."""
    rot = np.broadcast_to(np.asarray(rot_rad, dtype=np.float64), (3,))
    trans = np.broadcast_to(np.asarray(trans_m, dtype=np.float64), (3,))
    return np.concatenate([rot, trans])


def to_pose3(T: FloatArray) -> gtsam.Pose3:
    return gtsam.Pose3(T)


def odometry_sigmas(dt_s: float, params: SlamParams) -> FloatArray:
    """Pose3 sigmas of an odometry step spanning ``dt_s`` seconds: variance = rate × dt."""
    dt_s = max(dt_s, MIN_ODOMETRY_DT_S)
    return pose_sigmas(
        rot_rad=math.sqrt(params.odom_angular_var_rad2_per_s * dt_s),
        trans_m=math.sqrt(params.odom_linear_var_m2_per_s * dt_s),
    )


def tag_covariance_in_tag_frame(camera_T_tag: FloatArray, params: SlamParams) -> FloatArray:
    """(6, 6) covariance of a tag detection in the tag frame, ``[rot rad, trans m]``.

    Position: variance ``tag_position_var_m2 · d²`` across the line of sight and
    ``tag_depth_var_ratio`` times that along it (the OpenCV camera's z), d the distance in m.
    Orientation: ``tag_orientation_var_rad2`` about each axis.
    """
    distance_m = float(np.linalg.norm(camera_T_tag[:3, 3]))
    lateral_var_m2 = params.tag_position_var_m2 * max(distance_m, 0.1) ** 2
    camera_cov_m2 = np.diag([1.0, 1.0, params.tag_depth_var_ratio]) * lateral_var_m2
    camera_R_tag = camera_T_tag[:3, :3]
    tag_cov_m2 = camera_R_tag.T @ camera_cov_m2 @ camera_R_tag
    covariance = np.zeros((6, 6))
    covariance[:3, :3] = np.eye(3) * params.tag_orientation_var_rad2
    covariance[3:, 3:] = tag_cov_m2
    return covariance


def gravity_variances(
    offsets_s: FloatArray,
    keyframe_of_pose: IntArray,
    num_keyframes: int,
    params: SlamParams,
    angular_scale: FloatArray,
) -> FloatArray:
    """(K,) the variance of each keyframe's gravity factor, rad², with the gravity of the poses
    it stands for folded in.

    Pose ``j`` between keyframes measures the same up vector as its nearest keyframe ``k`` (both
    come from ARKit's gravity-aligned world, carried to ``k`` by the raw odometry), with the
    odometry's tilt noise over the time between them added: variance ``gravity_var_rad2 +
    angular rate × |t_j − t_k|``. The keyframe's factor holds their combined information
    ``Σ_j 1 / (gravity_var_rad2 + rate · |t_j − t_k|)``; with every pose a keyframe that is one
    factor per pose at ``gravity_var_rad2``, as the paper's graph has.

    offsets_s: (N,) |t_j − t_k| of each pose from the keyframe it is folded into, s.
    keyframe_of_pose: (N,) that keyframe's row in the graph's keyframes. angular_scale: (N,) the
    angular variance factor of each pose's walk.
    """
    rate = params.odom_angular_var_rad2_per_s * angular_scale
    information = 1.0 / (params.gravity_var_rad2 + rate * offsets_s)
    total = np.bincount(
        keyframe_of_pose.astype(np.int64), weights=information, minlength=num_keyframes
    )
    return np.asarray(1.0 / total, dtype=np.float64)


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


@dataclass(frozen=True, slots=True, kw_only=True)
class Solution:
    """What :func:`solve` found: the values, the problem they solve (for residuals and
    marginals), the iterations (of the first stage, and after it), and the noise estimate."""

    values: gtsam.Values
    problem: _Problem
    start_iterations: int
    iterations: int
    final_error: float
    initial_error: float
    noise: tuple[NoiseEstimate, ...] | None


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
    problem = _build_problem(inputs, params)
    initial_error = float(problem.graph.error(initial))
    # every setting gives the same graph structure, so one ordering serves every stage
    ordering = gtsam.Ordering.ColamdNonlinearFactorGraph(problem.graph)
    start_iterations = 0
    if params.estimate_noise:
        values = initial
        if not params.has_default_variances and start is None:
            first = params.with_default_variances()
            values, start_iterations, _ = _levenberg_marquardt(
                _build_problem(inputs, first).graph, initial, first, on_iteration, ordering=ordering
            )
        chains = list(range(inputs.num_chains))
        if _estimate_size(inputs) > MAX_NOISE_ESTIMATE_ENTRIES:
            chains = []  # too large to estimate: the configured variances, said so below
        values, iterations, estimates = _estimate_noise(
            inputs,
            params,
            values,
            chains,
            _counting_from(start_iterations, on_iteration),
            ordering,
        )
        problem = _build_problem(inputs, params)
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
        values, iterations, final_error = _levenberg_marquardt(
            problem.graph, initial, params, on_iteration, ordering=ordering
        )
    else:
        start_problem = _build_problem(inputs, start_params)
        first_values, start_iterations, _ = _levenberg_marquardt(
            start_problem.graph, initial, start_params, on_iteration, ordering=ordering
        )
        values, iterations, final_error = _levenberg_marquardt(
            problem.graph,
            first_values,
            params,
            _counting_from(start_iterations, on_iteration),
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


def refine(
    inputs: GraphInputs,
    params: SlamParams,
    start: gtsam.Values,
    *,
    on_iteration: IterationCallback | None = None,
) -> Solution:
    """One Levenberg–Marquardt run of ``inputs``' graph from ``start`` with ``params``' variances
    and ``inputs.noise_scales`` as they are (no estimate, no first stage): a joint map's rounds."""
    problem = _build_problem(inputs, params)
    initial_error = float(problem.graph.error(start))
    values, iterations, final_error = _levenberg_marquardt(
        problem.graph, start, params, on_iteration
    )
    return Solution(
        values=values,
        problem=problem,
        start_iterations=0,
        iterations=iterations,
        final_error=final_error,
        initial_error=initial_error,
        noise=None,
    )


def chain_costs(inputs: GraphInputs, params: SlamParams, values: gtsam.Values) -> FloatArray:
    """(S,) each pose chain's cost at ``values`` with ``inputs.noise_scales``: its odometry
    factors' chi² plus its tag factors' robust cost (2 × gtsam's error under the Huber kernel);
    gravity left out (the odometry's own tilt)."""
    problem = _build_problem(inputs, params)
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


def local_landmark_key(index: int) -> int:
    """The graph key of the ``index``-th landmark that is not a tag of the map (``GraphInputs``'
    ``local_landmarks``)."""
    return int(gtsam.symbol("m", index))


def _counting_from(offset: int, on_iteration: IterationCallback | None) -> IterationCallback | None:
    """``on_iteration`` for a later LM stage: its iterations numbered on from ``offset``."""
    if on_iteration is None or offset == 0:
        return on_iteration
    return lambda iteration, error: on_iteration(offset + iteration, error)


def linearize_and_solve_ms(session: Session, params: SlamParams | None = None) -> float:
    """Wall time of one linearization and sparse solve of ``session``'s graph, ms.

    The floor for LM: it cannot take less than one Gauss–Newton step on the same graph.
    """
    params = params or SlamParams()
    inputs = GraphInputs(session, params)
    problem = _build_problem(inputs, params)
    ordering = gtsam.Ordering.ColamdNonlinearFactorGraph(problem.graph)
    started = time.perf_counter()
    linear = problem.graph.linearize(inputs.initial)
    delta = linear.optimize(ordering)  # multifrontal: the cheaper of the two here
    inputs.initial.retract(delta)
    return (time.perf_counter() - started) * 1e3


def values_from(
    inputs: GraphInputs,
    world_T_keyframe: FloatArray,
    world_T_tag: Mapping[int, FloatArray],
    world_T_local: Mapping[int, FloatArray] | None = None,
) -> gtsam.Values:
    """Start values for ``inputs``' graph: the keyframes from ``world_T_keyframe`` ((K, 4, 4), in
    ``inputs.keyframes`` order), each tag from ``world_T_tag`` (else its initial value), each
    landmark of its own from ``world_T_local`` by key (else its initial value): a warm start."""
    values = gtsam.Values()
    for i, pose in zip(inputs.keyframes.tolist(), world_T_keyframe, strict=True):
        values.insert(X(i), to_pose3(pose))
    for key in _landmark_keys(inputs):
        symbol = gtsam.Symbol(key)
        if symbol.chr() == ord("l") and int(symbol.index()) in world_T_tag:
            values.insert(key, to_pose3(world_T_tag[int(symbol.index())]))
        elif world_T_local is not None and key in world_T_local:
            values.insert(key, to_pose3(world_T_local[key]))
        else:
            values.insert(key, inputs.initial.atPose3(key))
    return values


def solved_poses(
    inputs: GraphInputs, values: gtsam.Values
) -> tuple[FloatArray, dict[int, FloatArray], dict[int, FloatArray]]:
    """``values`` as arrays: the keyframes' poses ((K, 4, 4)), the tags' by id, and the other
    landmarks' by graph key (the inverse of :func:`values_from`)."""
    world_T_keyframe = np.stack([values.atPose3(X(int(i))).matrix() for i in inputs.keyframes])
    world_T_tag = {t: values.atPose3(L(t)).matrix() for t in sorted(inputs.tag_rows)}
    world_T_local = {key: values.atPose3(key).matrix() for key in sorted(inputs.local_rows)}
    return world_T_keyframe, world_T_tag, world_T_local


def _landmark_keys(inputs: GraphInputs) -> list[int]:
    return [int(L(t)) for t in sorted(inputs.tag_rows)] + sorted(inputs.local_rows)


# --------------------------------------------------------------------------- building


class GraphInputs:
    """What the factor graph is built from that no noise parameter changes: the screened
    detections, the keyframes (the phone poses in the graph: ``params.keyframe_interval_s``),
    the odometry between consecutive keyframes, their measured up vectors, the tag measurements
    and the initial values; and each pose chain's (walk's) noise scales (``noise_scales``). A
    sweep prepares them once (:func:`prepare_graph_inputs`) and builds a graph per trial. Phone
    pose ``i`` of the session is the variable ``X(i)``.
    """

    def __init__(
        self,
        session: Session,
        params: SlamParams,
        initial_world_T_phone: FloatArray | None = None,
        *,
        screening: Screening | None = None,
        chain_starts: Sequence[int] = (0,),
        local_landmarks: Mapping[int, int] | None = None,
        tag_variance_scale: FloatArray | None = None,
        odometry_variance_scale: FloatArray | None = None,
        noise_scales: FloatArray | None = None,
        odometry_added_variance: FloatArray | None = None,
    ) -> None:
        """``chain_starts``: the first pose row of each pose chain (a joint map's sessions,
        ``joint.py``): no odometry links the last pose of one chain to the first of the next, and
        both are keyframes; keyframes are chosen in each chain on its own. ``screening``:
        computed by the caller (per session, for a joint map). ``local_landmarks``: detection row
        → a landmark key other than ``L(tag_id)`` (a session's sightings of a shared tag that
        disagree with the others'); those landmarks are solved but are not tags of the map.
        ``tag_variance_scale`` ((M,) per detection; default: each chain's bursts of sightings,
        ``screening.burst_variance_scale``) and ``odometry_variance_scale`` ((N,) per pose, taken
        at the step's first keyframe) multiply the noise variances. ``noise_scales``: (S, 4)
        per chain, the factors on its odometry linear, odometry angular, tag position and tag
        orientation variances (``noise.COMPONENTS``; what each walk's data support).
        ``odometry_added_variance``: (N, 2) variance added to the odometry from pose i to pose
        i + 1, translation (m², per axis) and rotation (rad², per axis), on top of the rate ×
        time and not scaled by ``noise_scales``; a step between keyframes adds up its poses'
        (a building map's stairs, ``joint/stairs.py``)."""
        self.session = session
        self.screening = screening or screen_detections(session.detections, params)
        detections = session.detections
        world_T_phone = session.world_T_phone
        start_T_phone = world_T_phone if initial_world_T_phone is None else initial_world_T_phone
        n = session.num_poses
        starts = sorted({int(s) for s in chain_starts} | {0})
        #: (S,) first pose row of each pose chain
        self.chain_starts = np.array(starts, dtype=np.int64)
        ends = [*starts[1:], n]
        used_poses = detections.pose_index[self.screening.used]
        keyframes: list[int] = []
        keyframe_chain: list[int] = []
        #: (N,) for each pose, the keyframe row its gravity is folded into and the time to it, s
        self.gravity_keyframe = np.zeros(n, dtype=np.int64)
        self.gravity_offset_s = np.zeros(n)
        #: (N,) the chain each pose belongs to
        self.pose_chain = np.zeros(n, dtype=np.int64)
        for c, (a, b) in enumerate(zip(starts, ends, strict=True)):
            times = session.timestamp_s[a:b]
            chosen = select_keyframes(
                times,
                required=used_poses[(used_poses >= a) & (used_poses < b)] - a,
                interval_s=params.keyframe_interval_s,
            )
            nearest = _nearest_keyframe(times, chosen)
            self.gravity_keyframe[a:b] = len(keyframes) + nearest
            self.gravity_offset_s[a:b] = np.abs(times - times[chosen[nearest]])
            self.pose_chain[a:b] = c
            keyframes.extend((chosen + a).tolist())
            keyframe_chain.extend([c] * len(chosen))
        #: (K,) the session's pose indices in the graph, sorted; (K,) the chain of each
        self.keyframes = np.array(keyframes, dtype=np.int64)
        self.keyframe_chain = np.array(keyframe_chain, dtype=np.int64)
        self.gauge_pose = to_pose3(world_T_phone[0])
        #: the first pose's up direction in its phone frame (the gauge leaves its tilt free)
        self.gauge_up = world_T_phone[0, :3, :3].T @ WORLD_UP
        first_of_chain = set(starts)
        #: (K−1,) whether consecutive keyframes k, k+1 are joined by odometry (same chain)
        self.odometry_linked = np.array(
            [b not in first_of_chain for b in keyframes[1:]], dtype=bool
        )
        self.odometry_dt_s = np.round(
            np.maximum(np.diff(session.timestamp_s[self.keyframes]), MIN_ODOMETRY_DT_S), 4
        )
        phone_T_next = (
            se3_inverse(world_T_phone[self.keyframes[:-1]]) @ (world_T_phone[self.keyframes[1:]])
        )
        self.phone_T_next = [to_pose3(T) for T in phone_T_next]
        #: (K, 3) each keyframe's measured up direction, phone frame
        self.phone_up_xyz = np.einsum("nji,j->ni", world_T_phone[self.keyframes, :3, :3], WORLD_UP)
        self.phone_up = [gtsam.Unit3(up) for up in self.phone_up_xyz]
        self.tag_detection_rows = [int(row) for row in np.flatnonzero(self.screening.used)]
        self.tag_ids = [int(detections.tag_id[row]) for row in self.tag_detection_rows]
        local = dict(local_landmarks or {})
        #: the landmark key each used detection's factor connects to
        self.landmark_keys = [
            local.get(row, L(tag_id))
            for row, tag_id in zip(self.tag_detection_rows, self.tag_ids, strict=True)
        ]
        self.tag_pose_indices = [int(detections.pose_index[row]) for row in self.tag_detection_rows]
        #: (U,) the chain each used detection belongs to
        self.detection_chain = self.pose_chain[np.array(self.tag_pose_indices, dtype=np.int64)]
        self.phone_T_tag = [
            to_pose3(detections.phone_T_tag[row]) for row in self.tag_detection_rows
        ]
        self.camera_T_tag = detections.camera_T_tag[self.tag_detection_rows]
        if tag_variance_scale is None:  # each chain's bursts of sightings (screening.py)
            tag_variance_scale = np.ones(len(detections))
            for a, b in zip(starts, ends, strict=True):
                chain_rows = np.flatnonzero(
                    (detections.pose_index >= a) & (detections.pose_index < b)
                )
                tag_variance_scale[chain_rows] = burst_variance_scale(
                    _detection_rows(detections, chain_rows), self.screening.used[chain_rows]
                )
        #: (U,) and (K−1,) variance multipliers of the tag and odometry factors
        self.tag_variance_scale = np.asarray(tag_variance_scale, dtype=np.float64)[
            self.tag_detection_rows
        ]
        self.odometry_variance_scale = (
            np.ones(len(keyframes) - 1 if keyframes else 0)
            if odometry_variance_scale is None
            else np.asarray(odometry_variance_scale, dtype=np.float64)[self.keyframes[:-1]]
        )
        #: (K−1, 2) variance added to each odometry step, translation m² and rotation rad²
        self.odometry_added_variance = np.zeros((max(len(keyframes) - 1, 0), 2))
        if odometry_added_variance is not None:
            added = np.asarray(odometry_added_variance, dtype=np.float64).reshape(n, 2)
            summed = np.concatenate([np.zeros((1, 2)), np.cumsum(added, axis=0)])
            self.odometry_added_variance = summed[self.keyframes[1:]] - summed[self.keyframes[:-1]]
        #: (S, 4) each chain's factors on its noise components (``noise.COMPONENTS``)
        self.noise_scales = (
            np.ones((len(starts), len(COMPONENTS)))
            if noise_scales is None
            else np.array(noise_scales, dtype=np.float64).reshape(len(starts), len(COMPONENTS))
        )
        self.initial = gtsam.Values()
        for i in keyframes:
            self.initial.insert(X(i), to_pose3(start_T_phone[i]))
        self.tag_rows: dict[int, list[int]] = {}
        #: rows of the detections of each local landmark, by key
        self.local_rows: dict[int, list[int]] = {}
        for row, tag_id, pose_index, key in zip(
            self.tag_detection_rows,
            self.tag_ids,
            self.tag_pose_indices,
            self.landmark_keys,
            strict=True,
        ):
            rows = self.tag_rows if key == L(tag_id) else self.local_rows
            label = tag_id if key == L(tag_id) else key
            if label not in rows:
                rows[label] = []
                first_T_tag = start_T_phone[pose_index] @ detections.phone_T_tag[row]
                self.initial.insert(key, to_pose3(first_T_tag))
            rows[label].append(row)

    @property
    def num_chains(self) -> int:
        return int(self.chain_starts.shape[0])

    def odometry_scales(self) -> tuple[FloatArray, FloatArray]:
        """(K−1,) the linear and the angular variance factor of each odometry step."""
        chain = self.keyframe_chain[:-1]
        legacy = self.odometry_variance_scale
        return legacy * self.noise_scales[chain, 0], legacy * self.noise_scales[chain, 1]

    def tag_scales(self) -> tuple[FloatArray, FloatArray]:
        """(U,) the position and the orientation variance factor of each tag factor."""
        chain = self.detection_chain
        burst = self.tag_variance_scale
        return burst * self.noise_scales[chain, 2], burst * self.noise_scales[chain, 3]


def _detection_rows(detections: TagDetections, rows: IntArray) -> TagDetections:
    """The detections ``rows`` of ``detections``, as a ``TagDetections`` of their own."""
    return TagDetections(
        **{f.name: getattr(detections, f.name)[rows] for f in dataclasses.fields(TagDetections)}
    )


def _nearest_keyframe(times_s: FloatArray, keyframes: IntArray) -> IntArray:
    """(n,) for each pose of a chain, the row in ``keyframes`` of the keyframe nearest in time
    (the earlier on a tie; a keyframe is its own)."""
    key_times = times_s[keyframes]
    after = np.clip(np.searchsorted(key_times, times_s, side="left"), 0, len(keyframes) - 1)
    before = np.clip(after - 1, 0, len(keyframes) - 1)
    earlier = np.abs(times_s - key_times[before]) <= np.abs(key_times[after] - times_s)
    nearest = np.where(earlier, before, after)
    nearest[keyframes] = np.arange(len(keyframes))
    return np.asarray(nearest, dtype=np.int64)


def prepare_graph_inputs(session: Session, params: SlamParams | None = None) -> GraphInputs:
    """Screen ``session`` with ``params``' rejection thresholds and precompute the graph's
    measurements, for :func:`optimize_tag_poses` with many noise parameters."""
    return GraphInputs(session, params or SlamParams())


def optimize_tag_poses(
    inputs: GraphInputs, params: SlamParams
) -> tuple[dict[int, FloatArray], int, gtsam.Values]:
    """The optimized ``world_T_tag`` of every tag in the graph, the number of LM iterations and
    the solution (no residuals, no marginals), one LM run from the initial values (raw odometry
    and first observations). ``params``' noise fields are used as given (no estimate); its
    rejection thresholds were applied when ``inputs`` were prepared. For many settings of one
    session, keep a :class:`TrialGraph` instead: it rebuilds only what a setting changes."""
    return TrialGraph(inputs).optimize(params)


#: The ``SlamParams`` fields each kind of factor is built from (besides ``GraphInputs``).
ODOMETRY_NOISE_FIELDS = ("odom_linear_var_m2_per_s", "odom_angular_var_rad2_per_s")
#: (the angular rate too: the gravity of the poses between keyframes is folded in through it)
GRAVITY_NOISE_FIELDS = ("gravity_var_rad2", "odom_angular_var_rad2_per_s")
TAG_NOISE_FIELDS = (
    "tag_position_var_m2",
    "tag_depth_var_ratio",
    "tag_orientation_var_rad2",
    "huber_k",
)


class TrialGraph:
    """One session's factor graph for many noise settings (a sweep's trials).

    The graph of a setting is the one :func:`optimize_session` builds, factor for factor and in
    the same order, so LM takes the same steps on it. What no setting changes is done once: the
    gauge prior, and the COLAMD ordering (the graph's structure is the same for every setting).
    Each kind of factor (odometry, gravity, tags) is rebuilt only when one of the parameters it
    is built from (``*_NOISE_FIELDS``) differs from the previous setting's; on the paper grid,
    where the odometry angular variance varies fastest, that leaves the ~N odometry factors and
    the K gravity factors.
    """

    def __init__(self, inputs: GraphInputs) -> None:
        self.inputs = inputs
        self._prior = _factor_graph([_gauge_prior(inputs)])
        self._kinds: dict[str, tuple[tuple[float, ...], gtsam.NonlinearFactorGraph]] = {}
        self._ordering: gtsam.Ordering | None = None

    def graph(self, params: SlamParams) -> gtsam.NonlinearFactorGraph:
        """The factor graph with ``params``' noise models."""
        inputs = self.inputs
        graph = gtsam.NonlinearFactorGraph()
        graph.push_back(self._prior)
        graph.push_back(
            self._kind("odometry", ODOMETRY_NOISE_FIELDS, params, _odometry_factors, inputs)
        )
        graph.push_back(
            self._kind("gravity", GRAVITY_NOISE_FIELDS, params, _gravity_factors, inputs)
        )
        graph.push_back(
            self._kind("tags", TAG_NOISE_FIELDS, params, lambda i, p: _tag_factors(i, p)[0], inputs)
        )
        return graph

    def optimize(
        self, params: SlamParams, *, on_iteration: IterationCallback | None = None
    ) -> tuple[dict[int, FloatArray], int, gtsam.Values]:
        """As :func:`optimize_tag_poses`: LM from the initial values (a build's first stage)."""
        return self.refine(params, self.inputs.initial, on_iteration=on_iteration)

    def refine(
        self,
        params: SlamParams,
        start: gtsam.Values,
        *,
        on_iteration: IterationCallback | None = None,
    ) -> tuple[dict[int, FloatArray], int, gtsam.Values]:
        """LM with ``params`` from ``start`` (the optimum with other variances, for a build's
        second stage): the tag poses, the iterations and the solution. ``on_iteration(iteration,
        error)`` is called after each LM iteration, as in :func:`optimize_session`; whatever it
        raises stops the optimization there and propagates (a job's cancel check)."""
        graph = self.graph(params)
        if self._ordering is None:
            self._ordering = gtsam.Ordering.ColamdNonlinearFactorGraph(graph)
        values, iterations, _ = _levenberg_marquardt(
            graph, start, params, on_iteration, ordering=self._ordering
        )
        poses = {
            tag_id: values.atPose3(L(tag_id)).matrix() for tag_id in sorted(self.inputs.tag_rows)
        }
        return poses, iterations, values

    def _kind(
        self,
        kind: str,
        fields: tuple[str, ...],
        params: SlamParams,
        build: Callable[[GraphInputs, SlamParams], list[Any]],
        inputs: GraphInputs,
    ) -> gtsam.NonlinearFactorGraph:
        key = tuple(float(getattr(params, name)) for name in fields)
        cached = self._kinds.get(kind)
        if cached is not None and cached[0] == key:
            return cached[1]
        factors = _factor_graph(build(inputs, params))
        self._kinds[kind] = (key, factors)
        return factors


class _Problem:
    """The factor graph and its factors by kind (for the residuals)."""

    def __init__(self) -> None:
        self.graph = gtsam.NonlinearFactorGraph()
        self.odometry_factors: list[gtsam.BetweenFactorPose3] = []
        self.gravity_factors: list[gtsam.AttitudeFactorPose3] = []
        self.tag_factors: list[gtsam.BetweenFactorPose3] = []
        self.tag_covariances: list[FloatArray] = []


def _build_problem(inputs: GraphInputs, params: SlamParams) -> _Problem:
    problem = _Problem()
    problem.odometry_factors = _odometry_factors(inputs, params)
    problem.gravity_factors = _gravity_factors(inputs, params)
    problem.tag_factors, problem.tag_covariances = _tag_factors(inputs, params)
    problem.graph = _problem_graph(inputs, problem)
    return problem


def _problem_graph(inputs: GraphInputs, problem: _Problem) -> gtsam.NonlinearFactorGraph:
    """The gauge prior, then the problem's odometry, gravity and tag factors, in that order."""
    graph = gtsam.NonlinearFactorGraph()
    graph.add(_gauge_prior(inputs))
    for kind in (problem.odometry_factors, problem.gravity_factors, problem.tag_factors):
        for factor in kind:
            graph.add(factor)
    return graph


def _factor_graph(factors: list[Any]) -> gtsam.NonlinearFactorGraph:
    graph = gtsam.NonlinearFactorGraph()
    for factor in factors:
        graph.add(factor)
    return graph


def _gauge_prior(inputs: GraphInputs) -> gtsam.PriorFactorPose3:
    """2a. The gauge prior on the first pose: its heading (the turn about the world's up, which
    is ``gauge_up`` in the phone frame) and its position; its roll and pitch are gravity's."""
    return _heading_position_prior(X(0), inputs.gauge_pose, inputs.gauge_up)


def gauge_prior(key: int, world_T_phone: FloatArray) -> gtsam.PriorFactorPose3:
    """The gauge prior of 2a on the pose ``key``, holding it at ``world_T_phone``'s heading and
    position (the world's +y seen from that pose is its up): the one a graph gets when its
    first walk, which held the gauge, is taken out (``mapping/incremental/isam.py``)."""
    return _heading_position_prior(key, to_pose3(world_T_phone), world_T_phone[:3, :3].T @ WORLD_UP)


def _heading_position_prior(
    key: int, pose: gtsam.Pose3, phone_up: FloatArray
) -> gtsam.PriorFactorPose3:
    up = phone_up / np.linalg.norm(phone_up)
    along_up = np.outer(up, up)
    information = np.zeros((6, 6))
    information[:3, :3] = along_up / GAUGE_PRIOR_SIGMA_RAD**2 + GAUGE_TILT_INFORMATION * (
        np.eye(3) - along_up
    )
    information[3:, 3:] = np.eye(3) / GAUGE_PRIOR_SIGMA_M**2
    noise = gtsam.noiseModel.Gaussian.Information(information)
    return gtsam.PriorFactorPose3(key, pose, noise)


def chain_graph(
    inputs: GraphInputs, params: SlamParams, *, key_offset: int = 0, gauge: bool = True
) -> gtsam.NonlinearFactorGraph:
    """The graph :func:`refine` solves for ``inputs`` of one pose chain (a walk), in the same
    order (the gauge prior only with ``gauge``; then odometry, gravity, tags), every phone pose
    ``X(i)`` renamed ``X(key_offset + i)``; landmark keys are kept. A walk's share of a building
    map's joint graph, numbered where the building keeps it (``mapping/incremental/isam.py``):
    for the walk at pose row ``key_offset`` of ``joint.combine_sessions``, factor for factor
    the joint graph's factors of that chain."""
    if inputs.num_chains != 1:
        raise ValueError(f"one pose chain expected, got {inputs.num_chains}")
    problem = _build_problem(inputs, params)
    graph = gtsam.NonlinearFactorGraph()
    pose_tag = ord("x")
    for k in range(0 if gauge else 1, int(problem.graph.size())):
        factor = problem.graph.at(k)
        if key_offset:
            keys = factor.keys()  # a gtsam KeyVector
            factor = factor.rekey(
                [key + key_offset if key >> 56 == pose_tag else key for key in keys]
            )
        graph.add(factor)
    return graph


def _odometry_factors(inputs: GraphInputs, params: SlamParams) -> list[gtsam.BetweenFactorPose3]:
    """2b. Odometry between consecutive keyframes, noise growing with the time between them, plus
    any variance added to the step (``GraphInputs.odometry_added_variance``; one noise model per
    distinct duration, walk and added variance)."""
    noise_by_dt: dict[tuple[float, ...], gtsam.noiseModel.Base] = {}
    factors = []
    keyframes = inputs.keyframes.tolist()
    linear_scale, angular_scale = inputs.odometry_scales()
    added = inputs.odometry_added_variance
    for k, phone_T_next in enumerate(inputs.phone_T_next):
        if not inputs.odometry_linked[k]:
            continue  # the next keyframe starts another pose chain (session)
        key = (
            float(inputs.odometry_dt_s[k]),
            float(linear_scale[k]),
            float(angular_scale[k]),
            float(added[k, 0]),
            float(added[k, 1]),
        )
        noise = noise_by_dt.get(key)
        if noise is None:
            sigmas = odometry_sigmas(key[0], params)
            sigmas[:3] *= math.sqrt(key[2])
            sigmas[3:] *= math.sqrt(key[1])
            if key[3] or key[4]:
                sigmas[:3] = np.sqrt(sigmas[:3] ** 2 + key[4])
                sigmas[3:] = np.sqrt(sigmas[3:] ** 2 + key[3])
            noise = gtsam.noiseModel.Diagonal.Sigmas(sigmas)
            noise_by_dt[key] = noise
        factors.append(
            gtsam.BetweenFactorPose3(X(keyframes[k]), X(keyframes[k + 1]), phone_T_next, noise)
        )
    return factors


def _gravity_factors(inputs: GraphInputs, params: SlamParams) -> list[gtsam.AttitudeFactorPose3]:
    """2c. Gravity: the measured up direction in the phone frame, held to the map's up, at every
    keyframe, with the gravity of the poses between keyframes folded in
    (:func:`gravity_variances`)."""
    world_up = gtsam.Unit3(WORLD_UP)
    variances = gravity_variances(
        inputs.gravity_offset_s,
        inputs.gravity_keyframe,
        len(inputs.keyframes),
        params,
        inputs.noise_scales[inputs.pose_chain, 1],
    )
    noise_by_variance: dict[float, gtsam.noiseModel.Base] = {}
    factors = []
    for i, phone_up, variance in zip(inputs.keyframes, inputs.phone_up, variances, strict=True):
        noise = noise_by_variance.get(float(variance))
        if noise is None:
            noise = gtsam.noiseModel.Isotropic.Sigma(2, math.sqrt(float(variance)))
            noise_by_variance[float(variance)] = noise
        factors.append(gtsam.AttitudeFactorPose3(X(int(i)), world_up, noise, phone_up))
    return factors


def _tag_factors(
    inputs: GraphInputs, params: SlamParams
) -> tuple[list[gtsam.BetweenFactorPose3], list[FloatArray]]:
    """2d. Tags, under a Huber kernel; and each factor's covariance (tag frame)."""
    huber = gtsam.noiseModel.mEstimator.Huber.Create(params.huber_k) if params.huber_k > 0 else None
    covariances = _tag_covariances(inputs, params)
    factors = []
    for k, landmark_key in enumerate(inputs.landmark_keys):
        noise: gtsam.noiseModel.Base = gtsam.noiseModel.Gaussian.Covariance(covariances[k])
        if huber is not None:
            noise = gtsam.noiseModel.Robust.Create(huber, noise)
        factors.append(
            gtsam.BetweenFactorPose3(
                X(inputs.tag_pose_indices[k]), landmark_key, inputs.phone_T_tag[k], noise
            )
        )
    return factors, list(covariances)


def _tag_covariances(inputs: GraphInputs, params: SlamParams) -> FloatArray:
    """(U, 6, 6) each tag factor's covariance: :func:`tag_covariance_in_tag_frame` of its
    detection, its blocks scaled by its walk's and its burst's factors (vectorized)."""
    camera_T_tag = inputs.camera_T_tag
    distance_m = np.maximum(np.linalg.norm(camera_T_tag[:, :3, 3], axis=1), 0.1)
    camera_R_tag = camera_T_tag[:, :3, :3]
    along = np.array([1.0, 1.0, params.tag_depth_var_ratio])
    tag_cov = np.einsum("uji,j,ujk->uik", camera_R_tag, along, camera_R_tag)
    position_scale, orientation_scale = inputs.tag_scales()
    covariance = np.zeros((camera_T_tag.shape[0], 6, 6))
    covariance[:, :3, :3] = (
        np.eye(3) * (params.tag_orientation_var_rad2 * orientation_scale)[:, None, None]
    )
    covariance[:, 3:, 3:] = (
        tag_cov * (params.tag_position_var_m2 * distance_m**2 * position_scale)[:, None, None]
    )
    return covariance


# --------------------------------------------------------------------------- solving


def _levenberg_marquardt(
    graph: gtsam.NonlinearFactorGraph,
    initial: gtsam.Values,
    params: SlamParams,
    on_iteration: IterationCallback | None,
    *,
    ordering: gtsam.Ordering | None = None,
) -> tuple[gtsam.Values, int, float]:
    """The solution, the iterations and the final error. ``ordering``: COLAMD's of ``graph``
    when it is known already (the default computes it).

    Stops when an iteration moved no pose or tag by more than ``params.converged_step_m`` and
    turned none by more than ``converged_step_rad`` (a step LM could not take moves nothing), when
    it lowered the error by less than ``relative_error_tol`` of it, or after ``max_iterations``.
    ``on_iteration(iteration, error)`` after each iteration; what it raises propagates."""
    lm_params = gtsam.LevenbergMarquardtParams()
    lm_params.setMaxIterations(params.max_iterations)
    lm_params.setRelativeErrorTol(0.0)
    lm_params.setAbsoluteErrorTol(0.0)
    lm_params.setOrdering(
        gtsam.Ordering.ColamdNonlinearFactorGraph(graph) if ordering is None else ordering
    )
    lm_params.setLinearSolverType(LINEAR_SOLVER)
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, initial, lm_params)
    previous = gtsam.utilities.extractPose3(initial)
    error = optimizer.error()
    iterations = 0
    while iterations < params.max_iterations:
        optimizer.iterate()
        iterations += 1
        new_error = optimizer.error()
        current = gtsam.utilities.extractPose3(optimizer.values())
        if on_iteration is not None:
            on_iteration(iterations, float(new_error))
        step_m, step_rad = _largest_step(previous, current)
        stalled = error - new_error <= params.relative_error_tol * error
        if (step_m <= params.converged_step_m and step_rad <= params.converged_step_rad) or stalled:
            break
        previous, error = current, new_error
    return optimizer.values(), iterations, float(optimizer.error())


def _largest_step(before: FloatArray, after: FloatArray) -> tuple[float, float]:
    """The largest translation (m) and rotation (rad) between two ``extractPose3`` stacks
    ((M, 12): each pose's rotation, 9 entries, then its translation)."""
    if before.shape[0] == 0:
        return 0.0, 0.0
    step_m = float(np.max(np.linalg.norm(after[:, 9:] - before[:, 9:], axis=1)))
    # ‖R_a − R_b‖_F = 2√2 sin(θ/2): θ to within 1% below 0.5 rad
    chord = float(np.max(np.linalg.norm(after[:, :9] - before[:, :9], axis=1)))
    step_rad = 2.0 * math.asin(min(1.0, chord / (2.0 * math.sqrt(2.0))))
    return step_m, step_rad


def _estimate_noise(
    inputs: GraphInputs,
    params: SlamParams,
    start: gtsam.Values,
    chains: Sequence[int],
    on_iteration: IterationCallback | None,
    ordering: gtsam.Ordering,
) -> tuple[gtsam.Values, int, tuple[NoiseEstimate, ...]]:
    """Iterated variance-component estimation of ``chains``' noise (``noise.py``): optimize,
    read each component's residuals and redundancy, rescale, repeat until no scale changes by
    more than ``NOISE_TOLERANCE``; then optimize with the final scales. Sets
    ``inputs.noise_scales``. Returns the solution, LM's iterations (all rounds) and one estimate
    per chain of ``inputs`` (the chains not estimated: their given scales, 0 rounds)."""
    selected = np.zeros(inputs.num_chains, dtype=bool)
    selected[list(chains)] = True
    values, iterations = start, 0
    rounds, converged, note = 0, False, ""
    chi2 = redundancy = rows = np.full((inputs.num_chains, len(COMPONENTS)), np.nan)
    previous_step: FloatArray | None = None
    # the rounds before the last need the optimum to within centimetres, not its last 0.1 mm
    rough = dataclasses.replace(
        params,
        converged_step_m=params.converged_step_m * ROUGH_STEP_FACTOR,
        converged_step_rad=params.converged_step_rad * ROUGH_STEP_FACTOR,
        max_iterations=min(params.max_iterations, ROUGH_MAX_ITERATIONS),
    )
    while True:
        last = converged or not selected.any() or rounds + 1 > MAX_NOISE_ROUNDS
        problem = _build_problem(inputs, params)
        values, done, _ = _levenberg_marquardt(
            problem.graph,
            values,
            params if last else rough,
            _counting_from(iterations, on_iteration),
            ordering=ordering,
        )
        iterations += done
        rounds += 1
        if last:
            break
        try:
            chi2, redundancy, rows = _component_statistics(inputs, problem, values)
        except RuntimeError as err:  # indeterminate: keep the last scales
            note = f"stopped after {rounds} rounds: the system became indeterminate ({_first(err)})"
            break
        scales = inputs.noise_scales.copy()
        new = updated_scales(
            scales[selected],
            chi2[selected],
            redundancy[selected],
            prior_dof=params.noise_prior_dof,
            bounds=NOISE_SCALE_BOUNDS,
        )
        step = np.log(new / scales[selected])
        change = float(np.max(np.abs(step)))
        converged = change <= math.log1p(NOISE_TOLERANCE)
        if previous_step is not None and not converged:
            new = np.exp(np.log(new) + _aitken_tail(previous_step, step))
            previous_step = None  # extrapolate from fresh steps only
        else:
            previous_step = step
        scales[selected] = new
        inputs.noise_scales = scales
    if not converged and not note and selected.any():
        note = f"not converged after {MAX_NOISE_ROUNDS} rounds; the last variances are used"
    if not selected.any():
        note = (
            f"not estimated: {len(inputs.keyframes)} keyframes × {len(_landmark_keys(inputs))} "
            f"landmarks is beyond what the estimate holds in memory "
            f"({MAX_NOISE_ESTIMATE_ENTRIES:.0e} entries); the configured variances are used"
        )
    estimates = []
    for c in range(inputs.num_chains):
        with np.errstate(invalid="ignore", divide="ignore"):
            per_redundancy = chi2[c] / redundancy[c]
        estimates.append(
            NoiseEstimate(
                scales=inputs.noise_scales[c].copy(),
                redundancy=redundancy[c].copy(),
                rows=rows[c].copy(),
                chi2_per_redundancy=np.where(redundancy[c] > 0, per_redundancy, np.nan),
                rounds=rounds if selected[c] else 0,
                converged=bool(converged and selected[c]),
                note=note,
            )
        )
    return values, iterations, tuple(estimates)


def _estimate_size(inputs: GraphInputs) -> int:
    """Entries of the keyframe–landmark covariance the estimate holds (:class:`_ChainCovariance`:
    K × 6 × 6T), for a graph of one pose chain (a walk); 0 for a building's several chains."""
    if inputs.num_chains != 1:
        return 0
    return len(inputs.keyframes) * 36 * len(_landmark_keys(inputs))


def _aitken_tail(previous: FloatArray, step: FloatArray) -> FloatArray:
    """What is left of an oscillating sequence after its last ``step`` (log-scales), from the
    ratio of its last two steps: ``step · r / (1 − r)`` where the ratio is within (−0.9, 0)
    (Aitken's Δ²: the odometry's yaw component oscillates, ratio ≈ −0.5, and settles rounds
    sooner), 0 elsewhere (a monotone sequence's first steps, from far, are not geometric yet:
    extrapolating them overshoots)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = np.where(previous != 0, step / previous, 0.0)
    usable = (ratio > -0.9) & (ratio < 0.0)
    return np.asarray(np.where(usable, step * ratio / (1.0 - np.where(usable, ratio, 0.0)), 0.0))


def _component_statistics(
    inputs: GraphInputs, problem: _Problem, values: gtsam.Values
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """(S, 4) each chain's whitened squared residuals ``vᵀPv``, redundancy ``Σ (1 − h_ii)`` and
    rows, per component (``noise.COMPONENTS``), at ``values``. The hat matrix's block of a factor
    is ``A Σ Aᵀ``, ``A`` its whitened (robust-weighted) Jacobian and ``Σ`` the joint marginal
    covariance of its variables (:func:`_factor_covariances`). The odometry's rotation counts about
    the world's up only (its yaw, along the phone-frame up vector ``u``: ``(uᵀ e)²`` and
    ``1 − uᵀ H u``): its tilt is gravity's."""
    shape = (inputs.num_chains, len(COMPONENTS))
    chi2, redundancy, rows = np.zeros(shape), np.zeros(shape), np.zeros(shape)
    odometry, tags = _factor_hats(inputs, problem, values)
    linked = np.flatnonzero(inputs.odometry_linked)
    chain = inputs.keyframe_chain[linked]
    H, b = odometry
    u = inputs.phone_up_xyz[linked]
    np.add.at(chi2[:, 0], chain, np.einsum("fi,fi->f", b[:, 3:], b[:, 3:]))
    np.add.at(redundancy[:, 0], chain, 3.0 - np.einsum("fii->f", H[:, 3:, 3:]))
    np.add.at(chi2[:, 1], chain, np.einsum("fi,fi->f", u, b[:, :3]) ** 2)
    np.add.at(redundancy[:, 1], chain, 1.0 - np.einsum("fi,fij,fj->f", u, H[:, :3, :3], u))
    np.add.at(rows[:, 0], chain, 3.0)
    np.add.at(rows[:, 1], chain, 1.0)
    H, b = tags
    chain = inputs.detection_chain
    np.add.at(chi2[:, 3], chain, np.einsum("fi,fi->f", b[:, :3], b[:, :3]))
    np.add.at(redundancy[:, 3], chain, 3.0 - np.einsum("fii->f", H[:, :3, :3]))
    np.add.at(chi2[:, 2], chain, np.einsum("fi,fi->f", b[:, 3:], b[:, 3:]))
    np.add.at(redundancy[:, 2], chain, 3.0 - np.einsum("fii->f", H[:, 3:, 3:]))
    np.add.at(rows[:, 2], chain, 3.0)
    np.add.at(rows[:, 3], chain, 3.0)
    return chi2, np.maximum(redundancy, 0.0), rows


Hats = tuple[FloatArray, FloatArray]


def _factor_hats(inputs: GraphInputs, problem: _Problem, values: gtsam.Values) -> tuple[Hats, Hats]:
    """The hat blocks ``A Σ Aᵀ`` ((F, 6, 6)) and whitened residuals ``b`` ((F, 6)) of the odometry
    factors and of the tag factors, at ``values``.

    A graph of one pose chain (one walk: where the noise is estimated) has a structure that gives
    every block needed in O(K) (:class:`_ChainCovariance`); any other graph asks gtsam's
    ``Marginals`` factor by factor (some 10–100 times slower)."""
    odometry = [f.linearize(values) for f in problem.odometry_factors]
    tags = [f.linearize(values) for f in problem.tag_factors]
    if inputs.num_chains == 1 and len(inputs.keyframes) >= 2:
        covariance = _ChainCovariance(inputs, problem, values, odometry, tags)
        return covariance.hats(odometry), covariance.hats(tags)
    marginals = gtsam.Marginals(problem.graph, values)

    def hats(linear: list[Any]) -> Hats:
        H, b = np.zeros((len(linear), 6, 6)), np.zeros((len(linear), 6))
        for k, factor in enumerate(linear):
            A, b[k] = factor.jacobian()
            keys = gtsam.KeyVector(factor.keys())
            H[k] = A @ marginals.jointMarginalCovariance(keys).fullMatrix() @ A.T
        return H, b

    return hats(odometry), hats(tags)


class _ChainCovariance:
    """The blocks of the posterior covariance ``N⁻¹`` that the factors of a one-chain graph
    touch, from its whitened Jacobians at the solution.

    Order the variables as the keyframes (in time), then the landmarks: ``N = [[P, B], [Bᵀ, C]]``,
    ``P`` block-tridiagonal (odometry joins consecutive keyframes only; gravity, the gauge and the
    sightings add to its diagonal), ``C`` block-diagonal, ``B`` a keyframe's sightings. With
    ``Y = P⁻¹B`` (block-tridiagonal solve) and the landmarks' Schur complement ``S = C − BᵀY``:
    ``Σ_ll = S⁻¹``, ``Σ_xl = −Y S⁻¹`` and ``Σ_xx = P⁻¹ + Y S⁻¹ Yᵀ``. ``P⁻¹``'s diagonal and first
    off-diagonal blocks come from a forward elimination ``F_k = P_kk − E_{k−1}ᵀ F_{k−1}⁻¹ E_{k−1}``
    and the backward pass ``G_kk = F_k⁻¹ + F_k⁻¹ E_k G_{k+1,k+1} E_kᵀ F_k⁻¹``,
    ``G_{k,k+1} = −F_k⁻¹ E_k G_{k+1,k+1}`` (``E_k = P_{k,k+1}``)."""

    def __init__(
        self,
        inputs: GraphInputs,
        problem: _Problem,
        values: gtsam.Values,
        odometry: list[Any],
        tags: list[Any],
    ) -> None:
        K = len(inputs.keyframes)
        self.row = {int(X(i)): k for k, i in enumerate(inputs.keyframes.tolist())}
        self.column = {key: t for t, key in enumerate(_landmark_keys(inputs))}
        T = len(self.column)
        D, E = np.zeros((K, 6, 6)), np.zeros((K - 1, 6, 6))
        C, B = np.zeros((T, 6, 6)), np.zeros((K, T, 6, 6))
        prior, _ = problem.graph.at(0).linearize(values).jacobian()
        D[0] += prior.T @ prior
        gravity = np.stack([f.linearize(values).jacobian()[0] for f in problem.gravity_factors])
        D += np.swapaxes(gravity, 1, 2) @ gravity
        if odometry:
            A = np.stack([f.jacobian()[0] for f in odometry])
            first = np.array([self.row[f.keys()[0]] for f in odometry])
            At = np.swapaxes(A, 1, 2)
            information = At @ A
            np.add.at(D, first, information[:, :6, :6])
            np.add.at(D, first + 1, information[:, 6:, 6:])
            np.add.at(E, first, information[:, :6, 6:])
        if tags:
            A = np.stack([f.jacobian()[0] for f in tags])
            keyframe = np.array([self.row[f.keys()[0]] for f in tags])
            landmark = np.array([self.column[f.keys()[1]] for f in tags])
            information = np.swapaxes(A, 1, 2) @ A
            np.add.at(D, keyframe, information[:, :6, :6])
            np.add.at(C, landmark, information[:, 6:, 6:])
            np.add.at(B, (keyframe, landmark), information[:, :6, 6:])
        B6 = np.swapaxes(B, 1, 2).reshape(K, 6, 6 * T)
        # forward elimination (P's block LDLᵀ), with B's columns carried along: Y = P⁻¹ B
        forward_inv = np.empty_like(D)
        carried = np.empty_like(B6)
        pivot = D[0]
        carried[0] = B6[0]
        for k in range(K):
            if k:
                pivot = D[k] - E[k - 1].T @ forward_inv[k - 1] @ E[k - 1]
                carried[k] = B6[k] - E[k - 1].T @ (forward_inv[k - 1] @ carried[k - 1])
            forward_inv[k] = np.linalg.inv(pivot)
        p_diagonal, p_next = np.empty_like(D), np.empty_like(E)
        Y = np.empty_like(B6)
        p_diagonal[K - 1] = forward_inv[K - 1]
        Y[K - 1] = forward_inv[K - 1] @ carried[K - 1]
        for k in range(K - 2, -1, -1):
            back = forward_inv[k] @ E[k]
            p_next[k] = -back @ p_diagonal[k + 1]
            p_diagonal[k] = forward_inv[k] - p_next[k] @ back.T
            Y[k] = forward_inv[k] @ carried[k] - back @ Y[k + 1]
        schur = -(B6.reshape(6 * K, 6 * T).T @ Y.reshape(6 * K, 6 * T))
        for t in range(T):
            schur[6 * t : 6 * t + 6, 6 * t : 6 * t + 6] += C[t]
        covariance_l = np.asarray(np.linalg.inv(schur) if T else np.zeros((0, 0)), np.float64)
        #: (T, 6, 6) each landmark's covariance; (K, 6, 6T) −(keyframe–landmark covariance)
        self.landmark_blocks = (
            np.stack([covariance_l[6 * t : 6 * t + 6, 6 * t : 6 * t + 6] for t in range(T)])
            if T
            else np.zeros((0, 6, 6))
        )
        # one large product rather than K small ones (BLAS runs it an order faster)
        self.W = (Y.reshape(6 * K, 6 * T) @ covariance_l).reshape(K, 6, 6 * T)
        #: (K, 6, 6) and (K−1, 6, 6): Σ_xx's diagonal and first off-diagonal blocks
        self.diagonal = p_diagonal + np.einsum("kiu,kju->kij", self.W, Y)
        self.next = p_next + np.einsum("kiu,kju->kij", self.W[:-1], Y[1:])

    def hats(self, linear: list[Any]) -> Hats:
        """The hat blocks and whitened residuals of ``linear``'s factors (each on two
        consecutive keyframes, or on a keyframe and a landmark)."""
        F = len(linear)
        A, b = np.zeros((F, 6, 12)), np.zeros((F, 6))
        covariance = np.zeros((F, 12, 12))
        for f, factor in enumerate(linear):
            A[f], b[f] = factor.jacobian()
            first, second = factor.keys()
            i = self.row[first]
            covariance[f, :6, :6] = self.diagonal[i]
            if second in self.row:  # the next keyframe
                covariance[f, :6, 6:] = self.next[i]
                covariance[f, 6:, 6:] = self.diagonal[i + 1]
            else:
                t = self.column[second]
                covariance[f, :6, 6:] = -self.W[i, :, 6 * t : 6 * t + 6]
                covariance[f, 6:, 6:] = self.landmark_blocks[t]
            covariance[f, 6:, :6] = covariance[f, :6, 6:].T
        return A @ covariance @ np.swapaxes(A, 1, 2), b


def _first(err: BaseException) -> str:
    text = str(err).strip()
    return text.splitlines()[0] if text else type(err).__name__


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


def _residuals(inputs: GraphInputs, problem: _Problem, values: gtsam.Values) -> FactorResiduals:
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
