"""Building maps: several mapping sessions of one building optimized together (§8, issue 15).

    joint = optimize_sessions([floor_2, desnat, occam_209], SlamParams(), names=[...])
    joint.map                      # a MapResult over every session's poses and the shared tags
    joint.parts[1].alignment       # how session 1 was placed in the map before optimizing

Each session keeps its own pose chain (no odometry joins two sessions), tags are landmarks shared
by every session that saw them, every keyframe of every session has its gravity factor, and one
prior on the first pose of the first session (the *reference*) fixes the gauge: the map frame is
the reference session's world frame.

Before optimizing, each other session is placed in the map by the tags it shares with the sessions
placed so far (:func:`align_session`): since both frames are gravity-aligned (+y up), only a turn
about +y and a translation are estimated, robustly (every shared tag's orientation, and every pair
of shared tags' horizontal direction, proposes a turn; the translation is the median over tags;
the proposal that most shared tags agree with wins, then a least-squares refit on those). An
alignment the shared tags do not support is refused with a reason (:class:`AlignmentError`): no
shared tag, fewer than ``min_shared_tags``, or too few of them agreeing.

A shared tag whose sightings in one session disagree with the map by more than
``ALIGNMENT_INLIER_M`` (a tag moved or re-printed between two walks) is not allowed to drag the
others: that session's sightings of it get a landmark of their own (solved, not a tag of the map),
and the map's warnings say so.

Tag size. Some sessions' tag poses imply another tag side than the prints have (the app assumed
one; README, "Screening"), which puts that session's tags too near or too far along each line of
sight, and so pulls the sessions apart where they share tags. Per session, :func:`tag_depth_scale`
estimates what the session's own data supports: the factor on its camera-to-tag translations that
makes its sightings of each tag from different places agree best, given its own odometry (VIO is
metric). A session with too little parallax, or whose factor is within 5% of 1, keeps factor 1
(the poses as given): on the three real mac-building sessions the parallax is too small to tell
(docs/multi-session.md), so their poses are used as given.

In a map of several sessions, a burst of k sightings of one tag (consecutive sightings less than
3 s apart: one viewpoint, one PnP bias) weighs as √k sightings: each gets its variance multiplied
by √k (:func:`sighting_burst_sizes`), so a walk that lingers at each tag does not outvote one that
passes by.

Each session's odometry is weighed by what its residuals support: after a first optimization with
the default variances, a session whose odometry residuals (chi² per degree of freedom) are larger
than the best-fitting session's gets its odometry variances raised by that ratio (a
variance-component estimate; at most ``MAX_ODOMETRY_VARIANCE_SCALE``), and the map is optimized
again from there. A walk whose odometry drifted more then bends to the others' shared tags instead
of dragging them.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from app.domain.errors import InvisibleMapError
from app.domain.frames import FloatArray, make_pose, rotation_about_y
from app.domain.mapping.map_result import MapResult, Rejection
from app.domain.mapping.params import SlamParams
from app.domain.mapping.screening import DetectionGeometry, Screening, screen_detections
from app.domain.mapping.slam import GraphInputs, local_landmark_key, optimize_graph_inputs
from app.domain.upload.session import PointOfInterest, Session, TagDetections

IntArray = npt.NDArray[np.int64]
BoolArray = npt.NDArray[np.bool_]

#: Fewest tags a session must share with the map to be placed in it.
MIN_SHARED_TAGS = 2
#: A shared tag agrees with an alignment when its position, aligned, is within this of the map's, m.
ALIGNMENT_INLIER_M = 1.0
#: Fewest of the shared tags that must agree with the alignment, as a fraction of them.
MIN_INLIER_FRACTION = 0.5
#: Two shared tags closer than this horizontally propose no turn (their direction is noise), m.
MIN_PAIR_BASELINE_M = 2.0
#: Largest factor by which a session's odometry variances are raised when its odometry residuals
#: are larger than the other sessions' (see :func:`optimize_sessions`).
MAX_ODOMETRY_VARIANCE_SCALE = 100.0
#: Sightings of one tag less than this apart (s) are one burst (``sighting_burst_sizes``).
BURST_GAP_S = 3.0
#: A burst of k sightings weighs as k^(1 − power) sightings (each one's variance × k^power): 0.5,
#: between independent sightings (0: best on simulated walks, whose noise is drawn independently
#: per sighting) and fully correlated ones (1: best on the real mac-building walks);
#: docs/multi-session.md has both ends' numbers.
BURST_WEIGHT_POWER = 0.5
#: Time between consecutive sessions in the joint map's clock, s (no odometry spans it).
SESSION_GAP_S = 1.0
#: Parallax (Σ‖Δ camera-to-tag vector‖² over pairs of sightings of a tag) below which a session's
#: tag depth scale is not estimated, m².
MIN_SCALE_PARALLAX_M2 = 1.0
#: A depth scale closer to 1 than this is noise (±3% on simulated walks whose sizes are right); the
#: poses are used as given.
MIN_DEPTH_SCALE_CHANGE = 0.05
#: Sightings of a tag further apart in time than this are not compared for the scale (VIO drift), s.
SCALE_PAIR_WINDOW_S = 15.0


class AlignmentError(InvisibleMapError):
    """A session that cannot be placed in the map. ``reason``: ``no_shared_tags``,
    ``too_few_shared_tags`` or ``inconsistent_shared_tags``; ``dataset``: which session."""

    def __init__(self, dataset: str, reason: str, detail: str) -> None:
        self.dataset = dataset
        self.reason = reason
        self.detail = detail
        super().__init__(f"session {dataset!r} cannot be placed in the map ({reason}): {detail}")


@dataclass(frozen=True, slots=True, kw_only=True)
class SessionAlignment:
    """Where a session's world frame sits in the map, before optimizing.

    map_T_world: (4, 4) a turn about +y by ``yaw_rad`` and a translation, m.
    shared_tags: tags the session shares with the map so far; inlier_tags: those that agree.
    residual_m: (len(shared_tags),) each shared tag's distance from the map's after aligning, m.
    """

    dataset: str
    map_T_world: FloatArray
    yaw_rad: float
    shared_tags: tuple[int, ...]
    inlier_tags: tuple[int, ...]
    residual_m: FloatArray

    @property
    def outlier_tags(self) -> tuple[int, ...]:
        return tuple(t for t in self.shared_tags if t not in set(self.inlier_tags))


@dataclass(frozen=True, slots=True, kw_only=True)
class SessionPart:
    """One session's share of a joint map.

    pose_rows: the rows of the joint map's pose arrays that are this session's, in order.
    detection_rows: the rows of the joint session's detections that are this session's.
    tag_depth_scale: the factor applied to its camera-to-tag translations (1: as given).
    odometry_variance_scale: the factor on its odometry variances (what its residuals support).
    local_tags: shared tags whose sightings here disagreed with the map and got their own
        landmark (not the map's).
    """

    dataset: str
    alignment: SessionAlignment
    pose_rows: slice
    detection_rows: slice
    tag_ids: tuple[int, ...]
    tag_depth_scale: float
    odometry_variance_scale: float
    local_tags: tuple[int, ...]
    detections_used: int
    detections_rejected: int
    tag_chi2_mean: float

    @property
    def is_reference(self) -> bool:
        return not self.alignment.shared_tags and self.pose_rows.start == 0


@dataclass(frozen=True, slots=True, kw_only=True)
class JointMap:
    """A map of several sessions: the optimized map, the sessions it was made of, and the
    concatenated session it was optimized as (poses and detections in session order)."""

    map: MapResult
    parts: tuple[SessionPart, ...]
    combined: Session
    sessions: tuple[Session, ...]
    detection_mask: BoolArray

    def part(self, dataset: str) -> SessionPart:
        for part in self.parts:
            if part.dataset == dataset:
                return part
        raise KeyError(f"no session {dataset!r} in the map")

    def session_tag_poses(self, dataset: str) -> dict[int, FloatArray]:
        """The joint map's tags that ``dataset`` saw (and kept), by id."""
        tags = set(self.part(dataset).tag_ids)
        return {t: pose for t, pose in self.map.tag_poses().items() if t in tags}

    def session_masks(self) -> list[BoolArray]:
        return [self.detection_mask[part.detection_rows] for part in self.parts]


# --------------------------------------------------------------------------- alignment


def observed_tag_poses(session: Session, used: BoolArray | None = None) -> dict[int, FloatArray]:
    """Each tag's pose in the session's world from its raw sightings: the median position and
    the first sighting's rotation. ``used``: (M,) which detections count (default all)."""
    world_T_tag = session.world_T_tag_observed()
    rows = np.arange(len(session.detections)) if used is None else np.flatnonzero(used)
    poses: dict[int, FloatArray] = {}
    tag_ids = session.detections.tag_id
    for tag_id in np.unique(tag_ids[rows]):
        tag_rows = rows[tag_ids[rows] == tag_id]
        pose = world_T_tag[tag_rows[0]].copy()
        pose[:3, 3] = np.median(world_T_tag[tag_rows, :3, 3], axis=0)
        poses[int(tag_id)] = pose
    return poses


def yaw_of(R: FloatArray) -> float:
    """The turn about +y closest to rotation ``R``, rad."""
    return math.atan2(float(R[0, 2] - R[2, 0]), float(R[0, 0] + R[2, 2]))


def align_session(
    dataset: str,
    world_T_tag: Mapping[int, FloatArray],
    map_T_tag: Mapping[int, FloatArray],
    *,
    min_shared_tags: int = MIN_SHARED_TAGS,
    inlier_m: float = ALIGNMENT_INLIER_M,
    min_inlier_fraction: float = MIN_INLIER_FRACTION,
) -> SessionAlignment:
    """``map_T_world``: a turn about +y and a translation placing the session's tags
    (``world_T_tag``) on the map's (``map_T_tag``), from the tags both have (see the module
    docstring). Raises :class:`AlignmentError` when the shared tags do not support one."""
    shared = tuple(sorted(set(world_T_tag) & set(map_T_tag)))
    if not shared:
        raise AlignmentError(dataset, "no_shared_tags", "it shares no tag with the map")
    if len(shared) < min_shared_tags:
        raise AlignmentError(
            dataset,
            "too_few_shared_tags",
            f"it shares {len(shared)} tag(s) ({_ids(shared)}) with the map; at least "
            f"{min_shared_tags} are needed",
        )
    world_p = np.stack([world_T_tag[t][:3, 3] for t in shared])
    map_p = np.stack([map_T_tag[t][:3, 3] for t in shared])
    candidates = [yaw_of(map_T_tag[t][:3, :3] @ world_T_tag[t][:3, :3].T) for t in shared]
    for i in range(len(shared)):
        for j in range(i + 1, len(shared)):
            d_world, d_map = world_p[j] - world_p[i], map_p[j] - map_p[i]
            if min(math.hypot(d_world[0], d_world[2]), math.hypot(d_map[0], d_map[2])) < (
                MIN_PAIR_BASELINE_M
            ):
                continue
            # the turn about +y taking the horizontal direction d_world to d_map
            candidates.append(math.atan2(d_world[2], d_world[0]) - math.atan2(d_map[2], d_map[0]))
    best: tuple[int, float, float, FloatArray] | None = None
    for yaw in candidates:
        map_T_world = _yaw_translation(yaw, world_p, map_p)
        residual = _residuals_m(map_T_world, world_p, map_p)
        inliers = int(np.sum(residual <= inlier_m))
        score = (inliers, -float(np.median(residual)))
        if best is None or score > (best[0], best[1]):
            best = (inliers, score[1], yaw, map_T_world)
    assert best is not None
    inlier = _residuals_m(best[3], world_p, map_p) <= inlier_m
    needed = max(min_shared_tags, math.ceil(min_inlier_fraction * len(shared)))
    if int(inlier.sum()) < needed:
        residual = _residuals_m(best[3], world_p, map_p)
        listed = ", ".join(f"{t}: {r:.2f} m" for t, r in zip(shared, residual, strict=True))
        raise AlignmentError(
            dataset,
            "inconsistent_shared_tags",
            f"of its {len(shared)} shared tags, at most {int(inlier.sum())} agree within "
            f"{inlier_m:g} m on one placement ({needed} needed); distances after the best "
            f"placement: {listed}",
        )
    yaw = _refit_yaw(best[2], world_p[inlier], map_p[inlier])
    map_T_world = _yaw_translation(yaw, world_p[inlier], map_p[inlier], mean=True)
    residual = _residuals_m(map_T_world, world_p, map_p)
    return SessionAlignment(
        dataset=dataset,
        map_T_world=map_T_world,
        yaw_rad=yaw,
        shared_tags=shared,
        inlier_tags=tuple(t for t, ok in zip(shared, residual <= inlier_m, strict=True) if ok),
        residual_m=residual,
    )


def _yaw_translation(
    yaw: float, world_p: FloatArray, map_p: FloatArray, *, mean: bool = False
) -> FloatArray:
    R = rotation_about_y(yaw)
    offsets = map_p - world_p @ R.T
    return make_pose(R, offsets.mean(axis=0) if mean else np.median(offsets, axis=0))


def _residuals_m(map_T_world: FloatArray, world_p: FloatArray, map_p: FloatArray) -> FloatArray:
    aligned = world_p @ map_T_world[:3, :3].T + map_T_world[:3, 3]
    return np.asarray(np.linalg.norm(aligned - map_p, axis=1), dtype=np.float64)


def _refit_yaw(yaw: float, world_p: FloatArray, map_p: FloatArray) -> float:
    """Least-squares turn about +y between two horizontal point sets (2D Procrustes), or ``yaw``
    when the points have no horizontal spread to fix it."""
    a = world_p[:, [0, 2]] - world_p[:, [0, 2]].mean(axis=0)
    b = map_p[:, [0, 2]] - map_p[:, [0, 2]].mean(axis=0)
    if len(a) < 2 or float(np.sum(a**2)) < MIN_PAIR_BASELINE_M**2:
        return yaw
    # R_y(θ) maps (x, z) to (x cosθ + z sinθ, −x sinθ + z cosθ)
    cross = float(np.sum(a[:, 1] * b[:, 0] - a[:, 0] * b[:, 1]))
    dot = float(np.sum(a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1]))
    return math.atan2(cross, dot)


