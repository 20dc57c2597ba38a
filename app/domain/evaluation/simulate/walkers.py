"""Simulated walkers who stray from the corridors as real mappers do (issue 18): the walker's
config, the unseen walkers of issue 26, ``simulate_walk`` and ``walks_of_one_building``."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import cast

import networkx as nx
import numpy as np

from app.domain.errors import ParameterError, require_finite_non_negative
from app.domain.frames import FloatArray

from .building import Building, build_building
from .config import CEILING_HEIGHT_M, OBLIQUE_STANDOFF_M, BoolArray, IntArray, SimulationConfig
from .numeric import gaussian_smooth, smooth_noise
from .walk import route

# --------------------------------------------------------------------------- walkers (issue 18)


@dataclass(frozen=True, slots=True, kw_only=True)
class WalkerConfig:
    """How a simulated walker strays from the corridors' centrelines, as real mappers do (issue 18):
    they step up to tags on the walls, sway, walk a corridor again beside their first pass, and
    leave passes of one corridor that do not meet. All keyword-only, SI units in the names.

        WalkerConfig()                                   # all of it, the defaults below
        WalkerConfig(tag_step_probability=0.0, pass_offset_m=0.0, cut_corridors=0)   # on the line

    length_m                walked along the building's corridors (tag steps come on top), m.
    spacing_m               between recorded positions (a real session: ≈ 0.33 m), m.
    sway_m                  σ of the smooth side-to-side sway, m (correlated over ``sway_scale_m``).
    sway_scale_m            length scale of the sway, m.
    pass_offset_m           each walk along a corridor keeps its own offset from the centreline,
                            uniform in ± this, m (so two passes can be twice this apart).
    corner_cut_m            σ of the rounding of corners (walkers cut them), m.
    tag_step_probability    chance that the walker, passing a tag for the first time, steps out to
                            it and back.
    tag_standoff_m          how far from the tag the step stops, m.
    cut_corridors           corridors (of the lowest floor) walked only from both ends, each pass
                            turning back ``cut_gap_m`` short of the other: passes that never meet.
    cut_gap_m               the gap between the two dead ends of a cut corridor, m.
    oblique_probability     chance that a pass of a corridor reaches its tags by crossing the
                            corridor diagonally, wall to wall (from the left and from the right),
                            instead of keeping its offset (issue 26: the unseen real walks).
    lobby_probability       chance that the walker, at a junction it reaches for the first time,
                            pauses and looks around a lobby there: ``lobby_pause_poses`` positions
                            on the spot, then a loop of ``lobby_radius_m`` through the junction.
    lobby_radius_m          the radius of the loop round a lobby, m.
    lobby_pause_poses       positions recorded while pausing in a lobby (a pose every 0.5 s).
    partial_corridors       corridors (of the lowest floor, not at the start) walked in from one
                            end only, ``partial_fraction`` of their length, and back.
    partial_fraction        how far into a partial corridor the walker goes (share of its length).
    seed                    the same seed gives the same walk.

    ``UNSEEN_WALKERS`` holds one walker per behaviour the shipped walks do not show, and all of
    them together.
    """

    length_m: float = 500.0
    spacing_m: float = 0.35
    sway_m: float = 0.15
    sway_scale_m: float = 3.0
    pass_offset_m: float = 0.5
    corner_cut_m: float = 0.5
    tag_step_probability: float = 0.7
    tag_standoff_m: float = 0.2
    cut_corridors: int = 1
    cut_gap_m: float = 1.5
    oblique_probability: float = 0.0
    lobby_probability: float = 0.0
    lobby_radius_m: float = 2.5
    lobby_pause_poses: int = 20
    partial_corridors: int = 0
    partial_fraction: float = 0.5
    seed: int = 0

    def __post_init__(self) -> None:
        require_finite_non_negative(self)
        if self.spacing_m <= 0 or self.length_m <= 0:
            raise ParameterError("spacing_m and length_m must be > 0")
        for name in (
            "tag_step_probability",
            "oblique_probability",
            "lobby_probability",
            "partial_fraction",
        ):
            if getattr(self, name) > 1:
                raise ParameterError(f"{name} must be in [0, 1], got {getattr(self, name)!r}")


#: A building like floor 2 of the mac building: corridors 3.2 m wide (its facing tags are 2.8–3.8 m
#: apart) and tags 1.5–8 m apart along a corridor, on either wall (303 and 302 face each other
#: 0.8 m apart along it), so that a walker reaching tags on both walls crosses it steeply.
UNSEEN_BUILDING = SimulationConfig(num_poses=2, corridor_width_m=3.2, tag_spacing_m=(1.5, 8.0))

#: Walkers who fail the skeleton as the unseen real walks of issue 26 did, one per behaviour and
#: all together: crossing the corridor diagonally to tags on both walls, cutting corners hard,
#: pausing and looking round lobbies at junctions, and walking only part of a corridor.
UNSEEN_WALKERS: dict[str, WalkerConfig] = {
    "oblique": WalkerConfig(oblique_probability=1.0, tag_step_probability=0.0),
    "corner cutting": WalkerConfig(corner_cut_m=1.5),
    "lobby": WalkerConfig(lobby_probability=1.0),
    "partial corridors": WalkerConfig(partial_corridors=2),
    "all": WalkerConfig(
        oblique_probability=0.7,
        corner_cut_m=1.2,
        lobby_probability=0.5,
        partial_corridors=1,
    ),
}


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class SimulatedWalk:
    """A walker's recorded positions in a procedural building, and the building's truth.

    positions_m: (N, 3) the phone's positions in time order, world frame (y up), m.
    building: the true building (cut corridors are whole in it).
    tag_ids: (K,) and tag_positions_m: (K, 3) every tag of the building, m.
    cut_edges: the building edges that were walked only from both ends.
    phone_height_m: the phone's height above the floor, m.
    partial_edges: (edge, share) for each building edge walked in from its first node only, that
        share of its length, and back.
    """

    positions_m: FloatArray
    building: Building
    tag_ids: tuple[int, ...]
    tag_positions_m: FloatArray
    cut_edges: tuple[int, ...]
    phone_height_m: float
    partial_edges: tuple[tuple[int, float], ...] = ()

    def tag_normals(self, tag_ids: Sequence[int]) -> FloatArray:
        """(K, 3) each tag's +z axis: out of its wall, into the corridor."""
        return np.array([self.building.world_T_tag[t][:3, 2] for t in tag_ids]).reshape(-1, 3)

    def seen_tags(self, *, within_m: float = 3.0) -> tuple[tuple[int, ...], FloatArray]:
        """(ids (K,), positions (K, 3) m) of the tags that came within ``within_m`` (horizontally,
        on their floor) of the walk: the tags a map of it holds (a phone detects tags up to
        ~3 m away), as a real map has no tag its walker never saw."""
        ids, rows = [], []
        for k, (tag, p) in enumerate(zip(self.tag_ids, self.tag_positions_m, strict=True)):
            above_m = p[1] - self.positions_m[:, 1]
            same_floor = np.abs(above_m) < 2.0
            horizontal_m = np.hypot(*(self.positions_m[same_floor][:, [0, 2]] - p[[0, 2]]).T)
            if horizontal_m.size and float(horizontal_m.min()) <= within_m:
                ids.append(tag)
                rows.append(k)
        return tuple(ids), self.tag_positions_m[rows].reshape(-1, 3)


