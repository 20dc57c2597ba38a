"""Graph SLAM on a mapping session with gtsam (§3). All gtsam calls of the project live here.

    result = optimize_session(session, SlamParams())

Steps:
 1. screen detections (``screening.py``): the rejected never enter the graph; choose the
    keyframes (``keyframes.py``): the poses a used detection hangs on, and as many others as keep
    consecutive keyframes at most ``keyframe_interval_s`` apart;
 2. build the factor graph over the keyframes ``t < u`` (consecutive)
    2a. a prior on the first phone pose fixes the gauge,
    2b. odometry: ``BetweenFactorPose3(X(t), X(u), world_T_phone_t⁻¹ · world_T_phone_u)`` with
        variance growing linearly with the time between the poses,
    2c. gravity: an ``AttitudeFactorPose3`` per keyframe holds the phone's up vector (ARKit's
        world +y, seen in the phone frame) to the map's +y,
    2d. tags: ``BetweenFactorPose3(X(a), L(b), phone_T_tag)`` per used detection, noise in the
        camera frame (depth the weak axis, growing with distance²), under a Huber kernel;
 3. initial values: raw odometry for the poses, each tag's first used observation;
 4. Levenberg–Marquardt with a COLAMD ordering computed once, in two stages when the noise
    variances are not the defaults: first with the default variances from the initial values,
    then with the parameters' own from that optimum (see :func:`optimize_session`);
 5. the poses between keyframes placed by their interpolated odometry correction; per-factor
    residuals and the marginal covariances of the tag poses.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, X

from app.domain.frames import FloatArray, se3_inverse
from app.domain.mapping.keyframes import interpolate_poses, select_keyframes
from app.domain.mapping.map_result import FactorResiduals, MapResult, OptimizationStats
from app.domain.mapping.params import SlamParams
from app.domain.mapping.screening import Screening, screen_detections
from app.domain.upload.session import Session, first_observation_tag_poses, require_tags

#: σ of the gauge prior on the first pose: rotation rad, translation m.
GAUGE_PRIOR_SIGMA_RAD = 1e-6
GAUGE_PRIOR_SIGMA_M = 1e-6
#: Shortest time credited to an odometry step, s (repeated timestamps would give zero noise).
MIN_ODOMETRY_DT_S = 1e-3
#: The map's up direction, in the world frame (y up).
WORLD_UP = np.array([0.0, 1.0, 0.0])

#: Sparse solver: sequential Cholesky measured ~10% faster than multifrontal on 10k-pose walks.
LINEAR_SOLVER = "SEQUENTIAL_CHOLESKY"

#: Called with (iteration, error) after each LM iteration.
IterationCallback = Callable[[int, float], None]
#: Given the odometry factors' chi² at a first optimum, new odometry variance scales (or None).
OdometryReweighing = Callable[[FloatArray], FloatArray | None]


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


def optimize_session(
    session: Session,
    params: SlamParams | None = None,
    *,
    on_iteration: IterationCallback | None = None,
    initial_world_T_phone: FloatArray | None = None,
) -> MapResult:
    """Optimize ``session`` into a map. Raises ``NoTagsRecorded`` for a session with no tag
    detection (``session.require_tags``); never raises on any other session the parser accepted.

    A map whose noise variances are the defaults is one Levenberg–Marquardt run from the initial
    values. Any other setting is optimized in two stages: first with the default variances
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


