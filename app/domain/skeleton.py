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
2. **Occupancy per floor.** The walked segments of each floor are drawn on a grid of ``cell_m``
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
   its own floor (the edge is split there), so a route ends beside it; its side of the corridor
   follows from where it is relative to the walking direction (see ``app.domain.instructions``).

Node attributes: ``position_m``, ``floor``, ``kind`` (``"junction"`` where three or more branches
meet, ``"node"`` otherwise), ``pose_index`` (None: a skeleton node is no pose). Edge attributes:
``length_m``, ``kind`` (walk/stairs/elevator), ``floor``. One connected graph per connected walk.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass, fields

import networkx as nx
import numpy as np
import numpy.typing as npt

from app.domain.errors import ParameterError
from app.domain.floors import assign_floors, find_floor_levels
from app.domain.frames import FloatArray
from app.domain.map_result import MapResult
from app.domain.path_graph import ELEVATOR, JUNCTION, NODE, STAIRS, WALK, Anchor, PathGraph

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
    loop_max_m: float = 12.0
    junction_merge_m: float = 3.0
    gap_close_m: float = 4.0
    straight_tolerance_m: float = 0.4
    stairs_min_rise_per_run: float = 0.25
    elevator_max_horizontal_m: float = 1.5
    elevator_min_rise_per_run: float = 2.0

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
                raise ParameterError(f"{f.name} must be a finite number ≥ 0, got {value!r}")
        if self.cell_m <= 0 or self.corridor_width_m <= 0:
            raise ParameterError("cell_m and corridor_width_m must be > 0")


DEFAULT_SKELETON_PARAMS = SkeletonParams()


def build_skeleton(
    result: MapResult, *, params: SkeletonParams = DEFAULT_SKELETON_PARAMS
) -> PathGraph:
    """The corridor skeleton of an optimized map (see :func:`build_skeleton_from_arrays`)."""
    return build_skeleton_from_arrays(
        result.world_T_phone[:, :3, 3],
        tag_ids=[int(t) for t in result.tag_ids],
        tag_positions_m=result.world_T_tag[:, :3, 3],
        poi_names=result.poi_names,
        poi_positions_m=result.world_T_poi[:, :3, 3],
        params=params,
    )


def build_skeleton_from_arrays(
    positions_m: npt.ArrayLike,
    *,
    tag_ids: Sequence[int] = (),
    tag_positions_m: npt.ArrayLike | None = None,
    poi_names: Sequence[str] = (),
    poi_positions_m: npt.ArrayLike | None = None,
    params: SkeletonParams = DEFAULT_SKELETON_PARAMS,
) -> PathGraph:
    """The corridor skeleton of a walk (the steps are in the module docstring).

    positions_m: (N, 3) the walked positions in time order, map frame (y up), m.
    tag_ids, tag_positions_m: (K,) ids and (K, 3) positions of the tags, m.
    poi_names, poi_positions_m: (P,) names and (P, 3) positions of the points of interest, m.
    """
    world_p_phone = np.asarray(positions_m, dtype=np.float64).reshape(-1, 3)
    world_p_tag = _points(tag_positions_m, len(tag_ids), "tag_positions_m")
    world_p_poi = _points(poi_positions_m, len(poi_names), "poi_positions_m")
    if not np.all(np.isfinite(world_p_phone)):
        raise ParameterError("positions_m must be finite")
    levels_m = find_floor_levels(world_p_phone[:, 1])
    G: nx.Graph[int] = nx.Graph()
    if world_p_phone.shape[0] == 0:
        return PathGraph(floor_levels_m=tuple(float(v) for v in levels_m))
    pose_floor, changes = _floor_changes(world_p_phone, levels_m, params)
    on_floor = np.ones(max(world_p_phone.shape[0] - 1, 0), dtype=np.bool_)
    for change in changes:
        on_floor[change.first : change.last] = False
    for floor in range(len(levels_m)):
        segments = np.flatnonzero(on_floor & (pose_floor[:-1] == floor) & (pose_floor[1:] == floor))
        lone = np.flatnonzero(pose_floor == floor)
        p_xz = world_p_phone[:, [0, 2]]
        starts, ends = p_xz[segments], p_xz[segments + 1]
        if segments.size == 0 and lone.size:
            starts = ends = p_xz[lone[:1]]
        if starts.shape[0]:
            _add_floor(G, starts, ends, floor, float(levels_m[floor]), params)
    for change in changes:
        _add_floor_change(G, world_p_phone, levels_m, change, params)
    tags = {
        int(t): attach_anchor(G, str(t), p, levels_m)
        for t, p in zip(tag_ids, world_p_tag, strict=True)
    }
    pois = tuple(
        attach_anchor(G, n, p, levels_m) for n, p in zip(poi_names, world_p_poi, strict=True)
    )
    _mark_junctions(G)
    return PathGraph(
        graph=G, floor_levels_m=tuple(float(v) for v in levels_m), tags=tags, pois=pois
    )