def simulate_walk(
    config: SimulationConfig, walker: WalkerConfig, *, building: Building | None = None
) -> SimulatedWalk:
    """A walk through ``config``'s building by a walker who strays as ``walker`` says (no odometry
    drift: the positions are what an optimized map would hold, minus its error). ``building``:
    walk this building (several walkers of one building) instead of the one drawn from the
    walker's seed."""
    rng = np.random.default_rng(walker.seed)
    if building is None:
        building = build_building(config, rng)
    walked, cut = _cut_corridors(building, walker, rng)
    walked, partial = _partial_corridors(walked, building, walker, rng)
    vertices = route(walked, walker.length_m, rng)
    centre, segment = _resample(vertices, walker.spacing_m)
    per_m = 1.0 / walker.spacing_m
    flat = np.abs(np.diff(vertices[:, 1]))[segment] < 1e-9
    offset_m = rng.uniform(-walker.pass_offset_m, walker.pass_offset_m, len(vertices) - 1)
    oblique = rng.uniform(size=len(vertices) - 1) < walker.oblique_probability
    offset_m = np.where(flat, offset_m[segment], 0.0)
    if oblique.any():
        offset_m = _oblique_offsets(
            offset_m, vertices, segment, oblique & _flat(vertices), building
        )
    if walker.corner_cut_m > 0:
        offset_m = gaussian_smooth(offset_m, walker.corner_cut_m * per_m)
        rounded = np.column_stack(
            [gaussian_smooth(centre[:, k], walker.corner_cut_m * per_m) for k in (0, 2)]
        )
        # a walker rounds corners but walks to the end of a dead end before turning back
        keep = _near_reversals(vertices, len(centre), walker.spacing_m, 3 * walker.corner_cut_m)
        centre[:, [0, 2]] = keep[:, None] * centre[:, [0, 2]] + (1 - keep[:, None]) * rounded
    sway_m = smooth_noise(rng, len(centre), walker.sway_m, walker.sway_scale_m * per_m)
    forward = np.gradient(centre[:, [0, 2]], axis=0)
    forward /= np.maximum(np.linalg.norm(forward, axis=1, keepdims=True), 1e-12)
    left = np.column_stack([forward[:, 1], -forward[:, 0]])
    side_m = offset_m + np.where(flat, sway_m, 0.0)
    positions = centre.copy()
    positions[:, [0, 2]] += side_m[:, None] * left
    positions[:, 1] += config.phone_height_m
    positions = _tag_steps(positions, building, walker, rng)
    positions = _lobbies(positions, walked, walker, rng)
    ids = tuple(sorted(building.world_T_tag))
    return SimulatedWalk(
        positions_m=positions,
        building=building,
        tag_ids=ids,
        tag_positions_m=np.array([building.world_T_tag[t][:3, 3] for t in ids]),
        cut_edges=cut,
        phone_height_m=config.phone_height_m,
        partial_edges=partial,
    )


