"""Building maps: several mapping sessions of one building optimized together (§8, issues 15, 25).

    joint = optimize_sessions([floor_2, desnat, occam_209], SlamParams(), names=[...])
    joint.map                      # a MapResult over every session's poses and the shared tags
    joint.parts[1].alignment       # how session 1 was placed in the map before optimizing
    joint.parts[1].noise           # its noise, as its own data support it
    joint.parts[1].alone           # its own map, alone: what the report compares with
    optimize_sessions([..., new_walk], initial=joint)   # the same map, from the last optimum

The map is the optimum of one graph over all the walks, and nothing about it depends on the order
the walks are given in, nor on which walk fixes the gauge (that only says which walk's world frame
the map is drawn in: the first one's). How each step stays free of order:

1. *Each walk alone.* Each walk is screened on its own (its tags' effective side from its own
   sightings), its tag depth scale estimated from its own sightings (:func:`tag_depth_scale`), and
   optimized alone with its noise estimated from its own residuals (``noise.py``:
   variance-component estimation; ``params.estimate_noise``). This is the walk's own map and its
   noise: a walk's weight in the building comes from its own data, not from the others'.
2. *Placing the walks together* (:func:`align_walks`). Every pair of walks that shares tags is
   aligned by a turn about +y and a translation (both frames are gravity-aligned) robustly
   (:func:`align_session`, on the walks' own optimized tags); a spanning tree of the best pairs
   gives a first placement, and an iteratively reweighted fit of all walks to all shared tags at
   once refines it. The result is the same for any order (the fit is to a fixed point; ties are
   broken by the walks' names, never by their position). A walk no other walk's tags place is
   refused with the reason (:class:`AlignmentError`).
3. *Odometry scale* (:func:`odometry_scale_candidates`, then ``_tested_scales``). ARKit's scale
   drifts by a percent or two, which the odometry's random-walk noise does not describe. Each
   pair of walks sharing ≥ 3 tags gives their relative scale (symmetrically); the walks' scales
   are the least-squares solution about their median; a walk off significantly is rescaled only
   if that lowers the joint map's cost beyond χ²₁(0.999) (drift can look like scale on the shared
   tags; a real scale error lowers the cost of the whole graph), in maps of ≥ 3 walks, for walks
   mostly inside the overlap (``MIN_SCALE_COVERAGE``).
4. *One graph.* The walks' poses and detections are concatenated (:func:`combine_sessions`); each
   keeps its own pose chain and its own noise (``GraphInputs.noise_scales``), tags are shared.
   It is solved from the walks' own optima placed by step 2 (or, with ``initial``, from the last
   version's optimum: a warm start), to convergence in metres and radians.
5. *A tag that moved between walks* (re-printed, re-hung) shows as one walk's sightings of it
   disagreeing with the map beyond its noise (mean χ² per sighting above the 99.9% quantile of a
   6-D residual, once divided by the walk's own level of disagreement). The worst such (walk,
   tag) gets a landmark of its own (solved, not a tag of the map), and the map is solved again,
   until none is left. Of two walks that disagree, the one with the larger normalized residual
   (the looser one) is split off; the map's warnings name it.
6. *A walk whose disagreement its own noise does not explain is down-weighted* (never silently:
   ``SessionPart.weighting`` says why). Joining adds constraints to each walk; if its noise
   were right, its cost would grow by about the redundancy it gains, Δr (a shared tag seen by m
   walks gives 6(m − 1) degrees of freedom, shared by the walks in proportion to how loosely each
   holds it; 4 per extra walk go to placing it). A walk whose cost grows by more than χ²(Δr)'s
   99% quantile gets all its variances multiplied by ``(cost joint − cost alone) / Δr`` (a
   variance component of its own, estimated in the joint map; at least 1, at most
   ``MAX_DISAGREEMENT_FACTOR``), and the map is solved again.

docs/multi-session.md explains each step and what it measured.

In a map of several sessions, a burst of k sightings of one tag (consecutive sightings less than
3 s apart) weighs as √k sightings (``screening.burst_variance_scale``), as in a map of one.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from app.domain.errors import InvisibleMapError
from app.domain.frames import FloatArray, make_pose, rotation_about_y, se3_inverse
from app.domain.mapping.map_result import MapResult, Rejection
from app.domain.mapping.noise import NoiseEstimate, chi2_quantile
from app.domain.mapping.params import SlamParams
from app.domain.mapping.screening import (
    BURST_GAP_S,
    BURST_WEIGHT_POWER,
    DetectionGeometry,
    Screening,
    screen_detections,
)
from app.domain.mapping.screening import sighting_burst_sizes as _burst_sizes
from app.domain.mapping.slam import (
    GraphInputs,
    Solution,
    chain_costs,
    local_landmark_key,
    map_result,
    refine,
    solution_residuals,
    solve,
    solved_poses,
    values_from,
)
from app.domain.upload.session import PointOfInterest, Session, TagDetections

IntArray = npt.NDArray[np.int64]
BoolArray = npt.NDArray[np.bool_]

#: Fewest tags two walks must share for one to place the other.
MIN_SHARED_TAGS = 2
#: A shared tag agrees with an alignment when its position, aligned, is within this of the map's, m.
ALIGNMENT_INLIER_M = 1.0
#: Fewest of the shared tags that must agree with the alignment, as a fraction of them.
MIN_INLIER_FRACTION = 0.5
#: Two shared tags closer than this horizontally propose no turn (their direction is noise), m.
MIN_PAIR_BASELINE_M = 2.0
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
#: Largest factor by which a walk's variances are raised when it disagrees with the others.
MAX_DISAGREEMENT_FACTOR = 100.0
#: A walk is down-weighted only when its cost grew by more than this quantile of χ²(Δr) allows.
DISAGREEMENT_QUANTILE = 0.99
#: A walk's sightings of a shared tag whose mean χ² per sighting is above this quantile of a 6-D
#: residual's get a landmark of their own.
SPLIT_QUANTILE = 0.999
#: Degrees of freedom of placing one more walk: a turn about +y and a translation.
PLACEMENT_DOF = 4.0
#: Most times the joint map is solved (each after a change of weights or a split tag).
MAX_JOINT_ROUNDS = 12
#: A change of a walk's disagreement factor smaller than this fraction is not worth a round.
DISAGREEMENT_TOLERANCE = 0.05
#: A walk's odometry is rescaled when its scale against the other walks' is off by more than
#: this many standard errors of the placement's fit …
SCALE_SIGMAS = 3.0
#: … and by more than this fraction …
MIN_ODOMETRY_SCALE_CHANGE = 0.005
#: … in a map of at least this many walks (of two whose scales differ, the data cannot tell
#: whose is right) …
MIN_WALKS_FOR_SCALE = 3
#: … and when it lowers the joint map's cost by more than this quantile of χ²(1) allows …
SCALE_TEST_QUANTILE = 0.999
#: … for a walk at least this fraction of whose tags other walks share (its scale is measured
#: where they overlap; chosen on straight_209_occam, whose two floors share 6 of 19 tags: its
#: floor 2 measures 0.7% short, and scaling all of it took its floor-1 tags 35% further from
#: the ground truth; docs/multi-session.md).
MIN_SCALE_COVERAGE = 0.5
#: Robust weight scale of the walks' placement fit: a shared tag this far from the others' weighs
#: half, m.
PLACEMENT_ROBUST_M = 1.0
#: Iterations of that fit (each an exact weighted fit; it stops earlier when nothing moves).
PLACEMENT_ITERATIONS = 50


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
    shared_tags: tags the session shares with other sessions; inlier_tags: those that agree with
        the others' within ``ALIGNMENT_INLIER_M`` once every session is placed (the tags that
        place it).
    residual_m: (len(shared_tags),) each shared tag's distance from the other sessions' (their
        median) after placing, m.
    odometry_scale: the factor on the session's odometry lengths in the map (1: as recorded):
        a walk whose odometry runs long or short against the other walks' (ARKit's scale drifts
        by a percent or two) is scaled before ``map_T_world`` places it (:func:`align_walks`).
    """

    dataset: str
    map_T_world: FloatArray
    yaw_rad: float
    shared_tags: tuple[int, ...]
    inlier_tags: tuple[int, ...]
    residual_m: FloatArray
    odometry_scale: float = 1.0

    def place(self, world_T_a: FloatArray) -> FloatArray:
        """(…, 4, 4) poses of the session's world in the map: lengths scaled by
        ``odometry_scale`` about the world's origin, then placed by ``map_T_world``."""
        scaled = np.array(world_T_a, dtype=np.float64)
        scaled[..., :3, 3] *= self.odometry_scale
        return np.asarray(self.map_T_world @ scaled, dtype=np.float64)

    @property
    def outlier_tags(self) -> tuple[int, ...]:
        return tuple(t for t in self.shared_tags if t not in set(self.inlier_tags))


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class WalkFit:
    """A walk optimized alone (step 1): its own map and its noise, in its own world frame. It
    depends on the walk's data and the parameters only, so a later version of the map reuses it
    (``optimize_sessions(initial=…)``).

    alone: the walk's own map (``optimize_session``'s, with its depth scale applied).
    noise: what its residuals say about its noise (None when the variances are used as given).
    noise_scales: (4,) the factors on its odometry linear, odometry angular, tag position and tag
        orientation variances (``noise.COMPONENTS``).
    cost: its odometry and tag factors' cost at its own optimum (``slam.chain_costs``).
    """

    dataset: str
    alone: MapResult
    noise: NoiseEstimate | None
    noise_scales: FloatArray
    cost: float
    tag_depth_scale: float