def _points(values: npt.ArrayLike | None, count: int, name: str) -> FloatArray:
    points = np.empty((0, 3)) if values is None else np.asarray(values, dtype=np.float64)
    points = points.reshape(-1, 3)
    if points.shape[0] != count:
        raise ParameterError(f"{name} has {points.shape[0]} rows for {count} names")
    return points


# --------------------------------------------------------------------------- floors


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
    samples = _densify(starts_xz, ends_xz, cell / 2)
    grow_px = (params.corridor_width_m / 2 + params.close_m) / cell
    margin = math.ceil(grow_px) + 3
    origin = samples.min(axis=0) - margin * cell
    index = np.floor((samples - origin) / cell).astype(np.int64)
    shape = (int(index[:, 0].max()) + margin + 1, int(index[:, 1].max()) + margin + 1)
    band = np.zeros(shape, dtype=np.bool_)
    band[index[:, 0], index[:, 1]] = True
    band = _dilate(band, grow_px)
    if params.close_m > 0:
        band = ~_dilate(~band, params.close_m / cell)
    line = _thin(band)
    branches = _branches(line)
    _emit(G, _clean(branches, params), origin, floor, height_m, params)


def _densify(starts: FloatArray, ends: FloatArray, spacing_m: float) -> FloatArray:
    """Points along segments (M, 2) → (M, 2), no two consecutive farther apart than spacing."""
    length = np.linalg.norm(ends - starts, axis=1)
    pieces = np.maximum(1, np.ceil(length / spacing_m).astype(np.int64))
    segment = np.repeat(np.arange(starts.shape[0]), pieces + 1)
    offsets = np.concatenate([[0], np.cumsum(pieces + 1)[:-1]])
    t = (np.arange(segment.shape[0]) - np.repeat(offsets, pieces + 1)) / np.repeat(
        pieces, pieces + 1
    )
    return np.asarray(starts[segment] + (ends - starts)[segment] * t[:, None], dtype=np.float64)


def _dilate(mask: BoolArray, radius_px: float) -> BoolArray:
    """``mask`` widened by a disk of ``radius_px`` cells: a row dilation (by running sums) per
    row offset of the disk."""
    r = math.floor(radius_px)
    if r <= 0:
        return mask.copy()
    rows, cols = mask.shape
    padded = np.zeros((rows + 2 * r, cols + 2 * r + 1), dtype=np.int32)
    padded[r : r + rows, r + 1 : r + 1 + cols] = mask
    running = np.cumsum(padded, axis=1)
    by_width: dict[int, BoolArray] = {}
    out = np.zeros((rows, cols), dtype=np.bool_)
    for dy in range(-r, r + 1):
        w = math.floor(math.sqrt(max(radius_px * radius_px - dy * dy, 0.0)))
        if w not in by_width:
            # columns c − w … c + w of the padded row (shifted by r + 1)
            hi = running[:, r + 1 + w : r + 1 + w + cols]
            lo = running[:, r - w : r - w + cols]
            by_width[w] = (hi - lo) > 0
        out |= by_width[w][r + dy : r + dy + rows]
    return out