def _near_reversals(
    vertices: FloatArray, count: int, spacing_m: float, within_m: float
) -> FloatArray:
    """(count,) for the route's points every ``spacing_m``: 1 at a vertex where the route turns
    back (≥ 150°), falling linearly to 0 at ``within_m`` from it along the route."""
    keep = np.zeros(count)
    steps = np.diff(vertices[:, [0, 2]], axis=0)
    lengths = np.linalg.norm(steps, axis=1)
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(vertices, axis=0), axis=1))])
    along = np.arange(count) * spacing_m
    for k in range(1, len(vertices) - 1):
        a, b = steps[k - 1], steps[k]
        if lengths[k - 1] < 1e-9 or lengths[k] < 1e-9:
            continue
        if float(a @ b) / (lengths[k - 1] * lengths[k]) <= math.cos(math.radians(150)):
            keep = np.maximum(keep, np.clip(1 - np.abs(along - arc[k]) / within_m, 0.0, 1.0))
    return keep


def _flat(vertices: FloatArray) -> BoolArray:
    """(P − 1,) whether each segment of the route's vertices (P, 3) is level."""
    return np.asarray(np.abs(np.diff(vertices[:, 1])) < 1e-9, dtype=np.bool_)


def _oblique_offsets(
    offset_m: FloatArray,
    vertices: FloatArray,
    segment: IntArray,
    oblique: BoolArray,
    building: Building,
) -> FloatArray:
    """``offset_m`` (per point, + left) where the passes ``oblique`` (per route segment) instead
    run from wall to wall: at each tag of the corridor the walker stands ``OBLIQUE_STANDOFF_M``
    from its wall, and between two tags (and from the pass's ends, at its own offset) it walks
    straight, so it crosses the corridor diagonally between tags on opposite walls."""
    out = offset_m.copy()
    tag_xz = np.array(
        [building.world_T_tag[t][:3, 3][[0, 2]] for t in sorted(building.world_T_tag)]
    )
    tag_y = np.array([building.world_T_tag[t][1, 3] for t in sorted(building.world_T_tag)])
    for s in np.flatnonzero(oblique).tolist():
        rows = np.flatnonzero(segment == s)
        if rows.size < 2:
            continue
        a, b = vertices[s], vertices[s + 1]
        length_m = float(np.hypot(*(b - a)[[0, 2]]))
        forward = (b - a)[[0, 2]] / max(length_m, 1e-12)
        left = np.array([forward[1], -forward[0]])
        rel = tag_xz - a[[0, 2]]
        along_m, lateral_m = rel @ forward, rel @ left
        here = (
            (np.abs(tag_y - a[1]) < CEILING_HEIGHT_M)
            & (tag_y >= a[1])
            & (np.abs(lateral_m) < 2.0)
            & (along_m > 0.5)
            & (along_m < length_m - 0.5)
        )
        order = np.argsort(along_m[here])
        wall_m = lateral_m[here][order]
        wall_m = np.sign(wall_m) * np.maximum(np.abs(wall_m) - OBLIQUE_STANDOFF_M, 0.0)
        anchors_along = np.concatenate([[0.0], along_m[here][order], [length_m]])
        anchors_side = np.concatenate([[offset_m[rows[0]]], wall_m, [offset_m[rows[-1]]]])
        point_along = np.linspace(0.0, length_m, rows.size + 1)[:-1]
        out[rows] = np.interp(point_along, anchors_along, anchors_side)
    return out


