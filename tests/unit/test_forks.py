"""Forks and starts the steps used to leave unsaid (issue 39): "keep left" where the route bends a
little while another way goes straight on, a route that starts off the graph, tags facing each
other across a corridor, the tail of a corner told again at the next junction, and the goal's
side after an untold jog at the end."""

from __future__ import annotations

import itertools
import math

import networkx as nx
import pytest

from app.domain.navigation.forks import FORK_AHEAD_MAX_DEG
from app.domain.navigation.instructions import plan_guided_route, route_text
from app.domain.navigation.path_graph import JUNCTION, NODE, WALK, Anchor, PathGraph
from app.domain.navigation.routing import PositionEnd, TagEnd

#: Straight on from the south: −z (heading 0); a bend of ``deg`` to the left turns towards −x.
SOUTH_XZ = (0.0, 0.0)
FORK_XZ = (0.0, -20.0)


def ahead_xz(from_xz: tuple[float, float], deg: float, length_m: float) -> tuple[float, float]:
    """The point ``length_m`` from ``from_xz`` walking ``deg`` left of −z (x–z, m)."""
    rad = math.radians(deg)
    return (from_xz[0] - length_m * math.sin(rad), from_xz[1] - length_m * math.cos(rad))


def graph_of(
    lines: list[list[tuple[float, float]]], tags: dict[int, tuple[float, float]]
) -> PathGraph:
    """Corridor centrelines (x–z, m; shared points are shared nodes; three or more edges make a
    junction) with tags attached to the nodes at the given points."""
    G: nx.Graph[int] = nx.Graph()
    ids: dict[tuple[float, float], int] = {}

    def node(xz: tuple[float, float]) -> int:
        if xz not in ids:
            ids[xz] = len(ids)
            G.add_node(ids[xz], position_m=(xz[0], 0.0, xz[1]), floor=0, kind=NODE, pose_index=None)
        return ids[xz]

    for corridor in lines:
        for a, b in itertools.pairwise(corridor):
            G.add_edge(node(a), node(b), length_m=math.dist(a, b), kind=WALK, floor=0)
    for n in G.nodes:
        if G.degree(n) >= 3:
            G.nodes[n]["kind"] = JUNCTION
    anchors = {
        tag: Anchor(name=str(tag), node=ids[xz], position_m=(xz[0], 1.3, xz[1]), floor=0)
        for tag, xz in tags.items()
    }
    return PathGraph(graph=G, floor_levels_m=(0.0,), tags=anchors)


def fork(route_deg: float, other_deg: float) -> PathGraph:
    """From the south 20 m to a fork; one branch ``route_deg`` left of straight on to tag 2,
    the other ``other_deg`` to tag 3 (15 m each). Tag 1 at the south end."""
    to_2 = ahead_xz(FORK_XZ, route_deg, 15.0)
    to_3 = ahead_xz(FORK_XZ, other_deg, 15.0)
    return graph_of(
        [[SOUTH_XZ, FORK_XZ], [FORK_XZ, to_2], [FORK_XZ, to_3]], {1: SOUTH_XZ, 2: to_2, 3: to_3}
    )


def kinds(route) -> list[str]:
    return [s.kind for s in route.steps]


def test_a_slight_bend_at_a_fork_with_a_way_straight_on_gets_keep_left() -> None:
    """The corridor bends 15° left (silent: under 30°) where a spur goes straight on."""
    route = plan_guided_route(fork(15.0, 0.0), TagEnd(1), TagEnd(2), heading_rad=0.0)
    assert kinds(route) == ["go", "keep", "go", "arrive"]
    keep = route.steps[1]
    assert keep.instruction == "keep left at the fork"
    assert keep.side == "left"
    assert keep.turn_deg == pytest.approx(15.0, abs=0.5)
    assert keep.position_m == pytest.approx((0.0, 0.0, -20.0))
    assert route.steps[0].distance_m == pytest.approx(20.0)
    assert "Keep left at the fork." in route_text(route)


def test_going_straight_on_where_a_branch_bends_off_slightly_is_keep_right() -> None:
    route = plan_guided_route(fork(15.0, 0.0), TagEnd(1), TagEnd(3), heading_rad=0.0)
    assert kinds(route) == ["go", "keep", "go", "arrive"]
    assert route.steps[1].instruction == "keep right at the fork"
    assert route.steps[1].side == "right"


def test_a_y_fork_of_two_bears_is_told_as_bears_not_keeps() -> None:
    """±35°: each branch is a bear, spoken at a junction; no keep on top of it."""
    route = plan_guided_route(fork(-35.0, 35.0), TagEnd(1), TagEnd(2), heading_rad=0.0)
    assert "keep" not in kinds(route)
    assert [s.instruction for s in route.steps if s.kind == "turn"] == ["bear right"]


