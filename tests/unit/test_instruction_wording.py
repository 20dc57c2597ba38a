"""Instruction wording (issue 39): one rule for the word of a turn, clock directions, metres and
steps, landmarks, and the text form a screen reader reads (app.domain.navigation.instructions)."""

from __future__ import annotations

import math

import networkx as nx
import numpy as np
import pytest

from app.domain.errors import ParameterError
from app.domain.navigation.instructions import (
    LANDMARK_NEAR_M,
    SHARP_MIN_DEG,
    STRAIGHT_MAX_DEG,
    TURN_AROUND_MIN_DEG,
    TURN_MIN_DEG,
    GuidanceStyle,
    Landmark,
    clock_hour,
    clock_words,
    landmark_near,
    plan_guided_route,
    route_text,
    spoken_distance,
    steps_count,
    turn_class,
    turn_words,
)
from app.domain.navigation.path_graph import JUNCTION, NODE, STAIRS, WALK, Anchor, PathGraph
from app.domain.navigation.routing import PoiEnd, TagEnd, signed_turn_deg

# --------------------------------------------------------------------------- the one rule

#: Each boundary of the rule, with the class just below and from it on.
BOUNDARIES = [
    (STRAIGHT_MAX_DEG, "straight", "bear"),
    (TURN_MIN_DEG, "bear", "turn"),
    (SHARP_MIN_DEG, "turn", "sharp"),
    (TURN_AROUND_MIN_DEG, "sharp", "around"),
]


def test_the_documented_thresholds() -> None:
    assert (STRAIGHT_MAX_DEG, TURN_MIN_DEG, SHARP_MIN_DEG, TURN_AROUND_MIN_DEG) == (
        20.0,
        45.0,
        135.0,
        150.0,
    )


@pytest.mark.parametrize(("boundary_deg", "below", "from_on"), BOUNDARIES)
@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_each_boundary_just_below_and_above(boundary_deg, below, from_on, sign) -> None:
    assert turn_class(sign * (boundary_deg - 1e-6)) == below
    assert turn_class(sign * boundary_deg) == from_on
    assert turn_class(sign * (boundary_deg + 1e-6)) == from_on


def test_the_class_depends_on_the_angle_alone() -> None:
    assert turn_class(0.0) == "straight"
    assert turn_class(180.0) == turn_class(-180.0) == "around"
    for deg in np.linspace(-180.0, 180.0, 3601):
        assert turn_class(deg) == turn_class(-deg)  # either side, the same word


@pytest.mark.parametrize(
    ("turn_deg", "words", "clock"),
    [
        (30.0, "bear left", 11),
        (-30.0, "bear right", 1),
        (90.0, "turn left", 9),
        (-90.0, "turn right", 3),
        (-50.0, "turn right", 2),
        (120.0, "turn left", 8),
        (-140.0, "turn sharp right", 5),
        (140.0, "turn sharp left", 7),
        (180.0, "turn around", 6),
        (-155.0, "turn around", 5),
    ],
)
def test_words_and_clock_of_each_class(turn_deg, words, clock) -> None:
    assert turn_words(turn_deg) == words
    assert clock_hour(turn_deg) == clock
    assert clock_words(turn_deg) == f"{words}, to {clock} o'clock"
    assert turn_words(turn_deg, GuidanceStyle(clock=True)) == f"turn to {clock} o'clock"


def test_each_class_has_its_own_clock_hours() -> None:
    hours = {"straight": set(), "bear": set(), "turn": set(), "sharp": set(), "around": set()}
    for deg in np.linspace(-180.0, 180.0, 7201):
        hours[turn_class(deg)].add(clock_hour(deg))
    assert hours["bear"] == {1, 11}
    assert hours["turn"] == {2, 3, 4, 8, 9, 10}
    assert hours["sharp"] == {5, 7}
    assert hours["around"] == {5, 6, 7}
    assert hours["straight"] == {11, 12, 1}  # 15–20° is nearer 1 o'clock, and said nowhere
    # The class boundaries at 45° and 135° are clock half hours, taken away from 12.
    assert [clock_hour(d) for d in (-45.0, 45.0, -135.0, 135.0, -15.0, 14.999)] == [
        2,
        10,
        5,
        7,
        1,
        12,
    ]


# --------------------------------------------------------------------------- metres and steps


