"""The corridor skeleton on the real sessions: one connected graph, every tag attached, and on
floor 2 of the mac building routes with no zigzag, no turn-around, and the same turns from two
independent walks (the full before → after table is ``bench.navigation``)."""

from __future__ import annotations

import itertools
from functools import cache
from pathlib import Path

import networkx as nx
import pytest

from app.domain.evaluation.turn_metrics import (
    announced_turns,
    has_turn_around,
    has_zigzag,
    turn_sides,
)
from app.domain.mapping.map_result import MapResult
from app.domain.mapping.slam import optimize_session
from app.domain.navigation.instructions import plan_guided_route
from app.domain.navigation.path_graph import JUNCTION, WALK
from app.domain.navigation.routing import TagEnd
from app.domain.navigation.skeleton import build_skeleton
from app.domain.upload.session import load_session

SESSIONS = Path(__file__).parents[2] / "data" / "sessions"
REAL = ("occam_room", "floor_2_straight", "straight_209_occam", "desnat_straight_once")


@cache
def optimized(name: str) -> MapResult:
    return optimize_session(load_session(SESSIONS / f"{name}.json"))


@pytest.mark.parametrize("name", REAL)
def test_the_skeleton_is_one_graph_with_every_tag(name):
    result = optimized(name)
    pg = build_skeleton(result)
    assert nx.is_connected(pg.graph)
    assert set(pg.tags) == {int(t) for t in result.tag_ids}
    walked_m = float(
        sum(
            ((result.world_T_phone[1:, :3, 3] - result.world_T_phone[:-1, :3, 3]) ** 2).sum(1)
            ** 0.5
        )
    )
    length_m = sum(d["length_m"] for _, _, d in pg.graph.edges(data=True) if d["kind"] == WALK)
    assert length_m < walked_m


def test_floor_2_routes_have_no_zigzag_and_no_turn_around():
    pg = build_skeleton(optimized("floor_2_straight"))
    junctions = [n for n in pg.graph if pg.graph.nodes[n]["kind"] == JUNCTION]
    assert len(junctions) <= 4  # the floor has 4 branch points (bench/mac_floor_2_reference.py)
    assert not nx.cycle_basis(pg.graph)  # … and no loop
    for a, b in itertools.permutations(sorted(pg.tags), 2):
        route = plan_guided_route(pg, TagEnd(a), TagEnd(b))
        assert not has_zigzag(announced_turns(route, min_deg=30.0)), (a, b)
        assert not has_turn_around(route), (a, b)


def test_two_walks_of_floor_2_announce_the_same_turns():
    first = build_skeleton(optimized("floor_2_straight"))
    second = build_skeleton(optimized("desnat_straight_once"))
    common = sorted(set(first.tags) & set(second.tags))
    assert len(common) >= 6
    pairs = list(itertools.permutations(common, 2))
    same = sum(
        turn_sides(announced_turns(plan_guided_route(first, TagEnd(a), TagEnd(b))))
        == turn_sides(announced_turns(plan_guided_route(second, TagEnd(a), TagEnd(b))))
        for a, b in pairs
    )
    assert same >= 0.9 * len(pairs)