def _partial_corridors(
    walked: Building, building: Building, walker: WalkerConfig, rng: np.random.Generator
) -> tuple[Building, tuple[tuple[int, float], ...]]:
    """The building the walker walks: ``partial_corridors`` corridors of the lowest floor (edges
    of ``building`` whose removal leaves it connected, not at node 0) ending
    ``partial_fraction`` of the way along, as a dead end."""
    if walker.partial_corridors == 0:
        return walked, ()
    ends = walked.edge_nodes
    y = walked.node_xyz_m[:, 1]
    lowest = float(y.min())
    G: nx.Graph[int] = nx.Graph()
    G.add_edges_from((int(a), int(b)) for a, b in ends)
    bridges: set[frozenset[int]] = set()
    for u, v in cast("Iterator[tuple[int, int]]", nx.bridges(G)):  # typed as ints in the stubs
        bridges.add(frozenset((u, v)))
    candidates = [
        e
        for e in range(len(building.edge_nodes))
        if y[ends[e, 0]] == lowest
        and y[ends[e, 1]] == lowest
        and 0 not in ends[e]
        and frozenset((int(ends[e, 0]), int(ends[e, 1]))) not in bridges
        and tuple(ends[e]) == tuple(building.edge_nodes[e])  # not a cut corridor
    ]
    count = min(walker.partial_corridors, len(candidates))
    chosen = (
        sorted(int(e) for e in rng.choice(candidates, size=count, replace=False)) if count else []
    )
    nodes = [*walked.node_xyz_m]
    edges = [tuple(int(v) for v in e) for e in ends]
    polylines = list(walked.edge_polylines_m)
    for e in chosen:
        a, b = edges[e]
        pa, pb = walked.node_xyz_m[a], walked.node_xyz_m[b]
        nodes.append(pa + (pb - pa) * walker.partial_fraction)
        edges[e] = (a, len(nodes) - 1)
        polylines[e] = np.array([pa, nodes[-1]])
    out = dataclasses.replace(
        walked,
        node_xyz_m=np.array(nodes, dtype=np.float64),
        edge_nodes=np.array(edges, dtype=np.int64),
        edge_polylines_m=tuple(polylines),
    )
    return out, tuple((e, walker.partial_fraction) for e in chosen)