# --------------------------------------------------------------------------- tag size


def tag_depth_scale(session: Session, used: BoolArray | None = None) -> float:
    """The factor on the session's camera-to-tag translations that makes its sightings of each
    tag, from different places within ``SCALE_PAIR_WINDOW_S``, agree best given its odometry
    (least squares over pairs of sightings), or 1.0 when the pairs' parallax is below
    ``MIN_SCALE_PARALLAX_M2`` (the data cannot tell) or the factor is within
    ``MIN_DEPTH_SCALE_CHANGE`` of 1."""
    detections = session.detections
    rows = np.arange(len(detections)) if used is None else np.flatnonzero(used)
    world_T_phone = session.world_T_phone[detections.pose_index[rows]]
    world_p_phone = world_T_phone[:, :3, 3]
    world_v_tag = np.einsum(
        "nij,nj->ni", world_T_phone[:, :3, :3], detections.phone_T_tag[rows, :3, 3]
    )
    times = detections.timestamp_s[rows]
    tag_ids = detections.tag_id[rows]
    numerator = denominator = 0.0
    for tag_id in np.unique(tag_ids):
        k = np.flatnonzero(tag_ids == tag_id)
        if k.size < 2:
            continue
        i, j = np.triu_indices(k.size, 1)
        close = np.abs(times[k[j]] - times[k[i]]) <= SCALE_PAIR_WINDOW_S
        d_phone = world_p_phone[k[j[close]]] - world_p_phone[k[i[close]]]
        d_tag = world_v_tag[k[j[close]]] - world_v_tag[k[i[close]]]
        numerator -= float(np.sum(d_phone * d_tag))
        denominator += float(np.sum(d_tag * d_tag))
    if denominator < MIN_SCALE_PARALLAX_M2:
        return 1.0
    scale = numerator / denominator
    return scale if abs(scale - 1.0) > MIN_DEPTH_SCALE_CHANGE else 1.0


