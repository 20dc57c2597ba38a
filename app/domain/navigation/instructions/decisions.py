"""Where the turns of a walked stretch are (steps 1–2 of the package docstring): its decision
points (:func:`decision_points`: bends measured over ``CHORD_M``, placed at junctions, a stronger
one's tail dropped), which of them are spoken (:func:`announced`), and the one rule that names a
turn by its angle alone (:func:`turn_class`)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TypeAlias

import numpy as np

from app.domain.frames import FloatArray
from app.domain.navigation.routing import TurnClass

#: Bends closer than this along the route are one decision; instructions are at least this far
#: apart except at junctions, m.
MIN_SPACING_M = 5.0
#: A bend is measured between the directions over this distance before and after it, m.
CHORD_M = 4.0
#: No decision this close to either end of a walked stretch (the arrival or the facing step
#: covers it), m.
END_MARGIN_M = 2.0
#: A bend this close to a junction (along the route, m) is at that junction.
JUNCTION_SNAP_M = 3.0
#: A bend within ``CHORD_M`` of a stronger decision is measured again with its chords stopping
#: there (:func:`_tail_of`) when both are at least this long, m.
TAIL_MIN_CHORD_M = 0.5
#: One rule for the words of a turn, by its angle alone (:func:`turn_class`, docs/navigation.md
#: "Instruction wording"): |turn| below this is straight on (no facing step, a goal "ahead"),
#: degrees.
STRAIGHT_MAX_DEG = 20.0
#: From ``STRAIGHT_MAX_DEG`` up to this, "bear left/right"; from this, "turn left/right",
#: degrees.
TURN_MIN_DEG = 45.0
#: From this, "turn sharp left/right", degrees.
SHARP_MIN_DEG = 135.0
#: From this, "turn around" (a goal "behind you"), degrees.
TURN_AROUND_MIN_DEG = 150.0
#: A bend of a walked stretch is a decision from this much (and spoken if it is a turn, or a bear
#: at a junction), degrees.
BEAR_MIN_DEG = 30.0


@dataclass(frozen=True, slots=True, kw_only=True)
class Decision:
    """A decision point of a route: ``index`` of the polyline point, signed ``turn_deg`` (+ left),
    ``at_junction``, ``along_m`` (distance along the route from its start, m)."""

    index: int
    turn_deg: float
    at_junction: bool
    along_m: float


def decision_points(
    xyz: FloatArray,
    junction: Sequence[bool],
    *,
    end_margin_m: float = END_MARGIN_M,
) -> list[Decision]:
    """The decision points of a walked stretch (N, 3) whose points ``junction`` flags (module
    step 2): bends of at least ``BEAR_MIN_DEG`` measured over ``CHORD_M`` either side, strongest
    first, none within ``MIN_SPACING_M`` of a stronger one (unless both are junctions), none within
    ``end_margin_m`` of the stretch's ends."""
    walked_m = walked_distances_m(xyz)
    return [
        Decision(index=index, turn_deg=turn_deg, at_junction=at_junction, along_m=along_m)
        for index, turn_deg, at_junction, along_m in decisions_along(
            xyz, junction, walked_m, walked_m.tolist(), end_margin_m
        )
    ]


#: A decision point as (index, turn_deg, at_junction, along_m): the fields of :class:`Decision`.
_DecisionTuple: TypeAlias = tuple[int, float, bool, float]


def decisions_along(
    xyz: FloatArray,
    junction: Sequence[bool],
    walked_m: FloatArray,
    walked: list[float],
    end_margin_m: float,
) -> list[_DecisionTuple]:
    """:func:`decision_points` as tuples, given each point's distance along the stretch both as
    an array and as a list."""
    chosen: list[_DecisionTuple] = []
    junctions = [j for j in range(len(xyz)) if junction[j]]
    for k, turn_deg in sorted(_bends(xyz, walked_m, walked, end_margin_m), key=_strongest):
        index, at_junction = k, False
        nearest_m = JUNCTION_SNAP_M
        for j in junctions:  # the nearest junction within JUNCTION_SNAP_M, the first of equals
            gap_m = abs(walked[j] - walked[k])
            if gap_m <= nearest_m and not (at_junction and gap_m == nearest_m):
                index, at_junction, nearest_m = j, True, gap_m
        along_m = walked[index]
        if not any(
            index == d_index
            or (abs(along_m - d_along_m) < MIN_SPACING_M and not (at_junction and d_at_junction))
            for d_index, _, d_at_junction, d_along_m in chosen
        ) and not _tail_of(xyz, walked_m, walked[k], [d[3] for d in chosen]):
            chosen.append((index, turn_deg, at_junction, along_m))
    chosen.sort(key=_along)
    return chosen