def _lobbies(
    positions: FloatArray, walked: Building, walker: WalkerConfig, rng: np.random.Generator
) -> FloatArray:
    """Insert a pause and a loop round a lobby (``lobby_radius_m``) at junctions (nodes of three
    or more corridors) reached for the first time, each with ``lobby_probability``."""
    if walker.lobby_probability == 0:
        return positions
    degree = np.bincount(walked.edge_nodes.ravel(), minlength=walked.node_xyz_m.shape[0])
    loops: dict[int, FloatArray] = {}
    for node in np.flatnonzero(degree >= 3).tolist():
        p = walked.node_xyz_m[node]
        horizontal_m = np.hypot(*(positions[:, [0, 2]] - p[[0, 2]]).T)
        above_m = positions[:, 1] - p[1]
        near = np.flatnonzero((above_m >= 0) & (above_m < 2.0) & (horizontal_m < 1.0))
        if near.size == 0 or rng.uniform() >= walker.lobby_probability:
            continue
        first_visit = near[near < near[0] + int(3.0 / walker.spacing_m)]
        k = int(first_visit[np.argmin(horizontal_m[first_visit])])
        pause = positions[k] + rng.normal(0.0, 0.03, (walker.lobby_pause_poses, 3)) * [1, 0, 1]
        start_rad = rng.uniform(0.0, 2 * math.pi)
        count = max(8, math.ceil(2 * math.pi * walker.lobby_radius_m / walker.spacing_m))
        angle = start_rad + np.linspace(0.0, 2 * math.pi, count + 1)[1:]
        centre = positions[k][[0, 2]] - walker.lobby_radius_m * np.array(
            [math.cos(start_rad), math.sin(start_rad)]
        )
        loop = np.repeat(positions[k][None], count, axis=0)
        loop[:, 0] = centre[0] + walker.lobby_radius_m * np.cos(angle)
        loop[:, 2] = centre[1] + walker.lobby_radius_m * np.sin(angle)
        loops[k] = np.concatenate([pause, loop])
    return _inserted_after(positions, loops)


def _inserted_after(positions: FloatArray, inserts: dict[int, FloatArray]) -> FloatArray:
    """``positions`` with ``inserts[k]`` walked right after row k (a pause and loop, a step to a
    tag and back)."""
    pieces: list[FloatArray] = []
    start = 0
    for k in sorted(inserts):
        pieces += [positions[start : k + 1], inserts[k]]
        start = k + 1
    pieces.append(positions[start:])
    return np.concatenate(pieces)


