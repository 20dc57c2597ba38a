"""Tags mark walls (issue 26): the walked positions a corridor skeleton is drawn from, moved off
the walls that the tags' normals reveal, so that a walk that veered to its tags draws the corridor
and not the way to its walls.

    walls = facing_walls(world_p_tag, world_n_tag, max_apart_m=5.0, max_along_m=8.0, reach_m=1.0)
    moved = between_facing_walls(world_p_phone, walls, taper_m=2.0)    # onto the corridor's middle
    moved = away_from_tag_walls(moved, world_p_tag, world_n_tag, clearance_m=0.8, reach_m=1.0)

The distances are the :class:`~app.domain.navigation.skeleton.SkeletonParams` of the same names
(``facing_max_apart_m``, ``facing_max_along_m``, ``tag_reach_m``, ``facing_taper_m``,
``tag_clearance_m``).

1. **Facing walls.** Two tags whose walls face each other (normals within
   ``FACING_MAX_ANGLE_DEG`` of opposite, each in front of the other, ``FACING_MIN_APART_M`` to
   ``max_apart_m`` apart across, at most ``max_along_m`` apart along the walls) bound a
   corridor. The positions between the two walls, from ``reach_m`` before the first tag to
   ``reach_m`` past the second, are moved onto the line midway between the walls, and those up
   to ``taper_m`` beyond less and less: a walker
   who crossed from a tag on one wall to a tag on the other then draws the corridor's
   middle, not a zigzag. Where two such stretches overlap, a position moves by the weighted mean.
   The caller leaves out the pairs with a junction of the corridors between them (see
   :func:`FacingWalls.holds_any`): there the two tags may be on the walls of different corridors
   (on the real floor 2 of the mac building, tags 312 and 313 face each other 3 m apart across
   the corners of a junction, and their middle line is neither corridor's).
2. **One wall.** A position in front of a tag (on its floor, within ``reach_m`` of it along its
   wall) nearer its wall than ``clearance_m`` is moved straight out to that distance.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from app.domain.frames import FloatArray

BoolArray = npt.NDArray[np.bool_]

#: A tag this far above or below a position is on another floor, m.
TAG_SAME_FLOOR_M = 1.5
#: Two tags' walls face each other when their normals are within this of opposite, degrees.
FACING_MAX_ANGLE_DEG = 25.0
#: … and they are at least this far apart across (two tags on one pillar are not), m.
FACING_MIN_APART_M = 1.0
#: A position this far behind either wall is beyond it, not between the two, m.
BEHIND_WALL_M = 0.5
#: A normal shorter than this in the horizontal plane belongs to a tag on the floor or the
#: ceiling: no wall.
MIN_HORIZONTAL_NORMAL = 0.5


@dataclass(frozen=True, slots=True)
class FacingWalls:
    """The walls of two tags that face each other, in the frame of the corridor between them:
    ``across`` the unit horizontal (x, z) direction from the first wall to the second, ``along``
    perpendicular to it; the walls at ``first_m`` and ``second_m`` across; the tags from
    ``from_m`` to ``to_m`` along (each widened by the reach); ``height_m`` the tags' mean height."""

    across: FloatArray
    along: FloatArray
    first_m: float
    second_m: float
    from_m: float
    to_m: float
    height_m: float

    def between(self, world_p: FloatArray) -> tuple[FloatArray, FloatArray, BoolArray]:
        """(across_m, along_m, between) of the positions (K, 3): their coordinates in the
        corridor's frame, and whether each is between the walls and on the tags' floor."""
        xz = world_p[:, [0, 2]]
        across_m, along_m = xz @ self.across, xz @ self.along
        between = (
            (across_m > self.first_m - BEHIND_WALL_M)
            & (across_m < self.second_m + BEHIND_WALL_M)
            & (np.abs(world_p[:, 1] - self.height_m) < TAG_SAME_FLOOR_M)
        )
        return across_m, along_m, between

    def holds_any(self, world_p: FloatArray) -> bool:
        """Whether any of the positions (K, 3) is between the walls, within the tags' stretch
        and on their floor."""
        if world_p.shape[0] == 0:
            return False
        _, along_m, between = self.between(world_p)
        return bool(np.any(between & (along_m >= self.from_m) & (along_m <= self.to_m)))