@dataclass(frozen=True, slots=True, kw_only=True)
class SessionPart:
    """One session's share of a joint map.

    pose_rows: the rows of the joint map's pose arrays that are this session's, in order.
    detection_rows: the rows of the joint session's detections that are this session's.
    tag_depth_scale: the factor applied to its camera-to-tag translations (1: as given).
    odometry_variance_scale: the factor on its odometry linear variance, against the configured
        one: its estimated noise × its disagreement factor.
    local_tags: shared tags whose sightings here disagreed with the map beyond this walk's noise
        and got their own landmark (not the map's).
    noise: its noise estimate alone (None when the variances were used as given).
    noise_scales: (4,) the factors on its variances in the map (``noise.COMPONENTS``), its
        disagreement factor included.
    disagreement_factor: ≥ 1, how much more its variances were raised in the joint map than its
        own data say (1: its disagreement with the other walks is what its noise explains).
    cost_alone, cost_joint: its odometry and tag factors' cost alone and in the map (with its own
        noise, i.e. without the disagreement factor).
    redundancy_gain: Δr, the degrees of freedom joining gave it (step 6 of the module docstring).
    weighting: why it weighs what it does, in a sentence ("" for a map of one walk).
    alone: its own map, alone (in its own world frame): the report compares with it.
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
    noise: NoiseEstimate | None = None
    noise_scales: FloatArray = field(default_factory=lambda: np.ones(4))
    disagreement_factor: float = 1.0
    cost_alone: float = math.nan
    cost_joint: float = math.nan
    redundancy_gain: float = 0.0
    weighting: str = ""
    alone: MapResult | None = None
    fit: WalkFit | None = None

    @property
    def is_reference(self) -> bool:
        return bool(self.pose_rows.start == 0)

    @property
    def shared_tags(self) -> tuple[int, ...]:
        """Its tags that other sessions saw too (and placed in the map)."""
        return tuple(t for t in self.alignment.shared_tags if t in set(self.tag_ids))

    @property
    def own_tags(self) -> tuple[int, ...]:
        """Its tags no other session saw: the map has them from this session only."""
        shared = set(self.alignment.shared_tags)
        return tuple(t for t in self.tag_ids if t not in shared)


@dataclass(frozen=True, slots=True, kw_only=True)
class JointMap:
    """A map of several sessions: the optimized map, the sessions it was made of, and the
    concatenated session it was optimized as (poses and detections in session order).
    ``rounds``: how many times the joint graph was solved (steps 5 and 6 of the module
    docstring); ``timings_ms``: where the build's time went, by step."""

    map: MapResult
    parts: tuple[SessionPart, ...]
    combined: Session
    sessions: tuple[Session, ...]
    detection_mask: BoolArray
    rounds: int = 1
    timings_ms: Mapping[str, float] = field(default_factory=dict)
    #: the walks' pairwise alignments (by names), which a later version reuses
    pair_alignments: Mapping[tuple[str, str], PairAlignment] = field(default_factory=dict)

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
    yaw = candidates[_best_candidate(candidates, world_p, map_p, inlier_m)]
    first = _yaw_translation(yaw, world_p, map_p)
    inlier = _residuals_m(first, world_p, map_p) <= inlier_m
    needed = max(min_shared_tags, math.ceil(min_inlier_fraction * len(shared)))
    if int(inlier.sum()) < needed:
        residual = _residuals_m(first, world_p, map_p)
        listed = ", ".join(f"{t}: {r:.2f} m" for t, r in zip(shared, residual, strict=True))
        raise AlignmentError(
            dataset,
            "inconsistent_shared_tags",
            f"of its {len(shared)} shared tags, at most {int(inlier.sum())} agree within "
            f"{inlier_m:g} m on one placement ({needed} needed); distances after the best "
            f"placement: {listed}",
        )
    yaw = _refit_yaw(yaw, world_p[inlier], map_p[inlier])
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


