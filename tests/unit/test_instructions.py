"""Instructions at decision points (app.domain.navigation.instructions): facing, announcements,
spacing, junction bears, the arrival's side, stairs, styles."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from app.domain.navigation.instructions import (
    ANNOUNCE_BEFORE_M,
    MIN_SPACING_M,
    GuidanceStyle,
    clock_hour,
    decision_points,
    distance_words,
    heading_direction,
    plan_guided_route,
)
from app.domain.navigation.path_graph import JUNCTION
from app.domain.navigation.routing import PoiEnd, TagEnd
from app.domain.navigation.skeleton import build_skeleton_from_arrays
from tests.unit.walks import walk


def corridor_l():
    """An L: 20 m east, then 15 m north (+z, a right turn seen from above with y up)."""
    positions = walk((0, 0), (20, 0), (20, 15))
    tags = [(1.0, 1.4, -1.0), (19.0, 1.4, 14.0), (21.0, 1.4, 14.0)]
    return build_skeleton_from_arrays(positions, tag_ids=[1, 2, 3], tag_positions_m=tags)


def along_m(route, position) -> float:
    xyz = np.asarray(route.polyline_m)
    walked = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xyz, axis=0), axis=1))])
    p = np.asarray(position)
    best, best_d = 0.0, math.inf
    for k in range(len(xyz) - 1):
        a, b = xyz[k], xyz[k + 1]
        ab = b - a
        t = float(np.clip((p - a) @ ab / max(ab @ ab, 1e-12), 0, 1))
        d = float(np.linalg.norm(a + t * ab - p))
        if d < best_d:
            best, best_d = walked[k] + t * float(np.linalg.norm(ab)), d
    return best


def test_a_corner_is_announced_before_and_told_at_the_corner() -> None:
    route = plan_guided_route(corridor_l(), TagEnd(1), TagEnd(2))
    kinds = [s.kind for s in route.steps]
    assert kinds == ["go", "announce", "turn", "go", "arrive"]
    announce, turn = route.steps[1], route.steps[2]
    assert announce.instruction == f"in {distance_words(ANNOUNCE_BEFORE_M, 'm')}, turn right"
    assert turn.instruction == "turn right"
    gap_m = along_m(route, turn.position_m) - along_m(route, announce.position_m)
    assert gap_m == pytest.approx(ANNOUNCE_BEFORE_M, abs=0.3)
    assert abs(turn.position_m[0] - 20.0) < 1.5
    assert abs(turn.position_m[2]) < 1.5


def test_the_last_step_gives_the_side_and_the_remaining_distance() -> None:
    pg = corridor_l()
    left = plan_guided_route(pg, TagEnd(1), TagEnd(2)).steps
    right = plan_guided_route(pg, TagEnd(1), TagEnd(3)).steps
    # Walking north (+z) along x = 20: x = 19 is on the right… seen from above with y up,
    # walking +z with +x on the left (x × z = −y): x = 21 is on the left.
    assert left[-1].instruction.endswith("on your right")
    assert right[-1].instruction.endswith("on your left")
    last_go = left[-2]
    assert last_go.kind == "go"
    assert last_go.instruction.startswith(f"go straight {round(last_go.distance_m)} m to tag 2")


def test_the_first_step_says_which_way_to_face() -> None:
    pg = corridor_l()
    # The route starts east (+x). Facing −z (heading 0) the way is to the right (clockwise).
    facing_north = plan_guided_route(pg, TagEnd(1), TagEnd(2), heading_rad=0.0).steps
    assert facing_north[0].kind == "face"
    assert facing_north[0].instruction.startswith("turn right 9")
    along = math.atan2(-1.0, 0.0)  # heading whose direction is +x: (−sin h, −cos h) = (1, 0)
    np.testing.assert_allclose(heading_direction(along), [1.0, 0.0], atol=1e-12)
    assert plan_guided_route(pg, TagEnd(1), TagEnd(2), heading_rad=along).steps[0].kind == "go"
    clock = plan_guided_route(
        pg, TagEnd(1), TagEnd(2), heading_rad=0.0, style=GuidanceStyle(clock=True)
    ).steps
    assert clock[0].instruction == "turn to 3 o'clock to face the way"


def test_styles_change_units_and_directions() -> None:
    pg = corridor_l()
    feet = plan_guided_route(pg, TagEnd(1), TagEnd(2), style=GuidanceStyle(units="ft")).steps
    metres = plan_guided_route(pg, TagEnd(1), TagEnd(2)).steps
    assert feet[0].instruction == f"go straight {round(metres[0].distance_m / 0.3048)} ft"
    steps = plan_guided_route(pg, TagEnd(1), TagEnd(2), style=GuidanceStyle(units="steps")).steps
    assert steps[0].instruction.endswith(" steps")
    clock = plan_guided_route(pg, TagEnd(1), TagEnd(2), style=GuidanceStyle(clock=True)).steps
    assert [s.instruction for s in clock if s.kind == "turn"] == ["turn to 3 o'clock"]
    assert [clock_hour(d) for d in (0, 90, -90, 180, 30, -150)] == [12, 9, 3, 6, 11, 5]


def test_a_zigzag_of_the_line_is_silent_and_a_curve_adds_up() -> None:
    zigzag = walk((0, 0), (10, 0), (12, 1.2), (24, 1.2))[:, [0, 1, 2]]  # a 1.2 m jog over 2 m
    assert all(abs(d.turn_deg) < 45 for d in decision_points(zigzag, [False] * len(zigzag)))
    # A 90° corner rounded off (15° bends every 0.6 m) is one turn (measured over the chords,
    # a little less than the whole 90°) …
    corner = announced(rounded_corner(0.6))
    assert len(corner) == 1
    assert -100 <= corner[0].turn_deg <= -60
    # … a corridor that curves gently (the same bends every 1.5 m) is followed, not announced.
    assert announced(rounded_corner(1.5)) == []


def rounded_corner(bend_spacing_m: float) -> np.ndarray:
    """(N, 3) 9 m straight, a 90° curve in 15° bends ``bend_spacing_m`` apart, 9 m."""
    headings = np.concatenate([[0.0] * 6, np.radians(np.arange(0, 105, 15)), [math.pi / 2] * 6])
    steps = [1.5] * 6 + [bend_spacing_m] * 7 + [1.5] * 6
    xz = np.cumsum(
        [np.zeros(2)]
        + [s * np.array([math.cos(h), math.sin(h)]) for h, s in zip(headings, steps, strict=False)],
        axis=0,
    )
    return np.column_stack([xz[:, 0], np.zeros(len(xz)), xz[:, 1]])


def announced(points: np.ndarray):
    return [d for d in decision_points(points, [False] * len(points)) if abs(d.turn_deg) >= 45]


def test_instructions_are_spaced_except_at_junctions() -> None:
    # A comb: a corridor with side corridors every 4 m; a route zig-zagging through them.
    positions = walk(
        (0, 0), (30, 0), (30, 6), (26, 6), (26, 0), (22, 0), (22, 6), (18, 6), (18, 0), (0, 0)
    )
    pg = build_skeleton_from_arrays(
        positions, tag_ids=[1, 2], tag_positions_m=[(1, 1.4, -1), (29, 1.4, 7)]
    )
    route = plan_guided_route(pg, TagEnd(1), TagEnd(2))
    spoken = [s for s in route.steps if s.kind in ("announce", "turn")]
    G = pg.graph
    junction_xyz = [
        np.asarray(G.nodes[n]["position_m"]) for n in G if G.nodes[n]["kind"] == JUNCTION
    ]
    for a, b in itertools.pairwise(spoken):
        gap_m = along_m(route, b.position_m) - along_m(route, a.position_m)
        at_junction = any(
            np.linalg.norm(np.asarray(s.position_m) - j) < 1.0 for s in (a, b) for j in junction_xyz
        )
        assert gap_m >= MIN_SPACING_M - 0.3 or at_junction or a.kind == "announce"


def test_the_arrival_names_the_asked_place_when_two_share_a_node() -> None:
    pg = build_skeleton_from_arrays(
        walk((0, 0), (20, 0)),
        tag_ids=[1],
        tag_positions_m=[(1.0, 1.4, -1.0)],
        poi_names=["Elevator", "Room 210"],
        poi_positions_m=[(10.0, 1.4, 1.0), (10.05, 1.4, -1.0)],
    )
    assert pg.pois[0].node == pg.pois[1].node
    for name in ("Elevator", "Room 210"):
        steps = plan_guided_route(pg, TagEnd(1), PoiEnd(name)).steps
        assert steps[-1].instruction.startswith(f"arrive at {name}, on your ")
    left = plan_guided_route(pg, TagEnd(1), PoiEnd("Elevator")).steps[-1].instruction
    right = plan_guided_route(pg, TagEnd(1), PoiEnd("Room 210")).steps[-1].instruction
    assert {left.rsplit(" ", 1)[-1], right.rsplit(" ", 1)[-1]} == {"left", "right"}
