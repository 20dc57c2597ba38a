"""The corridor skeleton: where a pedestrian can walk, as the building's corridors rather than the
walked line (DESIGN §8, issue 18). Same :class:`PathGraph` type and attributes as the path graph,
so routing, GeoJSON and the app-map exporter work on it unchanged.

    pg = build_skeleton(result)                                  # from an optimized MapResult
    pg = build_skeleton_from_arrays(positions_m, tag_ids=…, tag_positions_m=…)

How it is built (every threshold is a field of :class:`SkeletonParams`):

1. **Floors.** Levels from the pose heights (``find_floor_levels``); a pose within the floor band
   of a level is *settled* there. Between two consecutive settled poses on different floors lies a
   floor change, widened over the steps around it that still climb ``stairs_min_rise_per_run``:
   an elevator when it moves at most ``elevator_max_horizontal_m`` horizontally or
   rises at least ``elevator_min_rise_per_run`` m per m, stairs otherwise.
2. **Occupancy per floor.** With the tags' normals, the walked positions are first moved off the
   walls the tags mark (``app.domain.navigation.tag_walls``): between two tags whose walls face
   each other onto the corridor's middle (unless a junction of the skeleton drawn without that
   step lies between them), and in front of a single tag out to ``tag_clearance_m``. Then each
   walk's *look rounds* (a round loop on one floor, back
   where it began within ``loop_max_m`` of walking: a lobby walked round) are collapsed onto where
   they began, so they do not fill a lobby beside a corner or a junction. The walked segments of
   each floor are drawn on a grid of ``cell_m``
   in the horizontal x–z plane and widened by half the corridor width (a disk of radius
   ``corridor_width_m / 2``), then *closed* (widened and narrowed again by ``close_m``). So two
   passes of one corridor up to a corridor width apart (sway, a second pass beside the first, two
   passes that end near each other) become one band, and small holes between them are filled.
3. **Centreline.** The band is thinned to a one-cell-wide line (Zhang–Suen), which lies midway
   between the band's edges: the centreline of all the passes. Its cells become a graph
   (8-neighbours; a diagonal link that duplicates two straight ones is dropped).
4. **Cleaning.** Cells of degree ≠ 2 are *ends* and *branch points*; the runs between them are
   branches. Repeatedly: a dead-end branch shorter than ``stub_max_m`` is removed (a step toward a
   tag on the wall, a bulge of the band), a small cycle (≤ ``loop_max_m`` round) loses its longer
   side, and branch points joined by a branch shorter than ``junction_merge_m`` become one,
   placed where its branches' lines meet.
   Two dead ends within ``gap_close_m`` of each other that face each other are joined (a corridor
   walked in two passes that did not meet).
5. **Straight segments.** Each branch loses its cells within half a corridor width of its ends
   (the hook a merged branch point leaves) and is thinned by Douglas–Peucker with
   ``straight_tolerance_m``, so a straight corridor is one edge. Node heights are their floor's
   level.
6. **Stairs and elevators** keep the walked poses of the floor change (simplified), joined at both
   ends to the nearest point of their floor's skeleton.
7. **Anchors.** Each tag and point of interest is attached to the nearest point of a walk edge of
   its own floor (the edge is split there), before the stairs are linked to the floors (so a tag
   beside the stairs is on the corridor, not on the link), so a route ends beside it; its side
   of the corridor
   follows from where it is relative to the walking direction (see
   ``app.domain.navigation.instructions``).

Node attributes: ``position_m``, ``floor``, ``kind`` (``"junction"`` where three or more branches
meet, ``"node"`` otherwise), ``pose_index`` (None: a skeleton node is no pose). Edge attributes:
``length_m``, ``kind`` (walk/stairs/elevator), ``floor``. One connected graph per connected walk.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import networkx as nx
import numpy as np
import numpy.typing as npt

from app.domain.errors import ParameterError, require_finite_non_negative
from app.domain.frames import FloatArray
from app.domain.mapping.map_result import MapResult
from app.domain.navigation.centreline import Branches, branches_of, clean
from app.domain.navigation.floors import assign_floors, find_floor_levels
from app.domain.navigation.path_graph import (
    ELEVATOR,
    JUNCTION,
    NODE,
    STAIRS,
    WALK,
    Anchor,
    PathGraph,
)
from app.domain.navigation.path_graph.geometry import douglas_peucker, points_array
from app.domain.navigation.raster import densify, dilate, thin
from app.domain.navigation.tag_walls import (
    away_from_tag_walls,
    between_facing_walls,
    facing_walls,
    without_tag_visits,
)

IntArray = npt.NDArray[np.int64]
BoolArray = npt.NDArray[np.bool_]

#: A pose within this height of a floor level is settled on it, m (capped at 0.45 × level gap).
FLOOR_BAND_M = 0.75
#: A step shorter than this horizontally counts as this long when judging its slope, m.
STANDING_STILL_M = 0.05
#: A projection this close to an edge end is that end, m.
SNAP_TO_END_M = 0.3


@dataclass(frozen=True, slots=True, kw_only=True)
class SkeletonParams:
    """How a corridor skeleton is built; SI units in the names (see the module docstring).

    corridor_width_m            passes closer than this (horizontally) are one corridor, m.
    close_m                     holes in the band narrower than 2 × this are filled, m.
    cell_m                      the occupancy grid's cell, m.
    stub_max_m                  dead-end branches shorter than this are removed, m.
    loop_max_m                  cycles shorter than this (round) are cut open, m.
    junction_merge_m            branch points closer than this along a branch are one, m.
    gap_close_m                 dead ends this close and facing each other are joined, m.
    straight_tolerance_m        Douglas–Peucker tolerance of a branch, m.
    tag_clearance_m             walked positions nearer a tag's wall than this (in front of the
                                tag, within ``tag_reach_m`` along the wall) count as this far
                                from it: a walker who stepped or veered to a tag was at the wall,
                                not in the corridor's middle, m (needs the tags' normals).
    tag_reach_m                 how far along the wall from a tag that holds, m.
    facing_max_apart_m          two tags whose walls face each other at most this far apart
                                (across) bound a corridor: the positions between them are moved
                                onto its middle line (0: never), m (needs the tags' normals).
    facing_max_along_m          … when they are at most this far apart along the walls, m.
    facing_taper_m              … and the positions up to this far beyond the two tags less and
                                less, m.
    straighten_tag_visits       a walk's oblique visit to a tag (off its line to the tag's wall
                                and back, up to 5 m either side) is replaced by its line
                                (``tag_walls.without_tag_visits``; issue 39).
    spur_min_m                  a tag whose nearest walked position (within ``spur_reach_m``
                                of it) is at least this far from the corridors gets a *spur*:
                                the way the walk went from the corridors to it, as a short
                                branch (an alcove, a corridor's end hooking round a corner to
                                its last tag; issue 39). 0: never, m.
    spur_reach_m                … a walked position this near the tag (horizontally) reached it, m.
    stairs_min_rise_per_run     a floor change reaches out from the floors' bands over the steps
                                that still climb at least this steeply (rise over run), so it
                                starts where the stairs start.
    elevator_max_horizontal_m   a floor change moving at most this far horizontally is an
                                elevator, m.
    elevator_min_rise_per_run   … and so is one rising at least this many m per horizontal m.
    """

    corridor_width_m: float = 1.8
    close_m: float = 0.6
    cell_m: float = 0.25
    stub_max_m: float = 3.0
    loop_max_m: float = 20.0
    junction_merge_m: float = 3.0
    gap_close_m: float = 4.0
    straight_tolerance_m: float = 0.4
    tag_clearance_m: float = 0.8
    tag_reach_m: float = 1.0
    facing_max_apart_m: float = 5.0
    facing_max_along_m: float = 8.0
    facing_taper_m: float = 2.0
    straighten_tag_visits: bool = True
    spur_min_m: float = 2.0
    spur_reach_m: float = 1.5
    stairs_min_rise_per_run: float = 0.25
    elevator_max_horizontal_m: float = 1.5
    elevator_min_rise_per_run: float = 2.0

    def __post_init__(self) -> None:
        require_finite_non_negative(self)
        if self.cell_m <= 0 or self.corridor_width_m <= 0:
            raise ParameterError("cell_m and corridor_width_m must be > 0")


DEFAULT_SKELETON_PARAMS = SkeletonParams()


def build_skeleton(
    result: MapResult,
    *,
    walk_starts: Sequence[int] = (0,),
    params: SkeletonParams = DEFAULT_SKELETON_PARAMS,
) -> PathGraph:
    """The corridor skeleton of an optimized map (see :func:`build_skeleton_from_arrays`); a map
    of several walks passes the first pose row of each (``walk_starts``), so that its skeleton is
    fused from all of them."""
    return build_skeleton_from_arrays(
        result.world_T_phone[:, :3, 3],
        walk_starts=walk_starts,
        tag_ids=[int(t) for t in result.tag_ids],
        tag_positions_m=result.world_T_tag[:, :3, 3],
        tag_normals=result.world_T_tag[:, :3, 2],
        poi_names=result.poi_names,
        poi_positions_m=result.world_T_poi[:, :3, 3],
        params=params,
    )


def build_skeleton_from_arrays(
    positions_m: npt.ArrayLike,
    *,
    walk_starts: Sequence[int] = (0,),
    tag_ids: Sequence[int] = (),
    tag_positions_m: npt.ArrayLike | None = None,
    tag_normals: npt.ArrayLike | None = None,
    poi_names: Sequence[str] = (),
    poi_positions_m: npt.ArrayLike | None = None,
    params: SkeletonParams = DEFAULT_SKELETON_PARAMS,
) -> PathGraph:
    """The corridor skeleton of one or several walks (the steps are in the module docstring).

    positions_m: (N, 3) the walked positions in time order, map frame (y up), m; several walks
        one after the other.
    walk_starts: the row where each walk starts (0 is always one). No segment joins the end of
        one walk to the start of the next, and floor changes are found walk by walk; the floors'
        bands are drawn from all of them together, so the passes of every walk along a corridor
        are evidence of one centreline (a *fused* skeleton, issue 26).
    tag_ids, tag_positions_m: (K,) ids and (K, 3) positions of the tags, m.
    tag_normals: (K, 3) each tag's +z axis (out of its wall), map frame; with them, positions
        between the walls of two tags that face each other are moved onto the corridor's
        middle, and positions near a single tag's wall out to ``params.tag_clearance_m`` (step
        2). When two tags face each other the skeleton is drawn twice: first without the
        middle lines, to find the junctions they must not cross.
    poi_names, poi_positions_m: (P,) names and (P, 3) positions of the points of interest, m.
    """
    world_p_phone = np.asarray(positions_m, dtype=np.float64).reshape(-1, 3)
    world_p_tag = points_array(tag_positions_m, len(tag_ids), "tag_positions_m")
    world_p_poi = points_array(poi_positions_m, len(poi_names), "poi_positions_m")
    if not np.all(np.isfinite(world_p_phone)):
        raise ParameterError("positions_m must be finite")
    anchors = (tag_ids, world_p_tag, poi_names, world_p_poi)
    if tag_normals is None:
        return _skeleton(world_p_phone, walk_starts, anchors, params)
    world_n_tag = points_array(tag_normals, len(tag_ids), "tag_normals")
    clearance = {"clearance_m": params.tag_clearance_m, "reach_m": params.tag_reach_m}
    if params.straighten_tag_visits:
        bounds = _walk_bounds(walk_starts, world_p_phone.shape[0])
        world_p_phone = without_tag_visits(world_p_phone, bounds, world_p_tag, world_n_tag)
    off_walls = away_from_tag_walls(world_p_phone, world_p_tag, world_n_tag, **clearance)
    walls = facing_walls(
        world_p_tag,
        world_n_tag,
        max_apart_m=params.facing_max_apart_m,
        max_along_m=params.facing_max_along_m,
        reach_m=params.tag_reach_m,
    )
    if not walls:
        return _skeleton(off_walls, walk_starts, anchors, params)
    # Two facing tags bound one corridor only away from its junctions (where they may be on the
    # walls of two corridors): the junctions are those of the skeleton drawn without them.
    first = _skeleton(off_walls, walk_starts, anchors, params, corridors_only=True).graph
    junctions = np.array(
        [first.nodes[n]["position_m"] for n in first if first.nodes[n]["kind"] == JUNCTION],
        dtype=np.float64,
    ).reshape(-1, 3)
    walls = [w for w in walls if not w.holds_any(junctions)]
    between = between_facing_walls(world_p_phone, walls, taper_m=params.facing_taper_m)
    return _skeleton(
        away_from_tag_walls(between, world_p_tag, world_n_tag, **clearance),
        walk_starts,
        anchors,
        params,
    )


def _skeleton(
    world_p_phone: FloatArray,
    walk_starts: Sequence[int],
    anchors: tuple[Sequence[int], FloatArray, Sequence[str], FloatArray],
    params: SkeletonParams,
    *,
    corridors_only: bool = False,
) -> PathGraph:
    """:func:`build_skeleton_from_arrays` from the positions (N, 3) moved off the tags' walls,
    steps 1 and 2 on (``anchors``: the tags' ids and positions, the points of interest's names
    and positions); with ``corridors_only``, the floors' corridors alone (no stairs, no
    anchors): where their junctions are."""
    tag_ids, world_p_tag, poi_names, world_p_poi = anchors
    levels_m = find_floor_levels(world_p_phone[:, 1])
    G: nx.Graph[int] = nx.Graph()
    if world_p_phone.shape[0] == 0:
        return PathGraph(floor_levels_m=tuple(float(v) for v in levels_m))
    bounds = _walk_bounds(walk_starts, world_p_phone.shape[0])
    world_p_phone = _without_look_rounds(world_p_phone, bounds, params)  # x–z only: same floors
    pose_floor, changes, on_floor = _walks_floor_changes(world_p_phone, bounds, levels_m, params)
    for floor in range(len(levels_m)):
        segments = np.flatnonzero(on_floor & (pose_floor[:-1] == floor) & (pose_floor[1:] == floor))
        lone = np.flatnonzero(pose_floor == floor)
        p_xz = world_p_phone[:, [0, 2]]
        starts, ends = p_xz[segments], p_xz[segments + 1]
        if segments.size == 0 and lone.size:
            starts = ends = p_xz[lone[:1]]
        if starts.shape[0]:
            _add_floor(G, starts, ends, floor, float(levels_m[floor]), params)
    if params.spur_min_m > 0 and len(tag_ids):
        _add_tag_spurs(G, world_p_phone, pose_floor, bounds, world_p_tag, levels_m, params)
    if corridors_only:
        _mark_junctions(G)
        return PathGraph(graph=G, floor_levels_m=tuple(float(v) for v in levels_m))
    # tags and points of interest go on the corridors before the stairs' links to them exist: a
    # tag beside the top of the stairs is on the corridor, not on the link (issue 26)
    corridors_present = G.number_of_nodes() > 0
    if corridors_present:
        tags, pois = _attach_all(G, tag_ids, world_p_tag, poi_names, world_p_poi, levels_m)
    for change in changes:
        _add_floor_change(G, world_p_phone, levels_m, change, params)
    if not corridors_present:
        tags, pois = _attach_all(G, tag_ids, world_p_tag, poi_names, world_p_poi, levels_m)
    _mark_junctions(G)
    return PathGraph(
        graph=G, floor_levels_m=tuple(float(v) for v in levels_m), tags=tags, pois=pois
    )


# --------------------------------------------------------------------------- look rounds


#: A walk comes back to where it was when it passes within this of it again, m.
LOOK_ROUND_CLOSE_M = 0.5
#: … after walking at least this far (not the next few steps), m.
LOOK_ROUND_MIN_WALK_M = 2.0
#: A look round encloses at least this much floor (a step to a tag and back encloses none), m².
LOOK_ROUND_MIN_AREA_M2 = 2.0
#: … and is round: 4π area / perimeter² at least this (1 for a circle, 0.26 for a corridor
#: walked 10 m in and back 1 m to one side).
LOOK_ROUND_MIN_ROUNDNESS = 0.5
#: … on one floor: its heights within this of each other, m.
LOOK_ROUND_MAX_RISE_M = 0.5


def _without_look_rounds(
    world_p_phone: FloatArray, bounds: list[tuple[int, int]], params: SkeletonParams
) -> FloatArray:
    """``world_p_phone`` (N, 3) with each look round of a walk collapsed onto where it began: a
    stretch that comes back within ``LOOK_ROUND_CLOSE_M`` of where it began after at least
    ``LOOK_ROUND_MIN_WALK_M`` and at most ``params.loop_max_m`` of walking, on one floor, and
    encloses a round area of at least ``LOOK_ROUND_MIN_AREA_M2``. A walker who walks round a
    lobby to look at it goes nowhere; drawn into the band, the loop fills the lobby beside a
    junction or a corner and pulls the centreline into it (issue 26). An out-and-back (a step to
    a tag, a dead end walked in and back on its other side) encloses a thin strip, not a round
    area, and stays."""
    out = world_p_phone.copy()
    n = out.shape[0]
    if n < 4:
        return out
    xz = out[:, [0, 2]]
    walk_of = np.full(n, -1, dtype=np.int64)
    for k, (first, end) in enumerate(bounds):
        walk_of[first:end] = k
    step_m = np.hypot(*np.diff(xz, axis=0).T)
    step_m[walk_of[1:] != walk_of[:-1]] = 0.0  # no step from one walk's end to the next's start
    arc_m = np.concatenate([[0.0], np.cumsum(step_m)])
    moving = step_m[step_m > 1e-3]
    if moving.size == 0:
        return out
    window = int(min(n - 1, math.ceil(params.loop_max_m / float(np.median(moving))) + 1))
    returns = _first_returns(xz, arc_m, walk_of, window, params.loop_max_m)
    starts = np.flatnonzero(returns >= 0)
    ends = returns[starts]
    # every candidate's enclosed area at once (shoelace, by prefix sums of the edges' cross
    # products, about the walks' mean so that the sums stay small) and its perimeter
    rel = xz - xz.mean(axis=0)
    cross = rel[:-1, 0] * rel[1:, 1] - rel[1:, 0] * rel[:-1, 1]
    swept = np.concatenate([[0.0], np.cumsum(cross)])
    closing = rel[ends, 0] * rel[starts, 1] - rel[starts, 0] * rel[ends, 1]
    area_m2 = 0.5 * np.abs(swept[ends] - swept[starts] + closing)
    perimeter_m = arc_m[ends] - arc_m[starts] + np.hypot(*(xz[ends] - xz[starts]).T)
    round_enough = (area_m2 >= LOOK_ROUND_MIN_AREA_M2) & (
        4 * math.pi * area_m2 >= LOOK_ROUND_MIN_ROUNDNESS * perimeter_m**2
    )
    k = 0
    for i, j in zip(starts[round_enough].tolist(), ends[round_enough].tolist(), strict=True):
        if i < k:
            continue  # inside a loop already collapsed
        heights = out[i : j + 1, 1]
        if float(heights.max() - heights.min()) > LOOK_ROUND_MAX_RISE_M:
            continue
        out[i + 1 : j, 0] = xz[i, 0]
        out[i + 1 : j, 2] = xz[i, 1]
        k = j
    return out


def _first_returns(
    xz: FloatArray, arc_m: FloatArray, walk_of: IntArray, window: int, max_walk_m: float
) -> IntArray:
    """For each row i of ``xz`` (N, 2), the first later row j of the same walk (``walk_of``)
    within ``window`` rows that is within ``LOOK_ROUND_CLOSE_M`` of it after
    ``LOOK_ROUND_MIN_WALK_M`` to ``max_walk_m`` of walking (``arc_m``), or −1. One vector pass
    per offset over every walk at once (not per row, nor per walk)."""
    n = xz.shape[0]
    first = np.full(n, -1, dtype=np.int64)
    close_m2 = LOOK_ROUND_CLOSE_M**2
    for offset in range(1, min(window, n - 1) + 1):
        walked_m = arc_m[offset:] - arc_m[:-offset]
        if float(walked_m.max()) < LOOK_ROUND_MIN_WALK_M:
            continue
        d = xz[offset:] - xz[:-offset]
        hit = (
            (first[: n - offset] < 0)
            & (d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] <= close_m2)
            & (walked_m >= LOOK_ROUND_MIN_WALK_M)
            & (walked_m <= max_walk_m)
            & (walk_of[offset:] == walk_of[:-offset])
        )
        rows = np.flatnonzero(hit)
        first[rows] = rows + offset
    return first


# --------------------------------------------------------------------------- floors


def _walk_bounds(walk_starts: Sequence[int], n: int) -> list[tuple[int, int]]:
    """(first row, end row) of each non-empty walk of ``n`` rows starting at ``walk_starts``."""
    starts = sorted({int(s) for s in walk_starts} | {0})
    if starts[0] < 0 or starts[-1] > n:
        raise ParameterError(f"walk_starts must lie in [0, {n}], got {list(walk_starts)}")
    bounds = zip(starts, [*starts[1:], n], strict=True)
    return [(a, b) for a, b in bounds if b > a]


def _walks_floor_changes(
    world_p_phone: FloatArray,
    bounds: list[tuple[int, int]],
    levels_m: FloatArray,
    params: SkeletonParams,
) -> tuple[IntArray, list[_FloorChange], BoolArray]:
    """(pose floors (N,), the floor changes (rows of the whole array), segments (N − 1,) walked on
    one floor) of the walks ``bounds``: each walk's floor changes are its own, and the segment
    from one walk's last pose to the next walk's first is no segment."""
    n = world_p_phone.shape[0]
    pose_floor = np.zeros(n, dtype=np.int64)
    on_floor = np.zeros(max(n - 1, 0), dtype=np.bool_)
    changes: list[_FloorChange] = []
    for first, end in bounds:
        floors, own = _floor_changes(world_p_phone[first:end], levels_m, params)
        pose_floor[first:end] = floors
        on_floor[first : end - 1] = True
        for change in own:
            change = replace(change, first=change.first + first, last=change.last + first)
            on_floor[change.first : change.last] = False
            changes.append(change)
    return pose_floor, changes, on_floor


@dataclass(frozen=True, slots=True, kw_only=True)
class _FloorChange:
    """Poses ``first`` … ``last`` (rows) go from ``floor_from`` to ``floor_to`` by ``kind``."""

    first: int
    last: int
    floor_from: int
    floor_to: int
    kind: str


def _floor_changes(
    world_p_phone: FloatArray, levels_m: FloatArray, params: SkeletonParams
) -> tuple[IntArray, list[_FloorChange]]:
    """(pose floors (N,), the floor changes) of a walk (module step 1)."""
    heights_m = world_p_phone[:, 1]
    n = heights_m.shape[0]
    nearest = assign_floors(heights_m, levels_m)
    band_m = FLOOR_BAND_M
    if len(levels_m) > 1:
        band_m = min(band_m, 0.45 * float(np.min(np.diff(levels_m))))
    settled_floor = np.where(np.abs(heights_m - levels_m[nearest]) <= band_m, nearest, -1)
    settled_floor[0], settled_floor[-1] = nearest[0], nearest[-1]
    settled = np.flatnonzero(settled_floor >= 0)
    last_settled = np.maximum.accumulate(np.where(settled_floor >= 0, np.arange(n), 0))
    pose_floor = settled_floor[last_settled].astype(np.int64)
    changes: list[_FloorChange] = []
    steps = np.diff(world_p_phone, axis=0)
    run_m = np.maximum(np.hypot(steps[:, 0], steps[:, 2]), STANDING_STILL_M)
    slope = steps[:, 1] / run_m  # rise over run of each step
    done = 0
    for k in np.flatnonzero(settled_floor[settled[:-1]] != settled_floor[settled[1:]]).tolist():
        a, b = int(settled[k]), int(settled[k + 1])
        up = 1.0 if settled_floor[b] > settled_floor[a] else -1.0
        while a > done and up * slope[a - 1] >= params.stairs_min_rise_per_run:
            a -= 1  # where the stairs (or the lift) really begin …
        while b < n - 1 and up * slope[b] >= params.stairs_min_rise_per_run:
            b += 1  # … and end
        done = b
        horizontal_m = float(np.hypot(steps[a:b, 0], steps[a:b, 2]).sum())
        rise_m = abs(float(heights_m[b] - heights_m[a]))
        is_elevator = (
            horizontal_m <= params.elevator_max_horizontal_m
            or rise_m >= params.elevator_min_rise_per_run * horizontal_m
        )
        changes.append(
            _FloorChange(
                first=a,
                last=b,
                floor_from=int(settled_floor[a]),
                floor_to=int(settled_floor[b]),
                kind=ELEVATOR if is_elevator else STAIRS,
            )
        )
    return pose_floor, changes


# --------------------------------------------------------------------------- one floor


def _add_floor(
    G: nx.Graph[int],
    starts_xz: FloatArray,
    ends_xz: FloatArray,
    floor: int,
    height_m: float,
    params: SkeletonParams,
) -> None:
    """Add the skeleton of one floor's walked segments (M, 2) → (M, 2), x–z, m (steps 2–5)."""
    cell = params.cell_m
    samples = densify(starts_xz, ends_xz, cell / 2)
    grow_px = (params.corridor_width_m / 2 + params.close_m) / cell
    margin = math.ceil(grow_px) + 3
    # the grid's cells sit on multiples of cell_m in the map frame, wherever the walks reach: a
    # walk added elsewhere does not shift the raster under the corridors already walked
    origin = (np.floor(samples.min(axis=0) / cell) - margin) * cell
    index = np.floor((samples - origin) / cell).astype(np.int64)
    shape = (int(index[:, 0].max()) + margin + 1, int(index[:, 1].max()) + margin + 1)
    band = np.zeros(shape, dtype=np.bool_)
    band[index[:, 0], index[:, 1]] = True
    band = dilate(band, grow_px)
    if params.close_m > 0:
        band = ~dilate(~band, params.close_m / cell)
    state = clean(
        branches_of(thin(band)),
        stub_px=params.stub_max_m / cell,
        loop_px=params.loop_max_m / cell,
        knot_px=params.junction_merge_m / cell,
        gap_px=params.gap_close_m / cell,
        reach_px=params.corridor_width_m / cell,
    )
    _emit(G, state, origin, floor, height_m, params)
    _straighten_through_junctions(G, floor, params)
    _untangle_junctions(G, floor, params.corridor_width_m)