def _thin(mask: BoolArray) -> BoolArray:
    """Zhang–Suen thinning of a binary image to 8-connected one-cell lines (border cells must be
    empty)."""
    img = mask.astype(np.uint8)
    rows_any = np.flatnonzero(mask.any(axis=1))
    cols_any = np.flatnonzero(mask.any(axis=0))
    if rows_any.size == 0:
        return mask.copy()
    r0, r1 = max(rows_any[0] - 1, 0), min(rows_any[-1] + 2, mask.shape[0])
    c0, c1 = max(cols_any[0] - 1, 0), min(cols_any[-1] + 2, mask.shape[1])
    work = img[r0:r1, c0:c1].copy()
    while True:
        changed = False
        for step in (0, 1):
            P = work
            p2, p3, p4 = P[:-2, 1:-1], P[:-2, 2:], P[1:-1, 2:]
            p5, p6, p7 = P[2:, 2:], P[2:, 1:-1], P[2:, :-2]
            p8, p9 = P[1:-1, :-2], P[:-2, :-2]
            ring = (p2, p3, p4, p5, p6, p7, p8, p9, p2)
            count = p2 + p3 + p4 + p5 + p6 + p7 + p8 + p9
            transitions = sum(
                ((a == 0) & (b == 1)).astype(np.uint8) for a, b in itertools.pairwise(ring)
            )
            if step == 0:
                keep_rule = ((p2 * p4 * p6) == 0) & ((p4 * p6 * p8) == 0)
            else:
                keep_rule = ((p2 * p4 * p8) == 0) & ((p2 * p6 * p8) == 0)
            remove = (
                (P[1:-1, 1:-1] == 1) & (count >= 2) & (count <= 6) & (transitions == 1) & keep_rule
            )
            if remove.any():
                work[1:-1, 1:-1][remove] = 0
                changed = True
        if not changed:
            break
    out = np.zeros_like(mask)
    out[r0:r1, c0:c1] = work.astype(np.bool_)
    return out


# --------------------------------------------------------------------------- line → branches


@dataclass(slots=True, kw_only=True)
class _Branches:
    """Mutable working state of one floor's centreline (grid units): ends, branches between them.

    key_ij: end or branch point id → (2,) grid position. branches: id → (u, v, polyline (K, 2)
    from u to v, both ends included).
    """

    key_ij: dict[int, FloatArray]
    branches: dict[int, tuple[int, int, FloatArray]]

    def degrees(self) -> dict[int, int]:
        degree = dict.fromkeys(self.key_ij, 0)
        for u, v, _ in self.branches.values():
            degree[u] += 1
            degree[v] += 1
        return degree