def _best_candidate(
    candidates: Sequence[float], world_p: FloatArray, map_p: FloatArray, inlier_m: float
) -> int:
    """The index of the candidate turn whose placement (:func:`_yaw_translation`, median offset)
    puts the most tags within ``inlier_m``, then the smallest median residual; the first such.
    All candidates at once: (C, n) offsets and residuals."""
    R = np.stack([rotation_about_y(yaw) for yaw in candidates])
    rotated = np.einsum("cij,nj->cni", R, world_p)
    offsets = np.median(map_p[None] - rotated, axis=1)
    residual = np.linalg.norm(rotated + offsets[:, None, :] - map_p[None], axis=2)
    inliers = np.sum(residual <= inlier_m, axis=1)
    spread = np.median(residual, axis=1)
    most = inliers == inliers.max()
    return int(np.flatnonzero(most & (spread == spread[most].min()))[0])


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
    scale, parallax_m2 = tag_depth_fit(session, used)
    if parallax_m2 < MIN_SCALE_PARALLAX_M2:
        return 1.0
    return scale if abs(scale - 1.0) > MIN_DEPTH_SCALE_CHANGE else 1.0


def tag_depth_fit(session: Session, used: BoolArray | None = None) -> tuple[float, float]:
    """:func:`tag_depth_scale`'s least-squares factor, whatever its size (1.0 without pairs),
    and the parallax it rests on: Σ‖Δ camera-to-tag vector‖² over the pairs of sightings, m²."""
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
    return (numerator / denominator if denominator > 0 else 1.0), denominator


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


def keep_poses(session: Session, keep: BoolArray) -> Session:
    """``session`` with only the poses ``keep`` ((N,) bool) marks, and the detections and points
    of interest on them (a floor of a walk: straight_209_occam's floor 2). Timestamps are kept,
    so the odometry between the poses either side of a gap is their raw relative pose, held as
    loosely as the time across the gap asks."""
    keep = np.asarray(keep, dtype=bool)
    if keep.shape != (session.num_poses,):
        raise ValueError(f"keep must have shape ({session.num_poses},), got {keep.shape}")
    new_row = np.cumsum(keep) - 1
    detections = session.detections
    rows = keep[detections.pose_index]
    columns = {f.name: getattr(detections, f.name)[rows] for f in dataclasses.fields(TagDetections)}
    columns["pose_index"] = new_row[detections.pose_index[rows]].astype(np.int64)
    return dataclasses.replace(
        session,
        pose_id=session.pose_id[keep],
        timestamp_s=session.timestamp_s[keep],
        world_T_phone=session.world_T_phone[keep],
        detections=TagDetections(**columns),
        pois=tuple(
            dataclasses.replace(poi, pose_index=int(new_row[poi.pose_index]))
            for poi in session.pois
            if keep[poi.pose_index]
        ),
    )


def sighting_burst_sizes(session: Session, used: BoolArray) -> FloatArray:
    """(M,) the size of each used detection's burst of sightings (``screening``'s, for a whole
    session)."""
    return _burst_sizes(session.detections, used)


# --------------------------------------------------------------------------- placing the walks


def align_walks(
    datasets: Sequence[str],
    world_T_tag: Sequence[Mapping[int, FloatArray]],
    *,
    min_shared_tags: int = MIN_SHARED_TAGS,
    odometry_scales: Sequence[float] | None = None,
    first_placements: Mapping[int, FloatArray] | None = None,
) -> tuple[SessionAlignment, ...]:
    """Each walk's placement in the map frame (the first walk's world), from the tags the walks
    share (step 2 of the module docstring): pairwise robust alignments, a maximum spanning tree
    of the best pairs (:func:`first_placements`, unless given), then an iteratively reweighted
    fit of every walk to the others' tags at once, each walk's lengths multiplied by its
    ``odometry_scales`` (default 1). Raises :class:`AlignmentError` for a walk that cannot be
    placed."""
    n = len(datasets)
    odometry_scale = {s: (1.0 if odometry_scales is None else odometry_scales[s]) for s in range(n)}
    placed = dict(
        first_placements
        if first_placements is not None
        else walk_placements(datasets, world_T_tag, min_shared_tags=min_shared_tags)
    )
    if n > 1:
        placed, _ = _refined_placements(world_T_tag, placed, odometry_scale)
    return tuple(_alignment(s, datasets, world_T_tag, placed, odometry_scale) for s in range(n))


