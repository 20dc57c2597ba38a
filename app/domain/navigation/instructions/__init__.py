"""Turn-by-turn instructions at decision points only (issue 18): what a blind walker hears.

    route = plan_guided_route(pg, TagEnd(300), TagEnd(311), heading_rad=0.4)
    [s.instruction for s in route.steps]
    # ['turn right to face the way', 'go straight 23 m', 'in 5 m, turn left', 'turn left',
    #  'go straight 9 m to tag 311, on your right', 'arrive at tag 311, on your right']
    plan_guided_route(pg, …, style=GuidanceStyle(units="ft", clock=True))   # "turn to 9 o'clock"
    route_text(route)   # "1. Go straight 23 metres (33 steps).\n2. At tag 305, turn left, to …"

How instructions are chosen (angles in the horizontal x–z plane, + is left, as in routing):

1. **Legs.** Each walked stretch of the route is simplified (Douglas–Peucker, ``LEG_TOLERANCE_M``)
   into straight legs; on a corridor skeleton these are the corridors' straight segments.
2. **Decision points.** A bend's turn is the change between the directions over ``CHORD_M``
   before and after it, so a zig and its zag cancel and a curve taken in small bends adds up;
   bends closer than ``MIN_SPACING_M`` to a stronger one are the same decision, and a bend near a
   junction is placed at the junction. A decision is announced when |turn| ≥ ``TURN_MIN_DEG``,
   and when ``BEAR_MIN_DEG`` ≤ |turn| < ``TURN_MIN_DEG`` at a junction (a node where three or
   more corridors meet); else it is silent. Its words follow one rule of its angle alone
   (:func:`turn_class`: straight < 20°, bear 20–45°, turn 45–135°, sharp 135–150°, around
   ≥ 150°), whatever the map. So instructions are at least ``MIN_SPACING_M`` apart except at
   junctions. A decision at a node an operator quieted (a corridor edit,
   ``app.domain.navigation.corridor_edits``) is silent too. A bend within ``CHORD_M`` of a
   stronger decision that bends under ``BEAR_MIN_DEG`` measured with its chords stopping there is
   that decision's tail (:func:`_tail_of`). At a junction the route goes through silently while
   another branch leaves near straight on, "keep left at the fork" (:mod:`.forks`).
3. **Announcements.** Before a turn, a leg long enough to keep them ``MIN_SPACING_M`` apart gets
   "in N m, turn left" ``ANNOUNCE_BEFORE_M`` before the corner.
4. **First and last steps.** Given the phone's heading (``heading_rad``: the walking direction's
   angle in the x–z plane, atan2(−x, −z), 0 = facing −z, + turning left), the first step says how
   to turn to face the way — from where the walker stands, for a route from a position more than
   ``LEG_TOLERANCE_M`` off the graph (toward the end of the first go step; with nothing to walk
   on the graph, toward the goal, and straight to it). The last walked step gives the remaining
   distance and the side of the tag or point of interest ("on your left"), which the arrival
   repeats: as the walker sees it where the app says "arrive", ``END_MARGIN_M`` before the end,
   facing the way it walks there.
5. **Stairs and elevators** say their length and the floor you arrive at, by the building's floor
   labels when given (``floor_labels``), else numbered from 1.
6. **The conventions blind travellers use** (issue 39). Each step also gets ``turn`` (its class),
   ``clock`` (its clock hour), ``steps_count`` (in the walker's stride), ``landmark`` (the point
   of interest or tag within ``LANDMARK_NEAR_M``, or the goal), ``side`` (of the goal) and
   ``text``, a plain sentence for a screen reader ("At the tag by Room 150, turn left, to 9
   o'clock."); :func:`route_text` numbers them.

Distances are rounded to whole units (m, ft or steps of ``GuidanceStyle.stride_m``), at least 1.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import threading
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal, TypeAlias

import numpy as np

from app.domain.errors import ParameterError
from app.domain.frames import FloatArray
from app.domain.navigation.corridor_edits import QUIET_NODES
from app.domain.navigation.floors import assign_floors
from app.domain.navigation.forks import Fork, keep_step
from app.domain.navigation.forks import forks as _forks
from app.domain.navigation.path_graph import STAIRS, WALK, PathGraph
from app.domain.navigation.path_graph.geometry import douglas_peucker_end_legs
from app.domain.navigation.polyline import distances_along_m, point_along, segment_lengths_m
from app.domain.navigation.routing import (
    ROUNDED_DECIMALS,
    Endpoint,
    NodeEnd,
    NodeLookups,
    PoiEnd,
    Point3,
    PositionEnd,
    Route,
    Side,
    Step,
    TagEnd,
    TurnClass,
    measured_walk,
    node_lookups,
    search_pois,
    signed_turn_deg,
)

#: Douglas–Peucker tolerance of the legs, m (the skeleton's branches are already straight).
LEG_TOLERANCE_M = 0.5
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
#: "in N m" is said this far before a turn, m.
ANNOUNCE_BEFORE_M = 5.0
#: A fork this far or more along from the last step gets a "go straight" before its "keep left";
#: nearer (a fork at the route's start), the facing step is the last, m.
KEEP_MIN_LEG_M = 0.5
#: The first step says nothing about facing when the way is within this of the heading (straight
#: on), degrees.
FACING_OK_DEG = STRAIGHT_MAX_DEG
#: A tag this far from the arrival point (horizontally, m) gets a side; nearer, it is "here".
SIDE_MIN_M = 0.2
#: One walking step, m (units "steps"), unless the walker gives theirs (``GuidanceStyle.stride_m``).
STEP_LENGTH_M = 0.7
#: The strides a walker may give, m (a child's short step to a tall adult's long one).
STRIDE_MIN_M = 0.3
STRIDE_MAX_M = 1.5
#: A tag or point of interest this near a step's place (horizontally, on its floor) is the step's
#: landmark, m: the distance within which a bend is placed at a junction (``JUNCTION_SNAP_M``).
LANDMARK_NEAR_M = 3.0
#: Feet per metre.
FT_PER_M = 1 / 0.3048

Units = Literal["m", "ft", "steps"]


@dataclass(frozen=True, slots=True, kw_only=True)
class GuidanceStyle:
    """How instructions are worded: ``units`` of distances, ``clock`` for clock-face directions
    ("turn to 9 o'clock") instead of left/right in ``Step.instruction``; ``stride_m``: the
    walker's step, m, for distances in steps (``units="steps"``, ``Step.steps_count`` and the
    text form). ``Step.text`` always gives metres and steps, left/right and the clock."""

    units: Units = "m"
    clock: bool = False
    stride_m: float = STEP_LENGTH_M

    def __post_init__(self) -> None:
        if not STRIDE_MIN_M <= self.stride_m <= STRIDE_MAX_M:
            raise ParameterError(
                f"stride_m must be {STRIDE_MIN_M}-{STRIDE_MAX_M} m, not {self.stride_m}"
            )


DEFAULT_STYLE = GuidanceStyle()


@dataclass(frozen=True, slots=True, kw_only=True)
class Decision:
    """A decision point of a route: ``index`` of the polyline point, signed ``turn_deg`` (+ left),
    ``at_junction``, ``along_m`` (distance along the route from its start, m)."""

    index: int
    turn_deg: float
    at_junction: bool
    along_m: float


def plan_guided_route(
    pg: PathGraph,
    start: Endpoint,
    goal: Endpoint,
    *,
    avoid: frozenset[str] = frozenset(),
    heading_rad: float | None = None,
    style: GuidanceStyle = DEFAULT_STYLE,
    floor_labels: Sequence[str] | None = None,
) -> Route:
    """The route of :func:`app.domain.navigation.routing.plan_walk` with its instructions, at
    decision points only (the one instruction writer: issue 26 retired routing's own steps)."""
    walk = measured_walk(pg, start, goal, avoid=avoid)
    route = walk.route
    name, thing_m = _goal(pg, goal)
    steps = _guidance_steps(
        pg,
        walk.lookups,
        route.nodes,
        walk.xyz,
        route.polyline_m,  # (x, y, z) tuples of floats, as routing makes them
        walk.segment_lengths_m,
        goal_name=name,
        goal_thing_m=thing_m,
        heading_rad=heading_rad,
        style=style,
        floor_labels=floor_labels,
        origin_m=start.position_m if isinstance(start, PositionEnd) else None,
    )
    return dataclasses.replace(route, steps=steps)


def _goal(pg: PathGraph, goal: Endpoint) -> tuple[str, FloatArray | None]:
    match goal:
        case TagEnd(tag_id=tag):
            return f"tag {tag}", np.asarray(pg.tags[tag].position_m)
        case PoiEnd(name=name):
            found = search_pois(pg, name)  # exact names first; plan_walk refused ambiguity
            if found:
                return found[0].name, np.asarray(found[0].position_m)
            return name, None
        case NodeEnd(node_id=node):
            return f"node {node}", None
        case PositionEnd():
            return "your destination", None
    return "your destination", None


def guidance_steps(
    pg: PathGraph,
    route: Route,
    *,
    goal_name: str,
    goal_thing_m: FloatArray | None = None,
    heading_rad: float | None = None,
    style: GuidanceStyle = DEFAULT_STYLE,
    floor_labels: Sequence[str] | None = None,
) -> list[Step]:
    """The spoken steps of ``route`` (see the module docstring)."""
    xyz = np.asarray(route.polyline_m, dtype=np.float64).reshape(-1, 3)
    points = _points(xyz)
    return _guidance_steps(
        pg,
        node_lookups(pg),
        route.nodes,
        xyz,
        points,
        segment_lengths_m(points),
        goal_name=goal_name,
        goal_thing_m=goal_thing_m,
        heading_rad=heading_rad,
        style=style,
        floor_labels=floor_labels,
    )


def _guidance_steps(
    pg: PathGraph,
    lookups: NodeLookups,
    nodes: Sequence[int],
    xyz: FloatArray,
    points: Sequence[Point3],
    lengths_m: Sequence[float],
    *,
    goal_name: str,
    goal_thing_m: FloatArray | None,
    heading_rad: float | None,
    style: GuidanceStyle,
    floor_labels: Sequence[str] | None,
    origin_m: Point3 | None = None,
) -> list[Step]:
    """:func:`guidance_steps` of the route through ``nodes`` whose polyline is (N, 3) ``xyz``,
    the same as ``points``, with (N − 1) ``lengths_m`` the 3-D length of each segment; ``lookups``
    are ``pg``'s; ``origin_m`` where the walker stands when the route starts from a position (its
    facing step points from there)."""
    kinds, junction, at = _segment_kinds(lookups, points, nodes)
    quiet_at = pg.graph.graph.get(QUIET_NODES, ())  # corridor edits: silenced nodes
    quiet = [n in quiet_at for n in at] if quiet_at else [False] * len(at)
    floors = _point_floors(pg, lookups, points)
    steps: list[Step] = []
    heading: tuple[float, float] | None = None
    seen_from: Point3 | None = None
    first_walk = True
    for kind, i, j in _runs(kinds):
        if kind == WALK:
            facing = heading_rad if first_walk else None
            heading, seen_from = _walk_steps(
                xyz[i : j + 2],
                points[i : j + 2],
                lengths_m[i : j + 1],
                junction[i : j + 2],
                quiet[i : j + 2],
                floors[i],
                facing,
                style,
                steps,
                at=at[i : j + 2],
                lookups=lookups,
                origin_m=origin_m if i == 0 else None,  # the route starts walking there
            )
            first_walk = False
        else:
            heading, seen_from = None, None
            steps.append(_floor_change(xyz, floors, kind, i, j + 1, style, floor_labels))
    end = points[-1] if points else (0.0, 0.0, 0.0)
    if (
        origin_m is not None
        and goal_thing_m is not None
        and not any(s.kind in ("go", "stairs", "elevator") for s in steps)
    ):
        # nothing to walk on the graph (tags facing each other across a corridor): straight
        # from where the walker stands to the thing
        steps, heading, end = _straight_to(origin_m, goal_thing_m, heading_rad, style, floors)
        seen_from = end
    side = _side(heading, seen_from or end, goal_thing_m)
    said = SIDE_WORDS[side] if side else ""
    if steps and steps[-1].kind == "go" and side:
        last = steps[-1]
        steps[-1] = dataclasses.replace(
            last, instruction=f"{last.instruction} to {goal_name}, {said}", side=side
        )
    arrive = f"arrive at {goal_name}" + (f", {said}" if side else "")
    steps.append(
        Step(
            instruction=arrive,
            position_m=end,
            kind="arrive",
            distance_m=0.0,
            turn_deg=None,
            floor=floors[-1] if floors else 0,
            side=side,
        )
    )
    return _written(
        steps, _landmarks(pg), goal_name=goal_name, style=style, floor_labels=floor_labels
    )


def _straight_to(
    origin_m: Point3,
    thing_m: FloatArray,
    heading_rad: float | None,
    style: GuidanceStyle,
    floors: Sequence[int],
) -> tuple[list[Step], tuple[float, float] | None, Point3]:
    """The steps of a route too short to walk on the graph: face the thing from ``origin_m``
    (given the heading) and go straight to it; (steps, the heading walked, where they end)."""
    floor = floors[0] if floors else 0
    thing = (float(thing_m[0]), float(origin_m[1]), float(thing_m[2]))
    way = _direction(origin_m, thing)
    distance_m = _norm_xz(thing[0] - origin_m[0], thing[2] - origin_m[2])
    steps: list[Step] = []
    if way is None or distance_m < SIDE_MIN_M:
        return steps, None, origin_m
    if heading_rad is not None:
        facing = (-math.sin(heading_rad), 0.0, -math.cos(heading_rad))
        bearing = signed_turn_deg(facing, _xyz(way))
        if turn_class(bearing) != "straight":
            words = turn_words(bearing, style)
            if not style.clock and turn_class(bearing) != "around":
                words = f"{words} {round(abs(bearing))}°"
            steps.append(_step(f"{words} to face the way", origin_m, "face", 0.0, bearing, floor))
    said = distance_words(distance_m, style.units, style.stride_m)
    steps.append(_step(f"go straight {said}", origin_m, "go", distance_m, floor=floor))
    # the walk ends short of the thing (it is on a wall), so that it is "ahead"
    short_m = min(2 * SIDE_MIN_M, distance_m / 2)
    end = (thing[0] - short_m * way[0], origin_m[1], thing[2] - short_m * way[1])
    return steps, way, end


def walk_stretches(pg: PathGraph, route: Route) -> list[tuple[FloatArray, list[bool]]]:
    """The walked stretches of ``route`` between its stairs and elevators: each (points (K, 3),
    whether each point is a junction)."""
    xyz = np.asarray(route.polyline_m, dtype=np.float64).reshape(-1, 3)
    kinds, junction, _ = _segment_kinds(node_lookups(pg), _points(xyz), route.nodes)
    return [(xyz[i : j + 2], junction[i : j + 2]) for kind, i, j in _runs(kinds) if kind == WALK]


def _runs(kinds: Sequence[str]) -> list[tuple[str, int, int]]:
    """(kind, first, last) of each run of segments of one kind, in order."""
    runs = []
    first = 0
    for kind, run in itertools.groupby(kinds):
        last = first + len(list(run)) - 1
        runs.append((kind, first, last))
        first = last + 1
    return runs


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
        for index, turn_deg, at_junction, along_m in _decisions(
            xyz, junction, walked_m, walked_m.tolist(), end_margin_m
        )
    ]


