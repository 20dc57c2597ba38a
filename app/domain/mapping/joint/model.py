"""The joint map's values: what a build of several walks makes, and why it refuses a walk.

AlignmentError     a walk the others' tags cannot place (``reason`` says why)
SessionAlignment   where a walk's world frame sits in the map
WalkFit            a walk optimized alone: its own map and noise (step 1)
SessionPart        one walk's share of a joint map, with why it weighs what it does
JointMap           the optimized map, its walks and the concatenated session
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from app.domain.errors import InvisibleMapError
from app.domain.frames import FloatArray
from app.domain.mapping.joint.stairs import StairLink
from app.domain.mapping.map_result import MapResult
from app.domain.mapping.noise import NoiseEstimate
from app.domain.upload.session import Session

IntArray = npt.NDArray[np.int64]


BoolArray = npt.NDArray[np.bool_]


#: A pair of walks' alignment (by their names, sorted): its rank (fewest inliers last) and
#: ``i_T_j``, or None when they do not place each other.
PairAlignment = tuple[tuple[float, float, str, str], FloatArray] | None


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
    redundancy_gain: Δr, the degrees of freedom joining gave it (step 6, ``weights.py``).
    weighting: why it weighs what it does, in a sentence ("" for a map of one walk).
    stair_links: the stretches its odometry alone carries from a tag on one level to a tag on
        another (the stairs between floors), with the σ of heading the map gave each and its
        share of every walk's links between the same two levels (``stairs.StairLink``): how much
        it decides where one floor sits against another.
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
    stair_links: tuple[StairLink, ...] = ()
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
    ``rounds``: how many times the joint graph was solved (steps 5 and 6,
    ``weights.py``); ``timings_ms``: where the build's time went, by step."""

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
