"""The simulated blind walker (issue 39): it arrives when the steps are right, and not when a
turn is left unsaid."""

from __future__ import annotations

import dataclasses
import math

import networkx as nx
import numpy as np
import pytest

from app.domain.evaluation.walker import (
    BoxFreeSpace,
    CapsuleFreeSpace,
    Start,
    WalkerErrors,
    walk_steps,
)
from app.domain.navigation.instructions import plan_guided_route
from app.domain.navigation.path_graph import JUNCTION, NODE, WALK, Anchor, PathGraph
from app.domain.navigation.routing import TagEnd

#: An L: 20 m north (−z) from the origin, then 15 m east (+x); corridors 2 m wide, y 0 to 2.8.
L_CORNERS_XZ = [(0.0, 0.0), (0.0, -20.0), (15.0, -20.0)]
L_BOXES = np.array(
    [
        [[-1.0, 0.0, -21.0], [1.0, 2.8, 1.0]],
        [[-1.0, 0.0, -21.0], [16.0, 2.8, -19.0]],
    ]
)


def l_graph() -> PathGraph:
    """The L's centreline with tag 1 at its south end and tag 2 at its east end."""
    G: nx.Graph[int] = nx.Graph()
    for n, (x, z) in enumerate(L_CORNERS_XZ):
        G.add_node(n, position_m=(x, 0.0, z), floor=0, kind=NODE, pose_index=None)
    for a, b in ((0, 1), (1, 2)):
        length_m = math.dist(L_CORNERS_XZ[a], L_CORNERS_XZ[b])
        G.add_edge(a, b, length_m=length_m, kind=WALK, floor=0)
    tags = {
        1: Anchor(name="1", node=0, position_m=(0.0, 1.3, 0.5), floor=0),
        2: Anchor(name="2", node=2, position_m=(15.5, 1.3, -20.0), floor=0),
    }
    return PathGraph(graph=G, floor_levels_m=(0.0,), tags=tags)


def test_the_l_graph_has_no_junction() -> None:
    assert all(d["kind"] != JUNCTION for _, d in l_graph().graph.nodes(data=True))


@pytest.mark.parametrize("seed", range(20))
def test_the_walker_reaches_the_goal_round_an_l_turn(seed: int) -> None:
    start = Start(xz=(0.0, 0.0), heading_rad=0.0)  # facing north, along the corridor
    route = plan_guided_route(l_graph(), TagEnd(1), TagEnd(2), heading_rad=start.heading_rad)
    assert [s.kind for s in route.steps].count("turn") == 1
    outcome = walk_steps(
        route.steps,
        BoxFreeSpace(L_BOXES, (0.0,)),
        start,
        goal_xz=(15.5, -20.0),
        goal_floor=0,
        rng=np.random.default_rng(seed),
    )
    assert outcome.arrived, outcome.reason
    assert outcome.distance_to_goal_m <= 2.0


def test_the_walker_fails_where_a_turn_is_not_announced() -> None:
    start = Start(xz=(0.0, 0.0), heading_rad=0.0)
    route = plan_guided_route(l_graph(), TagEnd(1), TagEnd(2), heading_rad=start.heading_rad)
    unsaid = [s for s in route.steps if s.kind not in ("turn", "announce")]
    outcome = walk_steps(
        unsaid,
        BoxFreeSpace(L_BOXES, (0.0,)),
        start,
        goal_xz=(15.5, -20.0),
        goal_floor=0,
        rng=np.random.default_rng(0),
    )
    assert not outcome.arrived
    assert "wall" in outcome.reason
    x, z = outcome.where_xz
    assert z < -18.0  # stopped at the corridor's north end, where it should have turned
    assert abs(x) < 1.0


def test_walls_stop_the_walker_and_a_false_turn_fails() -> None:
    """A "turn left" where the corridor runs straight on sends the walker into the wall."""
    start = Start(xz=(0.0, 0.0), heading_rad=0.0)
    route = plan_guided_route(l_graph(), TagEnd(1), TagEnd(2), heading_rad=start.heading_rad)
    wrong = [
        s if s.kind != "turn" else dataclasses.replace(s, turn_deg=-float(s.turn_deg or 0))
        for s in route.steps
    ]
    outcome = walk_steps(
        wrong,
        BoxFreeSpace(L_BOXES, (0.0,)),
        start,
        goal_xz=(15.5, -20.0),
        goal_floor=0,
        rng=np.random.default_rng(1),
        errors=WalkerErrors(heading_error_deg=0.0, stride_error=0.0),
    )
    assert not outcome.arrived
    assert np.all(BoxFreeSpace(L_BOXES, (0.0,)).contains(outcome.path_xz, 0))


def test_capsule_free_space_is_the_lines_widened() -> None:
    space = CapsuleFreeSpace.of_lines([L_CORNERS_XZ], radius_m=1.0)
    inside = space.contains(np.array([[0.5, -10.0], [8.0, -20.9], [1.5, -10.0], [8.0, -18.5]]), 0)
    assert inside.tolist() == [True, True, False, False]


def y_fork() -> tuple[PathGraph, CapsuleFreeSpace, tuple[float, float]]:
    """20 m north to a fork: the corridor bends 15° left to tag 2 while a spur goes straight on
    (corridors 2 m wide); the graph of ``tests.unit.test_forks`` and its true building."""
    from tests.unit.test_forks import FORK_XZ, SOUTH_XZ, ahead_xz, fork

    to_2, to_3 = ahead_xz(FORK_XZ, 15.0, 15.0), ahead_xz(FORK_XZ, 0.0, 15.0)
    space = CapsuleFreeSpace.of_lines([[SOUTH_XZ, FORK_XZ, to_2], [FORK_XZ, to_3]], radius_m=1.0)
    return fork(15.0, 0.0), space, to_2


def test_told_keep_left_the_walker_takes_the_bending_branch_and_not_without() -> None:
    pg, space, goal_xz = y_fork()
    route = plan_guided_route(pg, TagEnd(1), TagEnd(2), heading_rad=0.0)
    assert "keep left at the fork" in [s.instruction for s in route.steps]
    unsaid = [s for s in route.steps if s.kind != "keep"]
    told = [
        walk_steps(
            steps,
            space,
            Start(xz=(0.0, 0.0), heading_rad=0.0),
            goal_xz=goal_xz,
            goal_floor=0,
            rng=np.random.default_rng(seed),
        ).arrived
        for steps in (route.steps, unsaid)
        for seed in range(20)
    ]
    assert sum(told[:20]) == 20
    assert sum(told[20:]) <= 2  # straight on into the spur