def facing_walls(
    world_p_tag: FloatArray,
    world_n_tag: FloatArray,
    *,
    max_apart_m: float,
    max_along_m: float,
    reach_m: float,
) -> list[FacingWalls]:
    """Every pair of tags (K, 3 positions; K, 3 normals out of their walls) whose walls face each
    other across a corridor (module step 1); none when ``max_apart_m`` is 0."""
    if max_apart_m <= 0:
        return []
    normals = world_n_tag[:, [0, 2]]
    lengths = np.linalg.norm(normals, axis=1)
    walled = np.flatnonzero(lengths >= MIN_HORIZONTAL_NORMAL).tolist()
    max_cos = -math.cos(math.radians(FACING_MAX_ANGLE_DEG))
    out = []
    for i, j in itertools.combinations(walled, 2):
        if abs(world_p_tag[i, 1] - world_p_tag[j, 1]) >= TAG_SAME_FLOOR_M:
            continue
        n_i, n_j = normals[i] / lengths[i], normals[j] / lengths[j]
        if float(n_i @ n_j) > max_cos:
            continue
        p_i, p_j = world_p_tag[i, [0, 2]], world_p_tag[j, [0, 2]]
        if float((p_j - p_i) @ n_i) <= 0 or float((p_i - p_j) @ n_j) <= 0:
            continue  # back to back: each behind the other's wall
        across = (n_i - n_j) / float(np.linalg.norm(n_i - n_j))
        along = np.array([-across[1], across[0]])
        first_m, second_m = float(p_i @ across), float(p_j @ across)
        a_i, a_j = float(p_i @ along), float(p_j @ along)
        if not FACING_MIN_APART_M <= second_m - first_m <= max_apart_m:
            continue
        if abs(a_j - a_i) > max_along_m:
            continue
        out.append(
            FacingWalls(
                across=across,
                along=along,
                first_m=first_m,
                second_m=second_m,
                from_m=min(a_i, a_j) - reach_m,
                to_m=max(a_i, a_j) + reach_m,
                height_m=0.5 * float(world_p_tag[i, 1] + world_p_tag[j, 1]),
            )
        )
    return out


def between_facing_walls(
    world_p_phone: FloatArray, walls: list[FacingWalls], *, taper_m: float
) -> FloatArray:
    """``world_p_phone`` (N, 3) with the positions between each pair of ``walls`` moved onto
    their middle line, fully along the tags' stretch and less and less over ``taper_m`` beyond
    it (module step 1)."""
    if not walls or world_p_phone.shape[0] == 0:
        return world_p_phone
    order = np.argsort(world_p_phone[:, 0], kind="stable")
    sorted_x = world_p_phone[order, 0]
    shift_sum = np.zeros((world_p_phone.shape[0], 2))
    weight_sum = np.zeros(world_p_phone.shape[0])
    weight_max = np.zeros(world_p_phone.shape[0])
    for w in walls:
        # only the positions whose x is within the stretch's box are looked at
        corners_x = [
            a * w.along[0] + c * w.across[0]
            for a in (w.from_m - taper_m, w.to_m + taper_m)
            for c in (w.first_m - BEHIND_WALL_M, w.second_m + BEHIND_WALL_M)
        ]
        rows = order[
            np.searchsorted(sorted_x, min(corners_x), "left") : np.searchsorted(
                sorted_x, max(corners_x), "right"
            )
        ]
        if rows.size == 0:
            continue
        across_m, along_m, between = w.between(world_p_phone[rows])
        beyond_m = np.maximum(w.from_m - along_m, along_m - w.to_m)
        if taper_m > 0:
            weight = np.clip(1.0 - beyond_m / taper_m, 0.0, 1.0)
        else:
            weight = (beyond_m <= 0).astype(np.float64)
        weight[~between] = 0.0
        middle_m = 0.5 * (w.first_m + w.second_m)
        shift_sum[rows] += (weight * (middle_m - across_m))[:, None] * w.across
        weight_sum[rows] += weight
        weight_max[rows] = np.maximum(weight_max[rows], weight)
    moved = np.flatnonzero(weight_sum > 0)
    out = world_p_phone.copy()
    shift = shift_sum[moved] / weight_sum[moved, None] * weight_max[moved, None]
    out[moved, 0] += shift[:, 0]
    out[moved, 2] += shift[:, 1]
    return out


