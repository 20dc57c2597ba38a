"""Regions of a building, and the odometry stretches that connect them (issue 37).

    regions = tag_regions(ground_truth)                   # tag id → Region(floor, half)
    errors = region_errors(map_T_tag, ground_truth, regions)   # tag RMSE over all and per region
    stretches = connecting_stretches(session, regions)    # where a walk goes from one to the next
    check = stretch_check(session, stretch, ground_truth) # that stretch's odometry against truth

A building map of several walks can beat every walk *inside* a region (a floor, half a corridor:
the tags there agree after a similarity fit of the region alone) and still lose *between* regions
(the tags of one floor placed against another's): each walk connects two regions through a few
odometry stretches (the stairs), and how the map places one region against the other is what
those stretches say, weighed by the noise the model gives them. This module measures both sides:
the per-region errors of a map, and, per connecting stretch, how much its odometry errs against
the truth (from the tags seen at its two ends) and how much the model trusts it (its σ).

Regions come from the ground truth's tag positions: floors are clusters of tag heights split
where two consecutive heights are more than ``floor_gap_m`` apart (a cluster of fewer than
``min_floor_tags`` tags, such as one tag on a stair landing, joins the nearer floor); each floor
is cut in two halves at the median of its tags along their main horizontal direction.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from app.domain.evaluation.metrics import umeyama_rigid
from app.domain.frames import FloatArray, rotation_angle_rad, se3_inverse
from app.domain.mapping.map_result import FactorResiduals
from app.domain.mapping.params import SlamParams
from app.domain.upload.session import Session

BoolArray = npt.NDArray[np.bool_]

#: Two consecutive tag heights further apart than this start a new floor, m.
FLOOR_GAP_M = 1.5
#: A height cluster of fewer tags than this is no floor of its own (a stair landing's tag).
MIN_FLOOR_TAGS = 3


@dataclass(frozen=True, slots=True, order=True)
class Region:
    """A part of a building: ``floor`` (0 the lowest) and ``half`` (0 or 1) of that floor."""

    floor: int
    half: int

    @property
    def label(self) -> str:
        return f"floor {self.floor} {'ab'[self.half]}"


def tag_regions(
    world_T_tag: Mapping[int, FloatArray],
    *,
    floor_gap_m: float = FLOOR_GAP_M,
    min_floor_tags: int = MIN_FLOOR_TAGS,
    landings: bool = False,
) -> dict[int, Region]:
    """Each tag's region (module docstring) from its pose (a ground truth, y up). ``landings``:
    a height cluster too small to be a floor (a stair landing's tag) stays a region of its own,
    numbered between the floors, instead of joining the nearer one."""
    ids = sorted(world_T_tag)
    if not ids:
        return {}
    height_m = np.array([world_T_tag[t][1, 3] for t in ids])
    order = np.argsort(height_m)
    clusters: list[list[int]] = [[int(order[0])]]
    for previous, k in itertools.pairwise(order):
        if height_m[k] - height_m[previous] > floor_gap_m:
            clusters.append([])
        clusters[-1].append(int(k))
    # a cluster too small to be a floor joins the nearer neighbouring cluster
    while not landings and len(clusters) > 1 and min(len(c) for c in clusters) < min_floor_tags:
        c = min(range(len(clusters)), key=lambda i: len(clusters[i]))
        below = height_m[clusters[c][0]] - height_m[clusters[c - 1][-1]] if c > 0 else math.inf
        above = (
            height_m[clusters[c + 1][0]] - height_m[clusters[c][-1]]
            if c + 1 < len(clusters)
            else math.inf
        )
        into = c - 1 if below <= above else c + 1
        clusters[into] = sorted(clusters[into] + clusters[c], key=lambda k: height_m[k])
        del clusters[c]
    regions: dict[int, Region] = {}
    for floor, members in enumerate(clusters):
        xz = np.array([[world_T_tag[ids[k]][0, 3], world_T_tag[ids[k]][2, 3]] for k in members])
        centred = xz - xz.mean(axis=0)
        along = centred @ np.linalg.svd(centred, full_matrices=False)[2][0]
        median = float(np.median(along))
        for k, a in zip(members, along, strict=True):
            regions[ids[k]] = Region(floor=floor, half=int(a > median))
    return regions


# --------------------------------------------------------------------------- per-region errors


def umeyama_similarity(source_xyz: FloatArray, target_xyz: FloatArray) -> FloatArray:
    """``target_T_source`` with a scale: the similarity (4, 4; its 3×3 block is s·R) that best maps
    the (N, 3) source points onto the target points in the least-squares sense (Umeyama 1991)."""
    source_mean, target_mean = source_xyz.mean(axis=0), target_xyz.mean(axis=0)
    source, target = source_xyz - source_mean, target_xyz - target_mean
    covariance = target.T @ source / len(source)
    U, singular, Vt = np.linalg.svd(covariance)
    sign = np.ones(3)
    sign[2] = float(np.sign(np.linalg.det(U) * np.linalg.det(Vt))) or 1.0
    R = U @ np.diag(sign) @ Vt
    variance = float(np.mean(np.sum(source**2, axis=1)))
    scale = float(np.sum(singular * sign) / variance) if variance > 0 else 1.0
    T = np.eye(4)
    T[:3, :3] = scale * R
    T[:3, 3] = target_mean - scale * R @ source_mean
    return T


def fitted_rmse_m(
    map_T_tag: Mapping[int, FloatArray],
    gt_T_tag: Mapping[int, FloatArray],
    tags: Sequence[int],
    *,
    scale: bool,
) -> float:
    """RMS distance of ``tags``' map positions from the truth's after the best rigid (``scale``
    False, as ``metrics.tag_rmse_m``) or similarity fit of those tags alone, m; NaN with fewer
    than 3 tags in both (two tags leave a rigid fit's turn about their line free)."""
    common = [t for t in tags if t in map_T_tag and t in gt_T_tag]
    if len(common) < 3:
        return math.nan
    source = np.array([map_T_tag[t][:3, 3] for t in common])
    target = np.array([gt_T_tag[t][:3, 3] for t in common])
    T = umeyama_similarity(source, target) if scale else umeyama_rigid(source, target)
    aligned = source @ T[:3, :3].T + T[:3, 3]
    return float(np.sqrt(np.mean(np.sum((aligned - target) ** 2, axis=1))))


def transfer_rmse_m(
    map_T_tag: Mapping[int, FloatArray],
    gt_T_tag: Mapping[int, FloatArray],
    fitted: Sequence[int],
    placed: Sequence[int],
) -> float:
    """How well the map places one region against another: the map fitted rigidly to the truth
    on the ``fitted`` tags alone, the RMS distance of the ``placed`` tags from the truth, m (NaN
    with fewer than 3 fitted or no placed tags in both)."""
    fit = [t for t in fitted if t in map_T_tag and t in gt_T_tag]
    place = [t for t in placed if t in map_T_tag and t in gt_T_tag]
    if len(fit) < 3 or not place:
        return math.nan
    T = umeyama_rigid(
        np.array([map_T_tag[t][:3, 3] for t in fit]), np.array([gt_T_tag[t][:3, 3] for t in fit])
    )
    source = np.array([map_T_tag[t][:3, 3] for t in place])
    target = np.array([gt_T_tag[t][:3, 3] for t in place])
    aligned = source @ T[:3, :3].T + T[:3, 3]
    return float(np.sqrt(np.mean(np.sum((aligned - target) ** 2, axis=1))))


@dataclass(frozen=True, slots=True, kw_only=True)
class RegionErrors:
    """A map's tag errors against the truth: over all its tags, per floor and per half floor.

    all_rigid_m, all_similarity_m: over every tag, one fit, m.
    by_floor, by_half: region (``Region(floor, 0)`` stands for a floor in ``by_floor``) →
        (tags, rigid-fit RMSE m, similarity-fit RMSE m), each region fitted alone.
    between_floors_m: the map fitted on one floor's tags, the RMS error of the other floors'
        (:func:`transfer_rmse_m`), averaged over the floors fitted on, m (NaN with one floor).
    """

    all_rigid_m: float
    all_similarity_m: float
    by_floor: dict[Region, tuple[int, float, float]]
    by_half: dict[Region, tuple[int, float, float]]
    between_floors_m: float = math.nan

    def inside_rigid_m(self, level: str = "half") -> float:
        """RMS over the tags of every region of ``level`` (``floor`` or ``half``), each region
        fitted rigidly alone: what is left once the regions are placed independently, m."""
        rows = self.by_half if level == "half" else self.by_floor
        return _pooled(rows, 1)

    def inside_similarity_m(self, level: str = "half") -> float:
        rows = self.by_half if level == "half" else self.by_floor
        return _pooled(rows, 2)


def _pooled(rows: Mapping[Region, tuple[int, float, float]], column: int) -> float:
    pairs = [(n, r[column]) for r in rows.values() if math.isfinite(r[column]) for n in [r[0]]]
    total = sum(n for n, _ in pairs)
    return math.sqrt(sum(n * e**2 for n, e in pairs) / total) if total else math.nan


def region_errors(
    map_T_tag: Mapping[int, FloatArray],
    gt_T_tag: Mapping[int, FloatArray],
    regions: Mapping[int, Region],
    tags: Sequence[int] | None = None,
) -> RegionErrors:
    """``map_T_tag``'s errors over ``tags`` (default: every tag it shares with the truth) and
    per region of ``regions``."""
    tags = sorted(
        t for t in (map_T_tag if tags is None else tags) if t in gt_T_tag and t in regions
    )
    by_floor: dict[Region, list[int]] = {}
    by_half: dict[Region, list[int]] = {}
    for t in tags:
        by_floor.setdefault(Region(regions[t].floor, 0), []).append(t)
        by_half.setdefault(regions[t], []).append(t)

    def row(members: list[int]) -> tuple[int, float, float]:
        return (
            len(members),
            fitted_rmse_m(map_T_tag, gt_T_tag, members, scale=False),
            fitted_rmse_m(map_T_tag, gt_T_tag, members, scale=True),
        )

    transfers = [
        transfer_rmse_m(map_T_tag, gt_T_tag, members, [t for t in tags if t not in members])
        for members in by_floor.values()
    ]
    transfers = [e for e in transfers if math.isfinite(e)]
    return RegionErrors(
        all_rigid_m=fitted_rmse_m(map_T_tag, gt_T_tag, tags, scale=False),
        all_similarity_m=fitted_rmse_m(map_T_tag, gt_T_tag, tags, scale=True),
        by_floor={r: row(m) for r, m in sorted(by_floor.items())},
        by_half={r: row(m) for r, m in sorted(by_half.items())},
        between_floors_m=float(np.mean(transfers)) if transfers else math.nan,
    )


# --------------------------------------------------------------------------- connecting stretches


@dataclass(frozen=True, slots=True, kw_only=True)
class Stretch:
    """A walk's odometry from its last sighting in one region to its first in the next.

    from_detection, to_detection: rows of the session's detections at the two ends.
    from_tag, to_tag: the tags seen there; from_pose, to_pose: the session's pose rows.
    from_region, to_region: the two regions; crosses_floor: whether their floors differ.
    duration_s: time between the two sightings, s; length_m: odometry path length, m.
    """

    from_detection: int
    to_detection: int
    from_tag: int
    to_tag: int
    from_pose: int
    to_pose: int
    from_region: Region
    to_region: Region
    duration_s: float
    length_m: float

    @property
    def crosses_floor(self) -> bool:
        return self.from_region.floor != self.to_region.floor

    @property
    def label(self) -> str:
        return f"{self.from_tag}→{self.to_tag} ({self.from_region.label} → {self.to_region.label})"


def connecting_stretches(
    session: Session,
    regions: Mapping[int, Region],
    used: BoolArray | None = None,
    *,
    level: str = "half",
) -> list[Stretch]:
    """The stretches where ``session`` goes from one region to another (``level``: ``half`` for
    every change of half floor, ``floor`` for changes of floor only), in time order, over its
    ``used`` detections (all by default) of tags with a region."""
    d = session.detections
    rows = np.flatnonzero(np.ones(len(d), dtype=bool) if used is None else used)
    rows = rows[np.isin(d.tag_id[rows], list(regions))]
    rows = rows[np.argsort(d.timestamp_s[rows], kind="stable")]

    def key(row: int) -> Region:
        region = regions[int(d.tag_id[row])]
        return region if level == "half" else Region(region.floor, 0)

    steps = np.linalg.norm(np.diff(session.world_T_phone[:, :3, 3], axis=0), axis=1)
    walked_m = np.concatenate([[0.0], np.cumsum(steps)])
    out = []
    for a, b in itertools.pairwise(rows):
        if key(int(a)) == key(int(b)):
            continue
        i, j = int(d.pose_index[a]), int(d.pose_index[b])
        out.append(
            Stretch(
                from_detection=int(a),
                to_detection=int(b),
                from_tag=int(d.tag_id[a]),
                to_tag=int(d.tag_id[b]),
                from_pose=i,
                to_pose=j,
                from_region=regions[int(d.tag_id[a])],
                to_region=regions[int(d.tag_id[b])],
                duration_s=float(d.timestamp_s[b] - d.timestamp_s[a]),
                length_m=float(walked_m[j] - walked_m[i]),
            )
        )
    return out


@dataclass(frozen=True, slots=True, kw_only=True)
class PairError:
    """The pose of one tag relative to another, a map's (or the odometry's) against the truth.

    position_m: ‖(a_T_b).t − (a_T_b, true).t‖, in tag a's frame, m (a's orientation error moves
        it by distance × angle).
    rotation_deg: the angle of the relative rotation's error, deg.
    distance_m: error of the distance between the two tags (no orientation enters), m.
    height_m: error of the height of b above a (gravity-aligned frames), m.
    """

    position_m: float
    rotation_deg: float
    distance_m: float
    height_m: float


def pair_error(
    world_T_a: FloatArray, world_T_b: FloatArray, gt_T_a: FloatArray, gt_T_b: FloatArray
) -> PairError:
    """How tag b sits relative to tag a in one world against the truth (see :class:`PairError`)."""
    a_T_b = se3_inverse(world_T_a) @ world_T_b
    a_T_b_true = se3_inverse(gt_T_a) @ gt_T_b
    return PairError(
        position_m=float(np.linalg.norm(a_T_b[:3, 3] - a_T_b_true[:3, 3])),
        rotation_deg=math.degrees(rotation_angle_rad(a_T_b[:3, :3].T @ a_T_b_true[:3, :3])),
        distance_m=float(
            np.linalg.norm(world_T_b[:3, 3] - world_T_a[:3, 3])
            - np.linalg.norm(gt_T_b[:3, 3] - gt_T_a[:3, 3])
        ),
        height_m=float((world_T_b[1, 3] - world_T_a[1, 3]) - (gt_T_b[1, 3] - gt_T_a[1, 3])),
    )


def odometry_pair_error(
    session: Session, stretch: Stretch, gt_T_tag: Mapping[int, FloatArray]
) -> PairError:
    """The stretch's odometry against the truth: the two end sightings placed on the raw
    odometry (``world_T_phone · phone_T_tag``), relative to each other, against the true tags."""
    d = session.detections
    world_T_a = session.world_T_phone[stretch.from_pose] @ d.phone_T_tag[stretch.from_detection]
    world_T_b = session.world_T_phone[stretch.to_pose] @ d.phone_T_tag[stretch.to_detection]
    return pair_error(world_T_a, world_T_b, gt_T_tag[stretch.from_tag], gt_T_tag[stretch.to_tag])


#: The sightings that place a stretch's start against the truth: of the last this many distinct
#: tags seen up to its start (at least 2 are needed; 3 when the walk saw them).
FIT_TAGS = 3
#: … seen at most this long before the stretch starts, s.
FIT_WINDOW_S = 60.0


@dataclass(frozen=True, slots=True, kw_only=True)
class EndError:
    """Where a stretch's odometry puts the tag at its end, against the truth, with no sighting's
    orientation in it: the walk's raw sightings (positions only) of the last tags before the
    stretch fitted to the truth by a turn about gravity and a translation, that fit applied to the
    end sighting's position.

    horizontal_m, vertical_m: the end tag's error across and along gravity, m.
    fit_tags: the tags the start was fitted on; fit_rms_m: their RMS residual after the fit, m.
    yaw_deg: the stretch's heading error, deg: the turn of the same fit made on the first tags
        after it less the turn before (NaN with fewer than 2 tags after it); after_tags: those.
    """

    horizontal_m: float
    vertical_m: float
    fit_tags: tuple[int, ...]
    fit_rms_m: float
    yaw_deg: float = math.nan
    after_tags: tuple[int, ...] = ()

    @property
    def position_m(self) -> float:
        return math.hypot(self.horizontal_m, self.vertical_m)


@dataclass(frozen=True, slots=True)
class _GravityFit:
    """A turn about +y by ``angle_rad`` and a translation taking points (x–z about ``seen_mean``,
    height shifted by ``height_m``) onto the truth's."""

    angle_rad: float
    seen_mean_xz: FloatArray
    true_mean_xz: FloatArray
    height_m: float

    def place(self, p: FloatArray) -> FloatArray:
        c, s = math.cos(self.angle_rad), math.sin(self.angle_rad)
        xz = np.array([[c, -s], [s, c]]) @ (p[[0, 2]] - self.seen_mean_xz) + self.true_mean_xz
        return np.array([xz[0], p[1] + self.height_m, xz[1]])


def _gravity_fit(seen: FloatArray, true: FloatArray) -> _GravityFit:
    """The best turn about gravity and translation of ``seen`` (K, 3) onto ``true`` (2-D
    Procrustes on x–z, the mean height difference)."""
    seen_mean, true_mean = seen[:, [0, 2]].mean(axis=0), true[:, [0, 2]].mean(axis=0)
    a, b = seen[:, [0, 2]] - seen_mean, true[:, [0, 2]] - true_mean
    angle = math.atan2(
        float(np.sum(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0])),
        float(np.sum(a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1])),
    )
    return _GravityFit(angle, seen_mean, true_mean, float(np.mean(true[:, 1] - seen[:, 1])))


