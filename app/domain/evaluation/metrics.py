"""Map quality metrics, exactly as docs/architecture.md §4 defines them.

    ground_truth_metric(map_T_tag, gt_T_tag)    # the authors' anchor metric, dimensionless
    tag_rmse_m(map_T_tag, gt_T_tag)             # anchor-free, m, after a best-fit rigid alignment
    shift_metric(session, map_T_tag)            # no ground truth needed, dimensionless
    shift_metric_joint(sessions, map_T_tag)     # over several sessions' detections
    compare_tag_sets(map_T_tag, gt_T_tag)       # which tags the comparison can use

Maps and ground truths are ``{tag_id: world_T_tag}`` with 4x4 float64 poses (m). Lower is better for
all three metrics; each is NaN when there is nothing to measure (too few common tags, no pairs).
Tags present in only one of map and ground truth are ignored; :func:`compare_tag_sets` lists them
so callers can report them.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from app.domain.frames import FloatArray, se3_inverse
from app.domain.upload.session import Session

if TYPE_CHECKING:
    from app.domain.mapping.joint import JointMap

BoolArray = npt.NDArray[np.bool_]

#: Which definition of the shift metric the numbers were computed with. 1: the origin-dependent
#: ``‖(rel_obs · rel_map⁻¹).t‖`` with ``rel = world_T_B · world_T_A⁻¹`` (before issue 15); 2: the
#: paper's, anchored at tag A (docs/architecture.md §4). Stored with sweeps and map metrics.
SHIFT_METRIC_VERSION = 2

#: Two ground-truth tags closer than this (m) give no ratio in the ground-truth metric.
COINCIDENT_TAGS_M = 1e-9


@dataclass(frozen=True, slots=True, kw_only=True)
class TagSetComparison:
    """Tag ids of a map against a ground truth, each tuple sorted.

    common: in both; the metrics use these only.
    only_in_map: mapped tags the ground truth does not cover.
    only_in_ground_truth: ground-truth tags the map lacks (unknown ids are ignored, not an error).
    """

    common: tuple[int, ...]
    only_in_map: tuple[int, ...]
    only_in_ground_truth: tuple[int, ...]


def compare_tag_sets(
    map_T_tag: Mapping[int, FloatArray], gt_T_tag: Mapping[int, FloatArray]
) -> TagSetComparison:
    """Which tags are in both the map and the ground truth, and which in only one of them."""
    map_ids, gt_ids = {int(t) for t in map_T_tag}, {int(t) for t in gt_T_tag}
    return TagSetComparison(
        common=tuple(sorted(map_ids & gt_ids)),
        only_in_map=tuple(sorted(map_ids - gt_ids)),
        only_in_ground_truth=tuple(sorted(gt_ids - map_ids)),
    )


# --------------------------------------------------------------------------- ground-truth metric


def ground_truth_metric(
    map_T_tag: Mapping[int, FloatArray], gt_T_tag: Mapping[int, FloatArray]
) -> float:
    """The authors' ground-truth metric (docs/architecture.md §4), dimensionless, lower is better.

    Over the tags common to map and ground truth: each tag ``a`` in turn is the anchor, the ground
    truth is aligned to the map by ``T = map_T_a · gt_T_a⁻¹`` (full SE(3)), and for every other tag
    ``i`` the ratio ``‖(T·gt_i).t - map_i.t‖ / ‖(T·gt_i).t - map_a.t‖`` is taken (the error at ``i``
    over the ground-truth distance from ``a`` to ``i``). The result is the mean over all ordered
    pairs (a, i ≠ a), which equals the mean of the per-anchor means since each anchor has the same
    number of partners. Pairs whose two ground-truth tags coincide (closer than
    :data:`COINCIDENT_TAGS_M`) give no ratio and are left out.

    Returns NaN with fewer than 2 common tags (no pair to measure).
    """
    common = compare_tag_sets(map_T_tag, gt_T_tag).common
    if len(common) < 2:
        return math.nan
    map_poses = _stack(map_T_tag, common)
    gt_poses = _stack(gt_T_tag, common)
    # anchor_T[a] = map_T_a · gt_T_a⁻¹ maps ground-truth coordinates into the map for anchor a.
    anchor_T = map_poses @ se3_inverse(gt_poses)
    # aligned_t[a, i] = (anchor_T[a] · gt_i).t, shape (n, n, 3).
    aligned_t = (
        np.einsum("aij,kj->aki", anchor_T[:, :3, :3], gt_poses[:, :3, 3]) + anchor_T[:, None, :3, 3]
    )
    error_m = np.linalg.norm(aligned_t - map_poses[None, :, :3, 3], axis=-1)
    reach_m = np.linalg.norm(aligned_t - map_poses[:, None, :3, 3], axis=-1)
    usable = ~np.eye(len(common), dtype=bool) & (reach_m > COINCIDENT_TAGS_M)
    if not usable.any():
        return math.nan
    return float(np.mean(error_m[usable] / reach_m[usable]))


# --------------------------------------------------------------------------- tag RMSE


def umeyama_rigid(source_xyz: npt.ArrayLike, target_xyz: npt.ArrayLike) -> FloatArray:
    """``target_T_source``: the rotation and translation (no scale) that best map the source points
    onto the target points in the least-squares sense (Umeyama 1991).

    source_xyz, target_xyz: (N, 3) corresponding points, N ≥ 1. The result is always a proper
    rotation (det +1), never a reflection. With N = 1 the rotation is undetermined (the identity
    direction of the SVD is used) and the translation makes the points coincide; with N = 2 or
    collinear points the rotation about their line is undetermined.
    """
    source = np.asarray(source_xyz, dtype=np.float64)
    target = np.asarray(target_xyz, dtype=np.float64)
    if source.ndim != 2 or source.shape[1] != 3 or source.shape != target.shape:
        raise ValueError(
            f"expected two (N, 3) point arrays of the same shape, got {source.shape} and "
            f"{target.shape}"
        )
    if source.shape[0] == 0:
        raise ValueError("need at least one point pair")
    if not (np.all(np.isfinite(source)) and np.all(np.isfinite(target))):
        raise ValueError("points contain a non-finite number")
    source_mean = source.mean(axis=0)
    target_mean = target.mean(axis=0)
    covariance = (target - target_mean).T @ (source - source_mean) / source.shape[0]
    U, _, Vt = np.linalg.svd(covariance)
    reflection = float(np.sign(np.linalg.det(U) * np.linalg.det(Vt)))  # ±1: U, V orthogonal
    target_R_source = U @ np.diag([1.0, 1.0, reflection]) @ Vt
    target_T_source = np.eye(4)
    target_T_source[:3, :3] = target_R_source
    target_T_source[:3, 3] = target_mean - target_R_source @ source_mean
    return target_T_source


def tag_rmse_m(map_T_tag: Mapping[int, FloatArray], gt_T_tag: Mapping[int, FloatArray]) -> float:
    """Anchor-free tag position error, m (docs/architecture.md §4).

    The map's tag positions (of the tags common to map and ground truth) are aligned to the ground
    truth's by the best-fit rigid transform (:func:`umeyama_rigid`, no scale); the result is the
    root-mean-square distance between aligned and ground-truth positions. Orientations are not used.

    Returns NaN with fewer than 2 common tags (a single tag always aligns exactly, so 0 would be
    meaningless).
    """
    distances_m = _aligned_distances_m(map_T_tag, gt_T_tag)
    return math.nan if distances_m is None else float(np.sqrt(np.mean(distances_m**2)))


def largest_tag_distance_m(
    map_T_tag: Mapping[int, FloatArray], other_T_tag: Mapping[int, FloatArray]
) -> float:
    """The largest distance between two maps' common tags after the best-fit rigid transform
    (as :func:`tag_rmse_m` aligns them), m: how far apart two builds of one building are (the
    order spread of docs/multi-session.md). NaN with fewer than 2 common tags."""
    distances_m = _aligned_distances_m(map_T_tag, other_T_tag)
    return math.nan if distances_m is None else float(np.max(distances_m))


def _aligned_distances_m(
    map_T_tag: Mapping[int, FloatArray], gt_T_tag: Mapping[int, FloatArray]
) -> FloatArray | None:
    """Per common tag, the distance between the map's position aligned to ``gt_T_tag``'s by the
    best-fit rigid transform and that position, m; None with fewer than 2 common tags."""
    common = compare_tag_sets(map_T_tag, gt_T_tag).common
    if len(common) < 2:
        return None
    return aligned_distances_m(
        _stack(map_T_tag, common)[:, :3, 3], _stack(gt_T_tag, common)[:, :3, 3]
    )


def aligned_distances_m(source_xyz: FloatArray, target_xyz: FloatArray) -> FloatArray:
    """(N,) the distance from each target point (N, 3) to its source point (N, 3) once the source
    is moved by the best-fit rigid transform onto the target (:func:`umeyama_rigid`), m."""
    target_T_source = umeyama_rigid(source_xyz, target_xyz)
    aligned_xyz = source_xyz @ target_T_source[:3, :3].T + target_T_source[:3, 3]
    distances_m: FloatArray = np.linalg.norm(aligned_xyz - target_xyz, axis=1)
    return distances_m


# --------------------------------------------------------------------------- shift metric


@dataclass(frozen=True, slots=True, kw_only=True)
class ShiftPairs:
    """The consecutive single-tag sightings of different tags that the shift metric compares,
    taken once from a session so that many maps of it can be scored (a sweep).

    tag_a, tag_b: (P,) the tag seen first and the one seen next.
    rel_obs: (P, 4, 4) ``A_T_B,obs = world_T_A,obs⁻¹ · world_T_B,obs``; reach_m: (P,)
        ``‖rel_obs.t‖`` > 0, the observed distance from A to B, m.
    """

    tag_a: npt.NDArray[np.int64]
    tag_b: npt.NDArray[np.int64]
    rel_obs: FloatArray
    reach_m: FloatArray


def shift_pairs(session: Session, *, detection_mask: BoolArray | None = None) -> ShiftPairs:
    """The pairs :func:`shift_metric` averages over, before any map is known (see there)."""
    detections = session.detections
    count = len(detections)
    selected = detections.frame_size == 1
    if detection_mask is not None:
        mask = np.asarray(detection_mask)
        if mask.shape != (count,) or mask.dtype != np.bool_:
            raise ValueError(
                f"detection_mask must be a bool array of shape ({count},), "
                f"got {mask.dtype} {mask.shape}"
            )
        selected = selected & mask
    rows = np.flatnonzero(selected)
    world_T_tag_obs = (
        session.world_T_phone[detections.pose_index[rows]] @ detections.phone_T_tag[rows]
    )
    tag_ids = detections.tag_id[rows].astype(np.int64)
    different = tag_ids[:-1] != tag_ids[1:]
    first, second = np.flatnonzero(different), np.flatnonzero(different) + 1
    rel_obs = se3_inverse(world_T_tag_obs[first]) @ world_T_tag_obs[second]
    reach_m = np.linalg.norm(rel_obs[:, :3, 3], axis=1)
    keep = reach_m > 0.0
    return ShiftPairs(
        tag_a=tag_ids[first][keep],
        tag_b=tag_ids[second][keep],
        rel_obs=rel_obs[keep],
        reach_m=reach_m[keep],
    )


def mean_shift_ratio(pairs: ShiftPairs, map_T_tag: Mapping[int, FloatArray]) -> float:
    """The shift metric of ``map_T_tag`` over ``pairs``; pairs with a tag not in the map are
    skipped (not bridged); NaN when no pair is left."""
    in_map = np.array(
        [
            int(a) in map_T_tag and int(b) in map_T_tag
            for a, b in zip(pairs.tag_a, pairs.tag_b, strict=True)
        ],
        dtype=bool,
    )
    if not in_map.any():
        return math.nan
    map_T_a = _stack(map_T_tag, tuple(int(t) for t in pairs.tag_a[in_map]))
    map_T_b = _stack(map_T_tag, tuple(int(t) for t in pairs.tag_b[in_map]))
    rel_map = se3_inverse(map_T_a) @ map_T_b
    shift_m = pairs.rel_obs[in_map, :3, 3] - rel_map[:, :3, 3]
    ratios = np.linalg.norm(shift_m, axis=1) / pairs.reach_m[in_map]
    return float(np.mean(ratios))


def shift_metric(
    session: Session,
    map_T_tag: Mapping[int, FloatArray],
    *,
    detection_mask: BoolArray | None = None,
) -> float:
    """The shift metric (§4): how far the map "jumps" between consecutive tag sightings.

    Only single-tag detections count (frames with exactly one detection), in upload order; with
    ``detection_mask`` ((M,) bool over ``session.detections``) only the masked ones, so
    "consecutive" means consecutive among the masked single-tag detections. For each consecutive
    pair of detections of *different* tags A then B::

        rel_obs = world_T_A,obs⁻¹ · world_T_B,obs    # B seen from A, raw observations
        rel_map = map_T_A⁻¹ · map_T_B                # B predicted from A by the map
        ratio   = ‖rel_obs.t − rel_map.t‖ / ‖rel_obs.t‖

    and the result is the mean ratio over pairs, dimensionless. A pair is skipped when A or B is
    not in the map (the pair is not bridged to the next detection), or when ``‖rel_obs.t‖`` is 0.
    Returns NaN when no pair is left.

    Both relative poses are expressed in tag A's frame, so the value is the same for any world
    origin and heading of the session, and of the map (the paper's anchoring; version
    :data:`SHIFT_METRIC_VERSION`). An earlier form, ``‖(rel_obs · rel_map⁻¹).t‖`` with
    ``rel = world_T_B · world_T_A⁻¹``, depended on where the world origin was.
    """
    return mean_shift_ratio(shift_pairs(session, detection_mask=detection_mask), map_T_tag)


def joint_shift_pairs(sessions: Sequence[Session], masks: Sequence[BoolArray]) -> ShiftPairs:
    """Every session's shift-metric pairs (each from its own detections, in its own frame)."""
    pairs = [
        shift_pairs(session, detection_mask=mask)
        for session, mask in zip(sessions, masks, strict=True)
    ]
    return ShiftPairs(
        tag_a=np.concatenate([p.tag_a for p in pairs]),
        tag_b=np.concatenate([p.tag_b for p in pairs]),
        rel_obs=np.concatenate([p.rel_obs for p in pairs]),
        reach_m=np.concatenate([p.reach_m for p in pairs]),
    )


def joint_shift_metric(joint: JointMap, map_T_tag: Mapping[int, FloatArray] | None = None) -> float:
    """The shift metric of a building map over every session's own detections (each in its own
    frame, which the metric does not depend on): the mean over all sessions' pairs. ``map_T_tag``
    defaults to the joint map's optimized tags."""
    return mean_shift_ratio(
        joint_shift_pairs(joint.sessions, joint.session_masks()),
        joint.map.tag_poses() if map_T_tag is None else map_T_tag,
    )


def _stack(poses: Mapping[int, FloatArray], tag_ids: tuple[int, ...]) -> FloatArray:
    return np.stack([np.asarray(poses[t], dtype=np.float64) for t in tag_ids])