# --------------------------------------------------------------------------- branches → graph


def _emit(
    G: nx.Graph[int],
    state: Branches,
    origin_xz: FloatArray,
    floor: int,
    height_m: float,
    params: SkeletonParams,
) -> None:
    """Add the cleaned branches to ``G`` as straight walk edges (module step 5)."""
    cell = params.cell_m
    node_of: dict[int, int] = {}

    def key_node(key: int) -> int:
        if key not in node_of:
            node_of[key] = _new_node(
                G, (state.key_ij[key] + 0.5) * cell + origin_xz, floor, height_m
            )
        return node_of[key]

    for key in state.key_ij:
        key_node(key)
    for u, v, poly in state.branches.values():
        xz = (poly + 0.5) * cell + origin_xz
        if u != v:  # a merged branch point's old cells would make a hook at the junction
            radius_m = params.corridor_width_m / 2
            interior = np.minimum(
                np.linalg.norm(xz - xz[0], axis=1), np.linalg.norm(xz - xz[-1], axis=1)
            )
            keep = interior >= radius_m
            keep[0] = keep[-1] = True
            xz = xz[keep]
        kept = _kept_indices(xz, params.straight_tolerance_m)
        chain = [key_node(u)]
        chain += [_new_node(G, xz[k], floor, height_m) for k in kept[1:-1]]
        chain.append(key_node(v))
        for a, b in itertools.pairwise(chain):
            if a != b:
                _add_walk_edge(G, a, b, floor)