#: A decision point as (index, turn_deg, at_junction, along_m): the fields of :class:`Decision`.
_DecisionTuple: TypeAlias = tuple[int, float, bool, float]


def _decisions(
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


def _announced(turn_deg: float, at_junction: bool) -> bool:
    """Whether a decision (a bend of at least ``BEAR_MIN_DEG``) is spoken: a turn or stronger
    anywhere, a bear at a junction only (along a corridor the walker follows its bends)."""
    return turn_class(turn_deg) != "bear" or at_junction


def turn_words(turn_deg: float, style: GuidanceStyle = DEFAULT_STYLE) -> str:
    """ "bear left", "turn right", "turn sharp left", "turn around" (:func:`turn_class`), or with
    ``style.clock`` "turn to 9 o'clock"."""
    if style.clock:
        return f"turn to {clock_hour(turn_deg)} o'clock"
    side = "left" if turn_deg > 0 else "right"
    match turn_class(turn_deg):
        case "around":
            return "turn around"
        case "sharp":
            return f"turn sharp {side}"
        case "turn":
            return f"turn {side}"
        case "bear":
            return f"bear {side}"
    return "go straight on"


def clock_hour(turn_deg: float) -> int:
    """The clock-face hour of a direction ``turn_deg`` from straight ahead (+ left): 12 ahead,
    9 left, 3 right, 6 behind; the nearest hour, a half hour going away from 12 (so 45° is 2 or
    10 o'clock, a turn, and 135° is 5 or 7, sharp: each class of :func:`turn_class` from bear on
    has its own hours: bear 1/11, turn 2–4/8–10, sharp 5/7, around 5–7)."""
    hours = math.floor(abs(turn_deg) / 30.0 + 0.5)  # 0…6, half hours away from 12
    hour = (-hours if turn_deg > 0 else hours) % 12
    return 12 if hour == 0 else hour


def distance_words(distance_m: float, units: Units, stride_m: float = STEP_LENGTH_M) -> str:
    """ "12 m", "39 ft", "17 steps" (whole units, at least 1; steps of ``stride_m``)."""
    if units == "ft":
        return f"{max(1, round(distance_m * FT_PER_M))} ft"
    if units == "steps":
        return f"{steps_count(distance_m, stride_m)} steps"
    return f"{max(1, round(distance_m))} m"


def steps_count(distance_m: float, stride_m: float = STEP_LENGTH_M) -> int:
    """``distance_m`` in strides of ``stride_m``: whole steps, at least 1."""
    return max(1, round(distance_m / stride_m))


def spoken_distance(distance_m: float, stride_m: float = STEP_LENGTH_M) -> str:
    """ "12 metres (17 steps)", "1 metre (1 step)": whole metres and steps, at least 1, words a
    screen reader does not mangle (no "m" alone)."""
    metres = max(1, round(distance_m))
    strides = steps_count(distance_m, stride_m)
    return (
        f"{metres} {'metre' if metres == 1 else 'metres'} "
        f"({strides} {'step' if strides == 1 else 'steps'})"
    )


def clock_words(turn_deg: float) -> str:
    """ "turn right, to 3 o'clock", "bear left, to 11 o'clock", "turn around, to 6 o'clock"."""
    return f"{turn_words(turn_deg)}, to {clock_hour(turn_deg)} o'clock"


def heading_direction(heading_rad: float) -> FloatArray:
    """The x–z unit vector of a heading (0 = facing −z, + counter-clockwise seen from above)."""
    return np.array([-math.sin(heading_rad), -math.cos(heading_rad)])


# --------------------------------------------------------------------------- pieces


def _walk_steps(
    xyz: FloatArray,
    points: Sequence[Point3],
    lengths_m: Sequence[float],
    junction: Sequence[bool],
    quiet: Sequence[bool],
    floor: int,
    heading_rad: float | None,
    style: GuidanceStyle,
    steps: list[Step],
    *,
    at: Sequence[int | None] = (),
    lookups: NodeLookups | None = None,
    origin_m: Point3 | None = None,
) -> tuple[tuple[float, float] | None, Point3 | None]:
    """Append the steps of a walked stretch, (N, 3) ``xyz`` and the same as ``points``, whose
    segments are ``lengths_m`` long; return the x–z heading the goal's side is told in and the
    point it is told from (where the app says "arrive", walking the last leg). A decision at a
    point that ``quiet`` flags (a node an operator quieted) is not announced. Given the nodes
    ``at`` its points and the graph's ``lookups``, a junction the stretch goes through without a
    spoken decision where another branch leaves near straight on gets "keep left/right"
    (:mod:`app.domain.navigation.forks`). A walker who stands more than ``LEG_TOLERANCE_M`` off
    the stretch's start (``origin_m``, a route from a position) is turned to face, from where it
    stands, the end of the first go step (the first spoken decision, or the stretch's end)."""
    walked = distances_along_m(lengths_m)
    decisions = [
        d
        for d in _decisions(xyz, junction, np.array(walked), walked, END_MARGIN_M)
        if _announced(d[1], d[2]) and not quiet[d[0]]
    ]
    first_dir = last_dir = None
    if len(points) > 1:
        xs, zs = [p[0] for p in points], [p[2] for p in points]
        first_end, last_start = douglas_peucker_end_legs(xs, zs, LEG_TOLERANCE_M)
        first_dir = _direction(points[0], points[first_end])
        if (
            origin_m is not None
            and _norm_xz(origin_m[0] - points[0][0], origin_m[2] - points[0][2]) > LEG_TOLERANCE_M
        ):
            leg_end_m = decisions[0][3] if decisions else walked[-1]
            first_dir = _direction(origin_m, point_along(points, walked, leg_end_m)) or first_dir
        last_dir = _direction(points[last_start], points[-1])
    if heading_rad is not None and first_dir is not None:
        facing = (-math.sin(heading_rad), 0.0, -math.cos(heading_rad))  # heading_direction, x y z
        bearing = signed_turn_deg(facing, _xyz(first_dir))
        if turn_class(bearing) != "straight":
            words = turn_words(bearing, style)
            if not style.clock and turn_class(bearing) != "around":
                words = f"{words} {round(abs(bearing))}°"
            steps.append(_step(f"{words} to face the way", points[0], "face", 0.0, bearing, floor))
    if lookups is not None and len(at) == len(points):
        silent = {k for k, q in enumerate(quiet) if q} | {d[0] for d in decisions}
        silent |= {k for k, w in enumerate(walked) if walked[-1] - w < END_MARGIN_M}
        keeps = _forks(points, walked, at, junction, lookups, skip=frozenset(silent))
    else:
        keeps = []
    events = sorted([(d[3], d) for d in decisions] + [(f.along_m, f) for f in keeps], key=_first)

    def go_straight(leg_m: float, from_i: int) -> Step:
        words = distance_words(leg_m, style.units, style.stride_m)
        return _step(f"go straight {words}", points[from_i], "go", leg_m, floor=floor)

    from_m, from_i = 0.0, 0
    for along_m, event in events:
        leg_m = along_m - from_m
        if isinstance(event, Fork):
            if leg_m >= KEEP_MIN_LEG_M:
                steps.append(go_straight(leg_m, from_i))
            steps.append(keep_step(event, points[event.index], floor))
            from_m, from_i = along_m, event.index
            continue
        index, turn_deg = event[0], event[1]
        steps.append(go_straight(leg_m, from_i))
        words = turn_words(turn_deg, style)
        if leg_m >= ANNOUNCE_BEFORE_M + MIN_SPACING_M:
            announce_at = point_along(points, walked, along_m - ANNOUNCE_BEFORE_M)
            ahead = distance_words(ANNOUNCE_BEFORE_M, style.units, style.stride_m)
            steps.append(
                _step(f"in {ahead}, {words}", announce_at, "announce", 0.0, turn_deg, floor)
            )
        steps.append(_step(words, points[index], "turn", 0.0, turn_deg, floor))
        from_m, from_i = along_m, index
    rest_m = walked[-1] - from_m
    if rest_m >= 0.5:
        steps.append(go_straight(rest_m, from_i))
    # The goal's side is told as the walker sees it where the app says "arrive", END_MARGIN_M
    # before the end (no bend nearer the end is told, so the walker does not turn there),
    # facing the way it walks there: over the CHORD_M before that point, after the last told
    # decision. A last leg too short for that (under CHORD_M / 2) is seen from its end.
    seen_from = points[-1] if points else None
    heading_to_m = walked[-1] - END_MARGIN_M
    heading_from_m = max(heading_to_m - CHORD_M, from_m)
    if heading_to_m - heading_from_m >= CHORD_M / 2 and len(points) > 1:
        seen_from = point_along(points, walked, heading_to_m)
        last_dir = _direction(point_along(points, walked, heading_from_m), seen_from) or last_dir
    return last_dir, seen_from


def _first(event: tuple[float, object]) -> float:
    return event[0]


@dataclass(frozen=True, slots=True, kw_only=True)
class Landmark:
    """A tag or point of interest a step can be told by: ``name`` as said ("Room 210", "tag
    305"), ``position_xz_m`` (map frame, m), ``floor`` (index), ``is_tag``."""

    name: str
    position_xz_m: tuple[float, float]
    floor: int
    is_tag: bool


_LANDMARK_CACHE: dict[int, tuple[PathGraph, list[Landmark]]] = {}
_LANDMARK_CACHE_SIZE = 8
_LANDMARK_LOCK = threading.Lock()


def _landmarks(pg: PathGraph) -> list[Landmark]:
    """The map's points of interest, then its tags, as landmarks (made once per graph, as
    routing's index is: a graph must not change once routed on)."""
    with _LANDMARK_LOCK:
        cached = _LANDMARK_CACHE.get(id(pg))
    if cached is not None and cached[0] is pg:
        return cached[1]
    found = _landmarks_of(pg)
    with _LANDMARK_LOCK:
        _LANDMARK_CACHE[id(pg)] = (pg, found)
        while len(_LANDMARK_CACHE) > _LANDMARK_CACHE_SIZE:
            del _LANDMARK_CACHE[next(iter(_LANDMARK_CACHE))]
    return found


def _landmarks_of(pg: PathGraph) -> list[Landmark]:
    found = [
        Landmark(
            name=poi.name,
            position_xz_m=(poi.position_m[0], poi.position_m[2]),
            floor=poi.floor,
            is_tag=False,
        )
        for poi in pg.pois
    ]
    found += [
        Landmark(
            name=f"tag {tag_id}",
            position_xz_m=(tag.position_m[0], tag.position_m[2]),
            floor=tag.floor,
            is_tag=True,
        )
        for tag_id, tag in sorted(pg.tags.items())
    ]
    return found


def landmark_near(
    landmarks: Sequence[Landmark], position_m: Point3, floor: int
) -> tuple[str, str] | None:
    """(name, phrase) of the landmark of a step at ``position_m`` on ``floor``: the nearest point
    of interest within ``LANDMARK_NEAR_M`` (horizontally, on that floor), "at the tag by Room
    210" when a tag is that near too, else "by Room 210"; else the nearest tag, "at tag 305";
    else None. Ties go to the first listed (points of interest, then tags by id)."""
    x, _, z = position_m
    near_m2 = LANDMARK_NEAR_M * LANDMARK_NEAR_M
    poi: tuple[float, str] | None = None
    tag: tuple[float, str] | None = None
    for landmark in landmarks:  # squared distances: the same order, no square roots
        if landmark.floor != floor:
            continue
        dx, dz = landmark.position_xz_m[0] - x, landmark.position_xz_m[1] - z
        d_m2 = dx * dx + dz * dz
        if d_m2 > near_m2:
            continue
        if landmark.is_tag:
            if tag is None or d_m2 < tag[0]:
                tag = (d_m2, landmark.name)
        elif poi is None or d_m2 < poi[0]:
            poi = (d_m2, landmark.name)
    if poi is not None:
        return poi[1], (f"at the tag by {poi[1]}" if tag is not None else f"by {poi[1]}")
    if tag is not None:
        return tag[1], f"at {tag[1]}"
    return None


def _written(
    steps: list[Step],
    landmarks: Sequence[Landmark],
    *,
    goal_name: str,
    style: GuidanceStyle,
    floor_labels: Sequence[str] | None,
) -> list[Step]:
    """``steps`` with their structured words (``turn``, ``clock``, ``steps_count``,
    ``landmark``) and each one's ``text``: a plain sentence for a screen reader, in metres and
    the walker's steps, left/right and the clock, by landmarks. An announcement's landmark is its
    turn's."""
    written: list[Step] = []
    # (place, floor) → landmark_near: an announcement's landmark is its turn's, looked up once
    near_of: dict[tuple[Point3, int], tuple[str, str] | None] = {}

    def near(at: Step) -> tuple[str, str] | None:
        key = (at.position_m, at.floor)
        if key not in near_of:
            near_of[key] = landmark_near(landmarks, at.position_m, at.floor)
        return near_of[key]

    for k, step in enumerate(steps):
        turn: TurnClass | None = None
        clock: int | None = None
        count: int | None = None
        landmark: str | None = None
        match step.kind:
            case "face" | "turn" | "announce":
                turn_deg = step.turn_deg or 0.0
                turn, clock = turn_class(turn_deg), clock_hour(turn_deg)
                at = step
                if step.kind == "announce":
                    at = next((t for t in steps[k + 1 :] if t.kind == "turn"), step)
                found = near(at)
                landmark, phrase = found if found else (None, "")
                words = clock_words(turn_deg)
                if step.kind == "face":
                    text = f"{words}, to face the way"
                elif step.kind == "announce":
                    ahead = spoken_distance(ANNOUNCE_BEFORE_M, style.stride_m)
                    text = f"in {ahead}, {phrase + ', ' if phrase else ''}{words}"
                else:
                    text = f"{phrase + ', ' if phrase else ''}{words}"
            case "keep":
                found = near(step)
                landmark, phrase = found if found else (None, "")
                text = f"{phrase + ', ' if phrase else ''}{step.instruction}"
            case "go":
                count = steps_count(step.distance_m, style.stride_m)
                text = f"go straight {spoken_distance(step.distance_m, style.stride_m)}"
                if step.side is not None:
                    landmark = goal_name
                    text += f" to {goal_name}, {SIDE_WORDS[step.side]}"
            case "stairs" | "elevator":
                found = near(step)
                landmark, phrase = found if found else (None, "")
                following = steps[k + 1].floor if k + 1 < len(steps) else step.floor
                label = (
                    floor_labels[following]
                    if floor_labels is not None and 0 <= following < len(floor_labels)
                    else str(following + 1)
                )
                way = "up" if following > step.floor else "down"
                if step.kind == "stairs":
                    metres = max(1, round(step.distance_m))
                    length = f"{metres} {'metre' if metres == 1 else 'metres'}"
                    text = f"take the stairs {way}, {length}, to floor {label}"
                else:
                    text = f"take the elevator {way} to floor {label}"
                if phrase:
                    text = f"{phrase}, {text}"
            case _:  # arrive
                landmark = goal_name
                side = f", {SIDE_WORDS[step.side]}" if step.side else ""
                text = f"arrive at {goal_name}{side}"
        written.append(
            Step(  # not dataclasses.replace: a third of the time, on every route
                instruction=step.instruction,
                position_m=step.position_m,
                kind=step.kind,
                distance_m=step.distance_m,
                turn_deg=step.turn_deg,
                floor=step.floor,
                turn=turn,
                clock=clock,
                steps_count=count,
                landmark=landmark,
                side=step.side,
                text=text[:1].upper() + text[1:] + ".",
            )
        )
    return written


def route_text(route: Route) -> str:
    """The route as a screen reader reads it well: plain sentences, one numbered step a line,
    metres and steps spelled out, no symbols; the announcements ("in 5 metres, …"), which are for
    walking, are left out, since their turn follows::

        1. Go straight 29 metres (42 steps).
        2. At tag 305, turn right, to 3 o'clock.
        3. Go straight 7 metres (10 steps) to Room 210, on your right.
        4. Arrive at Room 210, on your right.
    """
    said = [step.text for step in route.steps if step.kind != "announce" and step.text]
    return "\n".join(f"{i}. {text}" for i, text in enumerate(said, start=1))


def _floor_change(
    xyz: FloatArray,
    floors: Sequence[int],
    kind: str,
    first: int,
    last: int,
    style: GuidanceStyle,
    floor_labels: Sequence[str] | None,
) -> Step:
    floor_from, floor_to = floors[first], floors[last]
    way = "up" if floor_to > floor_from else "down"
    label = (
        floor_labels[floor_to]
        if floor_labels is not None and 0 <= floor_to < len(floor_labels)
        else str(floor_to + 1)
    )
    length_m = float(np.linalg.norm(np.diff(xyz[first : last + 1], axis=0), axis=1).sum())
    if kind == STAIRS:
        stairs_m = distance_words(length_m, style.units, style.stride_m)
        words = f"take the stairs {way}, {stairs_m}, to floor {label}"
    else:
        words = f"take the elevator {way} to floor {label}"
    return Step(
        instruction=words,
        position_m=_point(xyz[first]),
        kind="stairs" if kind == STAIRS else "elevator",
        distance_m=length_m,
        turn_deg=None,
        floor=floor_from,
    )


#: How each side is said.
SIDE_WORDS: dict[Side, str] = {
    "ahead": "ahead",
    "left": "on your left",
    "right": "on your right",
    "behind": "behind you",
}


def _side(
    heading: tuple[float, float] | None, end: Point3, thing_m: FloatArray | None
) -> Side | None:
    """Where ``thing_m`` is from ``end`` facing ``heading`` (x–z): by :func:`turn_class` of its
    bearing, straight "ahead", around "behind", else left or right; None when there is no thing,
    no heading, or the thing is within ``SIDE_MIN_M``."""
    if thing_m is None:
        return None
    thing_x, _, thing_z = np.asarray(thing_m, dtype=np.float64).tolist()
    offset_x, offset_z = thing_x - end[0], thing_z - end[2]
    if _norm_xz(offset_x, offset_z) < SIDE_MIN_M or heading is None:
        return None
    bearing = signed_turn_deg(_xyz(heading), (offset_x, 0.0, offset_z))
    match turn_class(bearing):
        case "straight":
            return "ahead"
        case "around":
            return "behind"
    return "left" if bearing > 0 else "right"


def _segment_kinds(
    lookups: NodeLookups, points: Sequence[Point3], nodes: Sequence[int]
) -> tuple[list[str], list[bool], list[int | None]]:
    """(kind of each polyline segment, whether each point is a junction, the node at each point
    or None): a point is the route node at its position (rounded to ``ROUNDED_DECIMALS``; the
    last such node if several)."""
    place_of_node, place_of_point = lookups.place_of_node, lookups.place_of_point
    node_at = {place_of_node[n]: n for n in nodes}
    places = [place_of_point.get(p, -1) for p in points]  # -1: no node there
    for i, place in enumerate(places):
        if place < 0:  # not a node's position (a position on an edge): rounded, maybe one
            places[i] = lookups.place_of_rounded.get(_rounded(points[i]), -1)
    at = [node_at.get(place) for place in places]
    junctions = lookups.junctions
    junction = [n in junctions for n in at]
    kind_between = lookups.kind_between
    kinds = [
        WALK if a is None or b is None else kind_between[a].get(b, WALK)
        for a, b in itertools.pairwise(at)
    ]
    return kinds, junction, at


def _rounded(point: Point3) -> Point3:
    """``point`` rounded as :class:`app.domain.navigation.routing.NodeLookups` rounds the nodes'
    positions."""
    x, y, z = np.round(np.asarray(point, dtype=np.float64), ROUNDED_DECIMALS).tolist()
    return (x, y, z)


def _point_floors(pg: PathGraph, lookups: NodeLookups, points: Sequence[Point3]) -> list[int]:
    """The floor of each polyline point: the level nearest its height."""
    if not pg.floor_levels_m:
        return [0] * len(points)
    if lookups.floor_levels_m != pg.floor_levels_m:
        return _floors_of_heights(pg, [p[1] for p in points])
    known = lookups.floor_of_height
    floors = [known.get(p[1], -1) for p in points]
    if -1 in floors:  # a point off the graph's nodes (a position on an edge)
        return _floors_of_heights(pg, [p[1] for p in points])
    return floors


def _floors_of_heights(pg: PathGraph, heights_m: list[float]) -> list[int]:
    levels = np.asarray(pg.floor_levels_m, dtype=np.float64)
    return [int(f) for f in assign_floors(np.asarray(heights_m, dtype=np.float64), levels)]


def _step(
    instruction: str,
    at_m: Point3,
    kind: Literal["go", "turn", "announce", "face"],
    distance_m: float,
    turn_deg: float | None = None,
    floor: int = 0,
) -> Step:
    return Step(
        instruction=instruction,
        position_m=at_m,
        kind=kind,
        distance_m=float(distance_m),
        turn_deg=turn_deg,
        floor=floor,
    )


def _direction(a: Point3, b: Point3) -> tuple[float, float] | None:
    """The x–z unit vector from a to b (None if they are one above the other)."""
    dx, dz = b[0] - a[0], b[2] - a[2]
    norm = _norm_xz(dx, dz)
    if norm == 0:
        return None
    return (dx / norm, dz / norm)


def _norm_xz(x: float, z: float) -> float:
    """``np.linalg.norm([x, z])``: the square root of a dot product, which may round differently
    from ``math.hypot(x, z)`` or ``sqrt(x² + z²)``."""
    d = np.array([x, z])
    return math.sqrt(d.dot(d))


def _xyz(xz: tuple[float, float]) -> Point3:
    return (xz[0], 0.0, xz[1])


def _points(xyz: FloatArray) -> list[Point3]:
    """(N, 3) points as N (x, y, z) tuples of floats."""
    return [(x, y, z) for x, y, z in xyz.tolist()]


def _point(values: FloatArray) -> tuple[float, float, float]:
    x, y, z = np.asarray(values, dtype=np.float64).tolist()
    return (x, y, z)