def scaled_tag_depths(session: Session, scale: float) -> Session:
    """``session`` with every camera-to-tag translation multiplied by ``scale``."""
    if scale == 1.0:
        return session
    detections = session.detections
    camera_T_tag = detections.camera_T_tag.copy()
    phone_T_tag = detections.phone_T_tag.copy()
    camera_T_tag[:, :3, 3] *= scale
    phone_T_tag[:, :3, 3] *= scale
    return dataclasses.replace(
        session,
        detections=dataclasses.replace(
            detections, camera_T_tag=camera_T_tag, phone_T_tag=phone_T_tag
        ),
    )


# --------------------------------------------------------------------------- sighting bursts


def sighting_burst_sizes(session: Session, used: BoolArray) -> FloatArray:
    """(M,) for each used detection, how many used sightings of its tag its *burst* holds: the
    sightings of one tag with no gap longer than ``BURST_GAP_S`` between consecutive ones (the
    phone looking at the tag for a while, from about one place); 1 for unused detections.

    Sightings of one burst are not independent measurements (the same viewpoint, the same PnP
    bias), so in a map of several sessions each one's tag variance is multiplied by its burst's
    size to the power ``BURST_WEIGHT_POWER``: a burst of k weighs as √k sightings, and a walk that
    lingers at each tag (desnat_straight_once: 10 sightings per burst) does not outvote a walk
    that passes by (floor_2_straight: 1.1) as much.
    """
    detections = session.detections
    size = np.ones(len(detections))
    rows_used = np.flatnonzero(used)
    for tag_id in np.unique(detections.tag_id[rows_used]):
        rows = rows_used[detections.tag_id[rows_used] == tag_id]
        order = np.argsort(detections.timestamp_s[rows], kind="stable")
        rows = rows[order]
        burst = np.concatenate(
            [[0], np.cumsum(np.diff(detections.timestamp_s[rows]) > BURST_GAP_S)]
        )
        counts = np.bincount(burst)
        size[rows] = counts[burst]
    return size