#: Two branches of a junction whose directions (to their points ``THROUGH_REACH_M`` out) are
#: within this of opposite (degrees) are one corridor through it.
THROUGH_DEG = 20.0
#: … and each passes within this of the other's (else the corridor jogs there: a decision), m.
THROUGH_OFFSET_M = 1.0
#: A branch's line runs through its points this far and twice this far out along it, m.
THROUGH_REACH_M = 4.0


def _straighten_through_junctions(G: nx.Graph[int], floor: int, params: SkeletonParams) -> None:
    """A corridor that runs straight through a junction runs straight at it: where a space
    widens there (a lobby beside a T), the centreline bows into it and the junction goes with
    it, so a walker would be told to bear in and out. Two branches whose lines (through their
    points ``THROUGH_REACH_M`` and twice that out) are within ``THROUGH_DEG`` of opposite and
    ``THROUGH_OFFSET_M`` of each other are one corridor: the junction moves onto the line
    between their nearer points, where another branch's line crosses it (by at most
    ``junction_merge_m``; none crossing, it stays), and the branches' nodes it passes go (the
    corridor's up to its nearer points, the others' within the move plus half a corridor
    width)."""
    for node in [n for n in G.nodes if G.nodes[n]["floor"] == floor and G.degree[n] >= 3]:
        if node not in G or G.degree[node] < 3:
            continue
        here = np.asarray(G.nodes[node]["position_m"])
        chains = [_chain(G, node, m) for m in G.neighbors(node)]
        inner = [m for c in chains for m in c[:-1]]
        if any(c[-1] == node for c in chains) or len(set(inner)) < len(inner):
            continue  # a loop through the junction: left to the loop cutting
        near = [_point_along(G, node, c, THROUGH_REACH_M)[[0, 2]] for c in chains]
        far = [_point_along(G, node, c, 2 * THROUGH_REACH_M)[[0, 2]] for c in chains]
        for j in range(len(chains)):  # a branch that ends before 1.5 × the reach has no line
            if float(np.linalg.norm(far[j] - near[j])) < THROUGH_REACH_M / 2:
                far[j] = near[j]
        best: tuple[float, int, int] | None = None
        for i, k in itertools.combinations(range(len(chains)), 2):
            a, b = far[i] - near[i], far[k] - near[k]  # the two branches' lines, outward
            norms = float(np.linalg.norm(a) * np.linalg.norm(b))
            if norms == 0:
                continue
            angle_deg = math.degrees(math.acos(max(-1.0, min(1.0, float(a @ b) / norms))))
            offset_m = max(  # how far each line passes from the other's near point
                _off_line_m(near[k], near[i], far[i]), _off_line_m(near[i], near[k], far[k])
            )
            if (
                angle_deg >= 180 - THROUGH_DEG
                and offset_m <= THROUGH_OFFSET_M
                and (best is None or angle_deg > best[0])
            ):
                best = (angle_deg, i, k)
        if best is None:
            continue
        p, q = near[best[1]], near[best[2]]
        t = float((here[[0, 2]] - p) @ (q - p) / max(float((q - p) @ (q - p)), 1e-12))
        on_line = p + t * (q - p)
        crossings = [  # where the other branches' lines cross the corridor's
            crossing
            for j in range(len(chains))
            if j not in best[1:]
            and (crossing := _crossing(p, q, near[j], far[j])) is not None
            and float(np.linalg.norm(crossing - on_line)) <= params.junction_merge_m
        ]
        if not crossings:  # no corridor branches off there: the bend is the corridor's own
            continue
        on_line = np.mean(crossings, axis=0)
        move_m = float(np.linalg.norm(on_line - here[[0, 2]]))
        if move_m < 0.05 or move_m > params.junction_merge_m:
            continue
        G.nodes[node]["position_m"] = (float(on_line[0]), float(here[1]), float(on_line[1]))
        clear_m = move_m + params.corridor_width_m / 2
        for j, chain in enumerate(chains):
            if j in best[1:]:  # the corridor runs straight to its point THROUGH_REACH_M out
                along_m = np.cumsum(
                    [
                        math.dist(G.nodes[a]["position_m"], G.nodes[b]["position_m"])
                        if a != node
                        else float(np.linalg.norm(np.asarray(G.nodes[b]["position_m"]) - here))
                        for a, b in itertools.pairwise([node, *chain])
                    ]
                )
                passed = [
                    m
                    for m, _ in itertools.takewhile(
                        lambda md: md[1] < THROUGH_REACH_M, zip(chain[:-1], along_m, strict=False)
                    )
                ]
            else:
                centre = G.nodes[node]["position_m"]
                passed = []
                for m in chain[:-1]:
                    if math.dist(G.nodes[m]["position_m"], centre) >= clear_m:
                        break
                    passed.append(m)
            kept = chain[len(passed)] if len(passed) < len(chain) else chain[-1]
            for m in chain[: len(passed)]:
                if m != kept and m in G and G.degree[m] <= 2:
                    G.remove_node(m)
            _add_walk_edge(G, node, kept, floor)
        for m in list(G.neighbors(node)):
            G.edges[node, m]["length_m"] = math.dist(
                G.nodes[node]["position_m"], G.nodes[m]["position_m"]
            )