def test_steps_from_the_stride() -> None:
    assert steps_count(12.0) == 17  # 12 / 0.7 = 17.1
    assert steps_count(12.0, 0.5) == 24
    assert steps_count(0.1, 0.7) == 1  # at least one
    assert spoken_distance(12.0) == "12 metres (17 steps)"
    assert spoken_distance(0.8, 1.0) == "1 metre (1 step)"
    for stride_m in (0.29, 1.51, math.nan):
        with pytest.raises(ParameterError, match="stride_m"):
            GuidanceStyle(stride_m=stride_m)


# --------------------------------------------------------------------------- landmarks


def test_landmark_choice() -> None:
    room = Landmark(name="Room 210", position_xz_m=(2.0, 0.0), floor=0, is_tag=False)
    tag = Landmark(name="tag 305", position_xz_m=(0.0, 1.5), floor=0, is_tag=True)
    far_tag = Landmark(name="tag 306", position_xz_m=(0.0, 2.5), floor=0, is_tag=True)
    upstairs = Landmark(name="Library", position_xz_m=(0.5, 0.0), floor=1, is_tag=False)
    here = (0.0, 0.0, 0.0)
    assert landmark_near([room, far_tag, tag], here, 0) == ("Room 210", "at the tag by Room 210")
    assert landmark_near([room], here, 0) == ("Room 210", "by Room 210")
    assert landmark_near([far_tag, tag, upstairs], here, 0) == ("tag 305", "at tag 305")
    assert landmark_near([upstairs], here, 1) == ("Library", "by Library")
    assert landmark_near([upstairs], here, 0) is None  # another floor
    beyond = Landmark(name="Far", position_xz_m=(LANDMARK_NEAR_M + 0.01, 0), floor=0, is_tag=False)
    assert landmark_near([beyond], here, 0) is None


# --------------------------------------------------------------------------- a whole route


def _rotated_xz(direction_xz: np.ndarray, turn_deg: float) -> np.ndarray:
    """``direction_xz`` turned ``turn_deg`` (+ left, y up: from −z to −x is +90°)."""
    a = math.radians(turn_deg)
    x, z = direction_xz
    return np.array([x * math.cos(a) + z * math.sin(a), -x * math.sin(a) + z * math.cos(a)])


def two_floor_route_graph() -> PathGraph:
    """From tag 1: 20 m along −z to a junction (a side corridor leaves it to the left), bear 35°
    right, 15 m, turn 90° left by tag 7 and Room 150, 12 m, stairs up by tag 9 (5 m across, 3 m
    up), 10 m on floor 2 to Room 210 on the right."""
    G: nx.Graph[int] = nx.Graph()
    way = np.array([0.0, -1.0])
    xz = [np.zeros(2), np.array([0.0, -20.0])]
    way = _rotated_xz(way, -35.0)
    xz.append(xz[-1] + 15.0 * way)
    way = _rotated_xz(way, 90.0)
    xz.append(xz[-1] + 12.0 * way)
    xz.append(xz[-1] + 5.0 * way)  # the stairs' head
    xz.append(xz[-1] + 10.0 * way)
    heights = [0.0, 0.0, 0.0, 0.0, 3.0, 3.0]
    for n, (p, y) in enumerate(zip(xz, heights, strict=True)):
        kind = JUNCTION if n == 1 else NODE
        G.add_node(n, position_m=(p[0], y, p[1]), floor=int(y > 1), kind=kind, pose_index=None)
    G.add_node(6, position_m=(-10.0, 0.0, -20.0), floor=0, kind=NODE, pose_index=None)
    for u, v in [(0, 1), (1, 2), (2, 3), (3, 4), (4, 5), (1, 6)]:
        a, b = np.asarray(G.nodes[u]["position_m"]), np.asarray(G.nodes[v]["position_m"])
        kind = STAIRS if (u, v) == (3, 4) else WALK
        G.add_edge(u, v, length_m=float(np.linalg.norm(b - a)), kind=kind, floor=0 if v < 5 else 1)
    corner = xz[2]
    right_at_end = xz[5] + 1.5 * _rotated_xz(way, -90.0)
    return PathGraph(
        graph=G,
        floor_levels_m=(0.0, 3.0),
        tags={
            1: Anchor(name="1", node=0, position_m=(1.0, 1.4, 0.0), floor=0),
            7: Anchor(name="7", node=2, position_m=(corner[0] + 1.0, 1.4, corner[1]), floor=0),
            9: Anchor(name="9", node=3, position_m=(xz[3][0], 1.4, xz[3][1] + 1.0), floor=0),
        },
        pois=(
            Anchor(name="Room 150", node=2, position_m=(corner[0], 1.4, corner[1] - 1.2), floor=0),
            Anchor(
                name="Room 210",
                node=5,
                position_m=(right_at_end[0], 4.4, right_at_end[1]),
                floor=1,
            ),
        ),
    )