def away_from_tag_walls(
    world_p_phone: FloatArray,
    world_p_tag: FloatArray,
    world_n_tag: FloatArray,
    *,
    clearance_m: float,
    reach_m: float,
) -> FloatArray:
    """``world_p_phone`` (N, 3) with each position in front of a tag (on its floor, within
    ``reach_m`` of it along its wall) and nearer its wall than ``clearance_m`` moved straight out
    from the wall to that distance (module step 2): the passes that stepped or veered to a tag
    then draw the corridor, not the way to its wall."""
    out = world_p_phone.copy()
    # a position in front of a tag is within this of it in x and in z (a cheap first look)
    box_m = reach_m + max(clearance_m, BEHIND_WALL_M)
    for p_tag, n_tag in zip(world_p_tag, world_n_tag, strict=True):
        normal = np.array([n_tag[0], n_tag[2]])
        norm = float(np.linalg.norm(normal))
        if norm < MIN_HORIZONTAL_NORMAL or clearance_m <= 0:
            continue
        normal /= norm
        along_wall = np.array([-normal[1], normal[0]])
        rows = np.flatnonzero(
            (np.abs(out[:, 0] - p_tag[0]) < box_m) & (np.abs(out[:, 2] - p_tag[2]) < box_m)
        )
        rel = out[rows][:, [0, 2]] - p_tag[[0, 2]]
        out_m, beside_m = rel @ normal, rel @ along_wall
        near = (
            (np.abs(out[rows, 1] - p_tag[1]) < TAG_SAME_FLOOR_M)
            & (out_m > -BEHIND_WALL_M)  # a position just behind the tag's plane is at its wall
            & (out_m < clearance_m)
            & (np.abs(beside_m) < reach_m)
        )
        if near.any():
            out[np.ix_(rows[near], [0, 2])] += (clearance_m - out_m[near])[:, None] * normal
    return out


#: A visit to a tag leaves and rejoins the walk's line at most this far along the walk from the
#: point nearest the tag, m.
VISIT_MAX_REACH_M = 5.0
#: … and the way it would have gone (from where it left to where it rejoined) runs at least this
#: far along the tag's wall (a step in and back, or a dead end, goes nowhere along it), m.
VISIT_MIN_ALONG_M = 2.0
#: … within this of parallel to the wall, degrees.
VISIT_MAX_ANGLE_DEG = 20.0
#: … and the visit goes at most this much nearer the wall than that way (deeper is an alcove), m.
VISIT_MAX_DEPTH_M = 2.5
#: … and reaches within this of the wall (it went to the tag), m.
VISIT_NEAR_WALL_M = 1.2
#: … and comes back to its line: where it left and where it rejoined are within this of the same
#: distance from the wall (a walk from wall to wall, to tags on both, is no visit), m.
VISIT_SAME_LINE_M = 0.75


