"""The steps' geometry, made cheap (issue 16), agrees with the straightforward numpy it replaced:
decision points to the bit, and each polyline point matched to the same node (edge kinds,
junctions, floors) — on random stretches and graphs with coincident nodes."""

from __future__ import annotations

import itertools

import networkx as nx
import numpy as np
import pytest

from app.domain.navigation import instructions
from app.domain.navigation.floors import assign_floors
from app.domain.navigation.instructions import (
    BEAR_MIN_DEG,
    CHORD_M,
    JUNCTION_SNAP_M,
    MIN_SPACING_M,
    TAIL_MIN_CHORD_M,
    Decision,
    decision_points,
    guidance_steps,
    plan_guided_route,
)
from app.domain.navigation.path_graph import ELEVATOR, JUNCTION, NODE, STAIRS, WALK, PathGraph
from app.domain.navigation.routing import TagEnd, node_lookups, plan_walk
from tests.unit.test_route_answers import recorded_graph

# --------------------------------------------------------------------------- decision points


def reference_decision_points(
    xyz: np.ndarray, junction: list[bool], end_margin_m: float
) -> list[Decision]:
    """:func:`decision_points` as it was written before it was made cheap."""
    walked_m = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xyz, axis=0), axis=1))])
    total_m = float(walked_m[-1]) if len(xyz) else 0.0
    candidates: list[tuple[int, float]] = []
    inner = np.arange(1, max(len(xyz) - 1, 1))
    inner = inner[(walked_m[inner] >= end_margin_m) & (total_m - walked_m[inner] >= end_margin_m)]
    if inner.size:
        xz = xyz[:, [0, 2]]
        here = xz[inner]

        def points_at(along_m: np.ndarray) -> np.ndarray:
            return np.column_stack(
                [np.interp(along_m, walked_m, xz[:, 0]), np.interp(along_m, walked_m, xz[:, 1])]
            )

        before = here - points_at(np.maximum(walked_m[inner] - CHORD_M, 0.0))
        after = points_at(np.minimum(walked_m[inner] + CHORD_M, total_m)) - here
        cross_y = before[:, 1] * after[:, 0] - before[:, 0] * after[:, 1]
        dot = (before * after).sum(axis=1)
        turn_deg = np.degrees(np.arctan2(cross_y, dot))
        moving = (np.linalg.norm(before, axis=1) > 0) & (np.linalg.norm(after, axis=1) > 0)
        for k, turn in zip(inner[moving].tolist(), turn_deg[moving].tolist(), strict=True):
            if abs(turn) >= BEAR_MIN_DEG:
                candidates.append((k, turn))
    chosen: list[Decision] = []
    walked = walked_m.tolist()
    junctions = [j for j in range(len(xyz)) if junction[j]]
    for k, turn in sorted(candidates, key=lambda c: -abs(c[1])):
        index, at_junction, along_m = k, False, walked[k]
        near = [j for j in junctions if abs(walked[j] - along_m) <= JUNCTION_SNAP_M]
        if near:
            index = min(near, key=lambda j: abs(walked[j] - along_m))
            at_junction, along_m = True, walked[index]
        if any(
            abs(along_m - d.along_m) < MIN_SPACING_M and not (at_junction and d.at_junction)
            for d in chosen
        ) or any(index == d.index for d in chosen):
            continue
        if reference_tail(xyz, walked_m, walked[k], [d.along_m for d in chosen]):
            continue
        chosen.append(
            Decision(index=index, turn_deg=turn, at_junction=at_junction, along_m=along_m)
        )
    return sorted(chosen, key=lambda d: d.along_m)


def reference_tail(
    xyz: np.ndarray, walked_m: np.ndarray, at_m: float, chosen_m: list[float]
) -> bool:
    """The bend at ``at_m`` measured with its chords stopping at the chosen decisions within
    ``CHORD_M`` (issue 39): under ``BEAR_MIN_DEG``, it is the tail of one of them."""
    near = [d for d in chosen_m if 0 < abs(d - at_m) < CHORD_M]
    if not near:
        return False
    from_m = max([at_m - CHORD_M, 0.0] + [d for d in near if d < at_m])
    to_m = min([at_m + CHORD_M, float(walked_m[-1])] + [d for d in near if d > at_m])
    if at_m - from_m < TAIL_MIN_CHORD_M or to_m - at_m < TAIL_MIN_CHORD_M:
        return False
    xz = xyz[:, [0, 2]]
    here, back, ahead = (
        np.array([np.interp(m, walked_m, xz[:, 0]), np.interp(m, walked_m, xz[:, 1])])
        for m in (at_m, from_m, to_m)
    )
    before, after = here - back, ahead - here
    turn = np.degrees(
        np.arctan2(before[1] * after[0] - before[0] * after[1], float(before @ after))
    )
    return bool(abs(turn) < BEAR_MIN_DEG)


