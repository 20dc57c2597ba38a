"""What simulated walks are scored with: the true corridors they walked (``corridor_graph``,
the reference) and the skeleton a building map of them gets (``fused_skeleton``)."""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence

import networkx as nx
import numpy as np

from app.domain.frames import FloatArray
from app.domain.navigation.instructions import walked_distances_m
from app.domain.navigation.path_graph import PathGraph
from app.domain.navigation.skeleton import (
    DEFAULT_SKELETON_PARAMS,
    SkeletonParams,
    attach_anchor,
    build_skeleton_from_arrays,
)

from .config import BOX_FLOOR_SLACK_M, BoolArray
from .walkers import SimulatedWalk


def corridor_graph(
    walks: SimulatedWalk | Sequence[SimulatedWalk], *, walked_within_m: float = 2.0
) -> PathGraph:
    """The building's true corridors (and stairs) as far as the walks went along them (the runs
    of each corridor whose every point is within ``walked_within_m`` of a position of one walk,
    kept when that walk was *in* the corridor there: at a position inside the corridor's free
    space and no other corridor's, not only crossing it at a junction; of a partial corridor,
    the part walked; of several walks of one building, every part any of them walked), as a path
    graph with the tags attached: the reference that a skeleton of the walks is scored against.
    A corridor walked part of the way is known that far: a tag beside it is reached along it,
    not from another corridor it happens to be nearer once the corridor is left out."""
    walks = [walks] if isinstance(walks, SimulatedWalk) else list(walks)
    building = walks[0].building
    G: nx.Graph[int] = nx.Graph()
    ids: dict[tuple[float, float, float], int] = {}
    levels = np.asarray(building.floor_heights_m, dtype=np.float64)

    def node(p: FloatArray) -> int:
        key = (round(float(p[0]), 9), round(float(p[1]), 9), round(float(p[2]), 9))
        if key not in ids:
            ids[key] = len(ids)
            floor = int(np.argmin(np.abs(levels - key[1])))
            G.add_node(ids[key], position_m=key, floor=floor, kind="node", pose_index=None)
        return ids[key]

    # each walk's partial corridors, its positions at floor level and the free-space boxes each
    # is in, once
    boxes = building.free_space_boxes_m
    walked = []
    for w in walks:
        floor_m = w.positions_m - np.array([0.0, w.phone_height_m, 0.0])
        walked.append((dict(w.partial_edges), floor_m, _inside_boxes(floor_m, boxes)))
    for e, polyline in enumerate(building.edge_polylines_m):
        runs: list[tuple[float, float]] = []
        own_boxes = _inside_boxes(0.5 * (polyline[0] + polyline[-1])[None, :], boxes)[0]
        for partial, floor_m, inside in walked:
            in_it = floor_m[inside[:, own_boxes].any(axis=1) & ~inside[:, ~own_boxes].any(axis=1)]
            if e not in partial:
                runs += _walked_runs(polyline, floor_m, walked_within_m, in_it)
                continue
            # walked in from its first node that share of the way and back: that part is known,
            # and any part the walk went into from the other end (a step to a tag there)
            turned_m = float(np.linalg.norm(polyline[-1] - polyline[0])) * partial[e]
            first_part = np.array(
                [polyline[0], polyline[0] + (polyline[-1] - polyline[0]) * partial[e]]
            )
            runs += _walked_runs(first_part, floor_m, walked_within_m, in_it)
            runs += [
                (start_m, stop_m)
                for start_m, stop_m in _walked_runs(polyline, floor_m, walked_within_m, in_it)
                # a run from the far end; or one through the turning point that goes on well
                # past the within_m every run overshoots a walk's last position by
                if start_m > turned_m or stop_m > turned_m + 2 * walked_within_m
            ]
        stairs = abs(float(polyline[-1, 1] - polyline[0, 1])) > 1e-9
        for start_m, stop_m in _union(runs):
            run = _along(polyline, start_m, stop_m)
            for a, b in itertools.pairwise(run):
                u, v = node(a), node(b)
                if u == v:
                    continue
                floor = min(G.nodes[u]["floor"], G.nodes[v]["floor"])
                kind = "stairs" if stairs and a[1] != b[1] else "walk"
                G.add_edge(u, v, length_m=float(np.linalg.norm(b - a)), kind=kind, floor=floor)
    for n in G.nodes:
        walk_degree = sum(1 for m in G.neighbors(n) if G.edges[n, m]["kind"] == "walk")
        G.nodes[n]["kind"] = "junction" if walk_degree >= 3 else "node"
    tags = {
        t: attach_anchor(G, str(t), p, levels)
        for t, p in zip(walks[0].tag_ids, walks[0].tag_positions_m, strict=True)
    }
    return PathGraph(graph=G, floor_levels_m=tuple(float(v) for v in levels), tags=tags)