def _branches(line: BoolArray) -> _Branches:
    """The runs of a one-cell line between its ends and branch points (module step 3–4)."""
    cells = np.argwhere(line)
    ids = np.full(line.shape, -1, dtype=np.int64)
    ids[cells[:, 0], cells[:, 1]] = np.arange(cells.shape[0])
    neighbours: list[list[int]] = [[] for _ in range(cells.shape[0])]
    padded = np.zeros((line.shape[0] + 2, line.shape[1] + 2), dtype=np.bool_)
    padded[1:-1, 1:-1] = line
    for di, dj in ((0, 1), (1, 0), (1, 1), (1, -1)):
        i, j = cells[:, 0], cells[:, 1]
        has = padded[i + 1 + di, j + 1 + dj]
        if di and dj:  # a diagonal is redundant when a straight two-step path joins the cells
            has &= ~(padded[i + 1, j + 1 + dj] | padded[i + 1 + di, j + 1])
        for a in np.flatnonzero(has).tolist():
            b = int(ids[cells[a, 0] + di, cells[a, 1] + dj])
            neighbours[a].append(b)
            neighbours[b].append(a)
    degree = np.array([len(n) for n in neighbours], dtype=np.int64)
    is_key = degree != 2
    state = _Branches(key_ij={}, branches={})
    seen: set[tuple[int, int]] = set()

    def trace(start: int) -> None:
        for first in neighbours[start]:
            if (start, first) in seen:
                continue
            path = [start, first]
            seen.add((start, first))
            seen.add((first, start))
            while not is_key[path[-1]]:
                previous, here = path[-2], path[-1]
                step = next((n for n in neighbours[here] if n != previous), None)
                if step is None or (here, step) in seen:
                    break
                seen.add((here, step))
                seen.add((step, here))
                path.append(step)
            end = path[-1]
            if not is_key[end]:  # a closed loop back to a plain cell: make it a key
                is_key[end] = True
            state.key_ij.setdefault(end, cells[end].astype(np.float64))
            state.branches[len(state.branches)] = (start, end, cells[path].astype(np.float64))

    for key in np.flatnonzero(is_key).tolist():
        state.key_ij[key] = cells[key].astype(np.float64)
        trace(key)
    for cell in range(cells.shape[0]):  # pure cycles (no end, no branch point)
        if not is_key[cell] and not all((cell, n) in seen for n in neighbours[cell]):
            is_key[cell] = True
            state.key_ij[cell] = cells[cell].astype(np.float64)
            trace(cell)
    return state


def _polyline_length(points: FloatArray) -> float:
    return float(np.linalg.norm(np.diff(points, axis=0), axis=1).sum()) if len(points) > 1 else 0.0


def _clean(state: _Branches, params: SkeletonParams) -> _Branches:
    """Remove stubs and small loops, merge close branch points, join dead ends that face each
    other (module step 4). Lengths in grid cells."""
    cell = params.cell_m
    stub_px = params.stub_max_m / cell
    loop_px = params.loop_max_m / cell
    knot_px = params.junction_merge_m / cell
    for _ in range(100):
        changed = _prune_stubs(state, stub_px)
        changed |= _cut_small_loops(state, loop_px)
        changed |= _merge_knots(state, knot_px)
        changed |= _join_through_nodes(state)
        if not changed:
            break
    if _close_gaps(state, params.gap_close_m / cell, stub_px):
        _join_through_nodes(state)
    _centre_junctions(state, params.corridor_width_m / cell, knot_px)
    return state


def _centre_junctions(state: _Branches, reach_px: float, max_move_px: float) -> None:
    """Move each branch point to where its branches' lines meet (least squares), each line
    through the branch's points between 0.5 and 1.5 × ``reach_px`` from it: thinning bends the
    line into a crossing, and a merged knot sits at its cells' middle."""
    ends: dict[int, list[tuple[int, bool]]] = {}
    for b, (u, v, _) in state.branches.items():
        ends.setdefault(u, []).append((b, True))
        ends.setdefault(v, []).append((b, False))
    for key, incident in ends.items():
        if len(incident) < 3:
            continue
        normal_sum = np.zeros((2, 2))
        rhs = np.zeros(2)
        for b, from_start in incident:
            line = state.branches[b][2]
            line = line if from_start else line[::-1]
            arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(line, axis=0), axis=1))])
            near = line[int(np.searchsorted(arc, min(0.5 * reach_px, arc[-1])))]
            far = line[int(np.searchsorted(arc, min(1.5 * reach_px, arc[-1])))]
            d = far - near
            norm = float(np.linalg.norm(d))
            if norm == 0:
                continue
            d /= norm
            projector = np.eye(2) - np.outer(d, d)
            normal_sum += projector
            rhs += projector @ near
        if abs(float(np.linalg.det(normal_sum))) < 1e-6:
            continue
        centre = np.asarray(np.linalg.solve(normal_sum, rhs), dtype=np.float64)
        if float(np.linalg.norm(centre - state.key_ij[key])) > max_move_px:
            continue
        state.key_ij[key] = centre
        for b, from_start in incident:
            u, v, line = state.branches[b]
            line = line.copy()
            line[0 if from_start else -1] = centre
            state.branches[b] = (u, v, line)