def _off_line_m(point: FloatArray, a: FloatArray, b: FloatArray) -> float:
    """Distance of ``point`` from the line through ``a`` and ``b`` (x–z, m)."""
    d = b - a
    norm = float(np.linalg.norm(d))
    if norm == 0:
        return float(np.linalg.norm(point - a))
    return abs(float(d[0] * (point - a)[1] - d[1] * (point - a)[0])) / norm


def _crossing(p: FloatArray, q: FloatArray, a: FloatArray, b: FloatArray) -> FloatArray | None:
    """Where the line through ``a`` and ``b`` crosses the line through ``p`` and ``q`` (x–z, m);
    None when either has no direction or they are within 30° of parallel."""
    d, e = q - p, b - a
    cross = float(d[0] * e[1] - d[1] * e[0])
    norms = float(np.linalg.norm(d) * np.linalg.norm(e))
    if norms == 0 or abs(cross) < math.sin(math.radians(30)) * norms:
        return None
    t = float((a - p)[0] * e[1] - (a - p)[1] * e[0]) / cross
    return np.asarray(p + t * d, dtype=np.float64)


def _chain(G: nx.Graph[int], start: int, first: int) -> list[int]:
    """The nodes from ``first`` on, leaving ``start``, through nodes of degree 2, up to and
    including the first node of another degree (or ``start`` again)."""
    chain, previous, here = [first], start, first
    while G.degree[here] == 2 and here != start:
        following = next(m for m in G.neighbors(here) if m != previous)
        previous, here = here, following
        chain.append(here)
    return chain