# --------------------------------------------------------------------------- the joint map


@dataclass(frozen=True, slots=True, kw_only=True)
class JointPlan:
    """Everything decided before optimizing: the order (reference first), each session's
    screening, depth scale and alignment, and which sightings get a landmark of their own."""

    datasets: tuple[str, ...]
    sessions: tuple[Session, ...]
    screenings: tuple[Screening, ...]
    scales: tuple[float, ...]
    alignments: tuple[SessionAlignment, ...]
    local_tags: tuple[tuple[int, ...], ...]


def plan_sessions(
    sessions: Sequence[Session],
    params: SlamParams,
    *,
    names: Sequence[str] | None = None,
    scale_depths: bool = True,
    depth_scales: Mapping[str, float] | None = None,
    min_shared_tags: int = MIN_SHARED_TAGS,
) -> JointPlan:
    """Screen each session on its own, estimate its tag depth scale, and place each in the map
    in turn: the first session is the reference; then, repeatedly, the one sharing the most tags
    with the sessions placed so far. Raises :class:`AlignmentError` for the first session that
    cannot be placed (after trying every other)."""
    if not sessions:
        raise InvisibleMapError("a map needs at least one session")
    datasets = tuple(names) if names is not None else tuple(s.map_id for s in sessions)
    if len(datasets) != len(sessions):
        raise ValueError(f"{len(datasets)} names for {len(sessions)} sessions")
    if len(set(datasets)) != len(datasets):
        raise InvisibleMapError(f"a session is in the map twice: {list(datasets)}")
    screenings = [screen_detections(s.detections, params) for s in sessions]
    scales = [
        tag_depth_scale(s, screening.used) if scale_depths else 1.0
        for s, screening in zip(sessions, screenings, strict=True)
    ]
    for s, dataset in enumerate(datasets):
        if depth_scales and dataset in depth_scales:
            scales[s] = float(depth_scales[dataset])
    scaled = [scaled_tag_depths(s, k) for s, k in zip(sessions, scales, strict=True)]
    observed = [
        observed_tag_poses(s, screening.used)
        for s, screening in zip(scaled, screenings, strict=True)
    ]
    order = [0]
    alignments: dict[int, SessionAlignment] = {
        0: SessionAlignment(
            dataset=datasets[0],
            map_T_world=np.eye(4),
            yaw_rad=0.0,
            shared_tags=(),
            inlier_tags=(),
            residual_m=np.empty(0),
        )
    }
    map_positions: dict[int, list[FloatArray]] = {t: [p] for t, p in observed[0].items()}
    waiting = list(range(1, len(sessions)))
    while waiting:
        map_T_tag = {t: _median_pose(poses) for t, poses in map_positions.items()}
        waiting.sort(key=lambda s: -len(set(observed[s]) & set(map_T_tag)))
        failure: AlignmentError | None = None
        for s in waiting:
            try:
                alignment = align_session(
                    datasets[s], observed[s], map_T_tag, min_shared_tags=min_shared_tags
                )
            except AlignmentError as err:
                failure = failure or err
                continue
            alignments[s] = alignment
            order.append(s)
            waiting.remove(s)
            outliers = set(alignment.outlier_tags)
            for t, pose in observed[s].items():
                if t not in outliers:
                    map_positions.setdefault(t, []).append(alignment.map_T_world @ pose)
            break
        else:
            assert failure is not None
            raise failure
    return JointPlan(
        datasets=tuple(datasets[s] for s in order),
        sessions=tuple(scaled[s] for s in order),
        screenings=tuple(screenings[s] for s in order),
        scales=tuple(scales[s] for s in order),
        alignments=tuple(alignments[s] for s in order),
        local_tags=tuple(alignments[s].outlier_tags for s in order),
    )