def stretches() -> list[np.ndarray]:
    """(N, 3) walks: random turns, grid corners (right angles, equal bends), a point repeated,
    an out-and-back (turns of 180°), a chord too short to measure, a single point and none."""
    rng = np.random.default_rng(18)
    cases = [np.empty((0, 3)), np.zeros((1, 3)), np.zeros((4, 3))]
    for n in range(2, 60):
        cases.append(np.cumsum(rng.normal(size=(n, 3)) * [3.0, 0.05, 3.0], axis=0))
        grid = np.cumsum(rng.integers(-1, 2, size=(n, 3)) * [2.0, 0.0, 2.0], axis=0)
        cases.append(grid.astype(np.float64))
    repeated = np.cumsum(rng.normal(size=(30, 3)), axis=0)
    repeated[10] = repeated[9]
    cases.append(repeated)
    line = np.column_stack([np.arange(12.0), np.zeros(12), np.zeros(12)])
    cases.append(np.concatenate([line, line[::-1][1:]]))
    # The second point 1 m above the first and 1e-170 m off it in x–z: the chord before it is too
    # short for its squared length (a bend of −45° that is not a bend).
    cases.append(np.array([[0.0, 0.0, 0.0], [1e-170, 1.0, 1e-170], [0.0, 1.0, 5.0], [0, 1, 10]]))
    return cases


@pytest.mark.parametrize("end_margin_m", [0.0, 2.0])
def test_decision_points_are_the_straightforward_ones_to_the_bit(end_margin_m):
    rng = np.random.default_rng(int(end_margin_m))
    for xyz in stretches():
        junction = (rng.random(len(xyz)) < 0.2).tolist()
        want = reference_decision_points(xyz, junction, end_margin_m)
        assert decision_points(xyz, junction, end_margin_m=end_margin_m) == want


def test_the_reference_stretches_have_decisions_of_every_kind():
    found = [
        d
        for xyz in stretches()
        for d in reference_decision_points(xyz, [k % 5 == 0 for k in range(len(xyz))], 0.0)
    ]
    assert any(d.at_junction for d in found)
    assert any(abs(d.turn_deg) > 170 for d in found)
    assert any(d.turn_deg > 0 for d in found)
    assert any(d.turn_deg < 0 for d in found)


# --------------------------------------------------------------------------- points → nodes


def reference_segment_kinds(
    pg: PathGraph, xyz: np.ndarray, nodes: list[int]
) -> tuple[list[str], list[bool]]:
    """``segment_kinds`` as it was written before it was made cheap."""
    adjacency = pg.graph.adj
    positions = {n: tuple(float(c) for c in d["position_m"]) for n, d in pg.graph.nodes.items()}
    junctions = {n for n, d in pg.graph.nodes.items() if d["kind"] == JUNCTION}
    node_m = np.array([positions[n] for n in nodes], dtype=np.float64).reshape(-1, 3)
    node_at = {tuple(p): n for p, n in zip(np.round(node_m, 9).tolist(), nodes, strict=True)}
    at = [node_at.get(tuple(p)) for p in np.round(xyz, 9).tolist()]
    junction = [n is not None and n in junctions for n in at]
    kinds = []
    for a, b in itertools.pairwise(at):
        if a is not None and b is not None and b in adjacency[a]:
            kinds.append(str(adjacency[a][b]["kind"]))
        else:
            kinds.append(WALK)
    return kinds, junction


def graph_with_coincident_nodes(seed: int) -> PathGraph:
    """Nodes on a coarse grid on two floors (so several share a position), random edges of the
    three kinds; some positions differ from a grid point by less than the rounding."""
    rng = np.random.default_rng(seed)
    G: nx.Graph[int] = nx.Graph()
    n = 30
    for i in range(n):
        x, z = (float(v) for v in rng.integers(0, 4, size=2))
        y = 3.0 * float(rng.integers(0, 2))
        if rng.random() < 0.2:
            x += 1e-11
        kind = JUNCTION if rng.random() < 0.3 else NODE
        G.add_node(i, position_m=(x, y, z), floor=int(y > 1), kind=kind, pose_index=i)
    for _ in range(3 * n):
        u, v = (int(i) for i in rng.integers(0, n, size=2))
        if u != v:
            kind = str(rng.choice([WALK, WALK, STAIRS, ELEVATOR]))
            G.add_edge(u, v, length_m=1.0, kind=kind, floor=0)
    return PathGraph(graph=G, floor_levels_m=(0.1, 2.9))