def _point_along(G: nx.Graph[int], start: int, chain: list[int], distance_m: float) -> FloatArray:
    """The point ``distance_m`` from ``start`` along ``chain`` (its end if shorter), m."""
    points = [np.asarray(G.nodes[n]["position_m"], dtype=np.float64) for n in [start, *chain]]
    walked_m = 0.0
    for a, b in itertools.pairwise(points):
        step_m = float(np.linalg.norm(b - a))
        if walked_m + step_m >= distance_m and step_m > 0:
            return a + (b - a) * (distance_m - walked_m) / step_m
        walked_m += step_m
    return points[-1]


#: Two edges leaving a junction less than this apart (degrees) leave it the same way.
SAME_WAY_DEG = 35.0


def _untangle_junctions(G: nx.Graph[int], floor: int, within_m: float) -> None:
    """Where two edges leave a junction of ``floor`` the same way (within ``SAME_WAY_DEG``) and
    the nearer neighbour is within ``within_m``, the corridors branch at that neighbour, not at
    the junction: the farther one is linked to the nearer one instead. Else a route from one to
    the other would run into the junction and back (a turn-around)."""
    changed, rounds = True, 4 * G.number_of_nodes()  # each round moves one edge to a nearer node
    while changed and rounds > 0:
        changed, rounds = False, rounds - 1
        for node in [n for n in G.nodes if G.nodes[n]["floor"] == floor and G.degree[n] >= 3]:
            here = np.asarray(G.nodes[node]["position_m"])[[0, 2]]
            out = []
            for m in G.neighbors(node):
                d = np.asarray(G.nodes[m]["position_m"])[[0, 2]] - here
                out.append((float(np.linalg.norm(d)), m, math.atan2(d[1], d[0])))
            out.sort()
            pair = next(
                (
                    (a, b)
                    for a, b in itertools.combinations(out, 2)
                    if a[0] <= within_m
                    and a[0] > 0
                    and abs(math.remainder(a[2] - b[2], 2 * math.pi)) < math.radians(SAME_WAY_DEG)
                    and not G.has_edge(a[1], b[1])
                ),
                None,
            )
            if pair is None:
                continue
            (_, near, _), (_, far, _) = pair
            data = G.edges[node, far]
            G.remove_edge(node, far)
            _add_walk_edge(G, near, far, data["floor"], kind=data["kind"])
            changed = True
            break