def _union(runs: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """Intervals (start, stop) along one corridor merged where they overlap or touch, m."""
    merged: list[tuple[float, float]] = []
    for start_m, stop_m in sorted(runs):
        if merged and start_m <= merged[-1][1] + 1e-6:
            merged[-1] = (merged[-1][0], max(merged[-1][1], stop_m))
        else:
            merged.append((start_m, stop_m))
    return merged


def _along(polyline: FloatArray, start_m: float, stop_m: float) -> FloatArray:
    """The part of ``polyline`` (P, 3) from ``start_m`` to ``stop_m`` along it (its vertices
    between included)."""
    arc_m = walked_distances_m(polyline)
    inside = (arc_m > start_m) & (arc_m < stop_m)
    at_m = np.concatenate([[start_m], arc_m[inside], [stop_m]])
    return np.column_stack([np.interp(at_m, arc_m, polyline[:, k]) for k in range(3)])


def fused_skeleton(
    walks: Sequence[SimulatedWalk], params: SkeletonParams = DEFAULT_SKELETON_PARAMS
) -> PathGraph:
    """The corridor skeleton a building map of ``walks`` (one building, its frame, their true
    positions) gets: fused from all of them, with the tags any of them saw (a map holds no
    other); ``params`` to try other skeleton settings."""
    starts = np.cumsum([0, *(len(w.positions_m) for w in walks[:-1])]).tolist()
    seen: dict[int, FloatArray] = {}
    for w in walks:
        ids, positions = w.seen_tags()
        seen.update(zip(ids, positions, strict=True))
    tag_ids = sorted(seen)
    return build_skeleton_from_arrays(
        np.concatenate([w.positions_m for w in walks]),
        walk_starts=starts,
        tag_ids=tag_ids,
        tag_positions_m=np.array([seen[t] for t in tag_ids]).reshape(-1, 3),
        tag_normals=walks[0].tag_normals(tag_ids),
        params=params,
    )


def _walked_runs(
    polyline: FloatArray, positions_m: FloatArray, within_m: float, in_it_m: FloatArray
) -> list[tuple[float, float]]:
    """The parts of ``polyline`` (P, 3), as (start, stop) along it in m, along which every point,
    sampled every 0.5 m, has a walked position (N, 3) at floor level within ``within_m``
    (horizontally, and 1.5 m of height): the whole polyline when all of it was walked, else each
    run nearest to which one of the positions ``in_it_m`` (M, 3) lies, those inside this corridor
    and no other (a run without one is where a walk crossed the corridor at a junction)."""
    arc_m = walked_distances_m(polyline)
    length_m = float(arc_m[-1])
    at_m = np.linspace(0.0, length_m, max(1, math.ceil(length_m / 0.5)) + 1)
    samples = np.column_stack([np.interp(at_m, arc_m, polyline[:, k]) for k in range(3)])
    walked = np.zeros(len(samples), dtype=np.bool_)
    for k, p in enumerate(samples):
        near = np.abs(positions_m[:, 1] - p[1]) < 1.5
        horizontal = np.hypot(positions_m[near, 0] - p[0], positions_m[near, 2] - p[2])
        walked[k] = horizontal.size > 0 and float(horizontal.min()) <= within_m
    if walked.all():
        return [(0.0, length_m)]
    # the sample nearest to each position inside the corridor (and, for the stairs, its height)
    nearest = np.unique(
        np.argmin(np.linalg.norm(in_it_m[:, None, :] - samples[None, :, :], axis=2), axis=1)
    )
    runs = []
    edges = np.flatnonzero(np.diff(np.concatenate([[0], walked.astype(np.int8), [0]])))
    for first, end in zip(edges[::2], edges[1::2], strict=True):
        if np.any((nearest >= first) & (nearest < end)):
            runs.append((float(at_m[first]), float(at_m[end - 1])))
    return runs


def _inside_boxes(points_m: FloatArray, boxes_m: FloatArray) -> BoolArray:
    """(N, B) whether each point (N, 3) at floor level lies in each box (B, 2, 3) of free space
    (horizontally inside; at most ``BOX_FLOOR_SLACK_M`` below its floor, not above its top)."""
    low, high = boxes_m[None, :, 0, :], boxes_m[None, :, 1, :]
    p = points_m[:, None, :]
    return np.asarray(
        (p[..., 0] >= low[..., 0])
        & (p[..., 0] <= high[..., 0])
        & (p[..., 2] >= low[..., 2])
        & (p[..., 2] <= high[..., 2])
        & (p[..., 1] >= low[..., 1] - BOX_FLOOR_SLACK_M)
        & (p[..., 1] <= high[..., 1]),
        dtype=np.bool_,
    )