def _median_pose(poses: list[FloatArray]) -> FloatArray:
    pose = poses[0].copy()
    pose[:3, 3] = np.median(np.stack([p[:3, 3] for p in poses]), axis=0)
    return pose


@dataclass(slots=True, kw_only=True, eq=False)
class JointInputs:
    """Several sessions prepared as one factor graph: the plan, the concatenated session, where
    each session's poses and detections start in it, and the graph's inputs (their
    ``odometry_variance_scale`` set by :meth:`reweigh`)."""

    plan: JointPlan
    combined: Session
    starts: list[int]
    detection_starts: list[int]
    screening: Screening
    inputs: GraphInputs
    #: (S,) each session's odometry variance factor (1 until :meth:`reweigh`)
    odometry_scales: list[float]

    def reweigh(self, chi2: FloatArray) -> FloatArray | None:
        """Each session's odometry weighed by its residuals (``chi2``: (K−1,) the odometry
        factors' chi² at the defaults' optimum): the new (K−1,) variance scales for
        ``inputs.odometry_variance_scale``, or None when every session keeps 1."""
        per_dof = _odometry_chi2_per_dof(
            self.inputs.keyframes, chi2, self.starts, self.combined.num_poses
        )
        self.odometry_scales = _odometry_variance_scales(per_dof)
        if all(k == 1.0 for k in self.odometry_scales):
            return None
        scale_by_pose = np.ones(self.combined.num_poses)
        for s, k in enumerate(self.odometry_scales):
            start = self.starts[s]
            scale_by_pose[start : start + self.plan.sessions[s].num_poses] = k
        return np.asarray(scale_by_pose[self.inputs.keyframes[:-1]], dtype=np.float64)