#: A pair of walks' alignment (by their names, sorted): its rank (fewest inliers last) and
#: ``i_T_j``, or None when they do not place each other.
PairAlignment = tuple[tuple[float, float, str, str], FloatArray] | None


def walk_placements(
    datasets: Sequence[str],
    world_T_tag: Sequence[Mapping[int, FloatArray]],
    *,
    min_shared_tags: int = MIN_SHARED_TAGS,
    pairs: dict[tuple[str, str], PairAlignment] | None = None,
) -> dict[int, FloatArray]:
    """Each walk's first placement (``map_T_world``, rigid): pairwise robust alignments of the
    walks' tags (names break ties, never positions), composed along the maximum spanning tree of
    the best pairs from the first walk; a walk no single other walk places is tried against all
    placed ones. ``pairs``: pair alignments known already (a warm start's), filled in with the
    new ones. Raises :class:`AlignmentError` for a walk that cannot be placed."""
    n = len(datasets)
    if n == 1:
        return {0: np.eye(4)}
    pairs = {} if pairs is None else pairs
    order = sorted(range(n), key=lambda s: datasets[s])
    edges: list[tuple[tuple[float, float, str, str], int, int, FloatArray]] = []
    for a, i in enumerate(order):
        for j in order[a + 1 :]:
            key = (datasets[i], datasets[j])
            if key not in pairs:
                pairs[key] = _pair_alignment(
                    datasets[i], datasets[j], world_T_tag[i], world_T_tag[j], min_shared_tags
                )
            known = pairs[key]
            if known is not None:
                edges.append((known[0], i, j, known[1]))
    placed = _spanning_tree_placements(n, edges)
    waiting = [s for s in range(n) if s not in placed]
    while waiting:  # walks no single other walk places: try them against all placed ones
        merged = _merged_tags(world_T_tag, placed)
        for s in sorted(waiting, key=lambda s: datasets[s]):
            try:
                joined = align_session(
                    datasets[s], world_T_tag[s], merged, min_shared_tags=min_shared_tags
                )
            except AlignmentError:
                continue
            placed[s] = joined.map_T_world
            waiting.remove(s)
            break
        else:  # the first walk (in the order given) that cannot be placed says why
            align_session(
                datasets[waiting[0]],
                world_T_tag[waiting[0]],
                merged,
                min_shared_tags=min_shared_tags,
            )
            raise AssertionError("align_session placed a walk it could not place")
    return placed


def _pair_alignment(
    name_i: str,
    name_j: str,
    world_T_tag_i: Mapping[int, FloatArray],
    world_T_tag_j: Mapping[int, FloatArray],
    min_shared_tags: int,
) -> PairAlignment:
    """Walk j placed on walk i by their shared tags (:func:`align_session`), ranked."""
    if len(set(world_T_tag_i) & set(world_T_tag_j)) < min_shared_tags:
        return None
    try:
        pair = align_session(name_j, world_T_tag_j, world_T_tag_i, min_shared_tags=min_shared_tags)
    except AlignmentError:
        return None
    rank = (-float(len(pair.inlier_tags)), float(np.median(pair.residual_m)), name_i, name_j)
    return rank, pair.map_T_world


def _spanning_tree_placements(
    n: int, edges: list[tuple[tuple[float, float, str, str], int, int, FloatArray]]
) -> dict[int, FloatArray]:
    """``map_T_world`` of each walk connected to walk 0 through the maximum spanning tree of
    ``edges`` (best rank first: most inliers, smallest residual, then names)."""
    root = list(range(n))

    def find(s: int) -> int:
        while root[s] != s:
            root[s] = root[root[s]]
            s = root[s]
        return s

    tree: dict[int, list[tuple[int, FloatArray]]] = {s: [] for s in range(n)}
    for _, i, j, i_T_j in sorted(edges, key=lambda edge: edge[0]):
        if find(i) != find(j):
            root[find(i)] = find(j)
            tree[i].append((j, i_T_j))
            tree[j].append((i, se3_inverse(i_T_j)))
    placed = {0: np.eye(4)}
    frontier = [0]
    while frontier:
        s = frontier.pop()
        for other, s_T_other in tree[s]:
            if other not in placed:
                placed[other] = placed[s] @ s_T_other
                frontier.append(other)
    return placed


def _merged_tags(
    world_T_tag: Sequence[Mapping[int, FloatArray]], placed: Mapping[int, FloatArray]
) -> dict[int, FloatArray]:
    """The placed walks' tags in the map frame: each tag's median position, and the rotation of
    the walk of lowest index that saw it."""
    positions: dict[int, list[FloatArray]] = {}
    rotations: dict[int, FloatArray] = {}
    for s in sorted(placed):
        for t, pose in world_T_tag[s].items():
            map_T_tag = placed[s] @ pose
            positions.setdefault(t, []).append(map_T_tag[:3, 3])
            rotations.setdefault(t, map_T_tag[:3, :3])
    return {
        t: make_pose(rotations[t], np.median(np.stack(p), axis=0)) for t, p in positions.items()
    }