def _new_node(G: nx.Graph[int], xz: FloatArray, floor: int, height_m: float) -> int:
    node = G.number_of_nodes()
    while node in G:
        node += 1
    G.add_node(
        node,
        position_m=(float(xz[0]), height_m, float(xz[1])),
        floor=floor,
        kind=NODE,
        pose_index=None,
    )
    return node


def _add_walk_edge(G: nx.Graph[int], a: int, b: int, floor: int, kind: str = WALK) -> None:
    length_m = math.dist(G.nodes[a]["position_m"], G.nodes[b]["position_m"])
    if G.has_edge(a, b) and G.edges[a, b]["length_m"] <= length_m:
        return
    G.add_edge(a, b, length_m=length_m, kind=kind, floor=floor)


def _kept_indices(points: FloatArray, tolerance_m: float) -> list[int]:
    """:func:`douglas_peucker`'s kept points as their indices."""
    return [int(i) for i in np.flatnonzero(douglas_peucker(points, tolerance_m))]


# --------------------------------------------------------------------------- tag spurs


#: A spur starts where the walk, going back from the tag, was last this near the corridors, m.
SPUR_JOIN_M = 0.5
#: … looking back at most this far along the walk, m.
SPUR_MAX_M = 15.0


def _add_tag_spurs(
    G: nx.Graph[int],
    world_p_phone: FloatArray,
    pose_floor: IntArray,
    bounds: list[tuple[int, int]],
    world_p_tag: FloatArray,
    levels_m: FloatArray,
    params: SkeletonParams,
) -> None:
    """Add a spur to each tag the walks went to off the corridors (issue 39): where a walked
    position within ``params.spur_reach_m`` of the tag lies ``params.spur_min_m`` or more from
    every walk edge of its floor, the way that walk went to it (from where it last was within
    ``SPUR_JOIN_M`` of the corridors, at most ``SPUR_MAX_M`` back), simplified as the branches
    are, joins the corridors there. The band's thinning drops such a short branch (a stub, or a
    hook merged with its corridor into one blob), so the route to an alcove's tag used to end on
    the corridor beside it, its turn unsaid. A step to a tag on a corridor's wall stays within
    the corridor (less than ``spur_min_m`` off its middle) and makes none."""
    if world_p_tag.shape[0] == 0:
        return
    walk_of = np.full(world_p_phone.shape[0], -1, dtype=np.int64)
    for k, (first, end) in enumerate(bounds):
        walk_of[first:end] = k
    tag_floor = assign_floors(world_p_tag[:, 1], levels_m)
    xz = world_p_phone[:, [0, 2]]
    for t in range(world_p_tag.shape[0]):
        floor = int(tag_floor[t])
        on_floor = np.flatnonzero(pose_floor == floor)
        if on_floor.size == 0:
            continue
        to_tag_m = np.hypot(*(xz[on_floor] - world_p_tag[t, [0, 2]]).T)
        near = on_floor[to_tag_m <= params.spur_reach_m]
        if near.size == 0:
            continue
        edges = _walk_edges(G, floor, set())
        if not edges:
            continue
        a = np.array([G.nodes[u]["position_m"] for u, _ in edges], dtype=np.float64)[:, [0, 2]]
        b = np.array([G.nodes[v]["position_m"] for _, v in edges], dtype=np.float64)[:, [0, 2]]
        off_m = _distance_to_segments(xz[near], a, b)
        if float(off_m.max()) < params.spur_min_m:
            continue
        k = int(near[int(np.argmax(off_m))])  # the deepest the walks went
        # back along k's walk, on its floor, to where it was last near the corridors
        first = bounds[int(walk_of[k])][0]
        step_m = np.hypot(*np.diff(xz[first : k + 1], axis=0).T)
        back_m = np.concatenate([np.cumsum(step_m[::-1])[::-1], [0.0]])
        rows = np.arange(first, k + 1)[back_m <= SPUR_MAX_M]
        rows = rows[pose_floor[rows] == floor]
        joined = rows[_distance_to_segments(xz[rows], a, b) <= SPUR_JOIN_M]
        if joined.size == 0:
            continue
        i = int(joined.max())
        if np.any(pose_floor[i : k + 1] != floor):
            continue
        path = xz[i : k + 1]
        kept = _kept_indices(path, params.straight_tolerance_m)
        start = _split_nearest(G, world_p_phone[i], floor)
        if start is None:
            continue
        chain = [start] + [_new_node(G, path[j], floor, float(levels_m[floor])) for j in kept[1:]]
        for u, v in itertools.pairwise(chain):
            _add_walk_edge(G, u, v, floor)