def prepare_joint(
    sessions: Sequence[Session],
    params: SlamParams,
    *,
    names: Sequence[str] | None = None,
    scale_depths: bool = True,
    depth_scales: Mapping[str, float] | None = None,
    variance_scales: Mapping[str, tuple[float, float]] | None = None,
    min_shared_tags: int = MIN_SHARED_TAGS,
) -> JointInputs:
    """Plan ``sessions`` (:func:`plan_sessions`) and prepare their joint factor graph's inputs;
    ``variance_scales``: dataset → (tag, odometry) variance factors to use as given."""
    plan = plan_sessions(
        sessions,
        params,
        names=names,
        scale_depths=scale_depths,
        depth_scales=depth_scales,
        min_shared_tags=min_shared_tags,
    )
    combined, starts, detection_starts = combine_sessions(plan)
    screening = _combined_screening(plan, starts, detection_starts)
    local: dict[int, int] = {}
    landmark = 0
    for s, tags in enumerate(plan.local_tags):
        session = plan.sessions[s]
        for tag_id in tags:
            key = local_landmark_key(landmark)
            landmark += 1
            for row in np.flatnonzero(session.detections.tag_id == tag_id):
                local[int(row) + detection_starts[s]] = key
    given = dict(variance_scales or {})
    tag_variance_scale = np.ones(len(combined.detections))
    odometry_variance_scale = np.ones(combined.num_poses)
    odometry_scales = []
    several = len(plan.datasets) > 1
    for s, dataset in enumerate(plan.datasets):
        tag_k, odometry_k = given.get(dataset, (1.0, 1.0))
        detections = slice(
            detection_starts[s], detection_starts[s] + len(plan.sessions[s].detections)
        )
        burst = sighting_burst_sizes(plan.sessions[s], plan.screenings[s].used) if several else 1.0
        tag_variance_scale[detections] = tag_k * np.power(burst, BURST_WEIGHT_POWER)
        odometry_variance_scale[starts[s] : starts[s] + plan.sessions[s].num_poses] = odometry_k
        odometry_scales.append(float(odometry_k))
    inputs = GraphInputs(
        combined,
        params,
        screening=screening,
        chain_starts=starts,
        local_landmarks=local,
        tag_variance_scale=tag_variance_scale,
        odometry_variance_scale=odometry_variance_scale,
    )
    return JointInputs(
        plan=plan,
        combined=combined,
        starts=starts,
        detection_starts=detection_starts,
        screening=screening,
        inputs=inputs,
        odometry_scales=odometry_scales,
    )


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
) -> JointMap:
    """Optimize ``sessions`` into one map (see the module docstring). One session gives the map
    :func:`app.domain.mapping.slam.optimize_session` gives (with its depth scale applied).
    ``reweight``: weigh each session's odometry by its residuals (unless ``variance_scales``
    gives the factors)."""
    params = params or SlamParams()
    started = time.perf_counter()
    joint = prepare_joint(
        sessions,
        params,
        names=names,
        scale_depths=scale_depths,
        depth_scales=depth_scales,
        variance_scales=variance_scales,
        min_shared_tags=min_shared_tags,
    )
    plan, combined, screening = joint.plan, joint.combined, joint.screening
    starts, detection_starts = joint.starts, joint.detection_starts
    result = optimize_graph_inputs(
        joint.inputs,
        params,
        started=started,
        reweigh_odometry=(
            joint.reweigh if reweight and len(plan.datasets) > 1 and not variance_scales else None
        ),
    )
    odometry_scales = joint.odometry_scales
    warnings = list(result.warnings)
    for s, dataset in enumerate(plan.datasets):
        if plan.scales[s] != 1.0:
            warnings.append(
                f"{dataset}: camera-to-tag distances scaled by {plan.scales[s]:.3f} (what its "
                f"sightings and odometry support; the tag size the app assumed differs)"
            )
        if plan.local_tags[s]:
            residual = dict(
                zip(plan.alignments[s].shared_tags, plan.alignments[s].residual_m, strict=True)
            )
            listed = ", ".join(f"{t} ({residual[t]:.2f} m)" for t in plan.local_tags[s])
            warnings.append(
                f"{dataset}: its sightings of tags {listed} disagree with the other sessions' and "
                f"do not move the map's (moved or re-printed tags?)"
            )
    result = dataclasses.replace(result, warnings=tuple(warnings))
    parts = []
    ends = [*starts[1:], combined.num_poses]
    detection_ends = [*detection_starts[1:], len(combined.detections)]
    tag_chi2_by_row = dict(
        zip(
            result.residuals.tag_detection_index.tolist(),
            result.residuals.tag_chi2.tolist(),
            strict=True,
        )
    )
    for s, dataset in enumerate(plan.datasets):
        rows = slice(detection_starts[s], detection_ends[s])
        used = screening.used[rows]
        session_chi2 = [
            tag_chi2_by_row[r] for r in range(rows.start, rows.stop) if r in tag_chi2_by_row
        ]
        kept = set(result.tag_ids.tolist())
        parts.append(
            SessionPart(
                dataset=dataset,
                alignment=plan.alignments[s],
                pose_rows=slice(starts[s], ends[s]),
                detection_rows=rows,
                tag_ids=tuple(
                    sorted(
                        {int(t) for t in plan.sessions[s].detections.tag_id[used]}
                        - set(plan.local_tags[s])
                        & kept
                    )
                ),
                tag_depth_scale=plan.scales[s],
                odometry_variance_scale=odometry_scales[s],
                local_tags=plan.local_tags[s],
                detections_used=int(used.sum()),
                detections_rejected=int((~used).sum()),
                tag_chi2_mean=float(np.mean(session_chi2)) if session_chi2 else math.nan,
            )
        )
    return JointMap(
        map=result,
        parts=tuple(parts),
        combined=combined,
        sessions=plan.sessions,
        detection_mask=screening.used,
    )