def _refined_placements(
    world_T_tag: Sequence[Mapping[int, FloatArray]],
    placed: Mapping[int, FloatArray],
    scales: Mapping[int, float] | None = None,
) -> tuple[dict[int, FloatArray], dict[int, float]]:
    """Every walk but the first refitted at once (a Jacobi iteration: each to the others'
    weighted mean of every tag it shares), with Cauchy weights of scale ``PLACEMENT_ROBUST_M``
    on the tags' distances, until no walk moves; the first walk's frame is the map's. A walk is
    placed by a turn about +y, a translation and, unless ``scales`` fixes it, a scale (walk
    ``s``'s tag ``t`` lands at ``R (k p) + t``). Returns each walk's rigid part and its scale.
    Vectorized over the (walk, tag) sightings: each iteration is a handful of array sums."""
    walks = sorted(placed)
    where = {s: i for i, s in enumerate(walks)}
    tags = sorted({t for s in walks for t in world_T_tag[s]})
    column = {t: i for i, t in enumerate(tags)}
    pairs = [(s, t) for s in walks for t in sorted(world_T_tag[s])]
    walk = np.array([where[s] for s, _ in pairs], dtype=np.int64)
    tag = np.array([column[t] for _, t in pairs], dtype=np.int64)
    p = np.stack([world_T_tag[s][t][:3, 3] for s, t in pairs])
    W, T = len(walks), len(tags)
    shared = np.bincount(tag, minlength=T)[tag] >= 2
    R = np.stack([placed[s][:3, :3] for s in walks])
    t_w = np.stack([placed[s][:3, 3] for s in walks])
    k = np.array([1.0 if scales is None else float(scales[s]) for s in walks])
    weight = np.ones(len(pairs))
    free = np.zeros(W, dtype=bool)
    free[1:] = True  # the first walk's frame is the map's

    def others_means() -> tuple[FloatArray, FloatArray]:
        aligned = k[walk, None] * np.einsum("nij,nj->ni", R[walk], p) + t_w[walk]
        total = np.zeros((T, 3))
        np.add.at(total, tag, weight[:, None] * aligned)
        mass = np.bincount(tag, weights=weight, minlength=T)
        rest = np.maximum(mass[tag] - weight, 1e-12)
        return aligned, (total[tag] - weight[:, None] * aligned) / rest[:, None]

    for _ in range(PLACEMENT_ITERATIONS):
        _, target = others_means()
        w = np.where(shared, weight, 0.0)
        mass = np.bincount(walk, weights=w, minlength=W)
        fits = free & (mass > 0)
        safe = np.where(mass > 0, mass, 1.0)
        centre_p = _grouped_sum(walk, w[:, None] * p, W) / safe[:, None]
        centre_q = _grouped_sum(walk, w[:, None] * target, W) / safe[:, None]
        a, b = p - centre_p[walk], target - centre_q[walk]
        cross = np.bincount(walk, weights=w * (a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2]), minlength=W)
        dot = np.bincount(walk, weights=w * (a[:, 0] * b[:, 0] + a[:, 2] * b[:, 2]), minlength=W)
        spread = np.bincount(walk, weights=w * np.sum(a**2, axis=1), minlength=W)
        horizontal = spread * np.bincount(walk, weights=(w > 0).astype(float), minlength=W) / safe
        yaw = np.where(
            horizontal >= MIN_PAIR_BASELINE_M**2,
            np.arctan2(cross, dot),
            np.array([yaw_of(r) for r in R]),
        )
        new_R = np.stack([rotation_about_y(float(y)) for y in yaw])
        new_k = k.copy()
        if scales is None:
            rotated = np.einsum("nij,nj->ni", new_R[walk], a)
            along = np.bincount(walk, weights=w * np.sum(b * rotated, axis=1), minlength=W)
            fitted = np.where(spread > 0, along / np.where(spread > 0, spread, 1.0), 1.0)
            new_k = np.where(fits & (fitted > 0), fitted, k)
        new_t = centre_q - new_k[:, None] * np.einsum("wij,wj->wi", new_R, centre_p)
        moved = float(
            max(
                np.max(np.abs(np.where(fits[:, None, None], new_R - R, 0.0))),
                np.max(np.abs(np.where(fits[:, None], new_t - t_w, 0.0))),
                100.0 * np.max(np.abs(np.where(fits, new_k - k, 0.0))),
            )
        )
        R = np.where(fits[:, None, None], new_R, R)
        t_w = np.where(fits[:, None], new_t, t_w)
        k = np.where(fits, new_k, k)
        aligned, target = others_means()
        distance = np.linalg.norm(aligned - target, axis=1)
        weight = np.where(shared, 1.0 / (1.0 + (distance / PLACEMENT_ROBUST_M) ** 2), 1.0)
        if moved < 1e-9:
            break
    return (
        {s: make_pose(R[i], t_w[i]) for i, s in enumerate(walks)},
        {s: float(k[i]) for i, s in enumerate(walks)},
    )


def _grouped_sum(group: IntArray, values: FloatArray, groups: int) -> FloatArray:
    """(groups, 3) the sum of ``values`` ((n, 3)) by ``group`` ((n,))."""
    total = np.zeros((groups, values.shape[1]))
    np.add.at(total, group, values)
    return total


def odometry_scale_candidates(
    datasets: Sequence[str], world_T_tag: Sequence[Mapping[int, FloatArray]]
) -> tuple[float, ...]:
    """The factor on each walk's odometry lengths that would make it agree with the other walks
    (a candidate: :func:`optimize_sessions` keeps it only if the joint map's cost says so).

    Every pair of walks sharing at least 3 tags gives their relative scale, symmetrically (the
    mean of the two directions' log-scales of a similarity fit, so the pair's order does not
    matter) with its standard error; the walks' log-scales are the weighted least-squares
    solution over all pairs, taken about their median (no walk is the reference). A walk's scale
    is used where it is significant (beyond ``SCALE_SIGMAS`` standard errors and
    ``MIN_ODOMETRY_SCALE_CHANGE``) and the median is a majority's (``MIN_WALKS_FOR_SCALE``);
    else 1. ARKit's scale drifts by a percent or two: 2% over a
    30 m building is 60 cm, which the random-walk noise of the odometry does not describe."""
    n = len(datasets)
    if n < MIN_WALKS_FOR_SCALE:
        return (1.0,) * n
    rows, targets, weights = [], [], []
    for i in range(n):
        for j in range(i + 1, n):
            shared = sorted(set(world_T_tag[i]) & set(world_T_tag[j]))
            if len(shared) < 3:
                continue
            p_i = np.stack([world_T_tag[i][t][:3, 3] for t in shared])
            p_j = np.stack([world_T_tag[j][t][:3, 3] for t in shared])
            ones = np.ones(len(shared))
            i_from_j = _weighted_similarity(p_j, p_i, ones, np.eye(4))
            j_from_i = _weighted_similarity(p_i, p_j, ones, np.eye(4))
            sigma = 0.5 * (i_from_j.log_scale_sigma + j_from_i.log_scale_sigma)
            if not math.isfinite(sigma) or sigma <= 0:
                continue
            row = np.zeros(n)
            row[i], row[j] = 1.0, -1.0  # log k_i − log k_j, k: how long a walk's lengths run
            rows.append(row)
            targets.append(0.5 * (math.log(i_from_j.scale) - math.log(j_from_i.scale)))
            weights.append(1.0 / sigma**2)
    if not rows:
        return (1.0,) * n
    A, b, w = np.array(rows), np.array(targets), np.array(weights)
    # the gauge: the mean log-scale is 0 (then the median is taken out, below)
    normal = A.T @ (w[:, None] * A) + np.ones((n, n)) / n
    log_scale = np.linalg.solve(normal, A.T @ (w * b))
    information = np.diag(A.T @ (w[:, None] * A))
    log_scale -= float(np.median(log_scale))
    out = []
    for s in range(n):
        sigma = 1.0 / math.sqrt(information[s]) if information[s] > 0 else math.inf
        limit = max(SCALE_SIGMAS * sigma, math.log1p(MIN_ODOMETRY_SCALE_CHANGE))
        out.append(math.exp(-log_scale[s]) if abs(log_scale[s]) > limit else 1.0)
    return tuple(out)