def odometry_end_error(
    session: Session,
    stretch: Stretch,
    gt_T_tag: Mapping[int, FloatArray],
    used: BoolArray | None = None,
) -> EndError | None:
    """The stretch's odometry against the truth, orientation-free (:class:`EndError`); None when
    fewer than 2 distinct tags with truth were seen in the ``FIT_WINDOW_S`` before it."""
    d = session.detections
    rows = np.flatnonzero(np.ones(len(d), dtype=bool) if used is None else used)
    rows = rows[np.isin(d.tag_id[rows], list(gt_T_tag))]
    start_s = float(d.timestamp_s[stretch.from_detection])
    end_s = float(d.timestamp_s[stretch.to_detection])
    before = rows[
        (d.timestamp_s[rows] <= start_s) & (d.timestamp_s[rows] >= start_s - FIT_WINDOW_S)
    ]
    after = rows[(d.timestamp_s[rows] >= end_s) & (d.timestamp_s[rows] <= end_s + FIT_WINDOW_S)]
    last = _nearest_tags(d.tag_id, before[np.argsort(-d.timestamp_s[before], kind="stable")])
    if len(last) < 2:
        return None
    first = _nearest_tags(d.tag_id, after[np.argsort(d.timestamp_s[after], kind="stable")])

    def seen_at(row: int) -> FloatArray:
        world_T_tag = session.world_T_phone[d.pose_index[row]] @ d.phone_T_tag[row]
        return np.asarray(world_T_tag[:3, 3], dtype=np.float64)

    def fit(sightings: Mapping[int, int]) -> tuple[_GravityFit, FloatArray, FloatArray]:
        seen = np.array([seen_at(row) for row in sightings.values()])
        true = np.array([gt_T_tag[t][:3, 3] for t in sightings])
        return _gravity_fit(seen, true), seen, true

    start, seen, true = fit(last)
    fitted = np.array([start.place(p) for p in seen])
    end = start.place(seen_at(stretch.to_detection)) - gt_T_tag[stretch.to_tag][:3, 3]
    yaw_deg = math.nan
    if len(first) >= 2:
        turn = fit(first)[0].angle_rad - start.angle_rad
        yaw_deg = math.degrees(math.remainder(turn, 2 * math.pi))
    return EndError(
        horizontal_m=float(np.hypot(end[0], end[2])),
        vertical_m=float(end[1]),
        fit_tags=tuple(last),
        fit_rms_m=float(np.sqrt(np.mean(np.sum((fitted - true) ** 2, axis=1)))),
        yaw_deg=yaw_deg,
        after_tags=tuple(first),
    )


