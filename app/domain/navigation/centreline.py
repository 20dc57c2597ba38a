"""The centreline of a thinned band as branches between ends and branch points, and its cleaning
(``app.domain.navigation.skeleton`` steps 3–4). Grid units throughout (cells, not metres).

    state = branches_of(line)                   # line: one-cell 8-connected image
    clean(state, stub_px=12, loop_px=48, knot_px=12, gap_px=16, reach_px=7.2)
    state.key_ij, state.branches                # ends/branch points, and the runs between them
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import networkx as nx
import numpy as np
import numpy.typing as npt

from app.domain.frames import FloatArray

BoolArray = npt.NDArray[np.bool_]

#: A branch's line at a junction runs through its points between these multiples of the reach.
NEAR_REACH, FAR_REACH = 0.5, 1.5
#: At most this many rounds of cleaning (each round removes or merges at least one branch).
_MAX_ROUNDS = 100


@dataclass(slots=True, kw_only=True)
class Branches:
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


def branches_of(line: BoolArray) -> Branches:
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
    state = Branches(key_ij={}, branches={})
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


def polyline_length(points: FloatArray) -> float:
    return float(np.linalg.norm(np.diff(points, axis=0), axis=1).sum()) if len(points) > 1 else 0.0


def clean(
    state: Branches,
    *,
    stub_px: float,
    loop_px: float,
    knot_px: float,
    gap_px: float,
    reach_px: float,
) -> Branches:
    """Remove stubs shorter than ``stub_px`` and loops shorter than ``loop_px``, merge branch
    points closer than ``knot_px``, join dead ends within ``gap_px`` that face each other, and
    centre branch points on their branches' lines (measured ``reach_px`` out). Lengths in grid
    cells (see ``app.domain.navigation.skeleton`` step 4)."""
    for _ in range(_MAX_ROUNDS):
        changed = _prune_stubs(state, stub_px)
        changed |= _cut_small_loops(state, loop_px)
        changed |= _merge_knots(state, knot_px)
        changed |= _join_through_nodes(state)
        if not changed:
            break
    if _close_gaps(state, gap_px, stub_px):
        _join_through_nodes(state)
    _centre_junctions(state, reach_px, knot_px)
    return state


def _centre_junctions(state: Branches, reach_px: float, max_move_px: float) -> None:
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
            near = line[int(np.searchsorted(arc, min(NEAR_REACH * reach_px, arc[-1])))]
            far = line[int(np.searchsorted(arc, min(FAR_REACH * reach_px, arc[-1])))]
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
        moved_px = float(np.linalg.norm(centre - state.key_ij[key]))
        if moved_px > max_move_px:
            continue
        state.key_ij[key] = centre
        for b, from_start in incident:
            u, v, line = state.branches[b]
            line = line.copy() if from_start else line[::-1].copy()
            # the cells the junction left behind would make a hook (a route into the old
            # junction and back): drop those nearer the new centre than it moved, plus a margin
            line[0] = centre
            near = np.linalg.norm(line - centre, axis=1) < moved_px + 0.5 * reach_px
            near[0] = near[-1] = False
            first_far = int(np.argmin(near[1:])) + 1 if near[1:].any() else 1
            line = np.vstack([line[:1], line[first_far:]])
            state.branches[b] = (u, v, line if from_start else line[::-1])


def _prune_stubs(state: Branches, stub_px: float) -> bool:
    degree = state.degrees()
    changed = False
    for b, (u, v, poly) in sorted(state.branches.items(), key=lambda e: len(e[1][2])):
        if u == v or polyline_length(poly) >= stub_px:
            continue
        if (degree[u] == 1 and degree[v] >= 3) or (degree[v] == 1 and degree[u] >= 3):
            del state.branches[b]
            degree[u] -= 1
            degree[v] -= 1
            dead = u if degree[u] == 0 else v
            state.key_ij.pop(dead, None)
            changed = True
    return changed


def _cut_small_loops(state: Branches, loop_px: float) -> bool:
    changed = False
    by_pair: dict[tuple[int, int], list[int]] = {}
    for b, (u, v, poly) in list(state.branches.items()):
        if u == v:
            if polyline_length(poly) < loop_px:
                del state.branches[b]
                changed = True
            continue
        by_pair.setdefault((min(u, v), max(u, v)), []).append(b)
    for group in by_pair.values():
        while len(group) > 1:
            group.sort(key=lambda b: polyline_length(state.branches[b][2]))
            shortest, longest = group[0], group[-1]
            round_px = polyline_length(state.branches[shortest][2]) + polyline_length(
                state.branches[longest][2]
            )
            if round_px >= loop_px:
                break
            del state.branches[longest]
            group.pop()
            # what is left of a loop through an open space (a lobby walked round) is its chord,
            # not one of its sides: the way through goes straight across
            u, v, _ = state.branches[shortest]
            state.branches[shortest] = (u, v, np.vstack([state.key_ij[u], state.key_ij[v]]))
            changed = True
    return changed or _cut_small_cycle(state, loop_px)


def _cut_small_cycle(state: Branches, loop_px: float) -> bool:
    """Remove the longest branch of one cycle through three or more keys that is shorter than
    ``loop_px`` round (a lobby walked round beside a junction): True if one was cut."""
    keys: nx.Graph[int] = nx.Graph()
    for b, (u, v, poly) in state.branches.items():
        if u != v:
            keys.add_edge(u, v, branch=b, length=polyline_length(poly))
    for cycle in nx.cycle_basis(keys):
        if len(cycle) < 3:
            continue
        edges = [keys.edges[a, c] for a, c in zip(cycle, [*cycle[1:], cycle[0]], strict=True)]
        if sum(e["length"] for e in edges) < loop_px:
            del state.branches[max(edges, key=lambda e: e["length"])["branch"]]
            return True
    return False


def _merge_knots(state: Branches, knot_px: float) -> bool:
    degree = state.degrees()
    for b, (u, v, poly) in sorted(state.branches.items(), key=lambda e: len(e[1][2])):
        if u == v or degree[u] < 3 or degree[v] < 3 or polyline_length(poly) >= knot_px:
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


def _join_through_nodes(state: Branches) -> bool:
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


def _close_gaps(state: Branches, gap_px: float, back_px: float) -> bool:
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