@dataclass(frozen=True, slots=True)
class _Similarity:
    map_T_world: FloatArray
    scale: float
    log_scale_sigma: float


def _weighted_similarity(
    world_p: FloatArray,
    map_p: FloatArray,
    weights: FloatArray,
    fallback: FloatArray,
    *,
    scale: float | None = None,
) -> _Similarity:
    """The turn about +y, scale (unless given) and translation that best place ``world_p`` on
    ``map_p`` (weighted least squares: ``map_p ≈ R (k world_p) + t``), with the uncertainty of
    log k from the residuals; the turn of ``fallback`` when the points have no horizontal
    spread."""
    w = weights / max(float(weights.sum()), 1e-12)
    world_c, map_c = w @ world_p, w @ map_p
    a, b = world_p - world_c, map_p - map_c
    spread = float(np.sum(w * np.sum(a**2, axis=1)))
    if spread * len(w) < MIN_PAIR_BASELINE_M**2:
        yaw = yaw_of(fallback[:3, :3])
    else:  # R_y(θ) maps (x, z) to (x cosθ + z sinθ, −x sinθ + z cosθ)
        cross = float(np.sum(w * (a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2])))
        dot = float(np.sum(w * (a[:, 0] * b[:, 0] + a[:, 2] * b[:, 2])))
        yaw = math.atan2(cross, dot)
    R = rotation_about_y(yaw)
    rotated = a @ R.T
    k = scale
    if k is None:
        k = float(np.sum(w * np.sum(b * rotated, axis=1)) / spread) if spread > 0 else 1.0
        k = k if k > 0 else 1.0
    residual = b - k * rotated
    dof = 3 * len(w) - 5
    sigma = math.inf
    if dof > 0 and spread > 0:
        variance = float(np.sum(w * np.sum(residual**2, axis=1))) * len(w) / dof
        sigma = math.sqrt(variance / (spread * len(w))) / k
    return _Similarity(
        map_T_world=make_pose(R, map_c - k * (R @ world_c)), scale=k, log_scale_sigma=sigma
    )


def _alignment(
    s: int,
    datasets: Sequence[str],
    world_T_tag: Sequence[Mapping[int, FloatArray]],
    placed: Mapping[int, FloatArray],
    odometry_scale: Mapping[int, float],
) -> SessionAlignment:
    """Walk ``s``'s placement, with its shared tags and their distances from the others'."""

    def position(o: int, pose: FloatArray) -> FloatArray:
        return placed[o][:3, :3] @ (odometry_scale[o] * pose[:3, 3]) + placed[o][:3, 3]

    others: dict[int, list[FloatArray]] = {}
    for o in range(len(datasets)):
        if o != s:
            for t, pose in world_T_tag[o].items():
                others.setdefault(t, []).append(position(o, pose))
    shared = tuple(sorted(set(world_T_tag[s]) & set(others)))
    residual = np.array(
        [
            np.linalg.norm(position(s, world_T_tag[s][t]) - np.median(np.stack(others[t]), axis=0))
            for t in shared
        ]
    )
    return SessionAlignment(
        dataset=datasets[s],
        map_T_world=placed[s],
        yaw_rad=yaw_of(placed[s][:3, :3]),
        shared_tags=shared,
        inlier_tags=tuple(
            t for t, r in zip(shared, residual, strict=True) if r <= ALIGNMENT_INLIER_M
        ),
        residual_m=residual,
        odometry_scale=float(odometry_scale[s]),
    )