def _nearest_tags(tag_id: npt.NDArray[np.int64], rows: npt.NDArray[np.int64]) -> dict[int, int]:
    """The first ``FIT_TAGS`` distinct tags of ``rows`` (in their order), each with its first
    row there."""
    out: dict[int, int] = {}
    for row in rows.tolist():
        tag = int(tag_id[row])
        if tag not in out and len(out) < FIT_TAGS:
            out[tag] = row
    return out


@dataclass(frozen=True, slots=True, kw_only=True)
class StretchTrust:
    """How much the model trusts a stretch's odometry, and how a solution bent it.

    sigma_translation_m: σ per axis of the stretch's relative translation (rate × duration), m.
    sigma_yaw_deg: σ of its relative rotation about each axis (yaw), deg.
    sigma_end_m: σ of where the stretch's end lands from its start, heading noise included
        (√(σ_t² + σ_ψ² L² / 3) for a path of length L), m.
    factors: odometry factors of the graph inside the stretch; chi2: their whitened squared
        residual, summed (6 rows each), at the solution.
    bend_m, bend_deg: how far the solution's relative pose of the two end poses is from the
        odometry's (translation m, rotation deg): how much the solution corrected the stretch.
    """

    sigma_translation_m: float
    sigma_yaw_deg: float
    sigma_end_m: float
    factors: int
    chi2: float
    bend_m: float
    bend_deg: float