def test_the_text_of_a_route_with_a_bear_a_turn_stairs_and_an_arrival() -> None:
    pg = two_floor_route_graph()
    route = plan_guided_route(pg, TagEnd(1), PoiEnd("Room 210"), style=GuidanceStyle(stride_m=0.6))
    kinds = [s.kind for s in route.steps]
    assert kinds == [
        "go", "announce", "turn", "go", "announce", "turn", "go", "stairs", "go", "arrive",
    ]  # fmt: skip
    bear, turn = route.steps[2], route.steps[5]
    assert (bear.turn, bear.clock, bear.landmark) == ("bear", 1, None)
    assert bear.turn_deg == pytest.approx(-35.0, abs=1e-6)
    assert (turn.turn, turn.clock, turn.landmark) == ("turn", 9, "Room 150")
    assert route.steps[4].landmark == "Room 150"  # an announcement's landmark is its turn's
    assert [s.steps_count for s in route.steps if s.kind == "go"] == [33, 25, 20, 17]
    assert (route.steps[-1].side, route.steps[-2].side) == ("right", "right")
    assert route_text(route).split("\n") == [
        "1. Go straight 20 metres (33 steps).",
        "2. Bear right, to 1 o'clock.",
        "3. Go straight 15 metres (25 steps).",
        "4. At the tag by Room 150, turn left, to 9 o'clock.",
        "5. Go straight 12 metres (20 steps).",
        "6. At tag 9, take the stairs up, 6 metres, to floor 2.",
        "7. Go straight 10 metres (17 steps) to Room 210, on your right.",
        "8. Arrive at Room 210, on your right.",
    ]
    assert (
        route.steps[4].text
        == "In 5 metres (8 steps), at the tag by Room 150, turn left, to 9 o'clock."
    )
    # The spoken instructions keep their words (the app's): a bear, a turn, metres.
    assert [s.instruction for s in route.steps if s.kind == "turn"] == ["bear right", "turn left"]
    # A screen reader mangles symbols and "m" alone: the text has none.
    for forbidden in (" m ", " m.", "°", "&", "/", "~"):
        assert forbidden not in route_text(route)


def test_a_turn_angle_is_the_heading_change_along_the_route() -> None:
    pg = two_floor_route_graph()
    route = plan_guided_route(pg, TagEnd(1), PoiEnd("Room 210"))
    xyz = np.asarray(route.polyline_m)
    for step in route.steps:
        if step.kind != "turn":
            continue
        k = int(np.argmin(np.linalg.norm(xyz - np.asarray(step.position_m), axis=1)))
        along = signed_turn_deg(xyz[k] - xyz[k - 1], xyz[k + 1] - xyz[k])
        assert step.turn_deg == pytest.approx(along, abs=1e-6)
        assert step.turn == turn_class(along)


def test_the_facing_step_and_the_goal_side_follow_the_rule() -> None:
    pg = two_floor_route_graph()
    # The route starts along −z (heading 0). 19° off: no facing step; 21° off: a bear.
    near = plan_guided_route(pg, TagEnd(1), PoiEnd("Room 210"), heading_rad=math.radians(19.0))
    assert near.steps[0].kind == "go"
    off = plan_guided_route(pg, TagEnd(1), PoiEnd("Room 210"), heading_rad=math.radians(21.0))
    face = off.steps[0]
    assert (face.kind, face.turn, face.clock) == ("face", "bear", 1)
    assert face.instruction == "bear right 21° to face the way"
    assert face.text == "Bear right, to 1 o'clock, to face the way."
    sharp = plan_guided_route(pg, TagEnd(1), PoiEnd("Room 210"), heading_rad=math.radians(140.0))
    assert sharp.steps[0].instruction == "turn sharp right 140° to face the way"
    assert sharp.steps[0].text == "Turn sharp right, to 5 o'clock, to face the way."