@pytest.mark.parametrize("seed", range(20))
def test_each_point_is_matched_to_the_node_the_straightforward_way_matches(seed):
    pg = graph_with_coincident_nodes(seed)
    G = pg.graph
    rng = np.random.default_rng(seed)
    for _ in range(30):
        nodes = [int(rng.integers(0, len(G)))]
        for _ in range(int(rng.integers(0, 12))):
            around = list(G.adj[nodes[-1]])
            if not around:
                break
            nodes.append(around[int(rng.integers(0, len(around)))])
        points = [tuple(float(c) for c in G.nodes[n]["position_m"]) for n in nodes]
        if rng.random() < 0.5:  # a snapped start, sometimes on a node's position
            x, y, z = points[0]
            points.insert(0, (x + float(rng.choice([0.0, 0.5])), y, z))
        xyz = np.array(points, dtype=np.float64).reshape(-1, 3)
        fast_points = [(x, y, z) for x, y, z in xyz.tolist()]
        want = reference_segment_kinds(pg, xyz, nodes)
        assert instructions.segment_kinds(node_lookups(pg), fast_points, nodes)[:2] == want
        floors = assign_floors(xyz[:, 1], np.asarray(pg.floor_levels_m)).tolist()
        assert instructions.point_floors(pg, node_lookups(pg), fast_points) == floors


def test_a_point_shared_by_two_route_nodes_is_the_later_one():
    """Nodes 0 and 2 at one position, 0–1 stairs and 1–2 an elevator: the route 0, 1, 2's first
    point is taken for node 2 (the last route node there), so both segments read "elevator"."""
    G: nx.Graph[int] = nx.Graph()
    for i, p in enumerate([(0.0, 0.0, 0.0), (0.0, 3.0, 0.0), (0.0, 0.0, 0.0)]):
        G.add_node(i, position_m=p, floor=int(p[1] > 1), kind=NODE, pose_index=i)
    G.add_edge(0, 1, length_m=3.0, kind=STAIRS, floor=0)
    G.add_edge(1, 2, length_m=3.0, kind=ELEVATOR, floor=0)
    pg = PathGraph(graph=G, floor_levels_m=(0.0, 3.0))
    points = [(0.0, 0.0, 0.0), (0.0, 3.0, 0.0), (0.0, 0.0, 0.0)]
    want = reference_segment_kinds(pg, np.array(points), [0, 1, 2])
    assert instructions.segment_kinds(node_lookups(pg), points, [0, 1, 2])[:2] == want
    assert want == ([ELEVATOR, ELEVATOR], [False, False, False])


# --------------------------------------------------------------------------- directions


def test_a_direction_is_the_numpy_unit_vector_to_the_bit():
    """``d / np.linalg.norm(d)``: the norm is a dot product's square root, which may round
    differently from ``math.hypot`` or ``sqrt(dx² + dz²)``."""
    rng = np.random.default_rng(5)
    for a, b in rng.normal(size=(3000, 2, 3)) * rng.choice([1e-3, 1.0, 50.0], size=(3000, 1, 1)):
        d = (b - a)[[0, 2]]
        want = (d / np.linalg.norm(d)).tolist()
        got = instructions.direction(tuple(a.tolist()), tuple(b.tolist()))
        assert got is not None
        assert list(got) == want
    assert instructions.direction((1.0, 0.0, 2.0), (1.0, 5.0, 2.0)) is None


# --------------------------------------------------------------------------- the two ways in


@pytest.mark.parametrize("name", ["floor_2_straight", "floor_2_pois", "simulated_two_floors"])
def test_steps_of_a_given_route_are_those_planned_with_it(name):
    """:func:`guidance_steps` measures the route itself; :func:`plan_guided_route` takes the
    walk's own array and lengths: the steps are the same, to the bit."""
    pg = recorded_graph(name)
    tags = sorted(pg.tags)
    for a, b in list(itertools.permutations(tags, 2))[::17]:
        planned = plan_guided_route(pg, TagEnd(a), TagEnd(b), heading_rad=0.5)
        steps = guidance_steps(
            pg,
            plan_walk(pg, TagEnd(a), TagEnd(b)),
            goal_name=f"tag {b}",
            goal_thing_m=np.asarray(pg.tags[b].position_m),
            heading_rad=0.5,
        )
        assert steps == planned.steps, (a, b)