def _prune_stubs(state: _Branches, stub_px: float) -> bool:
    degree = state.degrees()
    changed = False
    for b, (u, v, poly) in sorted(state.branches.items(), key=lambda e: len(e[1][2])):
        if u == v or _polyline_length(poly) >= stub_px:
            continue
        if (degree[u] == 1 and degree[v] >= 3) or (degree[v] == 1 and degree[u] >= 3):
            del state.branches[b]
            degree[u] -= 1
            degree[v] -= 1
            dead = u if degree[u] == 0 else v
            state.key_ij.pop(dead, None)
            changed = True
    return changed


def _cut_small_loops(state: _Branches, loop_px: float) -> bool:
    changed = False
    by_pair: dict[tuple[int, int], list[int]] = {}
    for b, (u, v, poly) in list(state.branches.items()):
        if u == v:
            if _polyline_length(poly) < loop_px:
                del state.branches[b]
                changed = True
            continue
        by_pair.setdefault((min(u, v), max(u, v)), []).append(b)
    for group in by_pair.values():
        while len(group) > 1:
            group.sort(key=lambda b: _polyline_length(state.branches[b][2]))
            shortest, longest = group[0], group[-1]
            round_px = _polyline_length(state.branches[shortest][2]) + _polyline_length(
                state.branches[longest][2]
            )
            if round_px >= loop_px:
                break
            del state.branches[longest]
            group.pop()
            changed = True
    return changed