def stretch_trust(
    session: Session,
    stretch: Stretch,
    params: SlamParams,
    noise_scales: FloatArray,
    world_T_phone_solved: FloatArray,
    residuals: FactorResiduals,
    *,
    pose_offset: int = 0,
) -> StretchTrust:
    """The model's σ for ``stretch`` (``params``' odometry rates × the walk's ``noise_scales``,
    ``noise.COMPONENTS`` order) and what the solution made of it: ``world_T_phone_solved`` are
    the solution's poses of the session (its rows), ``residuals`` the solution's factor
    residuals, whose pose rows are the session's shifted by ``pose_offset`` (a joint map)."""
    linear_var = params.odom_linear_var_m2_per_s * float(noise_scales[0])
    angular_var = params.odom_angular_var_rad2_per_s * float(noise_scales[1])
    sigma_t = math.sqrt(linear_var * stretch.duration_s)
    sigma_r = math.sqrt(angular_var * stretch.duration_s)
    keyframes = residuals.keyframe_index
    start, stop = stretch.from_pose + pose_offset, stretch.to_pose + pose_offset
    inside = (keyframes[:-1] >= start) & (keyframes[1:] <= stop)
    odometry_rel = (
        se3_inverse(session.world_T_phone[stretch.from_pose])
        @ (session.world_T_phone[stretch.to_pose])
    )
    solved_rel = (
        se3_inverse(world_T_phone_solved[stretch.from_pose])
        @ (world_T_phone_solved[stretch.to_pose])
    )
    return StretchTrust(
        sigma_translation_m=sigma_t,
        sigma_yaw_deg=math.degrees(sigma_r),
        sigma_end_m=math.sqrt(sigma_t**2 + (sigma_r * stretch.length_m) ** 2 / 3.0),
        factors=int(np.count_nonzero(inside)),
        chi2=float(residuals.odometry_chi2[inside].sum()),
        bend_m=float(np.linalg.norm(solved_rel[:3, 3] - odometry_rel[:3, 3])),
        bend_deg=math.degrees(rotation_angle_rad(solved_rel[:3, :3].T @ odometry_rel[:3, :3])),
    )
