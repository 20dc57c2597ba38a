"""Step 2, all the walks: each walk placed in the map frame, and each walk's odometry scale.

Every pair of walks that shares tags is aligned (``alignment.align_session``); a spanning tree of
the best pairs gives a first placement (:func:`walk_placements`), and an iteratively reweighted
fit of all walks to all shared tags at once refines it (:func:`align_walks`). The result is the
same for any order (the fit is to a fixed point; ties are broken by the walks' names, never by
their position). A walk no other walk's tags place is refused with the reason
(``AlignmentError``).

Step 3's candidates come from the same fits (:func:`odometry_scale_candidates`): each pair of
walks sharing ≥ 3 tags gives their relative scale (symmetrically); the walks' scales are the
least-squares solution about their median. ``scale.py`` tests them on the joint map's cost.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np

from app.domain.frames import FloatArray, make_pose, rotation_about_y, se3_inverse
from app.domain.mapping.joint.alignment import (
    ALIGNMENT_INLIER_M,
    MIN_PAIR_BASELINE_M,
    MIN_SHARED_TAGS,
    align_session,
    weighted_similarity,
    yaw_of,
)
from app.domain.mapping.joint.model import AlignmentError, IntArray, PairAlignment, SessionAlignment

#: A walk's odometry is rescaled when its scale against the other walks' is off by more than
#: this many standard errors of the placement's fit …
SCALE_SIGMAS = 3.0


#: … and by more than this fraction …
MIN_ODOMETRY_SCALE_CHANGE = 0.005


#: … in a map of at least this many walks (of two whose scales differ, the data cannot tell
#: whose is right) …
MIN_WALKS_FOR_SCALE = 3


#: Robust weight scale of the walks' placement fit: a shared tag this far from the others' weighs
#: half, m.
PLACEMENT_ROBUST_M = 1.0


#: Iterations of that fit (each an exact weighted fit; it stops earlier when nothing moves).
PLACEMENT_ITERATIONS = 50


def align_walks(
    datasets: Sequence[str],
    world_T_tag: Sequence[Mapping[int, FloatArray]],
    *,
    min_shared_tags: int = MIN_SHARED_TAGS,
    odometry_scales: Sequence[float] | None = None,
    first_placements: Mapping[int, FloatArray] | None = None,
) -> tuple[SessionAlignment, ...]:
    """Each walk's placement in the map frame (the first walk's world), from the tags the walks
    share (step 2, the module docstring): pairwise robust alignments, a maximum spanning tree
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


def placed_alignments(
    datasets: Sequence[str],
    world_T_tag: Sequence[Mapping[int, FloatArray]],
    placed: Mapping[int, FloatArray],
) -> tuple[SessionAlignment, ...]:
    """The walks' alignments at placements made elsewhere (``placed``: each walk's
    ``map_T_world``, e.g. the ISAM2 engine's), unscaled: their shared tags and distances from
    the others', as :func:`align_walks` reports its own placements."""
    ones = dict.fromkeys(range(len(datasets)), 1.0)
    return tuple(_alignment(s, datasets, world_T_tag, placed, ones) for s in range(len(datasets)))


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
            i_from_j = weighted_similarity(p_j, p_i, ones, np.eye(4))
            j_from_i = weighted_similarity(p_i, p_j, ones, np.eye(4))
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