# --------------------------------------------------------------------------- the joint map


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
    """Steps 1 and 2 of the module docstring: each walk screened, scaled and optimized alone
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


#: Called with (step, fraction done) as a joint build goes ("walks", "joint").
ProgressCallback = Callable[[str, float], None]


def fit_walk(
    dataset: str, session: Session, screening: Screening, params: SlamParams, depth_scale: float
) -> WalkFit:
    """Step 1: ``session`` (depths scaled already) optimized alone, its noise estimated."""
    started = time.perf_counter()
    inputs = GraphInputs(session, params, screening=screening)
    prepared = time.perf_counter()
    solution = solve(inputs, params)
    optimized = time.perf_counter()
    alone = map_result(
        inputs,
        params,
        solution,
        build_ms=(prepared - started) * 1e3,
        optimize_ms=(optimized - prepared) * 1e3,
    )
    return WalkFit(
        dataset=dataset,
        alone=alone,
        noise=alone.noise,
        noise_scales=inputs.noise_scales[0].copy(),
        cost=float(chain_costs(inputs, params, solution.values)[0]),
        tag_depth_scale=depth_scale,
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
    return _joint_inputs(plan, params, variance_scales, initial)


def _joint_inputs(
    plan: JointPlan,
    params: SlamParams,
    variance_scales: Mapping[str, tuple[float, float]] | None,
    initial: JointMap | None,
) -> JointInputs:
    combined, starts, detection_starts = combine_sessions(plan)
    screening = _combined_screening(plan, starts, detection_starts)
    base = np.stack([fit.noise_scales for fit in plan.fits])
    for s, dataset in enumerate(plan.datasets):
        tag_k, odometry_k = (variance_scales or {}).get(dataset, (1.0, 1.0))
        base[s] *= (odometry_k, odometry_k, tag_k, tag_k)
    inputs = GraphInputs(
        combined, params, screening=screening, chain_starts=starts, noise_scales=base
    )
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
    return JointInputs(
        plan=plan,
        combined=combined,
        starts=starts,
        detection_starts=detection_starts,
        screening=screening,
        inputs=inputs,
        base_scales=base,
        start_T_keyframe=world_T_phone[inputs.keyframes],
        start_T_tag=world_T_tag,
        start_disagreement=disagreement,
    )


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
    return _weighted_similarity(
        previous_p, new_p, np.ones(len(common)), np.eye(4), scale=1.0
    ).map_T_world


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
    """Optimize ``sessions`` into one map (see the module docstring). One session gives the map
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
    tests = _tested_scales(plan, fixed, variance_scales, initial)
    plan, scale_drops = tests.plan, tests.drops
    joint = tests.joint or _joint_inputs(plan, params, variance_scales, initial)
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
    settled: _Weighing | None = None  # the last round's weighing, when it changed nothing
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
        split = _worst_split(joint, inputs, solution, splits)
        if split is not None:
            reasons[split[0]] = split[1]
            splits = splits | {split[0]}
            inputs = joint.graph_inputs(fixed, splits, disagreement)
            continue
        if reweight and not variance_scales:
            weighing = _disagreement(joint, inputs, fixed, solution, disagreement, splits)
            if _changed(weighing.factors, disagreement):
                disagreement = weighing.factors
                inputs.noise_scales = joint.base_scales * disagreement[:, None]
                continue
            settled = weighing
        break
    optimized = time.perf_counter()
    if settled is not None:
        weighing = settled
    else:
        weighing = _disagreement(joint, inputs, fixed, solution, disagreement, splits)
    result = map_result(
        inputs,
        params,
        solution,
        build_ms=plan.timings_ms.get("walks_alone", 0.0) + plan.timings_ms.get("placing", 0.0),
        optimize_ms=(optimized - solved) * 1e3,
        warnings=_joint_warnings(joint, splits, reasons, disagreement, weighing, scale_drops),
    )
    parts = _parts(joint, inputs, result, splits, disagreement, weighing, scale_drops)
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
    joint = _joint_inputs(plan, params, variance_scales, initial)
    solved = time.perf_counter()
    solution = solve(
        joint.inputs,
        params,
        start=values_from(joint.inputs, joint.start_T_keyframe, joint.start_T_tag),
    )
    optimized = time.perf_counter()
    ones = np.ones(len(plan.datasets))
    weighing = _disagreement(joint, joint.inputs, params, solution, ones, frozenset())
    weighing = dataclasses.replace(weighing, factors=ones, significant=np.zeros_like(ones, bool))
    result = map_result(
        joint.inputs,
        params,
        solution,
        build_ms=plan.timings_ms.get("walks_alone", 0.0) + plan.timings_ms.get("placing", 0.0),
        optimize_ms=(optimized - solved) * 1e3,
        warnings=_joint_warnings(joint, frozenset(), {}, ones, weighing, {}),
    )
    parts = _parts(joint, joint.inputs, result, frozenset(), ones, weighing, {})
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