def _distance_to_segments(p: FloatArray, a: FloatArray, b: FloatArray) -> FloatArray:
    """(N,) the distance of each point (N, 2) to the nearest of the segments a → b (E, 2), m."""
    ab = b - a
    ap = p[:, None, :] - a[None, :, :]
    t = np.clip((ap * ab).sum(axis=2) / np.maximum((ab * ab).sum(axis=1), 1e-12), 0.0, 1.0)
    return np.asarray(np.linalg.norm(ap - t[..., None] * ab, axis=2).min(axis=1))


# --------------------------------------------------------------------------- stairs, anchors


def _add_floor_change(
    G: nx.Graph[int],
    world_p_phone: FloatArray,
    levels_m: FloatArray,
    change: _FloorChange,
    params: SkeletonParams,
) -> None:
    """Add the stairs or elevator of ``change`` joined to both floors' skeletons (step 6)."""
    p = world_p_phone[change.first : change.last + 1]
    kept = _douglas_peucker3(p, params.straight_tolerance_m)
    floors = assign_floors(p[kept, 1], levels_m)
    chain = []
    for k, floor in zip(kept, floors.tolist(), strict=True):
        chain.append(_new_node(G, p[k][[0, 2]], int(floor), float(p[k, 1])))
    lower = min(change.floor_from, change.floor_to)
    for a, b in itertools.pairwise(chain):
        _add_walk_edge(G, a, b, lower, kind=change.kind)
    for end, floor in ((chain[0], change.floor_from), (chain[-1], change.floor_to)):
        G.nodes[end]["floor"] = floor
        joint = _split_nearest(G, np.asarray(G.nodes[end]["position_m"]), floor, avoid={*chain})
        if joint is None or joint == end:
            continue
        if _horizontal_m(G, joint, end) <= SNAP_TO_END_M and G.degree[end] == 1:
            # a link of a few centimetres would double back on the corridor: the stairs start
            # at the corridor's node instead
            (following,) = G.neighbors(end)
            _add_walk_edge(G, joint, following, lower, kind=change.kind)
            G.remove_node(end)
        else:
            _add_walk_edge(G, joint, end, floor)