def _cut_corridors(
    building: Building, walker: WalkerConfig, rng: np.random.Generator
) -> tuple[Building, tuple[int, ...]]:
    """The building the walker walks: ``cut_corridors`` corridors of the lowest floor replaced by
    two dead ends ``cut_gap_m`` apart in their middle."""
    ends = building.edge_nodes
    y = building.node_xyz_m[:, 1]
    lowest = float(y.min())
    degree = np.bincount(ends.ravel(), minlength=len(y))
    candidates = [
        e
        for e in range(len(ends))
        if y[ends[e, 0]] == lowest
        and y[ends[e, 1]] == lowest
        and 0 not in ends[e]
        and min(degree[ends[e]]) > 1  # not a dead end (a hook, an alcove: issue 39)
    ]
    count = min(walker.cut_corridors, len(candidates))
    cut = sorted(int(e) for e in rng.choice(candidates, size=count, replace=False)) if count else []
    nodes = [*building.node_xyz_m]
    edges = [tuple(int(v) for v in e) for e in ends]
    polylines = list(building.edge_polylines_m)
    for e in cut:
        a, b = edges[e]
        pa, pb = building.node_xyz_m[a], building.node_xyz_m[b]
        length_m = float(np.linalg.norm(pb - pa))
        half_gap = min(walker.cut_gap_m, length_m / 2) / 2
        x = pa + (pb - pa) * (0.5 - half_gap / length_m)
        z = pa + (pb - pa) * (0.5 + half_gap / length_m)
        nodes += [x, z]
        ix, iz = len(nodes) - 2, len(nodes) - 1
        edges[e] = (a, ix)
        polylines[e] = np.array([pa, x])
        edges.append((iz, b))
        polylines.append(np.array([z, pb]))
    walked = dataclasses.replace(
        building,
        node_xyz_m=np.array(nodes, dtype=np.float64),
        edge_nodes=np.array(edges, dtype=np.int64),
        edge_polylines_m=tuple(polylines),
    )
    return walked, tuple(cut)


def _resample(vertices: FloatArray, spacing_m: float) -> tuple[FloatArray, IntArray]:
    """(points every ``spacing_m`` along the polyline (P, 3), the segment of each point)."""
    keep = np.concatenate([[True], np.linalg.norm(np.diff(vertices, axis=0), axis=1) > 1e-9])
    vertices = vertices[keep]
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(vertices, axis=0), axis=1))])
    along = np.arange(0.0, arc[-1], spacing_m)
    points = np.column_stack([np.interp(along, arc, vertices[:, k]) for k in range(3)])
    segment = np.clip(np.searchsorted(arc, along, side="right") - 1, 0, len(vertices) - 2)
    return points, segment.astype(np.int64)


def _tag_steps(
    positions: FloatArray, building: Building, walker: WalkerConfig, rng: np.random.Generator
) -> FloatArray:
    """Insert an out-and-back step to each tag passed (first pass, with the step probability)."""
    steps: dict[int, FloatArray] = {}
    for tag in sorted(building.world_T_tag):
        world_T_tag = building.world_T_tag[tag]
        target = world_T_tag[:3, 3] + walker.tag_standoff_m * world_T_tag[:3, 2]
        horizontal_m = np.hypot(*(positions[:, [0, 2]] - target[[0, 2]]).T)
        same_floor = np.abs(positions[:, 1] - target[1]) < 1.5
        near = np.flatnonzero(same_floor & (horizontal_m < 2.0))
        if near.size == 0 or rng.uniform() >= walker.tag_step_probability:
            continue
        first_pass = near[near < near[0] + int(4.0 / walker.spacing_m)]
        k = int(first_pass[np.argmin(horizontal_m[first_pass])])
        goal = np.array([target[0], positions[k, 1], target[2]])
        distance_m = float(np.linalg.norm(goal - positions[k]))
        count = max(1, math.ceil(distance_m / walker.spacing_m))
        t = np.concatenate([np.arange(1, count + 1), np.arange(count - 1, -1, -1)]) / count
        steps[k] = positions[k] + t[:, None] * (goal - positions[k])
    return _inserted_after(positions, steps)


def walks_of_one_building(
    config: SimulationConfig,
    seed: int,
    walkers: Sequence[WalkerConfig],
    *,
    length_m: float = 500.0,
) -> list[SimulatedWalk]:
    """The walks of ``walkers`` through one building (``config`` with ``seed``), each in the
    building's frame: walker k walks with seed ``100 × seed + k``, ``length_m`` long."""
    building = build_building(dataclasses.replace(config, seed=seed), np.random.default_rng(seed))
    return [
        simulate_walk(
            config,
            dataclasses.replace(w, seed=100 * seed + k, length_m=length_m),
            building=building,
        )
        for k, w in enumerate(walkers)
    ]