def without_tag_visits(
    world_p_phone: FloatArray,
    bounds: list[tuple[int, int]],
    world_p_tag: FloatArray,
    world_n_tag: FloatArray,
) -> FloatArray:
    """``world_p_phone`` (N, 3) with every *oblique visit* to a tag straightened (issue 39): a
    stretch of one walk (``bounds``: (first row, end row) of each) that leaves its line, goes
    within ``VISIT_NEAR_WALL_M`` of a tag's wall in front of the tag and comes back to its line,
    each within ``VISIT_MAX_REACH_M`` along the walk, is replaced by the straight way from where
    it left to where it rejoined, when that way runs along the wall (at least
    ``VISIT_MIN_ALONG_M``, within ``VISIT_MAX_ANGLE_DEG`` of parallel), the two ends are as far
    from the wall (within ``VISIT_SAME_LINE_M``: it came back to its line) and the visit went
    at most ``VISIT_MAX_DEPTH_M`` nearer the wall than them. A walker who veers to a tag 3 m
    ahead and drifts back to the corridor's line drew a bend there, told as a turn (a 19° bend
    on real floor 2 of the mac building). Where it left and rejoined: going away from the point
    nearest the tag, the last position before the walk stops getting farther from the wall. A
    step straight in and back, and a walk into an alcove and back, rejoin where they left, and
    stay."""
    out = world_p_phone.copy()
    if world_p_tag.shape[0] == 0 or out.shape[0] < 3:
        return out
    xz = world_p_phone[:, [0, 2]]
    cos_max = math.cos(math.radians(VISIT_MAX_ANGLE_DEG))
    for p_tag, n_tag in zip(world_p_tag, world_n_tag, strict=True):
        n_xz = n_tag[[0, 2]]
        norm = float(np.hypot(*n_xz))
        if norm < MIN_HORIZONTAL_NORMAL:
            continue
        n_xz = n_xz / norm
        wall_dir = np.array([-n_xz[1], n_xz[0]])
        for first, end in bounds:
            rel = xz[first:end] - p_tag[[0, 2]]
            off_wall_m = rel @ n_xz
            along_m = rel @ wall_dir
            same_floor = np.abs(world_p_phone[first:end, 1] - p_tag[1]) < TAG_SAME_FLOOR_M
            near = same_floor & (off_wall_m > -BEHIND_WALL_M) & (off_wall_m < VISIT_NEAR_WALL_M)
            near &= np.abs(along_m) < VISIT_NEAR_WALL_M
            step_m = np.hypot(*np.diff(xz[first:end], axis=0).T)
            arc_m = np.concatenate([[0.0], np.cumsum(step_m)])
            done_to = -1
            for k in np.flatnonzero(near).tolist():
                if k <= done_to:
                    continue
                i = _rejoined(off_wall_m, arc_m, same_floor, k, -1)
                j = _rejoined(off_wall_m, arc_m, same_floor, k, +1)
                done_to = j
                way = xz[first + j] - xz[first + i]
                way_m = float(np.hypot(*way))
                if way_m < VISIT_MIN_ALONG_M or abs(float(way @ wall_dir)) < cos_max * way_m:
                    continue
                depth_m = min(off_wall_m[i], off_wall_m[j]) - float(off_wall_m[i : j + 1].min())
                if (
                    depth_m > VISIT_MAX_DEPTH_M
                    or abs(off_wall_m[i] - off_wall_m[j]) > VISIT_SAME_LINE_M
                ):
                    continue
                t = (arc_m[i : j + 1] - arc_m[i]) / max(arc_m[j] - arc_m[i], 1e-12)
                out[first + i : first + j + 1, [0, 2]] = xz[first + i] + t[:, None] * way
    return out


def _rejoined(
    off_wall_m: FloatArray, arc_m: FloatArray, same_floor: BoolArray, k: int, step: int
) -> int:
    """From row k, going ``step`` (±1) along the walk, the last row before the walk stops
    getting farther from the wall (``off_wall_m``), at most ``VISIT_MAX_REACH_M`` along it and
    on the tag's floor."""
    at = k
    while True:
        nxt = at + step
        if nxt < 0 or nxt >= off_wall_m.shape[0] or not same_floor[nxt]:
            return at
        if abs(arc_m[nxt] - arc_m[k]) > VISIT_MAX_REACH_M:
            return at
        if off_wall_m[nxt] < off_wall_m[at] + 0.01:  # no longer moving away from the wall
            return at
        at = nxt