def _horizontal_m(G: nx.Graph[int], a: int, b: int) -> float:
    pa, pb = G.nodes[a]["position_m"], G.nodes[b]["position_m"]
    return math.hypot(pa[0] - pb[0], pa[2] - pb[2])


def _douglas_peucker3(points: FloatArray, tolerance_m: float) -> list[int]:
    """Douglas–Peucker on (K, 3) points via the x–z and x–y projections (both within
    tolerance)."""
    horizontal = set(_kept_indices(points[:, [0, 2]], tolerance_m))
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])
    vertical = set(_kept_indices(np.column_stack([arc, points[:, 1]]), tolerance_m))
    return sorted(horizontal | vertical)


def _walk_edges(G: nx.Graph[int], floor: int, avoid: set[int]) -> list[tuple[int, int]]:
    return [
        (u, v)
        for u, v, data in G.edges(data=True)
        if data["kind"] == WALK and data["floor"] == floor and u not in avoid and v not in avoid
    ]


def _split_nearest(
    G: nx.Graph[int], world_p: FloatArray, floor: int, *, avoid: set[int] | None = None
) -> int | None:
    """The node at the nearest point (x–z) of a walk edge of ``floor``: an end when within
    ``SNAP_TO_END_M`` of it, else a new node splitting the edge; None if the floor has no edge."""
    edges = _walk_edges(G, floor, avoid or set())
    if not edges:
        lone = [n for n in G.nodes if G.nodes[n]["floor"] == floor and n not in (avoid or set())]
        if not lone:
            return None
        xz = np.array([np.asarray(G.nodes[n]["position_m"])[[0, 2]] for n in lone])
        return lone[int(np.argmin(np.linalg.norm(xz - world_p[[0, 2]], axis=1)))]
    a = np.array([G.nodes[u]["position_m"] for u, _ in edges], dtype=np.float64)
    b = np.array([G.nodes[v]["position_m"] for _, v in edges], dtype=np.float64)
    ab = (b - a)[:, [0, 2]]
    ap = world_p[[0, 2]] - a[:, [0, 2]]
    denominator = np.maximum((ab * ab).sum(axis=1), 1e-12)
    t = np.clip((ap * ab).sum(axis=1) / denominator, 0.0, 1.0)
    distance = np.linalg.norm(ap - t[:, None] * ab, axis=1)
    e = int(np.argmin(distance))
    u, v = edges[e]
    length_m = float(np.linalg.norm(ab[e]))
    if t[e] * length_m <= SNAP_TO_END_M:
        return u
    if (1 - t[e]) * length_m <= SNAP_TO_END_M:
        return v
    data = G.edges[u, v]
    node = _new_node(G, (a[e] + t[e] * (b[e] - a[e]))[[0, 2]], floor, float(a[e, 1]))
    G.remove_edge(u, v)
    _add_walk_edge(G, u, node, data["floor"])
    _add_walk_edge(G, node, v, data["floor"])
    return node


def attach_anchor(G: nx.Graph[int], name: str, world_p: FloatArray, levels_m: FloatArray) -> Anchor:
    """Attach a tag or point of interest to the nearest point of its floor's skeleton."""
    floor = int(assign_floors(world_p[None, 1], levels_m)[0])
    node = _split_nearest(G, world_p, floor)
    if node is None:
        floors_present = {G.nodes[n]["floor"] for n in G.nodes}
        other = min(floors_present, key=lambda f: abs(levels_m[f] - world_p[1]))
        floor = int(other)
        node = _split_nearest(G, world_p, floor)
    assert node is not None
    x, y, z = (float(c) for c in world_p)
    return Anchor(name=name, node=node, position_m=(x, y, z), floor=floor)


def _attach_all(
    G: nx.Graph[int],
    tag_ids: Sequence[int],
    world_p_tag: FloatArray,
    poi_names: Sequence[str],
    world_p_poi: FloatArray,
    levels_m: FloatArray,
) -> tuple[dict[int, Anchor], tuple[Anchor, ...]]:
    tags = {
        int(t): attach_anchor(G, str(t), p, levels_m)
        for t, p in zip(tag_ids, world_p_tag, strict=True)
    }
    pois = tuple(
        attach_anchor(G, n, p, levels_m) for n, p in zip(poi_names, world_p_poi, strict=True)
    )
    return tags, pois


def _mark_junctions(G: nx.Graph[int]) -> None:
    for node in G.nodes:
        walk_degree = sum(1 for m in G.neighbors(node) if G.edges[node, m]["kind"] == WALK)
        G.nodes[node]["kind"] = JUNCTION if walk_degree >= 3 else NODE