def optimize_graph_inputs(
    inputs: GraphInputs,
    params: SlamParams,
    *,
    on_iteration: IterationCallback | None = None,
    started: float | None = None,
    reweigh_odometry: OdometryReweighing | None = None,
) -> MapResult:
    """:func:`optimize_session` from prepared inputs (a joint map's several pose chains,
    ``joint.py``). ``started``: ``time.perf_counter()`` when preparing them began (build time).

    ``reweigh_odometry``: called with the odometry factors' chi² ((K−1,), 0 between pose chains)
    at the first stage's optimum (default variances, always run then); it returns new
    ``inputs.odometry_variance_scale`` ((K−1,)) or None to keep them. The second stage, with
    ``params``' variances and those scales, starts from that optimum."""
    session = inputs.session
    started = time.perf_counter() if started is None else started
    screening = inputs.screening
    problem = _build_problem(inputs, params)
    start_params = params.with_default_variances()
    start_problem = (
        problem if params.has_default_variances else _build_problem(inputs, start_params)
    )
    two_stages = reweigh_odometry is not None or not params.has_default_variances
    build_ms = (time.perf_counter() - started) * 1e3

    started = time.perf_counter()
    initial_error = float(problem.graph.error(inputs.initial))
    # every setting gives the same graph structure, so one ordering serves both stages
    ordering = gtsam.Ordering.ColamdNonlinearFactorGraph(problem.graph)
    if not two_stages:
        start_iterations = 0
        values, iterations, final_error = _levenberg_marquardt(
            problem.graph, inputs.initial, params, on_iteration, ordering=ordering
        )
    else:
        start, start_iterations, _ = _levenberg_marquardt(
            start_problem.graph, inputs.initial, start_params, on_iteration, ordering=ordering
        )
        if reweigh_odometry is not None:
            chi2 = np.zeros(inputs.odometry_linked.shape[0])
            chi2[inputs.odometry_linked] = [
                2.0 * factor.error(start) for factor in start_problem.odometry_factors
            ]
            scales = reweigh_odometry(chi2)
            if scales is not None:
                inputs.odometry_variance_scale = np.asarray(scales, dtype=np.float64)
                problem.odometry_factors = _odometry_factors(inputs, params)
                problem.graph = _problem_graph(inputs, problem)
        values, iterations, final_error = _levenberg_marquardt(
            problem.graph,
            start,
            params,
            _counting_from(start_iterations, on_iteration),
            ordering=ordering,
        )
    optimize_ms = (time.perf_counter() - started) * 1e3

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
    tag_covariance = _tag_marginals(problem.graph, values, tag_ids, params)
    marginals_ms = (time.perf_counter() - started) * 1e3

    pre = first_observation_tag_poses(session)
    warnings = list(session.warnings) + list(screening.warnings)
    dropped = sorted(set(pre) - set(inputs.tag_rows))
    if dropped:
        warnings.append(f"tags {dropped} are not in the map: every detection of them was rejected")
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
        residuals=_residuals(inputs, problem, values),
        stats=OptimizationStats(
            iterations=iterations,
            start_iterations=start_iterations,
            initial_error=initial_error,
            final_error=final_error,
            build_ms=build_ms,
            optimize_ms=optimize_ms,
            marginals_ms=marginals_ms,
            num_factors=int(problem.graph.size()),
            num_variables=int(inputs.initial.size()),
        ),
        poi_names=tuple(poi.name for poi in session.pois),
        world_T_poi=(
            np.stack([world_T_phone[poi.pose_index] @ poi.phone_T_poi for poi in session.pois])
            if session.pois
            else np.empty((0, 4, 4))
        ),
        warnings=tuple(warnings),
    )


def odometry_chi2(inputs: GraphInputs, params: SlamParams, values: gtsam.Values) -> FloatArray:
    """(K−1,) each odometry factor's chi² at ``values``; 0 between two pose chains."""
    chi2 = np.zeros(inputs.odometry_linked.shape[0])
    chi2[inputs.odometry_linked] = [
        2.0 * factor.error(values) for factor in _odometry_factors(inputs, params)
    ]
    return chi2


def local_landmark_key(index: int) -> int:
    """The graph key of the ``index``-th landmark that is not a tag of the map (``GraphInputs``'
    ``local_landmarks``)."""
    return int(gtsam.symbol("m", index))


def _counting_from(offset: int, on_iteration: IterationCallback | None) -> IterationCallback | None:
    """``on_iteration`` for a second LM stage: its iterations numbered on from ``offset``."""
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


# --------------------------------------------------------------------------- building