def _tested_scales(
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
        joint = _joint_inputs(trial, params, variance_scales, initial)
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


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class ScaleTests:
    """What :func:`_tested_scales` decided: the plan with the kept scales, each tested walk's
    drop of the joint cost, and, when the plan is the one tested unscaled, its joint inputs, its
    optimum and the time that first solve took (the build's own first solve, s)."""

    plan: JointPlan
    drops: dict[int, float]
    solved: Solved | None = None
    joint: JointInputs | None = None
    first_solve_s: float = 0.0


#: A joint solution's keyframe poses ((K, 4, 4)) and tags by id: where the next solve starts.
Solved = tuple[FloatArray, dict[int, FloatArray]]


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


@dataclass(frozen=True, slots=True, kw_only=True)
class _Weighing:
    """Step 4's figures per walk: the factors it implies, the walk's cost in the joint map with
    its own noise, its excess over its cost alone, and the redundancy joining gave it."""

    factors: FloatArray
    cost_joint: FloatArray
    excess: FloatArray
    gain: FloatArray
    significant: BoolArray


def _disagreement(
    joint: JointInputs,
    inputs: GraphInputs,
    params: SlamParams,
    solution: Solution,
    disagreement: FloatArray,
    splits: frozenset[tuple[int, int]],
) -> _Weighing:
    """Each walk's disagreement factor at ``solution`` (step 6 of the module docstring): its
    cost with its own noise, less its cost alone, over the redundancy it gained; 1 unless that
    excess is beyond ``DISAGREEMENT_QUANTILE`` of χ²(Δr)."""
    scales = inputs.noise_scales
    inputs.noise_scales = joint.base_scales
    try:
        cost_joint = chain_costs(inputs, params, solution.values)
    finally:
        inputs.noise_scales = scales
    cost_alone = np.array([fit.cost for fit in joint.plan.fits])
    gain = _redundancy_gain(joint, inputs, disagreement, splits)
    excess = cost_joint - cost_alone
    limit = np.array([chi2_quantile(DISAGREEMENT_QUANTILE, max(1, round(g))) for g in gain])
    significant = excess > limit
    factors = np.where(
        significant, np.clip(excess / gain, 1.0, MAX_DISAGREEMENT_FACTOR), 1.0
    ).astype(np.float64)
    return _Weighing(
        factors=factors, cost_joint=cost_joint, excess=excess, gain=gain, significant=significant
    )


def _redundancy_gain(
    joint: JointInputs,
    inputs: GraphInputs,
    disagreement: FloatArray,
    splits: frozenset[tuple[int, int]],
) -> FloatArray:
    """(S,) Δr of each walk: every shared tag's 6(m − 1) degrees of freedom, each walk taking
    the share ``1 − w / Σw`` (w: how firmly it holds the tag, the information of its sightings'
    positions), less ``PLACEMENT_DOF`` × (S − 1) / S for placing it; at least 1."""
    S = len(joint.plan.datasets)
    detections = joint.combined.detections
    rows = np.array(inputs.tag_detection_rows, dtype=np.int64)
    chain = inputs.detection_chain
    distance_m = np.maximum(np.linalg.norm(detections.camera_T_tag[rows, :3, 3], axis=1), 0.1)
    position_scale, _ = inputs.tag_scales()
    information = 1.0 / (position_scale * distance_m**2)
    tags = detections.tag_id[rows]
    firmness: dict[int, np.ndarray] = {}
    for k, (t, s) in enumerate(zip(tags.tolist(), chain.tolist(), strict=True)):
        if (s, t) in splits:
            continue
        firmness.setdefault(t, np.zeros(S))[s] += information[k]
    gain = np.full(S, -PLACEMENT_DOF * (S - 1) / S)
    for w in firmness.values():
        if np.count_nonzero(w) >= 2:
            gain += np.where(w > 0, 6.0 * (1.0 - w / w.sum()), 0.0)
    del disagreement  # the scales in ``inputs`` carry it
    return np.asarray(np.maximum(gain, 1.0), dtype=np.float64)


def _changed(new: FloatArray, old: FloatArray) -> bool:
    return bool(np.max(np.abs(np.log(new / old))) > math.log1p(DISAGREEMENT_TOLERANCE))


def _worst_split(
    joint: JointInputs,
    inputs: GraphInputs,
    solution: Solution,
    splits: frozenset[tuple[int, int]],
) -> tuple[tuple[int, int], float] | None:
    """The (walk, tag) whose sightings of a tag other walks saw too disagree most with the map,
    with its mean χ² per sighting, if that is beyond ``SPLIT_QUANTILE`` of a 6-D residual's once
    divided by the walk's own level of disagreement (the median over its shared tags, against
    the χ²'s median, when it has at least 3; step 5)."""
    residuals = solution_residuals(inputs, solution)
    detections = joint.combined.detections
    tags = detections.tag_id[residuals.tag_detection_index]
    chain = inputs.detection_chain
    chi2: dict[tuple[int, int], list[float]] = {}
    for t, s, c in zip(tags.tolist(), chain.tolist(), residuals.tag_chi2.tolist(), strict=True):
        if (s, t) not in splits:
            chi2.setdefault((s, t), []).append(c)
    walks_of: dict[int, int] = {}
    for _, t in chi2:
        walks_of[t] = walks_of.get(t, 0) + 1
    limit = chi2_quantile(SPLIT_QUANTILE, 6)
    typical = chi2_quantile(0.5, 6)
    mean = {st: float(np.mean(values)) for st, values in chi2.items() if walks_of[st[1]] >= 2}
    # each walk's own level of disagreement (the median of its shared tags'): a walk whose noise
    # is underestimated everywhere is step 6's business, not a reason to split all its tags
    level = {}
    for w in {st[0] for st in mean}:
        of_walk = [c for (s, _), c in mean.items() if s == w]
        level[w] = max(1.0, float(np.median(of_walk)) / typical) if len(of_walk) >= 3 else 1.0
    candidates = [
        (c / level[s], joint.plan.datasets[s], t, s)
        for (s, t), c in mean.items()
        if c / level[s] > limit
    ]
    if not candidates:
        return None
    _, _, t, s = max(candidates)
    return (s, t), mean[s, t]


def _joint_warnings(
    joint: JointInputs,
    splits: frozenset[tuple[int, int]],
    reasons: Mapping[tuple[int, int], float],
    disagreement: FloatArray,
    weighing: _Weighing,
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


def _weighting(s: int, disagreement: FloatArray, weighing: _Weighing) -> str:
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


def _parts(
    joint: JointInputs,
    inputs: GraphInputs,
    result: MapResult,
    splits: frozenset[tuple[int, int]],
    disagreement: FloatArray,
    weighing: _Weighing,
    scale_drops: Mapping[int, float],
) -> tuple[SessionPart, ...]:
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
    parts = []
    for s, dataset in enumerate(plan.datasets):
        rows = slice(joint.detection_starts[s], detection_ends[s])
        used = joint.screening.used[rows]
        session_chi2 = [
            tag_chi2_by_row[r] for r in range(rows.start, rows.stop) if r in tag_chi2_by_row
        ]
        local = tuple(sorted(t for w, t in splits if w == s))
        fit = plan.fits[s]
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
                noise=fit.noise,
                noise_scales=inputs.noise_scales[s].copy(),
                disagreement_factor=float(disagreement[s]),
                cost_alone=fit.cost,
                cost_joint=float(weighing.cost_joint[s]),
                redundancy_gain=float(weighing.gain[s]),
                weighting="; ".join(
                    note
                    for note in (
                        _weighting(s, disagreement, weighing),
                        _scale_note(s, plan, scale_drops),
                    )
                    if note
                ),
                alone=fit.alone,
                fit=fit,
            )
        )
    return tuple(parts)


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
    "BURST_GAP_S",
    "BURST_WEIGHT_POWER",
    "AlignmentError",
    "JointInputs",
    "JointMap",
    "JointPlan",
    "SessionAlignment",
    "SessionPart",
    "WalkFit",
    "align_session",
    "align_walks",
    "combine_sessions",
    "fit_walk",
    "keep_poses",
    "optimize_sessions",
    "plan_sessions",
    "prepare_joint",
    "sighting_burst_sizes",
    "tag_depth_scale",
    "walk_placements",
]
