"""The steps of a guided route (:func:`plan_guided_route`, :func:`guidance_steps`; steps 1–5 of
the package docstring): along each walked stretch the facing step, "go straight", announcements,
turns and "keep left/right", then stairs and elevators, the goal's side and the arrival."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from typing import Literal

import numpy as np

from app.domain.frames import FloatArray
from app.domain.navigation.corridor_edits import QUIET_NODES
from app.domain.navigation.forks import Fork, keep_step
from app.domain.navigation.forks import forks as _forks
from app.domain.navigation.instructions.decisions import (
    CHORD_M,
    END_MARGIN_M,
    MIN_SPACING_M,
    STRAIGHT_MAX_DEG,
    announced,
    decisions_along,
    turn_class,
)
from app.domain.navigation.instructions.landmarks import landmarks_of
from app.domain.navigation.instructions.stretches import (
    as_points,
    kind_runs,
    point_floors,
    segment_kinds,
)
from app.domain.navigation.instructions.wording import (
    ANNOUNCE_BEFORE_M,
    DEFAULT_STYLE,
    SIDE_WORDS,
    GuidanceStyle,
    distance_words,
    turn_words,
    written_steps,
)
from app.domain.navigation.path_graph import STAIRS, WALK, PathGraph
from app.domain.navigation.path_graph.geometry import douglas_peucker_end_legs
from app.domain.navigation.polyline import distances_along_m, point_along, segment_lengths_m
from app.domain.navigation.routing import (
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
    measured_walk,
    node_lookups,
    search_pois,
    signed_turn_deg,
)

#: Douglas–Peucker tolerance of the legs, m (the skeleton's branches are already straight).
LEG_TOLERANCE_M = 0.5
#: A fork this far or more along from the last step gets a "go straight" before its "keep left";
#: nearer (a fork at the route's start), the facing step is the last, m.
KEEP_MIN_LEG_M = 0.5
#: The first step says nothing about facing when the way is within this of the heading (straight
#: on), degrees.
FACING_OK_DEG = STRAIGHT_MAX_DEG
#: A tag this far from the arrival point (horizontally, m) gets a side; nearer, it is "here".
SIDE_MIN_M = 0.2


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
    points = as_points(xyz)
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
    kinds, junction, at = segment_kinds(lookups, points, nodes)
    quiet_at = pg.graph.graph.get(QUIET_NODES, ())  # corridor edits: silenced nodes
    quiet = [n in quiet_at for n in at] if quiet_at else [False] * len(at)
    floors = point_floors(pg, lookups, points)
    steps: list[Step] = []
    heading: tuple[float, float] | None = None
    seen_from: Point3 | None = None
    first_walk = True
    for kind, i, j in kind_runs(kinds):
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
    return written_steps(
        steps, landmarks_of(pg), goal_name=goal_name, style=style, floor_labels=floor_labels
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
    way = direction(origin_m, thing)
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
        for d in decisions_along(xyz, junction, np.array(walked), walked, END_MARGIN_M)
        if announced(d[1], d[2]) and not quiet[d[0]]
    ]
    first_dir = last_dir = None
    if len(points) > 1:
        xs, zs = [p[0] for p in points], [p[2] for p in points]
        first_end, last_start = douglas_peucker_end_legs(xs, zs, LEG_TOLERANCE_M)
        first_dir = direction(points[0], points[first_end])
        if (
            origin_m is not None
            and _norm_xz(origin_m[0] - points[0][0], origin_m[2] - points[0][2]) > LEG_TOLERANCE_M
        ):
            leg_end_m = decisions[0][3] if decisions else walked[-1]
            first_dir = direction(origin_m, point_along(points, walked, leg_end_m)) or first_dir
        last_dir = direction(points[last_start], points[-1])
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
        last_dir = direction(point_along(points, walked, heading_from_m), seen_from) or last_dir
    return last_dir, seen_from


def _first(event: tuple[float, object]) -> float:
    return event[0]


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


def direction(a: Point3, b: Point3) -> tuple[float, float] | None:
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


def _point(values: FloatArray) -> tuple[float, float, float]:
    x, y, z = np.asarray(values, dtype=np.float64).tolist()
    return (x, y, z)
