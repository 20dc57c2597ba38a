"""Steps 1 and 2 together, then step 4's one graph: what is decided before the joint solve.

:func:`plan_sessions` fits each walk alone (reusing earlier fits) and places them all
(:class:`JointPlan`). :func:`prepare_joint` turns a plan into one factor graph's inputs
(:class:`JointInputs`): the walks' poses and detections concatenated (:func:`combine_sessions`),
each keeping its own pose chain and its own noise (``GraphInputs.noise_scales``), tags shared,
and LM's start: the walks' own optima placed by step 2, or (with ``initial``) the last version's
optimum, a warm start.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from app.domain.errors import InvisibleMapError
from app.domain.frames import FloatArray, make_pose
from app.domain.mapping.joint.alignment import MIN_SHARED_TAGS, weighted_similarity
from app.domain.mapping.joint.model import JointMap, PairAlignment, SessionAlignment, WalkFit
from app.domain.mapping.joint.placing import (
    align_walks,
    odometry_scale_candidates,
    walk_placements,
)
from app.domain.mapping.joint.stairs import Climb, stairs_on, stairs_variance, walk_climbs
from app.domain.mapping.joint.walks import fit_walk, scaled_tag_depths, tag_depth_scale
from app.domain.mapping.map_result import Rejection
from app.domain.mapping.params import SlamParams
from app.domain.mapping.screening import DetectionGeometry, Screening, screen_detections
from app.domain.mapping.slam import (
    GraphInputs,
    chain_costs,
    local_landmark_key,
    values_from,
)
from app.domain.upload.session import PointOfInterest, Session, TagDetections

#: Time between consecutive sessions in the joint map's clock, s (no odometry spans it).
SESSION_GAP_S = 1.0


#: Called with (step, fraction done) as a joint build goes ("walks", "joint").
ProgressCallback = Callable[[str, float], None]


@dataclass(frozen=True, slots=True, kw_only=True)
class JointPlan:
    """Everything decided before optimizing the walks together: each walk's screening, depth
    scale, own map and noise (its :class:`WalkFit`), and placement. Walks stay in the order
    given (the first one's world is the map frame)."""

    datasets: tuple[str, ...]
    sessions: tuple[Session, ...]
    screenings: tuple[Screening, ...]
    scales: tuple[float, ...]
    alignments: tuple[SessionAlignment, ...]
    fits: tuple[WalkFit, ...]
    timings_ms: Mapping[str, float] = field(default_factory=dict)
    #: each walk's odometry scale against the others' (1: none significant), a candidate that
    #: ``optimize_sessions`` tests on the joint map's cost
    scale_candidates: tuple[float, ...] = ()
    min_shared_tags: int = MIN_SHARED_TAGS
    #: each walk's first (rigid) placement, before the joint fit (:func:`walk_placements`)
    first_placements: Mapping[int, FloatArray] = field(default_factory=dict)
    #: the pairwise alignments the placements came from, by the walks' names
    pair_alignments: Mapping[tuple[str, str], PairAlignment] = field(default_factory=dict)

    def with_odometry_scales(self, scales: Sequence[float]) -> JointPlan:
        """This plan with each walk's lengths multiplied by ``scales`` (placed again)."""
        return dataclasses.replace(
            self,
            alignments=align_walks(
                self.datasets,
                [fit.alone.tag_poses() for fit in self.fits],
                min_shared_tags=self.min_shared_tags,
                odometry_scales=scales,
                first_placements=self.first_placements or None,
            ),
        )


def plan_sessions(
    sessions: Sequence[Session],
    params: SlamParams,
    *,
    names: Sequence[str] | None = None,
    scale_depths: bool = True,
    depth_scales: Mapping[str, float] | None = None,
    min_shared_tags: int = MIN_SHARED_TAGS,
    initial: JointMap | None = None,
    fits: Sequence[WalkFit] = (),
    on_progress: ProgressCallback | None = None,
) -> JointPlan:
    """Steps 1 and 2 (``walks.py``, ``placing.py``): each walk screened, scaled and optimized alone
    (reusing ``initial``'s and ``fits``' fits of the same walks with the same parameters), then
    all placed together. Raises :class:`AlignmentError` for a walk that cannot be placed."""
    if not sessions:
        raise InvisibleMapError("a map needs at least one session")
    datasets = tuple(names) if names is not None else tuple(s.map_id for s in sessions)
    if len(datasets) != len(sessions):
        raise ValueError(f"{len(datasets)} names for {len(sessions)} sessions")
    if len(set(datasets)) != len(datasets):
        raise InvisibleMapError(f"a session is in the map twice: {list(datasets)}")
    started = time.perf_counter()
    screenings = [screen_detections(s.detections, params) for s in sessions]
    scales = [
        tag_depth_scale(s, screening.used) if scale_depths else 1.0
        for s, screening in zip(sessions, screenings, strict=True)
    ]
    for s, dataset in enumerate(datasets):
        if depth_scales and dataset in depth_scales:
            scales[s] = float(depth_scales[dataset])
    scaled = [scaled_tag_depths(s, k) for s, k in zip(sessions, scales, strict=True)]
    known = _reusable_fits(initial, fits, params)
    walk_fits = []
    for s, dataset in enumerate(datasets):
        fit = known.get(dataset)
        if fit is None or fit.tag_depth_scale != scales[s]:
            fit = fit_walk(dataset, scaled[s], screenings[s], params, scales[s])
        walk_fits.append(fit)
        if on_progress is not None:
            on_progress("walks", (s + 1) / len(datasets))
    fitted = time.perf_counter()
    tags = [fit.alone.tag_poses() for fit in walk_fits]
    # a pair's alignment depends on the two walks' own maps only: reuse the last version's
    # where both walks' fits were reused
    reused = {d for d, fit in zip(datasets, walk_fits, strict=True) if fit is known.get(d)}
    earlier = initial.pair_alignments if initial is not None else {}
    pairs = {names: pair for names, pair in earlier.items() if set(names) <= reused}
    first = walk_placements(datasets, tags, min_shared_tags=min_shared_tags, pairs=pairs)
    alignments = align_walks(
        datasets, tags, min_shared_tags=min_shared_tags, first_placements=first
    )
    return JointPlan(
        datasets=datasets,
        sessions=tuple(scaled),
        screenings=tuple(screenings),
        scales=tuple(scales),
        alignments=alignments,
        fits=tuple(walk_fits),
        timings_ms={
            "walks_alone": (fitted - started) * 1e3,
            "placing": (time.perf_counter() - fitted) * 1e3,
        },
        scale_candidates=odometry_scale_candidates(datasets, tags),
        min_shared_tags=min_shared_tags,
        first_placements=first,
        pair_alignments=pairs,
    )


def _reusable_fits(
    initial: JointMap | None, fits: Sequence[WalkFit], params: SlamParams
) -> dict[str, WalkFit]:
    """The walks' fits made before with the same parameters, by dataset."""
    known = [part.fit for part in initial.parts if part.fit is not None] if initial else []
    return {fit.dataset: fit for fit in [*known, *fits] if fit.alone.params == params}


@dataclass(slots=True, kw_only=True, eq=False)
class JointInputs:
    """Several sessions prepared as one factor graph: the plan, the concatenated session, where
    each session's poses and detections start in it, the graph's inputs (each walk's noise
    scales from its own data, ``inputs.noise_scales``) and where LM starts (``start``: the walks'
    own optima placed by the plan, or a warm start)."""

    plan: JointPlan
    combined: Session
    starts: list[int]
    detection_starts: list[int]
    screening: Screening
    inputs: GraphInputs
    #: (S, 4) each walk's noise scales from its own data (and ``variance_scales``)
    base_scales: FloatArray
    #: start values: each keyframe's pose (K, 4, 4), the tags' and the split landmarks' by
    #: (walk, tag)
    start_T_keyframe: FloatArray
    start_T_tag: dict[int, FloatArray]
    #: (S,) each walk's disagreement factor to start from (1, or a warm start's)
    start_disagreement: FloatArray
    #: (N, 2) the variance each walk's stairs add to its odometry (``stairs.py``), and each
    #: walk's climbs
    added_variance: FloatArray
    climbs: tuple[tuple[Climb, ...], ...]
    #: (S,) each walk's cost at its own optimum under the joint map's model (its stairs' variance
    #: included): what its cost in the joint map is compared with (``weights.weigh_walks``)
    cost_alone: FloatArray

    def graph_inputs(
        self, params: SlamParams, splits: frozenset[tuple[int, int]], disagreement: FloatArray
    ) -> GraphInputs:
        """The joint graph with walk ``s``'s sightings of tag ``t`` on a landmark of their own
        for each ``(s, t)`` of ``splits``, and every walk's variances × its disagreement."""
        local: dict[int, int] = {}
        for landmark, (s, t) in enumerate(
            sorted(splits, key=lambda st: (self.plan.datasets[st[0]], st[1]))
        ):
            rows = np.flatnonzero(self.plan.sessions[s].detections.tag_id == t)
            for row in rows:
                local[int(row) + self.detection_starts[s]] = local_landmark_key(landmark)
        return GraphInputs(
            self.combined,
            params,
            screening=self.screening,
            chain_starts=self.starts,
            local_landmarks=local,
            noise_scales=self.base_scales * disagreement[:, None],
            odometry_added_variance=self.added_variance,
        )


def prepare_joint(
    sessions: Sequence[Session],
    params: SlamParams,
    *,
    names: Sequence[str] | None = None,
    scale_depths: bool = True,
    depth_scales: Mapping[str, float] | None = None,
    variance_scales: Mapping[str, tuple[float, float]] | None = None,
    min_shared_tags: int = MIN_SHARED_TAGS,
    initial: JointMap | None = None,
    fits: Sequence[WalkFit] = (),
    on_progress: ProgressCallback | None = None,
) -> JointInputs:
    """Plan ``sessions`` (:func:`plan_sessions`) and prepare their joint factor graph's inputs;
    ``variance_scales``: dataset → (tag, odometry) factors on top of each walk's own noise."""
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
    return joint_inputs(plan, params, variance_scales, initial)


def joint_inputs(
    plan: JointPlan,
    params: SlamParams,
    variance_scales: Mapping[str, tuple[float, float]] | None,
    initial: JointMap | None,
) -> JointInputs:
    base = np.stack([fit.noise_scales for fit in plan.fits])
    for s, dataset in enumerate(plan.datasets):
        tag_k, odometry_k = (variance_scales or {}).get(dataset, (1.0, 1.0))
        base[s] *= (odometry_k, odometry_k, tag_k, tag_k)
    graph = _JointGraph.of(plan, params, base)
    combined, starts = graph.combined, graph.starts
    added = graph.added_variance
    # start: each walk's own optimum, placed; each tag where the walks put it (mean position)
    ends = [*starts[1:], combined.num_poses]
    world_T_phone = np.concatenate(
        [
            a.place(fit.alone.world_T_phone)
            for a, fit in zip(plan.alignments, plan.fits, strict=True)
        ]
    )
    tag_positions: dict[int, list[FloatArray]] = {}
    tag_rotations: dict[int, FloatArray] = {}
    for alignment, fit in zip(plan.alignments, plan.fits, strict=True):
        for t, pose in fit.alone.tag_poses().items():
            placed = alignment.place(pose)
            tag_positions.setdefault(t, []).append(placed[:3, 3])
            tag_rotations.setdefault(t, placed[:3, :3])
    world_T_tag = {
        t: make_pose(tag_rotations[t], np.mean(np.stack(p), axis=0))
        for t, p in tag_positions.items()
    }
    disagreement = np.ones(len(plan.datasets))
    if initial is not None:
        previous = {part.dataset: part for part in initial.parts}
        new_T_previous = _frame_change(initial.map.tag_poses(), world_T_tag)
        if new_T_previous is not None:
            for s, dataset in enumerate(plan.datasets):
                part = previous.get(dataset)
                if (
                    part is None
                    or part.pose_rows.stop - part.pose_rows.start != ends[s] - starts[s]
                ):
                    continue
                world_T_phone[starts[s] : ends[s]] = (
                    new_T_previous @ initial.map.world_T_phone[part.pose_rows]
                )
                disagreement[s] = part.disagreement_factor
            for t, pose in initial.map.tag_poses().items():
                if t in world_T_tag:
                    world_T_tag[t] = new_T_previous @ pose
    return graph.inputs_from(
        world_T_phone,
        world_T_tag,
        disagreement,
        _costs_alone(plan, params, [added[a:b] for a, b in zip(starts, ends, strict=True)]),
    )


def joint_inputs_at(
    plan: JointPlan,
    params: SlamParams,
    base_scales: FloatArray,
    cost_alone: FloatArray,
    world_T_phone: FloatArray,
    world_T_tag: Mapping[int, FloatArray],
) -> JointInputs:
    """The joint graph's inputs of ``plan`` with each walk's noise scales ``base_scales``
    ((S, 4)) and cost alone ``cost_alone`` ((S,)), at the map ``world_T_phone`` ((N, 4, 4),
    the combined session's poses) and ``world_T_tag``: an optimum made elsewhere (the ISAM2
    engine's, ``incremental.served_map``), which the batch build's report, weighing and residuals
    then read as they read their own. ``plan.fits`` is not read."""
    graph = _JointGraph.of(plan, params, np.array(base_scales, dtype=np.float64))
    return graph.inputs_from(
        world_T_phone, dict(world_T_tag), np.ones(len(plan.datasets)), cost_alone
    )


@dataclass(slots=True, kw_only=True, eq=False)
class _JointGraph:
    """The walks of a plan laid out as one graph (no start yet)."""

    plan: JointPlan
    combined: Session
    starts: list[int]
    detection_starts: list[int]
    screening: Screening
    climbs: tuple[tuple[Climb, ...], ...]
    added_variance: FloatArray
    base_scales: FloatArray
    inputs: GraphInputs

    @classmethod
    def of(cls, plan: JointPlan, params: SlamParams, base_scales: FloatArray) -> _JointGraph:
        combined, starts, detection_starts = combine_sessions(plan)
        screening = combined_screening(plan, starts, detection_starts)
        climbs = tuple(tuple(walk_climbs(session)) for session in plan.sessions)
        added = np.concatenate(
            [
                stairs_variance(session, params, walk)
                for session, walk in zip(plan.sessions, climbs, strict=True)
            ]
        )
        inputs = GraphInputs(
            combined,
            params,
            screening=screening,
            chain_starts=starts,
            noise_scales=base_scales,
            odometry_added_variance=added,
        )
        return cls(
            plan=plan,
            combined=combined,
            starts=starts,
            detection_starts=detection_starts,
            screening=screening,
            climbs=climbs,
            added_variance=added,
            base_scales=base_scales,
            inputs=inputs,
        )

    def inputs_from(
        self,
        world_T_phone: FloatArray,
        world_T_tag: dict[int, FloatArray],
        disagreement: FloatArray,
        cost_alone: FloatArray,
    ) -> JointInputs:
        return JointInputs(
            plan=self.plan,
            combined=self.combined,
            starts=self.starts,
            detection_starts=self.detection_starts,
            screening=self.screening,
            inputs=self.inputs,
            base_scales=self.base_scales,
            start_T_keyframe=world_T_phone[self.inputs.keyframes],
            start_T_tag=world_T_tag,
            start_disagreement=disagreement,
            added_variance=self.added_variance,
            climbs=self.climbs,
            cost_alone=cost_alone,
        )


def _costs_alone(plan: JointPlan, params: SlamParams, added: Sequence[FloatArray]) -> FloatArray:
    """(S,) each walk's cost at its own optimum (``WalkFit.cost``), evaluated with its stairs'
    variance ``added`` when there is any (the joint map's model of its odometry)."""
    costs = np.array([fit.cost for fit in plan.fits])
    if not stairs_on(params):
        return costs
    fixed = dataclasses.replace(params, estimate_noise=False)
    for s, fit in enumerate(plan.fits):
        if not added[s].any():
            continue
        inputs = GraphInputs(
            plan.sessions[s],
            fixed,
            screening=plan.screenings[s],
            noise_scales=fit.noise_scales,
            odometry_added_variance=added[s],
        )
        values = values_from(
            inputs, fit.alone.world_T_phone[inputs.keyframes], fit.alone.tag_poses()
        )
        costs[s] = float(chain_costs(inputs, fixed, values)[0])
    return costs


def _frame_change(
    previous_T_tag: Mapping[int, FloatArray], new_T_tag: Mapping[int, FloatArray]
) -> FloatArray | None:
    """``new_T_previous``: the turn about +y and translation taking the previous map's frame to
    the new one, fitted on their common tags (None without two of them)."""
    common = sorted(set(previous_T_tag) & set(new_T_tag))
    if len(common) < 2:
        return None
    previous_p = np.stack([previous_T_tag[t][:3, 3] for t in common])
    new_p = np.stack([new_T_tag[t][:3, 3] for t in common])
    return weighted_similarity(
        previous_p, new_p, np.ones(len(common)), np.eye(4), scale=1.0
    ).map_T_world


def combine_sessions(plan: JointPlan) -> tuple[Session, list[int], list[int]]:
    """One session holding every session's poses (placed by its alignment, in the map frame) and
    detections, in plan order; its clock runs on across sessions. Also the first pose row and the
    first detection row of each session."""
    world_T_phone, timestamp_s, pose_id = [], [], []
    fields: dict[str, list[npt.NDArray[np.generic]]] = {
        f.name: [] for f in dataclasses.fields(TagDetections)
    }
    pois: list[PointOfInterest] = []
    starts, detection_starts = [], []
    pose_offset = frame_offset = detection_offset = id_offset = 0
    clock_s = 0.0
    for session, alignment in zip(plan.sessions, plan.alignments, strict=True):
        starts.append(pose_offset)
        detection_starts.append(detection_offset)
        world_T_phone.append(alignment.place(session.world_T_phone))
        times = session.timestamp_s - (session.timestamp_s[0] if session.num_poses else 0.0)
        timestamp_s.append(times + clock_s)
        pose_id.append(session.pose_id + id_offset)
        detections = session.detections
        for name, values in fields.items():
            column = getattr(detections, name)
            if name == "pose_index":
                column = column + pose_offset
            elif name == "frame_index":
                column = column + frame_offset
            values.append(column)
        pois.extend(
            dataclasses.replace(poi, pose_index=poi.pose_index + pose_offset)
            for poi in session.pois
        )
        pose_offset += session.num_poses
        detection_offset += len(detections)
        frame_offset += int(detections.frame_index.max()) + 1 if len(detections) else 0
        id_offset += int(session.pose_id.max()) + 1 if session.num_poses else 0
        clock_s = float(timestamp_s[-1][-1]) + SESSION_GAP_S if session.num_poses else clock_s
    combined = Session(
        map_id="+".join(plan.datasets),
        pose_id=np.concatenate(pose_id).astype(np.int64),
        timestamp_s=np.concatenate(timestamp_s),
        world_T_phone=np.concatenate(world_T_phone),
        detections=TagDetections(**{name: np.concatenate(v) for name, v in fields.items()}),
        pois=tuple(pois),
        warnings=tuple(
            f"{dataset}: {w}"
            for dataset, session in zip(plan.datasets, plan.sessions, strict=True)
            for w in session.warnings
        ),
    )
    return combined, starts, detection_starts


def combined_screening(
    plan: JointPlan, starts: list[int], detection_starts: list[int]
) -> Screening:
    """The sessions' own screenings, end to end (rows renumbered, warnings named): the joint
    graph's, as ``combine_sessions`` lays the sessions out."""
    rejections: list[Rejection] = []
    for s, screening in enumerate(plan.screenings):
        rejections.extend(
            dataclasses.replace(
                r,
                detection_index=r.detection_index + detection_starts[s],
                pose_index=r.pose_index + starts[s],
            )
            for r in screening.rejections
        )
    geometry = DetectionGeometry(
        **{
            f.name: np.concatenate([getattr(s.geometry, f.name) for s in plan.screenings])
            for f in dataclasses.fields(DetectionGeometry)
        }
    )
    return Screening(
        used=np.concatenate([s.used for s in plan.screenings]),
        rejections=tuple(rejections),
        geometry=geometry,
        warnings=tuple(
            f"{dataset}: {w}"
            for dataset, screening in zip(plan.datasets, plan.screenings, strict=True)
            for w in screening.warnings
        ),
    )
