"""The app's corrections of a simulated walker (issue 39): it sees a tag, finds the walker off
its way (or lost), and routes it again; and a tag it cannot see corrects nothing."""

from __future__ import annotations

import math

import numpy as np

from app.domain.evaluation.walker import BoxFreeSpace, Start, walk_steps
from app.domain.evaluation.walker_app import SeenTag, TagCorrections
from app.domain.navigation.instructions import plan_guided_route
from app.domain.navigation.routing import TagEnd
from tests.unit.test_walker import L_BOXES, l_graph

#: A tag on the L's north end wall, facing south (+z), where a walker who misses the turn stops.
END_WALL_TAG = SeenTag(
    tag_id=9,
    xz=np.array([0.0, -21.0]),
    normal_xz=np.array([0.0, 1.0]),
    floor=0,
    map_xyz=np.array([0.0, 1.3, -21.0]),
)


def walk_without_the_turn(tags: list[SeenTag], *, app: bool):
    pg = l_graph()
    space = BoxFreeSpace(L_BOXES, (0.0,))
    start = Start(xz=(0.0, 0.0), heading_rad=0.0)
    route = plan_guided_route(pg, TagEnd(1), TagEnd(2), heading_rad=start.heading_rad)
    unsaid = [s for s in route.steps if s.kind not in ("turn", "announce")]
    corrections = TagCorrections(pg, space, tags, goal=TagEnd(2), route=route) if app else None
    return walk_steps(
        unsaid,
        space,
        start,
        goal_xz=(15.5, -20.0),
        goal_floor=0,
        rng=np.random.default_rng(0),
        app=corrections,
    )


def test_a_walker_stopped_by_a_wall_is_routed_again_from_the_tag_it_sees() -> None:
    alone = walk_without_the_turn([END_WALL_TAG], app=False)
    assert not alone.arrived
    helped = walk_without_the_turn([END_WALL_TAG], app=True)
    assert helped.arrived, helped.reason
    assert helped.corrections == 1


def test_no_tag_in_sight_no_correction() -> None:
    far = SeenTag(
        tag_id=8,
        xz=np.array([14.0, -21.0]),  # at the far end of the east arm: more than 3 m away
        normal_xz=np.array([0.0, 1.0]),
        floor=0,
        map_xyz=np.array([14.0, 1.3, -21.0]),
    )
    outcome = walk_without_the_turn([far], app=True)
    assert not outcome.arrived
    assert outcome.corrections == 0


def test_walking_the_phone_sees_ahead_only_and_looking_round_all_round() -> None:
    pg = l_graph()
    space = BoxFreeSpace(L_BOXES, (0.0,))
    route = plan_guided_route(pg, TagEnd(1), TagEnd(2))
    app = TagCorrections(pg, space, [END_WALL_TAG], goal=TagEnd(2), route=route)
    here = np.array([0.0, -19.0])
    facing_north, facing_south = 0.0, math.pi
    assert app.seen(here, facing_north, 0, scanning=False) is END_WALL_TAG
    assert app.seen(here, facing_south, 0, scanning=False) is None
    assert app.seen(here, facing_south, 0, scanning=True) is END_WALL_TAG
    # on its way (within 3 m of the route) it is not routed again; lost, it is
    assert app.correct((0.0, -19.0), facing_north, 0, scanning=False) is None
    assert app.correct((0.0, -19.0), facing_north, 0, scanning=True)