def _odometry_chi2_per_dof(
    keyframes: IntArray, chi2: FloatArray, starts: list[int], num_poses: int
) -> FloatArray:
    """(S,) each session's mean odometry chi² per degree of freedom, from the chi² of the
    factors between consecutive ``keyframes`` (0 between sessions)."""
    first, second = keyframes[:-1], keyframes[1:]
    ends = [*starts[1:], num_poses]
    values = []
    for start, end in zip(starts, ends, strict=True):
        in_session = (first >= start) & (second < end)
        values.append(float(np.mean(chi2[in_session])) / 6.0 if in_session.any() else 0.0)
    return np.array(values)


def _odometry_variance_scales(chi2_per_dof: FloatArray) -> list[float]:
    """Each session's odometry variance factor: its chi² per dof over the smallest session's
    (a variance-component estimate that keeps the best-fitting session at the defaults), within
    [1, ``MAX_ODOMETRY_VARIANCE_SCALE``]."""
    reference = float(np.min(chi2_per_dof))
    if not reference > 0:
        return [1.0] * len(chi2_per_dof)
    return [float(np.clip(c / reference, 1.0, MAX_ODOMETRY_VARIANCE_SCALE)) for c in chi2_per_dof]


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
        world_T_phone.append(alignment.map_T_world @ session.world_T_phone)
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


def _combined_screening(
    plan: JointPlan, starts: list[int], detection_starts: list[int]
) -> Screening:
    """The sessions' own screenings, end to end (rows renumbered, warnings named)."""
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


def _ids(ids: Sequence[int]) -> str:
    return ", ".join(str(i) for i in ids)


__all__ = [
    "AlignmentError",
    "JointInputs",
    "JointMap",
    "SessionAlignment",
    "SessionPart",
    "align_session",
    "optimize_sessions",
    "plan_sessions",
    "prepare_joint",
    "tag_depth_scale",
]