@pytest.mark.parametrize("other_deg", [-90.0, 90.0, FORK_AHEAD_MAX_DEG + 5.0])
def test_no_keep_where_the_other_way_is_a_turn_off(other_deg: float) -> None:
    route = plan_guided_route(fork(10.0, other_deg), TagEnd(1), TagEnd(2), heading_rad=0.0)
    assert "keep" not in kinds(route)


def test_a_crossing_gone_straight_through_says_nothing() -> None:
    west, east, north = (-15.0, -20.0), (15.0, -20.0), (0.0, -35.0)
    pg = graph_of(
        [[SOUTH_XZ, FORK_XZ, north], [west, FORK_XZ, east]], {1: SOUTH_XZ, 2: north, 3: east}
    )
    route = plan_guided_route(pg, TagEnd(1), TagEnd(2), heading_rad=0.0)
    assert kinds(route) == ["go", "arrive"]


def test_a_start_off_the_graph_faces_where_the_first_leg_ends() -> None:
    """The walker stands 1.5 m east of a north–south corridor; the first leg ends 20 m north.
    It is told to face that end from where it stands, not the direction of the corridor from
    the point it snaps to (the two differ by 4°; from 1.5 m off a 5 m leg, by 17°)."""
    north = (0.0, -20.0)
    pg = graph_of([[SOUTH_XZ, north]], {1: SOUTH_XZ, 2: north})
    stand = (1.5, 0.0, -15.0)
    route = plan_guided_route(pg, PositionEnd(stand), TagEnd(2), heading_rad=math.pi / 2)
    face = route.steps[0]
    assert face.kind == "face"
    # facing −x (heading 90°), the way to (0, −20) from (1.5, −15) is 90° − atan(1.5 / 5) right
    assert face.turn_deg == pytest.approx(-(90.0 - math.degrees(math.atan2(1.5, 5.0))), abs=0.1)


def test_tags_facing_each_other_across_a_corridor_get_a_step_across() -> None:
    """Both tags hang on the node between them: the route on the graph has no length. From in
    front of tag 1 the walker is told to face tag 2 and walk the 3 m across."""
    pg = graph_of([[(0.0, 0.0), (0.0, -10.0)]], {})
    pg.tags[1] = Anchor(name="1", node=0, position_m=(-1.5, 1.3, 0.0), floor=0)
    pg.tags[2] = Anchor(name="2", node=0, position_m=(1.5, 1.3, 0.0), floor=0)
    stand = (-1.0, 1.3, 0.0)  # 0.5 m in front of tag 1, facing it (−x: heading 90°)
    route = plan_guided_route(pg, PositionEnd(stand), TagEnd(2), heading_rad=math.pi / 2)
    assert kinds(route) == ["face", "go", "arrive"]
    assert route.steps[0].instruction == "turn around to face the way"
    go = route.steps[1]
    assert go.distance_m == pytest.approx(2.5)
    assert go.instruction == "go straight 2 m to tag 2, ahead"
    assert route.steps[-1].side == "ahead"


def test_the_tail_of_a_corner_is_no_second_decision_at_the_next_junction() -> None:
    """A right turn at a crossing, then a side branch 4 m on: the corner measured from 2.25 m past
    it still bends 38°, and the junction 1.75 m further on used to tell it again as "bear right"."""
    corner, side = (0.0, -20.0), (4.0, -20.0)
    pg = graph_of(
        [
            [SOUTH_XZ, corner, (0.0, -30.0)],
            [(-10.0, -20.0), corner, (2.25, -20.0), side, (20.0, -20.0)],
            [side, (4.0, -10.0)],
        ],
        {1: SOUTH_XZ, 2: (20.0, -20.0)},
    )
    route = plan_guided_route(pg, TagEnd(1), TagEnd(2), heading_rad=0.0)
    assert [s.instruction for s in route.steps if s.kind == "turn"] == ["turn right"]


def test_the_goal_side_is_told_facing_the_way_the_last_leg_is_walked() -> None:
    """The last leg runs 15 m east and ends in a 1.5 m jog to +z to the tag's node (a bend that
    near the end is never told, so the walker does not turn there): walking east, the tag 1.5 m
    beyond the node is on the right (+z), not ahead, as the jog's own direction would have it."""
    end = (15.0, 1.5)
    pg = graph_of([[SOUTH_XZ, (15.0, 0.0), end]], {1: SOUTH_XZ})
    pg.tags[2] = Anchor(name="2", node=2, position_m=(15.0, 1.3, 3.0), floor=0)
    route = plan_guided_route(pg, TagEnd(1), TagEnd(2), heading_rad=-math.pi / 2)
    last_go = [s for s in route.steps if s.kind == "go"][-1]
    assert last_go.side == "right"
    assert last_go.instruction == "go straight 16 m to tag 2, on your right"
