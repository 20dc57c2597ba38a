"""Forks a route goes through without a turn (issue 39): "keep left" where another way goes on.

A bend of less than ``BEAR_MIN_DEG`` is silent (``instructions``): the walker walks straight on.
At a junction that is right only if no other way leaves near straight on. Where one does — the
corridor bends 15° left while a spur goes straight ahead, or a corridor forks in a Y — a walker
who hears nothing takes whichever branch its heading error and the walls lead it into. So at a
junction the route passes through without a spoken decision, every other branch is measured as
the route is, over ``CHORD_M`` along it from the junction; a branch within
``FORK_AHEAD_MAX_DEG`` of straight on (the direction the walker comes from, over ``CHORD_M``)
makes the junction a fork when the route itself goes on within ``FORK_AHEAD_MAX_DEG`` of
straight on too, and the route says which way it goes there:

    keep left       every such branch is to the right of the route's own way out
    keep right      every such branch is to its left
    keep straight on    some on either side

The rule is one angle, the same on every map: ``FORK_AHEAD_MAX_DEG`` = ``TURN_MIN_DEG`` (45°), the
boundary below which a change of direction is not a turn (the one rule of the words,
``instructions.turn_class``); a branch less than a turn off straight on is one a walker going
straight on cannot tell from its own (docs/navigation.md §0b, "Forks").
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import TypeAlias

from app.domain.navigation.path_graph import ELEVATOR
from app.domain.navigation.polyline import point_along
from app.domain.navigation.routing import NodeLookups, Point3, Side, Step

#: Another branch leaving a junction within this of straight on makes it a fork, degrees (the
#: word rule's turn boundary, ``instructions.TURN_MIN_DEG``).
FORK_AHEAD_MAX_DEG = 45.0
#: A branch or the route is measured over this far from the junction, m (``instructions.CHORD_M``).
FORK_CHORD_M = 4.0
#: The way the walker comes from is measured over at least this (else its way out stands for it:
#: a fork at the route's start, after the facing step), m.
FORK_MIN_APPROACH_M = 1.0


@dataclass(frozen=True, slots=True, kw_only=True)
class Fork:
    """A fork of a walked stretch: ``index`` of the polyline point (a junction), ``side`` to keep
    ("left", "right", or "ahead" for straight on), ``turn_deg`` the route's own bend there
    (+ left, over ``FORK_CHORD_M``), ``along_m`` from the stretch's start, ``other_deg`` the
    directions of the branches near straight on (+ left of straight on)."""

    index: int
    side: Side
    turn_deg: float
    along_m: float
    other_deg: tuple[float, ...]


def forks(
    points: Sequence[Point3],
    walked_m: Sequence[float],
    at: Sequence[int | None],
    junction: Sequence[bool],
    lookups: NodeLookups,
    *,
    skip: frozenset[int] = frozenset(),
) -> list[Fork]:
    """The forks of a walked stretch through ``points`` (x, y, z, m) that are ``walked_m`` along
    it, at the nodes ``at`` (None off a node), ``junction`` flagged; the points ``skip`` (a spoken
    decision, a quieted node, the stretch's end) are none."""
    found: list[Fork] = []
    n = len(points)
    if n < 2:
        return found
    total_m = walked_m[-1]
    for k in range(n - 1):
        node = at[k]
        if not junction[k] or k in skip or node is None or total_m - walked_m[k] < 1e-9:
            continue
        here = _xz(points[k])
        way_out = _minus(
            _xz(point_along(points, walked_m, min(walked_m[k] + FORK_CHORD_M, total_m))), here
        )
        back_m = max(walked_m[k] - FORK_CHORD_M, 0.0)
        way_in = _minus(here, _xz(point_along(points, walked_m, back_m)))
        if math.hypot(*way_out) < 1e-9:
            continue
        if walked_m[k] - back_m < FORK_MIN_APPROACH_M or math.hypot(*way_in) < 1e-9:
            way_in = way_out  # at the start: the facing step turned the walker to the way out
        turn_deg = _signed_deg(way_in, way_out)
        if abs(turn_deg) >= FORK_AHEAD_MAX_DEG:
            continue  # the route itself turns off: a turn (told or at the start), not a fork
        route_neighbours = {
            m for m in (at[k - 1] if k > 0 else None, at[k + 1]) if m is not None and m != node
        }
        ahead = []
        for other, kind in lookups.kind_between[node].items():
            if other in route_neighbours or kind == ELEVATOR:
                continue
            if _on_route(points, k, _xz(lookups.point_of_node[other])):
                continue
            direction = _branch_direction(lookups, node, other)
            if direction is None:
                continue
            other_deg = _signed_deg(way_in, direction)
            if abs(other_deg) < FORK_AHEAD_MAX_DEG:
                ahead.append(other_deg)
        if not ahead:
            continue
        if all(d < turn_deg for d in ahead):
            side: Side = "left"
        elif all(d > turn_deg for d in ahead):
            side = "right"
        else:
            side = "ahead"
        found.append(
            Fork(
                index=k,
                side=side,
                turn_deg=turn_deg,
                along_m=float(walked_m[k]),
                other_deg=tuple(ahead),
            )
        )
    return found


XZ: TypeAlias = tuple[float, float]


def _on_route(points: Sequence[Point3], k: int, other_xz: XZ) -> bool:
    """Whether the edge from point ``k`` to the node at ``other_xz`` is the one the route takes in
    or out of ``k`` where its neighbouring point lies on that edge, not at a node (the route's
    start or end snapped onto it)."""
    here = _xz(points[k])
    to_other = _minus(other_xz, here)
    length_m = math.hypot(*to_other)
    for j in (k - 1, k + 1):
        if 0 <= j < len(points):
            step = _minus(_xz(points[j]), here)
            along = step[0] * to_other[0] + step[1] * to_other[1]
            off = abs(step[0] * to_other[1] - step[1] * to_other[0])
            if (
                along > 0
                and off <= 1e-9 * max(1.0, length_m * length_m)
                and (math.hypot(*step) <= length_m + 1e-9)
            ):
                return True
    return False


def _branch_direction(lookups: NodeLookups, node: int, first: int) -> XZ | None:
    """The x–z direction (unnormalized) from ``node`` to the point ``FORK_CHORD_M`` along the
    branch that leaves it to ``first``, through nodes of two neighbours (or to the branch's end,
    a junction or a dead end, when it is shorter); None if it has no horizontal extent."""
    points: Mapping[int, Point3] = lookups.point_of_node
    start = last = end = _xz(points[node])
    previous, current = node, first
    walked_m = 0.0
    for _ in range(1000):  # a branch is a chain of nodes; a loop back to ``node`` ends it
        p = _xz(points[current])
        seg = _minus(p, last)
        seg_m = math.hypot(*seg)
        if walked_m + seg_m >= FORK_CHORD_M:
            t = (FORK_CHORD_M - walked_m) / seg_m
            end = (last[0] + t * seg[0], last[1] + t * seg[1])
            break
        walked_m += seg_m
        last = end = p
        onward = [m for m in lookups.kind_between[current] if m != previous]
        if len(onward) != 1 or onward[0] == node:
            break
        previous, current = current, onward[0]
    direction = _minus(end, start)
    return direction if math.hypot(*direction) > 1e-9 else None


def _xz(p: Point3) -> XZ:
    return (p[0], p[2])


def _minus(a: XZ, b: XZ) -> XZ:
    return (a[0] - b[0], a[1] - b[1])


def _signed_deg(a: XZ, b: XZ) -> float:
    """The signed horizontal angle from a to b (x–z), degrees, + left
    (``routing.signed_turn_deg``)."""
    cross_y = a[1] * b[0] - a[0] * b[1]
    return math.degrees(math.atan2(cross_y, a[0] * b[0] + a[1] * b[1]))


#: How the side to keep at a fork is said.
KEEP_WORDS: dict[Side, str] = {
    "left": "keep left",
    "right": "keep right",
    "ahead": "keep straight on",
}


def keep_step(fork: Fork, at_m: Point3, floor: int) -> Step:
    """The step of a fork, "keep left at the fork": ``side`` the side to keep, ``turn_deg`` the
    route's own bend there."""
    return Step(
        instruction=f"{KEEP_WORDS[fork.side]} at the fork",
        position_m=at_m,
        kind="keep",
        distance_m=0.0,
        turn_deg=fork.turn_deg,
        floor=floor,
        side=fork.side,
    )
