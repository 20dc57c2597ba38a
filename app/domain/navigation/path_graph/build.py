"""Building a path graph from an optimized trajectory.

How the graph is built (:func:`build_path_graph_from_arrays`; every threshold is a field of
:class:`PathGraphParams`):

1. **Poses → chain.** One node per pose; a pose closer than ``MIN_STEP_M`` (3-D) to the previous
   kept pose is the same place and is skipped, so no edge has zero length. Consecutive poses are
   joined by an edge of their 3-D distance.
2. **Floors.** Levels from the pose heights (``find_floor_levels``). A pose within
   ``floor_band_m`` of a level is *settled* on that floor (the first and last pose always are).
   Between two consecutive settled poses on *different* floors lies a floor-change stretch,
   widened over the poses around it that still climb at least ``stairs_min_rise_per_run`` (so it
   starts at the first step, not at the band's edge); its edges are ``stairs`` or ``elevator``
   and carry the lower floor. **Stairs or elevator**: over the whole stretch, an elevator moves
   little horizontally (path length in x–z at most ``elevator_max_horizontal_m``) or rises at
   least ``elevator_min_rise_per_run`` metres per horizontal metre; anything else is stairs
   (stairs rise ≤ 0.9 m/m, so a 2.5 m storey takes ≥ 2.8 m of run). Poses between two settled
   poses on the *same* floor (a ramp, the phone raised) are walking on that floor. Nodes inside a
   floor-change stretch get the floor nearest their height.
   *Small loops are erased*: where the walk crosses itself and the loop in between never leaves
   ``erase_loops_within_m`` of the crossing (the phone turned round on the spot), the loop's poses
   are dropped (``_erase_small_loops``).
3. **Overlapping passes are merged** (walking a corridor twice, an out-and-back, a room walked
   round again): a later pose whose horizontal distance to an earlier kept walk segment of its
   floor is at most ``merge_distance_m``, and which reached it by a detour of at least
   ``merge_min_detour_m`` along the walk (so its own trail and corners never count), is *matched*.
   A run of consecutive matched poses at least ``merge_min_length_m`` long is dropped: the walk
   joins the earlier pass at a junction where the run starts and leaves it at a junction where it
   ends, and uses the earlier pass in between (where the matches jump to another part of the
   graph, an exit and an entry junction are linked). A join point at an end of a segment is that
   pose node, not a junction. The graph then has one line per corridor, both passes are
   connected along their whole common length, and a route along it cannot zig-zag between two
   near-copies. Shorter runs (a path crossing another, ≈ 2·merge distance long) are
   kept and become crossings. Stair and elevator stretches are never merged.
4. **Closing loops.** A path end (the first or last pose) within ``close_ends_within_m`` of a
   walk segment it reached by a detour (as in 3) is joined to the nearest point of it: a walk
   that ends where it began is a closed loop. When both ends are near each other, one link.
5. **Crossings.** A junction node is added wherever two walk edges of the same floor that share
   no node meet in the horizontal x–z plane (found through a uniform grid over the edges'
   bounding boxes, not by testing all pairs). Edges that merely share an endpoint never make a
   junction. The junction splits both edges and is joined to all four ends; a split edge's pieces
   get lengths in proportion to where it was cut, so the total walked length is unchanged. Its
   height is the mean of the two edges' heights at the crossing. When the crossing is at an
   existing node (the walk passes exactly through a pose of another pass, or two collinear
   segments overlap: then both ends of the overlap are such touches), the junction takes that
   node's place and its edges; overlapping collinear pieces then become one edge.
   *Knots*: junctions joined by an edge shorter than ``contract_junctions_within_m`` (passes
   turning one corner) become one junction at their centroid (``contract_junctions``).
   So a ``junction`` node is a crossing, a point where a merged pass joins or leaves an earlier
   one, or where a loop closes on a segment: any place where ways meet that is not a pose.
6. **Anchors.** Each tag and point of interest is attached to its nearest node (3-D), preferring
   a node on its own floor (the level nearest its height) within ``attach_max_distance_m``.
7. **Simplification.** Runs of degree-2 nodes between *keep* nodes (junctions, nodes of degree
   ≠ 2, anchor nodes, nodes where the edge kind or floor changes) are thinned by Douglas–Peucker
   in 3-D with ``simplify_tolerance_m``: no removed pose is farther than that from the remaining
   polyline. Merged edges sum their lengths.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TypeAlias

import networkx as nx
import numpy as np
import numpy.typing as npt

from app.domain.errors import ParameterError, require_finite_non_negative
from app.domain.frames import FloatArray
from app.domain.mapping.map_result import MapResult
from app.domain.navigation.floors import assign_floors, find_floor_levels
from app.domain.navigation.path_graph.geometry import (
    cross_2d,
    douglas_peucker,
    node_position,
    points_array,
    project_to_segments,
    tuple3,
)
from app.domain.navigation.path_graph.model import (
    EDGE_KINDS,
    ELEVATOR,
    JUNCTION,
    NODE,
    STAIRS,
    WALK,
    Anchor,
    PathGraph,
)

# =========================================================================== building

IntArray = npt.NDArray[np.int64]
BoolArray = npt.NDArray[np.bool_]

#: Consecutive poses closer than this (3-D), m, are one node (no zero-length edges).
MIN_STEP_M = 1e-3
#: Points closer than this, m, are the same point (a crossing at a node is a touch at the node).
COINCIDENT_M = 1e-6
#: A step shorter than this horizontally counts as this long when judging its slope, m.
_STANDING_STILL_M = 0.05
#: At most this many rounds of loop erasure (each round erases every loop it finds).
_MAX_LOOP_ERASURE_ROUNDS = 8
#: Loops walked longer than this many turns of a circle of ``erase_loops_within_m`` are not tried.
_MAX_LOOP_TURNS = 10
#: A segment covering more grid cells than this is tested against the others directly.
_MAX_CELLS_PER_SEGMENT = 256

_KIND_CODES = {WALK: 0, STAIRS: 1, ELEVATOR: 2}


@dataclass(frozen=True, slots=True, kw_only=True)
class PathGraphParams:
    """How a path graph is built; every field keyword-only, SI units in the names.

        PathGraphParams()                                # the defaults below
        PathGraphParams(simplify_tolerance_m=0.0)        # keep every pose (no simplification)
        PathGraphParams(merge_distance_m=0.0)            # no merging of passes
        PathGraphParams(erase_loops_within_m=0.0, merge_distance_m=0.0, close_ends_within_m=0.0)
                                                         # every crossing of the raw walk

    simplify_tolerance_m        Douglas–Peucker tolerance: no pose of a simplified run is farther
                                than this (3-D) from the polyline that replaces it, m.
    erase_loops_within_m        a loop of the walk that never goes farther than this from where it
                                crosses itself (horizontally, m) is cut out: the phone turning on
                                the spot, not a way round anything. 0 keeps every loop.
    merge_distance_m            a later pass within this horizontal distance of an earlier one is
                                the same way (merged), m. Parallel corridors are ≥ 2 m apart
                                (wall + half widths), two passes of one corridor well under 1 m.
                                0 disables merging.
    merge_min_length_m          a run of matched poses is merged only when at least this long
                                (walked), m; must exceed 2 × ``merge_distance_m``, the length of a
                                square crossing's matched run, so crossings stay crossings.
    merge_min_detour_m          a pose matches an earlier segment only if it walked at least this
                                far since (along the walk), m: one's own trail, corners and the
                                first metre after a U-turn never match.
    close_ends_within_m         a path end this close (horizontally) to a segment it reached by a
                                detour is joined to it (loop closure), m; 0 disables.
    contract_junctions_within_m junctions joined by an edge and this close (horizontally) become one
                                junction (passes turning one corner make a knot of them), m; a
                                group never spans more than this. 0 disables.
    floor_band_m                a pose within this height of a floor level is settled on that
                                floor, m (capped at 0.45 × the smallest gap between levels).
    stairs_min_rise_per_run     a floor change reaches out from its band edges over the next poses
                                while each step still climbs (or descends) at least this steeply,
                                rise over horizontal run (≥ 5 cm of run counted), so it starts where
                                the stairs start; steeper than ramps (≤ 0.083).
    elevator_max_horizontal_m   a floor change that moves at most this far horizontally (path
                                length in x–z over the stretch) is an elevator, m.
    elevator_min_rise_per_run   … and so is one rising at least this many metres per horizontal
                                metre walked (a long ride with the phone swaying). Stairs rise at
                                most ≈ 0.9 m/m (42°, building codes), ramps ≈ 0.08.
    attach_max_distance_m       a tag or POI attaches to the nearest node of its own floor if one
                                lies within this distance (3-D), else to the nearest node, m.
    """

    simplify_tolerance_m: float = 0.25
    erase_loops_within_m: float = 0.75
    merge_distance_m: float = 0.75
    merge_min_length_m: float = 3.0
    merge_min_detour_m: float = 2.0
    close_ends_within_m: float = 1.0
    contract_junctions_within_m: float = 0.5
    floor_band_m: float = 0.75
    stairs_min_rise_per_run: float = 0.25
    elevator_max_horizontal_m: float = 1.5
    elevator_min_rise_per_run: float = 2.0
    attach_max_distance_m: float = 5.0

    def __post_init__(self) -> None:
        require_finite_non_negative(self)
        if self.floor_band_m <= 0:
            raise ParameterError(f"floor_band_m must be > 0, got {self.floor_band_m!r}")
        if self.merge_distance_m > 0 and self.merge_min_length_m <= 2 * self.merge_distance_m:
            raise ParameterError(
                f"merge_min_length_m must exceed 2 × merge_distance_m "
                f"({2 * self.merge_distance_m:g} m), got {self.merge_min_length_m!r}"
            )


DEFAULT_PATH_GRAPH_PARAMS = PathGraphParams()


def build_path_graph(
    result: MapResult, *, params: PathGraphParams = DEFAULT_PATH_GRAPH_PARAMS
) -> PathGraph:
    """The path graph of an optimized map: its trajectory, tags and points of interest.

    Positions are the translations of ``world_T_phone``, ``world_T_tag`` and ``world_T_poi``
    (map frame, y up, m); see :func:`build_path_graph_from_arrays`.
    """
    return build_path_graph_from_arrays(
        result.world_T_phone[:, :3, 3],
        tag_ids=[int(t) for t in result.tag_ids],
        tag_positions_m=result.world_T_tag[:, :3, 3],
        poi_names=result.poi_names,
        poi_positions_m=result.world_T_poi[:, :3, 3],
        params=params,
    )


def build_path_graph_from_arrays(
    positions_m: npt.ArrayLike,
    *,
    tag_ids: Sequence[int] = (),
    tag_positions_m: npt.ArrayLike | None = None,
    poi_names: Sequence[str] = (),
    poi_positions_m: npt.ArrayLike | None = None,
    params: PathGraphParams = DEFAULT_PATH_GRAPH_PARAMS,
) -> PathGraph:
    """The path graph of a walk (the steps are in the module docstring).

    positions_m: (N, 3) the walked positions in time order, map frame (y up), m.
    tag_ids, tag_positions_m: (K,) ids and (K, 3) positions of the tags, m.
    poi_names, poi_positions_m: (P,) names and (P, 3) positions of the points of interest, m.
    """
    world_p_phone = np.asarray(positions_m, dtype=np.float64).reshape(-1, 3)
    world_p_tag = points_array(tag_positions_m, len(tag_ids), "tag_positions_m")
    world_p_poi = points_array(poi_positions_m, len(poi_names), "poi_positions_m")
    if not np.all(np.isfinite(world_p_phone)):
        raise ParameterError("positions_m must be finite")
    total = world_p_phone.shape[0]
    levels_m = find_floor_levels(world_p_phone[:, 1])
    if total == 0:
        return PathGraph(floor_levels_m=tuple(float(v) for v in levels_m))

    walk = _erase_small_loops(_Walk.of(world_p_phone, levels_m, params), world_p_phone, params)
    merged = _merge_passes(walk, params)
    G = _chain_graph(walk, merged, first_junction_id=total)
    insert_crossings(G, first_junction_id=total)
    contract_junctions(G, params.contract_junctions_within_m)
    tags = dict(
        zip(
            tag_ids,
            attach_anchors(G, [str(t) for t in tag_ids], world_p_tag, levels_m, params),
            strict=True,
        )
    )
    pois = tuple(attach_anchors(G, list(poi_names), world_p_poi, levels_m, params))
    anchored = {a.node for a in tags.values()} | {a.node for a in pois}
    _simplify(G, anchored, params.simplify_tolerance_m)
    return PathGraph(
        graph=G,
        floor_levels_m=tuple(float(v) for v in levels_m),
        tags={int(t): a for t, a in tags.items()},
        pois=pois,
    )


# --------------------------------------------------------------------------- the walk and floors


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class _Walk:
    """The deduplicated walk: n poses, n−1 segments (pose k → pose k+1).

    rows: (n,) trajectory row of each pose (= its node id).
    position_m: (n, 3) map frame, m. arc_m: (n,) walked length up to each pose (3-D), m.
    segment_length_m: (n−1,) 3-D. segment_kind: (n−1,) ``_KIND_CODES``. segment_floor: (n−1,).
    pose_floor: (n,) the floor each pose is on (walking floor, or nearest level on stairs).
    matchable: (n,) False on floor-change stretches (never merged).
    """

    rows: IntArray
    position_m: FloatArray
    arc_m: FloatArray
    segment_length_m: FloatArray
    segment_kind: IntArray
    segment_floor: IntArray
    pose_floor: IntArray
    matchable: BoolArray

    @property
    def n(self) -> int:
        return int(self.rows.shape[0])

    @staticmethod
    def of(world_p_phone: FloatArray, levels_m: FloatArray, params: PathGraphParams) -> _Walk:
        rows = _deduplicate(world_p_phone)
        p = world_p_phone[rows]
        steps = np.diff(p, axis=0)
        segment_length_m = np.linalg.norm(steps, axis=1)
        horizontal_step_m = np.hypot(steps[:, 0], steps[:, 2])
        kind, segment_floor, pose_floor, matchable = _floor_changes(
            p[:, 1], horizontal_step_m, levels_m, params
        )
        return _Walk(
            rows=rows,
            position_m=p,
            arc_m=np.concatenate([[0.0], np.cumsum(segment_length_m)]),
            segment_length_m=segment_length_m,
            segment_kind=kind,
            segment_floor=segment_floor,
            pose_floor=pose_floor,
            matchable=matchable,
        )

    def without(self, dropped: BoolArray) -> _Walk:
        """This walk without the ``dropped`` poses (n,); a new segment takes the kind and floor of
        the first segment it replaces (only ever used inside a stretch of one kind and floor)."""
        keep = np.flatnonzero(~dropped)
        keep = keep[_deduplicate(self.position_m[keep])]
        p = self.position_m[keep]
        segment_length_m = np.linalg.norm(np.diff(p, axis=0), axis=1)
        return _Walk(
            rows=self.rows[keep],
            position_m=p,
            arc_m=np.concatenate([[0.0], np.cumsum(segment_length_m)]),
            segment_length_m=segment_length_m,
            segment_kind=self.segment_kind[keep[:-1]],
            segment_floor=self.segment_floor[keep[:-1]],
            pose_floor=self.pose_floor[keep],
            matchable=self.matchable[keep],
        )


def _erase_small_loops(walk: _Walk, world_p_phone: FloatArray, params: PathGraphParams) -> _Walk:
    """Cut out the loops of the walk that stay near their crossing (module step 2b).

    Where segment j crosses a later segment k (x–z, same floor, all walk in between) and no pose
    of the loop between them — counting the poses of the original walk, so that repeated
    erasure cannot eat into a corridor bit by bit — is farther from the crossing (horizontally)
    than ``erase_loops_within_m``, poses j+1 … k go and pose j joins pose k+1. Outer loops first,
    repeated until no such loop is left (a new segment can make a new crossing). Collinear
    overlaps are not loops. No pose moves more than the limit: a turn on the spot goes, a U-turn
    keeps all but the last ``erase_loops_within_m`` of its dead end.
    """
    radius_m = params.erase_loops_within_m
    for _ in range(_MAX_LOOP_ERASURE_ROUNDS):
        if radius_m <= 0 or walk.n < 4:
            return walk
        p_xz = walk.position_m[:, [0, 2]]
        first, second = _segment_pairs(p_xz[:-1], p_xz[1:])
        walkable = walk.segment_kind == _KIND_CODES[WALK]
        ok = (
            (second >= first + 2)
            & walkable[first]
            & walkable[second]
            & (walk.segment_floor[first] == walk.segment_floor[second])
            & (
                walk.arc_m[second] - walk.arc_m[first + 1]
                <= _MAX_LOOP_TURNS * 2 * math.pi * radius_m
            )
        )
        touches = _touches(p_xz[:-1], p_xz[1:], first[ok], second[ok], collinear=False)
        # The loop must be one kind and one floor all along (no stairs inside it).
        not_walk = np.concatenate([[0], np.cumsum(~walkable)])
        floor_changes = np.concatenate([[0], np.cumsum(np.diff(walk.segment_floor) != 0)])
        loops = []
        for j, _, k, _, crossing_xz in touches:
            if not_walk[k + 1] != not_walk[j] or floor_changes[k] != floor_changes[j]:
                continue
            inside_xz = world_p_phone[walk.rows[j] + 1 : walk.rows[k + 1], :][:, [0, 2]]
            if np.max(np.linalg.norm(inside_xz - crossing_xz, axis=1)) <= radius_m:
                loops.append((j, -k))
        if not loops:
            return walk
        dropped = np.zeros(walk.n, dtype=np.bool_)
        erased_up_to = -1
        for j, minus_k in sorted(loops):
            if j + 1 > erased_up_to:
                dropped[j + 1 : -minus_k + 1] = True
                erased_up_to = -minus_k
        walk = walk.without(dropped)
    return walk


def _deduplicate(world_p_phone: FloatArray) -> IntArray:
    """Rows kept: each at least ``MIN_STEP_M`` (3-D) from the previous kept one."""
    n = world_p_phone.shape[0]
    steps = np.linalg.norm(np.diff(world_p_phone, axis=0), axis=1)
    if n < 2 or np.all(steps >= MIN_STEP_M):
        return np.arange(n, dtype=np.int64)
    kept = [0]
    last = world_p_phone[0]
    for i in range(1, n):
        if float(np.linalg.norm(world_p_phone[i] - last)) >= MIN_STEP_M:
            kept.append(i)
            last = world_p_phone[i]
    return np.asarray(kept, dtype=np.int64)


def _floor_changes(
    heights_m: FloatArray,
    horizontal_step_m: FloatArray,
    levels_m: FloatArray,
    params: PathGraphParams,
) -> tuple[IntArray, IntArray, IntArray, BoolArray]:
    """(segment kind codes, segment floors, pose floors, matchable) of a walk (module step 2)."""
    n = heights_m.shape[0]
    nearest = assign_floors(heights_m, levels_m)
    band_m = params.floor_band_m
    if len(levels_m) > 1:
        band_m = min(band_m, 0.45 * float(np.min(np.diff(levels_m))))
    settled_floor = np.where(np.abs(heights_m - levels_m[nearest]) <= band_m, nearest, -1)
    settled_floor[0], settled_floor[-1] = nearest[0], nearest[-1]
    settled = np.flatnonzero(settled_floor >= 0)
    last_settled = np.maximum.accumulate(np.where(settled_floor >= 0, np.arange(n), 0))
    pose_floor = settled_floor[last_settled].astype(np.int64)
    kind = np.zeros(max(n - 1, 0), dtype=np.int64)
    segment_floor = pose_floor[:-1].copy()
    matchable = np.ones(n, dtype=np.bool_)
    changes = np.flatnonzero(settled_floor[settled[:-1]] != settled_floor[settled[1:]])
    stretches = [(int(settled[k]), int(settled[k + 1])) for k in changes.tolist()]
    rise_per_step_m = np.diff(heights_m)

    def steep(segment: int, direction: float) -> bool:
        run_m = max(float(horizontal_step_m[segment]), _STANDING_STILL_M)
        rise_m = direction * float(rise_per_step_m[segment])
        return rise_m >= params.stairs_min_rise_per_run * run_m

    done_up_to = 0
    for k, (a0, b0) in enumerate(stretches):
        floor_a, floor_b = int(settled_floor[a0]), int(settled_floor[b0])
        direction = 1.0 if floor_b > floor_a else -1.0
        a, b = a0, b0
        limit = stretches[k + 1][0] if k + 1 < len(stretches) else n - 1
        while a > done_up_to and steep(a - 1, direction):
            a -= 1  # where the stairs (or the lift) really begin
        while b < limit and steep(b, direction):
            b += 1
        done_up_to = b
        rise_m = abs(float(heights_m[b] - heights_m[a]))
        horizontal_m = float(horizontal_step_m[a:b].sum())
        is_elevator = (
            horizontal_m <= params.elevator_max_horizontal_m
            or rise_m >= params.elevator_min_rise_per_run * horizontal_m
        )
        kind[a:b] = _KIND_CODES[ELEVATOR if is_elevator else STAIRS]
        segment_floor[a:b] = min(floor_a, floor_b)
        pose_floor[a : b + 1] = nearest[a : b + 1]
        matchable[a : b + 1] = False
    return kind, segment_floor, pose_floor, matchable


# --------------------------------------------------------------------------- merging passes

#: A place on the walk: a pose (its index in the deduplicated walk) or a point on a segment,
#: ``(segment, t)`` with t in [0, 1] from pose ``segment`` to pose ``segment + 1``.
_Place: TypeAlias = int | tuple[int, float]


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class _Merged:
    """What survives merging: kept poses (their segments are edges) and extra links."""

    pose_kept: BoolArray
    links: list[tuple[_Place, _Place]]


def _merge_passes(walk: _Walk, params: PathGraphParams) -> _Merged:
    """Drop later passes that run along earlier ones; links join the rest (module steps 3–4)."""
    n = walk.n
    pose_kept = np.ones(n, dtype=np.bool_)
    links: list[tuple[_Place, _Place]] = []
    if params.merge_distance_m > 0 and n > 2:
        _drop_repeated_runs(walk, params, pose_kept, links)
    if params.close_ends_within_m > 0 and n > 2:
        _close_loops(walk, params, pose_kept, links)
    return _Merged(pose_kept=pose_kept, links=links)


def _drop_repeated_runs(
    walk: _Walk, params: PathGraphParams, pose_kept: BoolArray, links: list[tuple[_Place, _Place]]
) -> None:
    """Module step 3, in one pass over the poses.

    Kept walk segments go into a uniform grid (a dict of cells, ``merge_distance_m`` wide) as soon
    as both their poses are decided, so a pose is only ever matched against what the graph keeps
    and each query looks at a few cells. Pure Python on purpose: a numpy call per pose costs more
    than the handful of segments near it.
    """
    radius_m = params.merge_distance_m
    detour_m = params.merge_min_detour_m
    n = walk.n
    xs, zs = walk.position_m[:, 0].tolist(), walk.position_m[:, 2].tolist()
    arc = walk.arc_m.tolist()
    segment_length = walk.segment_length_m.tolist()
    walkable = (walk.segment_kind == _KIND_CODES[WALK]).tolist()
    segment_floor = walk.segment_floor.tolist()
    pose_floor = walk.pose_floor.tolist()
    matchable = walk.matchable.tolist()
    kept = [True] * n
    decided = [False] * n
    cell_m = max(radius_m, 0.25)
    grid: dict[tuple[int, int], list[int]] = {}
    big: list[int] = []

    def insert(j: int) -> None:
        if not walkable[j]:
            return
        cx0, cx1 = sorted((math.floor(xs[j] / cell_m), math.floor(xs[j + 1] / cell_m)))
        cz0, cz1 = sorted((math.floor(zs[j] / cell_m), math.floor(zs[j + 1] / cell_m)))
        if (cx1 - cx0 + 1) * (cz1 - cz0 + 1) > _MAX_CELLS_PER_SEGMENT:
            big.append(j)
            return
        for cx in range(cx0, cx1 + 1):
            for cz in range(cz0, cz1 + 1):
                grid.setdefault((cx, cz), []).append(j)

    def nearest(i: int) -> tuple[int, float, float] | None:
        """(segment, t, arc at the point) of the nearest valid match of pose i, if any."""
        x, z, floor = xs[i], zs[i], pose_floor[i]
        best: tuple[int, float, float] | None = None
        best_m = radius_m
        seen: set[int] = set()
        cells = [
            grid.get((cx, cz), ())
            for cx in range(
                math.floor((x - radius_m) / cell_m), math.floor((x + radius_m) / cell_m) + 1
            )
            for cz in range(
                math.floor((z - radius_m) / cell_m), math.floor((z + radius_m) / cell_m) + 1
            )
        ]
        for segments in [*cells, big]:
            for j in segments:
                if j in seen or segment_floor[j] != floor:
                    continue
                seen.add(j)
                ax, az = xs[j], zs[j]
                dx, dz = xs[j + 1] - ax, zs[j + 1] - az
                length2 = dx * dx + dz * dz
                t = ((x - ax) * dx + (z - az) * dz) / length2 if length2 > 0 else 0.0
                t = min(1.0, max(0.0, t))
                distance_m = math.hypot(x - ax - t * dx, z - az - t * dz)
                arc_at = arc[j] + t * segment_length[j]
                if distance_m <= best_m and arc[i] - arc_at >= detour_m:
                    best, best_m = (j, t, arc_at), distance_m
        return best

    run: list[tuple[int, int, float, float]] = []  # (pose, segment, t, arc at the match)
    breaks: list[int] = []  # where in ``run`` the matches jump to another part of the graph
    runs_dropped: list[tuple[int, int, tuple[int, float], tuple[int, float]]] = []

    def flush() -> None:
        first, last = run[0][0], run[-1][0]
        if arc[last] - arc[first] >= params.merge_min_length_m:
            for k in range(first, last + 1):
                kept[k] = False
            for start, stop in zip([0, *breaks], [*breaks, len(run)], strict=True):
                (p0, j0, t0, _), (p1, j1, t1, _) = run[start], run[stop - 1]
                runs_dropped.append((p0, p1, (j0, t0), (j1, t1)))
        for k in range(first, last + 1):
            decided[k] = True
        for j in range(max(first - 1, 0), last):
            if kept[j] and kept[j + 1]:
                insert(j)
        run.clear()
        breaks.clear()

    for i in range(n):
        match = nearest(i) if matchable[i] else None
        if match is None:
            if run:
                flush()
            decided[i] = True
            if i > 0 and kept[i - 1]:
                insert(i - 1)
            continue
        if run:
            previous_pose, _, _, previous_arc = run[-1]
            walked_m = arc[i] - arc[previous_pose]
            if abs(match[2] - previous_arc) > 2 * walked_m + 2 * radius_m:
                breaks.append(len(run))  # jumped to another part of the earlier walk
        run.append((i, *match))
    if run:
        flush()
    pose_kept[:] = kept

    # Join what is left: into each dropped run at its first match, out at its last.
    exits = {last: exit_ for _, last, _, exit_ in runs_dropped}
    for first, last, entry, exit_ in runs_dropped:
        if first > 0:
            links.append((first - 1 if kept[first - 1] else exits[first - 1], entry))
        if last + 1 < n and kept[last + 1]:
            links.append((exit_, last + 1))


def _close_loops(
    walk: _Walk, params: PathGraphParams, pose_kept: BoolArray, links: list[tuple[_Place, _Place]]
) -> None:
    n = walk.n
    p_xz = walk.position_m[:, [0, 2]]
    segment_ok = pose_kept[:-1] & pose_kept[1:] & (walk.segment_kind == _KIND_CODES[WALK])
    closed_near: FloatArray | None = None
    for end in (n - 1, 0):
        if not pose_kept[end]:
            continue
        if (
            closed_near is not None
            and float(np.linalg.norm(closed_near - p_xz[end])) <= params.close_ends_within_m
        ):
            continue  # the other end already closed the loop here
        t, distance_m = project_to_segments(p_xz[end][None, :], p_xz[:-1], p_xz[1:])
        arc_at_m = walk.arc_m[:-1] + t * walk.segment_length_m
        ok = (
            segment_ok
            & (walk.segment_floor == walk.pose_floor[end])
            & (distance_m <= params.close_ends_within_m)
            & (np.abs(walk.arc_m[end] - arc_at_m) >= params.merge_min_detour_m)
        )
        if not np.any(ok):
            continue
        j = int(np.flatnonzero(ok)[np.argmin(distance_m[ok])])
        links.append((end, (j, float(t[j]))))
        closed_near = p_xz[j] + float(t[j]) * (p_xz[j + 1] - p_xz[j])


# --------------------------------------------------------------------------- the graph


def _chain_graph(walk: _Walk, merged: _Merged, *, first_junction_id: int) -> nx.Graph[int]:
    """Kept poses and segments (split where links join them), plus the links."""
    G: nx.Graph[int] = nx.Graph()
    kinds = list(EDGE_KINDS)
    rows = walk.rows.tolist()
    for k in np.flatnonzero(merged.pose_kept).tolist():
        G.add_node(
            rows[k],
            position_m=tuple3(walk.position_m[k]),
            floor=int(walk.pose_floor[k]),
            kind=NODE,
            pose_index=rows[k],
        )

    cuts: dict[int, list[float]] = {}
    for link in merged.links:
        for place in link:
            if isinstance(place, tuple):
                cuts.setdefault(place[0], []).append(place[1])
    next_id = first_junction_id
    # Each cut becomes a junction, or the pose at the segment's end when it is that close; cuts
    # that close together are one junction. cut_nodes: (segment, t) → (t as used, node).
    cut_nodes: dict[tuple[int, float], tuple[float, int]] = {}
    for j, ts in cuts.items():
        length_m = float(walk.segment_length_m[j])
        previous: tuple[float, int] | None = None
        for t in sorted(set(ts)):
            if t * length_m <= COINCIDENT_M:
                cut_nodes[(j, t)] = (0.0, rows[j])
            elif (1 - t) * length_m <= COINCIDENT_M:
                cut_nodes[(j, t)] = (1.0, rows[j + 1])
            elif previous is not None and (t - previous[0]) * length_m <= COINCIDENT_M:
                cut_nodes[(j, t)] = previous
            else:
                position = walk.position_m[j] + t * (walk.position_m[j + 1] - walk.position_m[j])
                G.add_node(
                    next_id,
                    position_m=tuple3(position),
                    floor=int(walk.segment_floor[j]),
                    kind=JUNCTION,
                    pose_index=None,
                )
                cut_nodes[(j, t)] = (t, next_id)
                next_id += 1
            previous = cut_nodes[(j, t)]

    kept = merged.pose_kept
    for j in np.flatnonzero(kept[:-1] & kept[1:]).tolist():
        kind = kinds[int(walk.segment_kind[j])]
        floor = int(walk.segment_floor[j])
        length_m = float(walk.segment_length_m[j])
        chain = [(0.0, rows[j])]
        chain += sorted({cut_nodes[(j, t)] for t in cuts.get(j, [])})
        chain.append((1.0, rows[j + 1]))
        for (t0, u), (t1, v) in itertools.pairwise(chain):
            _add_edge(G, u, v, length_m=(t1 - t0) * length_m, kind=kind, floor=floor)

    def node_of(place: _Place) -> int:
        return rows[place] if isinstance(place, int) else cut_nodes[place][1]

    for a, b in merged.links:
        u, v = node_of(a), node_of(b)
        length_m = float(np.linalg.norm(node_position(G, u) - node_position(G, v)))
        _add_edge(G, u, v, length_m=length_m, kind=WALK, floor=int(G.nodes[u]["floor"]))
    return G


def _add_edge(G: nx.Graph[int], u: int, v: int, *, length_m: float, kind: str, floor: int) -> None:
    """Add an edge; a self-loop is dropped, and of two edges between one pair the shorter stays."""
    if u == v:
        return
    if G.has_edge(u, v) and G.edges[u, v]["length_m"] <= length_m:
        return
    G.add_edge(u, v, length_m=float(length_m), kind=kind, floor=int(floor))


# --------------------------------------------------------------------------- crossings


def insert_crossings(G: nx.Graph[int], *, first_junction_id: int) -> None:
    """Junctions where walk edges of one floor sharing no node meet in x–z (module step 5)."""
    edges = [(u, v, d) for u, v, d in G.edges(data=True) if d["kind"] == WALK]
    if len(edges) < 2:
        return
    U = np.array([u for u, _, _ in edges], dtype=np.int64)
    V = np.array([v for _, v, _ in edges], dtype=np.int64)
    floor = np.array([d["floor"] for _, _, d in edges], dtype=np.int64)
    a3 = np.array([G.nodes[u]["position_m"] for u in U.tolist()], dtype=np.float64)
    b3 = np.array([G.nodes[v]["position_m"] for v in V.tolist()], dtype=np.float64)
    a, b = a3[:, [0, 2]], b3[:, [0, 2]]
    first, second = _segment_pairs(a, b)
    ok = (
        (floor[first] == floor[second])
        & (U[first] != U[second])
        & (U[first] != V[second])
        & (V[first] != U[second])
        & (V[first] != V[second])
    )
    touches = _touches(a, b, first[ok], second[ok])
    if not touches:
        return

    # A touch is at a node (an edge's end) or inside an edge; touches sharing a place are one event.
    horizontal_m = np.linalg.norm(b - a, axis=1)
    places: list[tuple[int, float] | int] = []  # node id, or (edge, t) inside the edge
    for edge, t, _ in ((e, t, p) for e1, t1, e2, t2, p in touches for e, t in ((e1, t1), (e2, t2))):
        if t * horizontal_m[edge] <= COINCIDENT_M:
            places.append(int(U[edge]))
        elif (1 - t) * horizontal_m[edge] <= COINCIDENT_M:
            places.append(int(V[edge]))
        else:
            places.append((edge, t))
    parent = list(range(len(touches)))

    def find(k: int) -> int:
        while parent[k] != k:
            parent[k] = parent[parent[k]]
            k = parent[k]
        return k

    by_node: dict[int, int] = {}
    inside: list[tuple[int, float, int]] = []
    for k, place in enumerate(places):
        touch = k // 2
        if isinstance(place, int):
            if place in by_node:
                parent[find(touch)] = find(by_node[place])
            else:
                by_node[place] = touch
        else:
            inside.append((place[0], place[1], touch))
    inside.sort()
    for (e0, t0, k0), (e1, t1, k1) in itertools.pairwise(inside):
        if e0 == e1 and (t1 - t0) * horizontal_m[e0] <= COINCIDENT_M:
            parent[find(k1)] = find(k0)

    events: dict[int, list[int]] = {}
    for k in range(len(touches)):
        events.setdefault(find(k), []).append(k)
    next_id = max(max(G.nodes) + 1, first_junction_id)
    junction_of_touch: dict[int, int] = {}
    for members in events.values():
        xz = np.mean([touches[k][4] for k in members], axis=0)
        heights = []
        for k in members:
            for place in (places[2 * k], places[2 * k + 1]):
                if isinstance(place, int):
                    heights.append(float(G.nodes[place]["position_m"][1]))
                else:
                    e, t = place
                    heights.append(float(a3[e, 1] + t * (b3[e, 1] - a3[e, 1])))
        G.add_node(
            next_id,
            position_m=(float(xz[0]), float(np.mean(heights)), float(xz[1])),
            floor=int(floor[touches[members[0]][0]]),
            kind=JUNCTION,
            pose_index=None,
        )
        for k in members:
            junction_of_touch[k] = next_id
        next_id += 1

    # Split edges at their inside places, then let junctions take the place of touched nodes.
    splits: dict[int, list[tuple[float, int]]] = {}
    replaced: dict[int, int] = {}
    for k, place in enumerate(places):
        junction = junction_of_touch[k // 2]
        if isinstance(place, int):
            replaced[place] = junction
        else:
            splits.setdefault(place[0], []).append((place[1], junction))
    for e, cuts in splits.items():
        u, v, data = edges[e]
        G.remove_edge(u, v)
        chain = [(0.0, u), *sorted(set(cuts)), (1.0, v)]
        for (t0, n0), (t1, n1) in itertools.pairwise(chain):
            _add_edge(
                G,
                n0,
                n1,
                length_m=(t1 - t0) * data["length_m"],
                kind=data["kind"],
                floor=data["floor"],
            )
    for node, junction in replaced.items():
        for _, neighbour, data in list(G.edges(node, data=True)):
            _add_edge(
                G,
                junction,
                neighbour,
                length_m=data["length_m"],
                kind=data["kind"],
                floor=data["floor"],
            )
        G.remove_node(node)


def _touches(
    a: FloatArray, b: FloatArray, first: IntArray, second: IntArray, *, collinear: bool = True
) -> list[tuple[int, float, int, float, FloatArray]]:
    """Where segment pairs meet in 2-D: (edge, t, other edge, t', point) per meeting point.

    a, b: (E, 2) segment ends; first, second: (M,) candidate pairs. Crossing and touching pairs
    give one point; collinear overlapping pairs give the two ends of the overlap (unless
    ``collinear`` is False).
    """
    out: list[tuple[int, float, int, float, FloatArray]] = []
    if first.size == 0:
        return out
    r = b[first] - a[first]
    s = b[second] - a[second]
    qp = a[second] - a[first]
    r_len = np.linalg.norm(r, axis=1)
    s_len = np.linalg.norm(s, axis=1)
    usable = (r_len > COINCIDENT_M) & (s_len > COINCIDENT_M)
    denominator = cross_2d(r, s)
    parallel = np.abs(denominator) <= 1e-12 * np.maximum(r_len * s_len, 1e-300)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = cross_2d(qp, s) / denominator
        u = cross_2d(qp, r) / denominator
    tol_t = COINCIDENT_M / np.maximum(r_len, 1e-300)
    tol_u = COINCIDENT_M / np.maximum(s_len, 1e-300)
    meets = usable & ~parallel & (t >= -tol_t) & (t <= 1 + tol_t) & (u >= -tol_u) & (u <= 1 + tol_u)
    for k in np.flatnonzero(meets).tolist():
        tk, uk = float(np.clip(t[k], 0, 1)), float(np.clip(u[k], 0, 1))
        point = a[first[k]] + tk * r[k]
        out.append((int(first[k]), tk, int(second[k]), uk, point))

    # Collinear pairs: each end of one segment lying on the other is a touch.
    line_distance = np.abs(cross_2d(qp, r)) / np.maximum(r_len, 1e-300)
    overlapping = usable & parallel & (line_distance <= COINCIDENT_M) & collinear
    for k in np.flatnonzero(overlapping).tolist():
        e1, e2 = int(first[k]), int(second[k])
        seen: list[FloatArray] = []
        for this, other in ((e1, e2), (e2, e1)):
            for end_t, end in ((0.0, a[this]), (1.0, b[this])):
                (t_other,), (distance,) = project_to_segments(
                    end[None, :], a[other][None], b[other][None]
                )
                if distance > COINCIDENT_M or any(
                    np.linalg.norm(end - q) <= COINCIDENT_M for q in seen
                ):
                    continue
                seen.append(end)
                if this == e1:
                    out.append((e1, end_t, e2, float(t_other), end))
                else:
                    out.append((e1, float(t_other), e2, end_t, end))
    return out


# --------------------------------------------------------------------------- uniform grid


def _grid_cells(lo: FloatArray, hi: FloatArray, cell_m: float) -> tuple[IntArray, IntArray]:
    """(owner, cell key) for every grid cell each box [lo, hi] (rows of (M, 2)) overlaps."""
    i0 = np.floor(lo / cell_m).astype(np.int64)
    i1 = np.floor(hi / cell_m).astype(np.int64)
    nx_, nz = i1[:, 0] - i0[:, 0] + 1, i1[:, 1] - i0[:, 1] + 1
    counts = nx_ * nz
    owner = np.repeat(np.arange(lo.shape[0], dtype=np.int64), counts)
    local = np.arange(int(counts.sum()), dtype=np.int64) - np.repeat(
        np.cumsum(counts) - counts, counts
    )
    cx = i0[owner, 0] + local // nz[owner]
    cz = i0[owner, 1] + local % nz[owner]
    return owner, _cell_key(cx, cz)


def _cell_key(cx: IntArray, cz: IntArray) -> IntArray:
    return np.asarray(cx * (1 << 32) + (cz + (1 << 31)), dtype=np.int64)


def _cell_size_m(a: FloatArray, b: FloatArray, at_least_m: float) -> float:
    """Grid cell: twice the median segment extent, at least ``at_least_m`` (m)."""
    extent = np.max(np.abs(b - a), axis=1)
    return max(2.0 * float(np.median(extent)) if extent.size else 0.0, at_least_m, 1e-3)


def _big_segments(lo: FloatArray, hi: FloatArray, cell_m: float) -> BoolArray:
    cells = np.prod(np.floor(hi / cell_m) - np.floor(lo / cell_m) + 1, axis=1)
    return np.asarray(cells > _MAX_CELLS_PER_SEGMENT, dtype=np.bool_)


def _segment_pairs(a: FloatArray, b: FloatArray) -> tuple[IntArray, IntArray]:
    """(first, second), first < second: the segment pairs whose bounding boxes may overlap."""
    m = a.shape[0]
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    cell_m = _cell_size_m(a, b, 0.25)
    big = _big_segments(lo, hi, cell_m)
    small = np.flatnonzero(~big)
    owner, key = _grid_cells(lo[small], hi[small], cell_m)
    owner = small[owner]
    order = np.argsort(key, kind="stable")
    owner, key = owner[order], key[order]
    boundaries = np.flatnonzero(np.diff(key)) + 1
    group_end = np.repeat(
        np.append(boundaries, key.size), np.diff(np.concatenate([[0], boundaries, [key.size]]))
    )
    position = np.arange(key.size, dtype=np.int64)
    count = group_end - position - 1
    i = np.repeat(position, count)
    j = (
        i
        + 1
        + np.arange(int(count.sum()), dtype=np.int64)
        - np.repeat(np.cumsum(count) - count, count)
    )
    p, q = owner[i], owner[j]
    pairs = [np.stack([np.minimum(p, q), np.maximum(p, q)], axis=1)]
    for s in np.flatnonzero(big).tolist():
        overlap = np.all((lo <= hi[s]) & (hi >= lo[s]), axis=1)
        overlap[s] = False
        others = np.flatnonzero(overlap)
        pairs.append(np.stack([np.minimum(others, s), np.maximum(others, s)], axis=1))
    every = np.concatenate(pairs).astype(np.int64)
    every = every[every[:, 0] != every[:, 1]]
    unique = np.unique(every[:, 0] * m + every[:, 1])
    return unique // m, unique % m


def _point_segment_candidates(
    points: FloatArray, a: FloatArray, b: FloatArray, radius_m: float
) -> tuple[IntArray, IntArray]:
    """(point, segment): every segment whose box grown by ``radius_m`` may reach the point."""
    lo, hi = np.minimum(a, b) - radius_m, np.maximum(a, b) + radius_m
    cell_m = _cell_size_m(a, b, 2 * radius_m)
    big = _big_segments(lo, hi, cell_m)
    small = np.flatnonzero(~big)
    owner, key = _grid_cells(lo[small], hi[small], cell_m)
    owner = small[owner]
    order = np.argsort(key, kind="stable")
    owner, key = owner[order], key[order]
    cell = np.floor(points / cell_m).astype(np.int64)
    point_key = _cell_key(cell[:, 0], cell[:, 1])
    left = np.searchsorted(key, point_key, side="left")
    right = np.searchsorted(key, point_key, side="right")
    count = right - left
    point = np.repeat(np.arange(points.shape[0], dtype=np.int64), count)
    index = np.repeat(left, count) + (
        np.arange(int(count.sum()), dtype=np.int64) - np.repeat(np.cumsum(count) - count, count)
    )
    pairs_point, pairs_segment = [point], [owner[index]]
    for s in np.flatnonzero(big).tolist():
        inside = np.flatnonzero(np.all((points >= lo[s]) & (points <= hi[s]), axis=1))
        pairs_point.append(inside)
        pairs_segment.append(np.full(inside.size, s, dtype=np.int64))
    return (
        np.concatenate(pairs_point).astype(np.int64),
        np.concatenate(pairs_segment).astype(np.int64),
    )


def contract_junctions(G: nx.Graph[int], within_m: float) -> None:
    """Merge knots of junctions (module step 5b): junctions joined by a walk edge shorter than
    ``within_m`` (horizontal) are grouped, shortest edges first, as long as every member of a
    group stays within ``within_m / 2`` of the group's centroid; a group becomes one junction at
    its centroid (the lowest id), and each moved edge end changes that edge's length by the
    change of its straight-line length (never below the straight line)."""
    if within_m <= 0:
        return
    short = []
    for u, v, d in G.edges(data=True):
        if d["kind"] != WALK or G.nodes[u]["kind"] != JUNCTION or G.nodes[v]["kind"] != JUNCTION:
            continue
        a, b = node_position(G, u), node_position(G, v)
        distance_m = float(np.hypot(*(a - b)[[0, 2]]))
        if distance_m <= within_m:
            short.append((distance_m, u, v))
    if not short:
        return
    group: dict[int, list[int]] = {}
    root: dict[int, int] = {}

    def find(node: int) -> int:
        while root.get(node, node) != node:
            node = root[node]
        return node

    for _, u, v in sorted(short):
        ru, rv = find(u), find(v)
        if ru == rv:
            continue
        members = group.get(ru, [ru]) + group.get(rv, [rv])
        xz = np.array([G.nodes[m]["position_m"] for m in members])[:, [0, 2]]
        if np.max(np.linalg.norm(xz - xz.mean(axis=0), axis=1)) > within_m / 2:
            continue
        keep, gone = min(ru, rv), max(ru, rv)
        root[gone] = keep
        group[keep] = members
        group.pop(gone, None)

    for keep, members in group.items():
        old = {m: node_position(G, m) for m in members}
        centroid = np.mean(list(old.values()), axis=0)
        G.nodes[keep]["position_m"] = tuple3(centroid)
        for m in sorted(members, key=lambda member: member != keep):  # keep first
            for _, other, d in list(G.edges(m, data=True)):
                if other in old:
                    continue  # inside the group: disappears
                far = node_position(G, other)
                straight_m = float(np.linalg.norm(centroid - far))
                length_m = max(
                    d["length_m"] + straight_m - float(np.linalg.norm(old[m] - far)), straight_m
                )
                if m != keep:
                    _add_edge(G, keep, other, length_m=length_m, kind=d["kind"], floor=d["floor"])
                else:
                    d["length_m"] = length_m
        G.remove_nodes_from(m for m in members if m != keep)


# --------------------------------------------------------------------------- anchors


def attach_anchors(
    G: nx.Graph[int],
    names: list[str],
    world_p_thing: FloatArray,
    levels_m: FloatArray,
    params: PathGraphParams,
) -> list[Anchor]:
    """Each thing's anchor: its nearest node, one of its own floor if within reach (step 6)."""
    if not names:
        return []
    node_ids = list(G.nodes)
    node_m = np.array([G.nodes[n]["position_m"] for n in node_ids], dtype=np.float64)
    node_floor = np.array([G.nodes[n]["floor"] for n in node_ids], dtype=np.int64)
    thing_floor = assign_floors(world_p_thing[:, 1], levels_m)
    anchors = []
    for name, p, floor in zip(names, world_p_thing, thing_floor.tolist(), strict=True):
        distance_m = np.linalg.norm(node_m - p, axis=1)
        same = (node_floor == floor) & (distance_m <= params.attach_max_distance_m)
        pool = np.flatnonzero(same) if np.any(same) else np.arange(len(node_ids))
        best = int(pool[np.argmin(distance_m[pool])])
        anchors.append(
            Anchor(
                name=name, node=node_ids[best], position_m=tuple3(p), floor=int(node_floor[best])
            )
        )
    return anchors


# --------------------------------------------------------------------------- simplification


def _simplify(G: nx.Graph[int], keep: set[int], tolerance_m: float) -> None:
    """Douglas–Peucker on every run of degree-2 nodes between keep nodes (module step 7)."""
    keep = set(keep)
    for node in G.nodes:
        data = G.nodes[node]
        if data["kind"] == JUNCTION or G.degree(node) != 2:
            keep.add(node)
            continue
        (_, _, d0), (_, _, d1) = G.edges(node, data=True)
        if d0["kind"] != d1["kind"] or d0["floor"] != d1["floor"]:
            keep.add(node)

    chains: list[list[int]] = []
    inner: set[int] = set()

    def walk_from(start: int, first: int) -> list[int]:
        chain, previous, current = [start], start, first
        while current not in keep:
            chain.append(current)
            inner.add(current)
            a, b = G.neighbors(current)
            previous, current = current, (b if a == previous else a)
        chain.append(current)
        return chain

    for start in sorted(keep):
        for first in list(G.neighbors(start)):
            if first not in keep and first not in inner:
                chains.append(walk_from(start, first))
    for node in list(G.nodes):  # loops with no keep node at all
        if node not in keep and node not in inner:
            keep.add(node)
            chains.append(walk_from(node, next(iter(G.neighbors(node)))))

    for chain in chains:
        points = np.array([G.nodes[n]["position_m"] for n in chain], dtype=np.float64)
        kept = douglas_peucker(points, tolerance_m)
        ends = (chain[0], chain[-1])
        if kept.sum() == 2 and (ends[0] == ends[1] or G.has_edge(*ends)):
            far = 1 + int(np.argmax(_segment_distance(points[1:-1], points[0], points[-1])))
            kept = douglas_peucker(points[: far + 1], tolerance_m)
            kept = np.concatenate([kept, douglas_peucker(points[far:], tolerance_m)[1:]])
        if kept.all():
            continue
        data = G.edges[chain[0], chain[1]]
        kind, floor = data["kind"], data["floor"]
        lengths = [G.edges[u, v]["length_m"] for u, v in itertools.pairwise(chain)]
        index = np.flatnonzero(kept).tolist()
        G.remove_nodes_from(chain[k] for k in range(1, len(chain) - 1) if not kept[k])
        for k0, k1 in itertools.pairwise(index):
            if k1 > k0 + 1:
                length_m = float(sum(lengths[k0:k1]))
                _add_edge(G, chain[k0], chain[k1], length_m=length_m, kind=kind, floor=floor)


def _segment_distance(points: FloatArray, a: FloatArray, b: FloatArray) -> FloatArray:
    """(M,) 3-D distance of each point to the segment a–b (a point when a = b)."""
    return project_to_segments(points, a[None, :], b[None, :])[1]