class GraphInputs:
    """What the factor graph is built from that no noise parameter changes: the screened
    detections, the keyframes (the phone poses in the graph: ``params.keyframe_interval_s``),
    the odometry between consecutive keyframes, their measured up vectors, the tag measurements
    and the initial values. A sweep prepares them once (:func:`prepare_graph_inputs`) and builds a
    graph per trial. Phone pose ``i`` of the session is the variable ``X(i)``.
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
    ) -> None:
        """``chain_starts``: the first pose row of each pose chain (a joint map's sessions,
        ``joint.py``): no odometry links the last pose of one chain to the first of the next, and
        both are keyframes. ``screening``: computed by the caller (per session, for a joint map).
        ``local_landmarks``: detection row → a landmark key other than ``L(tag_id)`` (a session's
        sightings of a shared tag that disagree with the others'); those landmarks are solved but
        are not tags of the map. ``tag_variance_scale`` ((M,) per detection) and
        ``odometry_variance_scale`` ((N,) per pose, taken at the step's first keyframe) multiply
        the noise variances (a joint map weighs each session by what its data supports)."""
        self.session = session
        self.screening = screening or screen_detections(session.detections, params)
        detections = session.detections
        world_T_phone = session.world_T_phone
        start_T_phone = world_T_phone if initial_world_T_phone is None else initial_world_T_phone
        n = session.num_poses
        starts = sorted({int(s) for s in chain_starts} | {0})
        #: (S,) first pose row of each pose chain
        self.chain_starts = np.array(starts, dtype=np.int64)
        chain_ends = [s - 1 for s in starts[1:]] + [n - 1]
        #: (K,) the session's pose indices in the graph, sorted
        self.keyframes = select_keyframes(
            session.timestamp_s,
            required=np.concatenate(
                [detections.pose_index[self.screening.used], starts, chain_ends]
            ).astype(np.int64),
            interval_s=params.keyframe_interval_s,
        )
        keyframes = self.keyframes.tolist()
        self.gauge_pose = to_pose3(world_T_phone[0])
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
        phone_up = np.einsum("nji,j->ni", world_T_phone[self.keyframes, :3, :3], WORLD_UP)
        self.phone_up = [gtsam.Unit3(up) for up in phone_up]
        self.tag_detection_rows = [int(row) for row in np.flatnonzero(self.screening.used)]
        self.tag_ids = [int(detections.tag_id[row]) for row in self.tag_detection_rows]
        local = dict(local_landmarks or {})
        #: the landmark key each used detection's factor connects to
        self.landmark_keys = [
            local.get(row, L(tag_id))
            for row, tag_id in zip(self.tag_detection_rows, self.tag_ids, strict=True)
        ]
        self.tag_pose_indices = [int(detections.pose_index[row]) for row in self.tag_detection_rows]
        self.phone_T_tag = [
            to_pose3(detections.phone_T_tag[row]) for row in self.tag_detection_rows
        ]
        self.camera_T_tag = detections.camera_T_tag[self.tag_detection_rows]
        #: (U,) and (K−1,) variance multipliers of the tag and odometry factors
        self.tag_variance_scale = (
            np.ones(len(self.tag_detection_rows))
            if tag_variance_scale is None
            else np.asarray(tag_variance_scale, dtype=np.float64)[self.tag_detection_rows]
        )
        self.odometry_variance_scale = (
            np.ones(len(keyframes) - 1 if keyframes else 0)
            if odometry_variance_scale is None
            else np.asarray(odometry_variance_scale, dtype=np.float64)[self.keyframes[:-1]]
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


def prepare_graph_inputs(session: Session, params: SlamParams | None = None) -> GraphInputs:
    """Screen ``session`` with ``params``' rejection thresholds and precompute the graph's
    measurements, for :func:`optimize_tag_poses` with many noise parameters."""
    return GraphInputs(session, params or SlamParams())


def optimize_tag_poses(
    inputs: GraphInputs, params: SlamParams
) -> tuple[dict[int, FloatArray], int, gtsam.Values]:
    """The optimized ``world_T_tag`` of every tag in the graph, the number of LM iterations and
    the solution (no residuals, no marginals), one LM run from the initial values (raw odometry
    and first observations). ``params``' noise fields are used; its rejection thresholds were
    applied when ``inputs`` were prepared. For many settings of one session, keep a
    :class:`TrialGraph` instead: it rebuilds only what a setting changes."""
    return TrialGraph(inputs).optimize(params)


#: The ``SlamParams`` fields each kind of factor is built from (besides ``GraphInputs``).
ODOMETRY_NOISE_FIELDS = ("odom_linear_var_m2_per_s", "odom_angular_var_rad2_per_s")
GRAVITY_NOISE_FIELDS = ("gravity_var_rad2",)
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
    where the odometry angular variance varies fastest, that leaves the ~N odometry factors.
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
    """2a. The gauge prior on the first pose."""
    prior_noise = gtsam.noiseModel.Diagonal.Sigmas(
        pose_sigmas(rot_rad=GAUGE_PRIOR_SIGMA_RAD, trans_m=GAUGE_PRIOR_SIGMA_M)
    )
    return gtsam.PriorFactorPose3(X(0), inputs.gauge_pose, prior_noise)


def _odometry_factors(inputs: GraphInputs, params: SlamParams) -> list[gtsam.BetweenFactorPose3]:
    """2b. Odometry between consecutive keyframes, noise growing with the time between them (one
    noise model per distinct duration)."""
    noise_by_dt: dict[tuple[float, float], gtsam.noiseModel.Base] = {}
    factors = []
    keyframes = inputs.keyframes.tolist()
    for k, phone_T_next in enumerate(inputs.phone_T_next):
        if not inputs.odometry_linked[k]:
            continue  # the next keyframe starts another pose chain (session)
        key_dt = float(inputs.odometry_dt_s[k])
        scale = float(inputs.odometry_variance_scale[k])
        noise = noise_by_dt.get((key_dt, scale))
        if noise is None:
            noise = gtsam.noiseModel.Diagonal.Sigmas(
                odometry_sigmas(key_dt, params) * math.sqrt(scale)
            )
            noise_by_dt[key_dt, scale] = noise
        factors.append(
            gtsam.BetweenFactorPose3(X(keyframes[k]), X(keyframes[k + 1]), phone_T_next, noise)
        )
    return factors


def _gravity_factors(inputs: GraphInputs, params: SlamParams) -> list[gtsam.AttitudeFactorPose3]:
    """2c. Gravity: the measured up direction in the phone frame, held to the map's up, at every
    keyframe."""
    gravity_noise = gtsam.noiseModel.Isotropic.Sigma(2, math.sqrt(params.gravity_var_rad2))
    world_up = gtsam.Unit3(WORLD_UP)
    return [
        gtsam.AttitudeFactorPose3(X(int(i)), world_up, gravity_noise, phone_up)
        for i, phone_up in zip(inputs.keyframes, inputs.phone_up, strict=True)
    ]


def _tag_factors(
    inputs: GraphInputs, params: SlamParams
) -> tuple[list[gtsam.BetweenFactorPose3], list[FloatArray]]:
    """2d. Tags, under a Huber kernel; and each factor's covariance (tag frame)."""
    huber = gtsam.noiseModel.mEstimator.Huber.Create(params.huber_k) if params.huber_k > 0 else None
    factors, covariances = [], []
    for k, landmark_key in enumerate(inputs.landmark_keys):
        covariance = tag_covariance_in_tag_frame(inputs.camera_T_tag[k], params)
        covariance = covariance * inputs.tag_variance_scale[k]
        noise: gtsam.noiseModel.Base = gtsam.noiseModel.Gaussian.Covariance(covariance)
        if huber is not None:
            noise = gtsam.noiseModel.Robust.Create(huber, noise)
        factors.append(
            gtsam.BetweenFactorPose3(
                X(inputs.tag_pose_indices[k]), landmark_key, inputs.phone_T_tag[k], noise
            )
        )
        covariances.append(covariance)
    return factors, covariances


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
    when it is known already (the default computes it)."""
    lm_params = gtsam.LevenbergMarquardtParams()
    lm_params.setMaxIterations(params.max_iterations)
    lm_params.setRelativeErrorTol(params.relative_error_tol)
    lm_params.setAbsoluteErrorTol(0.0)
    lm_params.setOrdering(
        gtsam.Ordering.ColamdNonlinearFactorGraph(graph) if ordering is None else ordering
    )
    lm_params.setLinearSolverType(LINEAR_SOLVER)
    if on_iteration is not None:
        lm_params.iterationHook = lambda iteration, _before, after: on_iteration(
            int(iteration), float(after)
        )
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, initial, lm_params)
    values = optimizer.optimize()
    return values, int(optimizer.iterations()), float(optimizer.error())


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
    "TrialGraph",
    "linearize_and_solve_ms",
    "local_landmark_key",
    "odometry_chi2",
    "odometry_sigmas",
    "optimize_graph_inputs",
    "optimize_session",
    "optimize_tag_poses",
    "pose_sigmas",
    "prepare_graph_inputs",
    "tag_covariance_in_tag_frame",
]