def _merge_knots(state: _Branches, knot_px: float) -> bool:
    degree = state.degrees()
    for b, (u, v, poly) in sorted(state.branches.items(), key=lambda e: len(e[1][2])):
        if u == v or degree[u] < 3 or degree[v] < 3 or _polyline_length(poly) >= knot_px:
            continue
        middle = poly[len(poly) // 2].copy()
        del state.branches[b]
        state.key_ij[u] = middle
        del state.key_ij[v]
        for other, (a, c, line) in list(state.branches.items()):
            a2, c2 = (u if a == v else a), (u if c == v else c)
            if (a2, c2) != (a, c) or u in (a, c):
                line = line.copy()
                if a2 == u:
                    line = np.vstack([middle, line[1:]]) if len(line) > 1 else middle[None]
                if c2 == u:
                    line = np.vstack([line[:-1], middle])
                state.branches[other] = (a2, c2, line)
        return True
    return False


def _join_through_nodes(state: _Branches) -> bool:
    """Join the two branches at every key of degree 2 into one."""
    changed = False
    while True:
        ends: dict[int, list[int]] = {}
        for b, (u, v, _) in state.branches.items():
            ends.setdefault(u, []).append(b)
            if v != u:
                ends.setdefault(v, []).append(b)
            else:
                ends[u].append(b)
        node = next((k for k, bs in ends.items() if len(bs) == 2 and bs[0] != bs[1]), None)
        if node is None:
            return changed
        b1, b2 = ends[node]
        u1, v1, p1 = state.branches.pop(b1)
        u2, v2, p2 = state.branches.pop(b2)
        if v1 != node:
            u1, v1, p1 = v1, u1, p1[::-1]
        if u2 != node:
            u2, v2, p2 = v2, u2, p2[::-1]
        state.branches[b1] = (u1, v2, np.vstack([p1, p2[1:]]))
        del state.key_ij[node]
        changed = True


def _close_gaps(state: _Branches, gap_px: float, back_px: float) -> bool:
    """Join dead ends within ``gap_px`` whose branches point at each other (within 60°)."""
    degree = state.degrees()
    direction: dict[int, FloatArray] = {}
    for u, v, poly in state.branches.values():
        for end, line in ((u, poly[::-1]), (v, poly)):
            if degree.get(end) == 1 and len(line) > 1:
                arc = np.concatenate(
                    [[0.0], np.cumsum(np.linalg.norm(np.diff(line, axis=0), axis=1))]
                )
                back = line[int(np.searchsorted(arc, max(arc[-1] - back_px, 0.0)))]
                d = line[-1] - back
                norm = float(np.linalg.norm(d))
                if norm > 0:
                    direction[end] = d / norm
    dead = sorted(direction)
    joined: set[int] = set()
    changed = False
    cos_limit = math.cos(math.radians(60))
    pairs = []
    for i, a in enumerate(dead):
        for c in dead[i + 1 :]:
            gap = state.key_ij[c] - state.key_ij[a]
            distance = float(np.linalg.norm(gap))
            if 0 < distance <= gap_px:
                toward = gap / distance
                if direction[a] @ toward >= cos_limit and direction[c] @ -toward >= cos_limit:
                    pairs.append((distance, a, c))
    for _, a, c in sorted(pairs):
        if a in joined or c in joined:
            continue
        line = np.vstack([state.key_ij[a], state.key_ij[c]])
        state.branches[max(state.branches, default=-1) + 1] = (a, c, line)
        joined |= {a, c}
        changed = True
    return changed


# --------------------------------------------------------------------------- branches → graph


def _emit(
    G: nx.Graph[int],
    state: _Branches,
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
        kept = _douglas_peucker(xz, params.straight_tolerance_m)
        chain = [key_node(u)]
        chain += [_new_node(G, xz[k], floor, height_m) for k in kept[1:-1]]
        chain.append(key_node(v))
        for a, b in itertools.pairwise(chain):
            if a != b:
                _add_walk_edge(G, a, b, floor)


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


def _douglas_peucker(points: FloatArray, tolerance_m: float) -> list[int]:
    """Indices of the points (K, 2) kept (first and last always)."""
    n = len(points)
    if n <= 2:
        return list(range(n))
    keep = np.zeros(n, dtype=np.bool_)
    keep[0] = keep[-1] = True
    stack = [(0, n - 1)]
    while stack:
        i, j = stack.pop()
        if j <= i + 1:
            continue
        distance = _distance_to_segment(points[i + 1 : j], points[i], points[j])
        k = int(np.argmax(distance))
        if distance[k] > tolerance_m:
            keep[i + 1 + k] = True
            stack += [(i, i + 1 + k), (i + 1 + k, j)]
    return [int(i) for i in np.flatnonzero(keep)]


def _distance_to_segment(points: FloatArray, a: FloatArray, b: FloatArray) -> FloatArray:
    ab = b - a
    denominator = float(ab @ ab)
    t = (
        np.zeros(len(points))
        if denominator == 0
        else np.clip((points - a) @ ab / denominator, 0, 1)
    )
    return np.asarray(np.linalg.norm(points - (a + t[:, None] * ab), axis=1), dtype=np.float64)


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
        if joint is not None and joint != end:
            _add_walk_edge(G, joint, end, floor)


def _douglas_peucker3(points: FloatArray, tolerance_m: float) -> list[int]:
    """Douglas–Peucker on (K, 3) points via the x–z and x–y projections (both within
    tolerance)."""
    horizontal = set(_douglas_peucker(points[:, [0, 2]], tolerance_m))
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])
    vertical = set(_douglas_peucker(np.column_stack([arc, points[:, 1]]), tolerance_m))
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


def _mark_junctions(G: nx.Graph[int]) -> None:
    for node in G.nodes:
        walk_degree = sum(1 for m in G.neighbors(node) if G.edges[node, m]["kind"] == WALK)
        G.nodes[node]["kind"] = JUNCTION if walk_degree >= 3 else NODE
