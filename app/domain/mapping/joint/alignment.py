"""Step 2, two walks: one walk's tags placed on another's by a turn about +y and a translation.

Both frames are gravity-aligned, so a placement is a turn about +y and a translation, fitted
robustly on the tags the two share (:func:`align_session`, on the walks' own optimized tags); a
walk whose shared tags support no placement is refused with the reason (:class:`AlignmentError`).
:func:`weighted_similarity` is the weighted least-squares fit (with a scale) that placing all the
walks at once and the odometry scale build on.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from app.domain.frames import FloatArray, make_pose, rotation_about_y
from app.domain.mapping.joint.model import AlignmentError, BoolArray, SessionAlignment
from app.domain.upload.session import Session

#: Fewest tags two walks must share for one to place the other.
MIN_SHARED_TAGS = 2


#: A shared tag agrees with an alignment when its position, aligned, is within this of the map's, m.
ALIGNMENT_INLIER_M = 1.0


#: Fewest of the shared tags that must agree with the alignment, as a fraction of them.
MIN_INLIER_FRACTION = 0.5


#: Two shared tags closer than this horizontally propose no turn (their direction is noise), m.
MIN_PAIR_BASELINE_M = 2.0


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


@dataclass(frozen=True, slots=True)
class Similarity:
    map_T_world: FloatArray
    scale: float
    log_scale_sigma: float


def weighted_similarity(
    world_p: FloatArray,
    map_p: FloatArray,
    weights: FloatArray,
    fallback: FloatArray,
    *,
    scale: float | None = None,
) -> Similarity:
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
    return Similarity(
        map_T_world=make_pose(R, map_c - k * (R @ world_c)), scale=k, log_scale_sigma=sigma
    )


def _ids(ids: Sequence[int]) -> str:
    return ", ".join(str(i) for i in ids)