def _tail_of(xyz: FloatArray, walked_m: FloatArray, at_m: float, chosen_m: list[float]) -> bool:
    """Whether the bend at ``at_m`` along the stretch (N, 3) is the tail of a stronger decision
    ``chosen_m`` along it within ``CHORD_M``: measured with its chords stopping at the decisions
    (the walker turned there), it bends less than ``BEAR_MIN_DEG``."""
    before_m = [d for d in chosen_m if at_m - CHORD_M < d < at_m]
    after_m = [d for d in chosen_m if at_m < d < at_m + CHORD_M]
    if not before_m and not after_m:
        return False
    total_m = float(walked_m[-1])
    from_m = max([at_m - CHORD_M, 0.0, *before_m])
    to_m = min([at_m + CHORD_M, total_m, *after_m])
    if at_m - from_m < TAIL_MIN_CHORD_M or to_m - at_m < TAIL_MIN_CHORD_M:
        return False
    here = np.array([np.interp(at_m, walked_m, xyz[:, c]) for c in (0, 2)])
    back = np.array([np.interp(from_m, walked_m, xyz[:, c]) for c in (0, 2)])
    ahead = np.array([np.interp(to_m, walked_m, xyz[:, c]) for c in (0, 2)])
    before, after = here - back, ahead - here
    cross_y = before[1] * after[0] - before[0] * after[1]
    turn_deg = math.degrees(math.atan2(cross_y, float(before @ after)))
    return abs(turn_deg) < BEAR_MIN_DEG


def _strongest(bend: tuple[int, float]) -> float:
    return -abs(bend[1])


def _along(decision: _DecisionTuple) -> float:
    return decision[3]


def _bends(
    xyz: FloatArray, walked_m: FloatArray, walked: list[float], end_margin_m: float
) -> list[tuple[int, float]]:
    """(index, turn_deg) of each inner point of the stretch (N, 3) at least ``end_margin_m`` from
    both ends whose bend, measured over ``CHORD_M`` either side, is at least ``BEAR_MIN_DEG``;
    ``walked_m`` (N,) and ``walked`` are each point's distance along the stretch (not
    decreasing, so the points far enough from both ends are the ones from ``first`` to ``last``)."""
    total_m = walked[-1] if walked else 0.0
    first, last = 1, len(walked) - 2
    while first <= last and not walked[first] >= end_margin_m:
        first += 1
    while last >= first and not total_m - walked[last] >= end_margin_m:
        last -= 1
    if first > last:
        return []
    xs, zs = xyz[:, 0], xyz[:, 2]
    here_x, here_z = xs[first : last + 1], zs[first : last + 1]
    along_m = walked_m[first : last + 1]
    back_m = np.maximum(along_m - CHORD_M, 0.0)
    ahead_m = np.minimum(along_m + CHORD_M, total_m)
    before_x = here_x - np.interp(back_m, walked_m, xs)
    before_z = here_z - np.interp(back_m, walked_m, zs)
    after_x = np.interp(ahead_m, walked_m, xs) - here_x
    after_z = np.interp(ahead_m, walked_m, zs) - here_z
    # Signed angle from ``before`` to ``after``, + left: as signed_turn_deg (y up). The dot
    # product adds to 0.0 first, as a sum over an axis does (so 0 keeps its sign, and the angle).
    cross_y = before_z * after_x - before_x * after_z
    dot = (0.0 + before_x * after_x) + before_z * after_z
    turn_deg = np.degrees(np.arctan2(cross_y, dot)).tolist()
    # A chord too short to have a direction (``np.linalg.norm(…, axis=1) > 0`` is false) bends not.
    bx, bz, ax, az = before_x.tolist(), before_z.tolist(), after_x.tolist(), after_z.tolist()
    return [
        (first + i, turn)
        for i, turn in enumerate(turn_deg)
        if abs(turn) >= BEAR_MIN_DEG
        and bx[i] * bx[i] + bz[i] * bz[i] > 0
        and ax[i] * ax[i] + az[i] * az[i] > 0
    ]


def walked_distances_m(xyz: FloatArray) -> FloatArray:
    """(N,) the distance of each of the (N, 3) points along the polyline from its first, m."""
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xyz, axis=0), axis=1))])


def turn_class(turn_deg: float) -> TurnClass:
    """The one rule for the word of a turn, by the size of its angle alone (degrees, either
    side; docs/navigation.md "Instruction wording")::

        |turn| <  20°        straight   (STRAIGHT_MAX_DEG: no facing step; a goal "ahead")
        20° ≤ |turn| <  45°  bear       (TURN_MIN_DEG)
        45° ≤ |turn| < 135°  turn       (SHARP_MIN_DEG)
       135° ≤ |turn| < 150°  sharp      (TURN_AROUND_MIN_DEG)
       150° ≤ |turn|         around     (a goal "behind you")
    """
    size = abs(turn_deg)
    if size >= TURN_AROUND_MIN_DEG:
        return "around"
    if size >= SHARP_MIN_DEG:
        return "sharp"
    if size >= TURN_MIN_DEG:
        return "turn"
    if size >= STRAIGHT_MAX_DEG:
        return "bear"
    return "straight"


def announced(turn_deg: float, at_junction: bool) -> bool:
    """Whether a decision (a bend of at least ``BEAR_MIN_DEG``) is spoken: a turn or stronger
    anywhere, a bear at a junction only (along a corridor the walker follows its bends)."""
    return turn_class(turn_deg) != "bear" or at_junction
