"""The corridor skeleton (app.domain.navigation.skeleton) on walks built to show each failure of the
walked line: passes side by side, steps to the wall, sway, passes that do not meet, crossings,
floors."""

from __future__ import annotations

import math

import networkx as nx
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from app.domain.errors import ParameterError
from app.domain.evaluation.turn_metrics import announced_turns, has_turn_around
from app.domain.navigation.instructions import plan_guided_route
from app.domain.navigation.path_graph import (
    JUNCTION,
    STAIRS,
    WALK,
    PathGraph,
    build_path_graph_from_arrays,
)
from app.domain.navigation.routing import NodeEnd, TagEnd, plan_walk
from app.domain.navigation.skeleton import (
    DEFAULT_SKELETON_PARAMS,
    SkeletonParams,
    _without_look_rounds,
    build_skeleton_from_arrays,
)
from tests.unit.walks import PHONE_Y_M, line, walk


def walk_length_m(pg: PathGraph) -> float:
    return sum(d["length_m"] for _, _, d in pg.graph.edges(data=True) if d["kind"] == WALK)


def junctions(pg: PathGraph) -> list[np.ndarray]:
    G = pg.graph
    return [np.asarray(G.nodes[n]["position_m"]) for n in G if G.nodes[n]["kind"] == JUNCTION]


def test_a_corridor_walked_twice_beside_itself_is_one_line() -> None:
    # Out along z = 0, back along z = 0.9 (a second pass 0.9 m beside the first).
    positions = np.concatenate([walk((0, 0), (30, 0)), walk((30, 0.9), (0, 0.9))])
    pg = build_skeleton_from_arrays(positions)
    assert nx.is_connected(pg.graph)
    assert not nx.cycle_basis(pg.graph)
    assert junctions(pg) == []
    assert 27.0 <= walk_length_m(pg) <= 31.0  # one 30 m corridor, not two
    z = [p[2] for p in (pg.graph.nodes[n]["position_m"] for n in pg.graph)]
    assert all(0.2 <= v <= 0.7 for v in z)  # between the passes


def test_steps_to_tags_on_the_walls_leave_no_stub_and_no_turn() -> None:
    pieces = [line((0, 0), (4, 0))]
    tags = []
    for k, x in enumerate((4.0, 10.0, 16.0, 22.0)):
        side = 1 if k % 2 else -1  # tags on both walls, 1 m from the centre
        out = line((x, 0), (x, 0.8 * side))
        pieces += [out[1:], out[::-1][1:], line((x, 0), (x + 6, 0))[1:]]
        tags.append((x, 1.4, 1.0 * side))
    positions = np.concatenate(pieces)
    pg = build_skeleton_from_arrays(positions, tag_ids=[1, 2, 3, 4], tag_positions_m=tags)
    assert junctions(pg) == []
    assert max(d for _, d in pg.graph.degree()) <= 2
    route = plan_guided_route(pg, TagEnd(1), TagEnd(4))
    assert announced_turns(route, min_deg=30.0) == []


def test_sway_and_oblique_walking_give_a_straight_corridor() -> None:
    x = np.arange(0.0, 40.0, 0.3)
    sway = 0.45 * np.sin(x / 3.0) + 0.25 * np.sin(x / 1.1)
    positions = np.column_stack([x, np.full_like(x, PHONE_Y_M), sway])
    pg = build_skeleton_from_arrays(
        positions, tag_ids=[1, 2], tag_positions_m=[(1, 1.4, 1), (39, 1.4, -1)]
    )
    route = plan_guided_route(pg, TagEnd(1), TagEnd(2))
    assert announced_turns(route, min_deg=30.0) == []
    assert route.length_m <= 1.05 * 38.0


def test_passes_that_do_not_meet_are_one_corridor() -> None:
    # The corridor z = 0 (x 0 … 30) is walked from each end, each pass turning back short of the
    # other (2.5 m apart); the walk goes round by the corridor z = 10.
    positions = walk(
        (0, 0), (13.75, 0), (0, 0.3), (0, 10), (30, 10), (30, 0.5), (16.25, 0.5), (30, 0.2)
    )
    tags = [(1.0, 1.4, -1.0), (29.0, 1.4, 1.5)]
    pg = build_skeleton_from_arrays(positions, tag_ids=[1, 2], tag_positions_m=tags)
    route = plan_guided_route(pg, TagEnd(1), TagEnd(2))
    assert not has_turn_around(route)
    assert route.length_m <= 1.1 * 28.0  # straight along z = 0, not round by z = 10
    assert announced_turns(route, min_deg=30.0) == []
    # The walked line goes round (the failure this fixes).
    walked = build_path_graph_from_arrays(positions, tag_ids=[1, 2], tag_positions_m=tags)
    assert plan_walk(walked, TagEnd(1), TagEnd(2)).length_m > 1.5 * 28.0


def test_dead_ends_side_by_side_are_not_joined() -> None:
    # Two spurs north of a corridor, 4 m apart, both ending to the north: not one corridor.
    positions = walk((0, 0), (10, 0), (10, 8), (10, 0.2), (14, 0.2), (14, 8), (14, 0), (24, 0))
    pg = build_skeleton_from_arrays(positions)
    assert not nx.cycle_basis(pg.graph)
    assert len(junctions(pg)) == 2


def test_a_crossing_is_one_junction_where_the_corridors_cross() -> None:
    positions = walk((0, 0), (20, 0), (20, 0.6), (10.3, 0.6), (10.3, 10), (10.3, -10))
    pg = build_skeleton_from_arrays(positions)
    found = junctions(pg)
    assert len(found) == 1
    assert np.hypot(found[0][0] - 10.2, found[0][2] - 0.3) < 1.0


def test_stairs_join_the_floors_skeletons() -> None:
    floor_1 = walk((0, 0), (20, 0))
    stairs = np.column_stack(
        [np.linspace(20, 24, 15), np.linspace(PHONE_Y_M, PHONE_Y_M + 3.0, 15), np.zeros(15)]
    )
    floor_2 = line((24, 0), (24, 15), y_m=PHONE_Y_M + 3.0)
    positions = np.concatenate([floor_1, stairs[1:], floor_2[1:]])
    tags = [(1.0, 1.4, -1.0), (25.0, 4.4, 14.0)]
    pg = build_skeleton_from_arrays(positions, tag_ids=[1, 2], tag_positions_m=tags)
    assert len(pg.floor_levels_m) == 2
    assert nx.is_connected(pg.graph)
    assert any(d["kind"] == STAIRS for _, _, d in pg.graph.edges(data=True))
    route = plan_guided_route(pg, TagEnd(1), TagEnd(2), floor_labels=["1", "2"])
    stairs_steps = [s for s in route.steps if s.kind == "stairs"]
    assert len(stairs_steps) == 1
    assert stairs_steps[0].instruction.startswith("take the stairs up, ")
    assert stairs_steps[0].instruction.endswith("to floor 2")
    assert 4.0 <= stairs_steps[0].distance_m <= 6.0
    assert [s.floor for s in route.steps if s.kind == "go"] == [0, 1]


@settings(max_examples=15, deadline=None)
@given(
    angle_rad=st.floats(0.0, 2 * math.pi),
    shift=st.tuples(st.floats(-50, 50), st.floats(-50, 50)),
    left=st.booleans(),
)
def test_an_l_corridor_has_one_turn_of_its_side_in_any_frame(angle_rad, shift, left) -> None:
    """Turn detection does not depend on where the map's frame is (rotation about up, shift)."""
    end_z = 15.0 if left else -15.0
    positions = np.concatenate(
        [walk((0, 0), (20, 0), (20, end_z)), walk((20, end_z), (20.6, 0), (0, 0.5))]
    )
    tags = np.array([(1.0, 1.4, -1.0), (21.0, 1.4, end_z * 0.9)])
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    up_R = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    move = np.array([shift[0], 0.0, shift[1]])
    pg = build_skeleton_from_arrays(
        positions @ up_R.T + move, tag_ids=[1, 2], tag_positions_m=tags @ up_R.T + move
    )
    turns = announced_turns(plan_guided_route(pg, TagEnd(1), TagEnd(2)))
    assert len(turns) == 1
    # Walking +x then +z turns right (clockwise seen from above, y up); then −z turns left.
    assert (turns[0].turn_deg > 0) == (not left)
    assert np.hypot(*(np.array(turns[0].position_xz_m) - (up_R @ [20, 0, 0] + move)[[0, 2]])) < 2.0


def test_tags_attach_beside_the_centreline() -> None:
    positions = walk((0, 0), (20, 0))
    pg = build_skeleton_from_arrays(positions, tag_ids=[7], tag_positions_m=[(8.0, 1.5, 1.0)])
    anchor = pg.graph.nodes[pg.tags[7].node]["position_m"]
    assert abs(anchor[0] - 8.0) < 0.35
    assert abs(anchor[2]) < 0.35


def test_parameters_are_checked() -> None:
    with pytest.raises(ParameterError):
        SkeletonParams(corridor_width_m=0.0)
    with pytest.raises(ParameterError):
        SkeletonParams(stub_max_m=-1.0)


def test_a_walk_veering_to_tags_on_both_walls_is_a_straight_corridor_given_their_normals() -> None:
    # A 3.2 m wide corridor along x; tags alternate walls every 4 m and the walker crosses the
    # corridor diagonally from one to the next, passing 0.4 m from each.
    xs = np.arange(5.0, 40.0, 4.0)
    sides = np.where(np.arange(len(xs)) % 2 == 0, 1.0, -1.0)
    corners = [
        (0.0, 0.0),
        *((x, 1.2 * side) for x, side in zip(xs, sides, strict=True)),
        (45.0, 0.0),
    ]
    positions = walk(*corners)
    tags = [(x, 1.4, 1.6 * side) for x, side in zip(xs, sides, strict=True)]
    normals = [(0.0, 0.0, -side) for side in sides]  # out of the wall, into the corridor
    ids = list(range(1, len(xs) + 1))
    without = build_skeleton_from_arrays(positions, tag_ids=ids, tag_positions_m=tags)
    with_normals = build_skeleton_from_arrays(
        positions, tag_ids=ids, tag_positions_m=tags, tag_normals=normals
    )

    def told_turns(pg: PathGraph) -> int:
        route = plan_guided_route(pg, TagEnd(1), TagEnd(len(xs)))
        return len(announced_turns(route))

    assert told_turns(without) > 0  # the zigzag is told as turns …
    assert told_turns(with_normals) == 0  # … and is a corridor once the tags' walls are known


def test_a_pass_that_keeps_to_each_wall_between_its_tags_draws_the_corridors_middle() -> None:
    # A 3.2 m wide corridor along x; its tags two by two on one wall, then on the other. The
    # walker stands 0.4 m from the wall at each tag and walks straight from one to the next, so
    # it keeps to one wall for 3 m and then crosses: the tags' own clearance (0.8 m out) leaves
    # its line 0.8–1.2 m off the middle, swinging from side to side.
    xs = [5, 8, 11, 14, 17, 20, 23, 26]
    sides = [1, 1, -1, -1, 1, 1, -1, -1]
    positions = walk((0, 0), *((x, 1.2 * side) for x, side in zip(xs, sides, strict=True)), (31, 0))
    tags = [(x, 1.4, 1.6 * side) for x, side in zip(xs, sides, strict=True)]
    normals = [(0.0, 0.0, -side) for side in sides]

    def off_middle_m(params: SkeletonParams) -> float:
        pg = build_skeleton_from_arrays(
            positions,
            tag_ids=list(range(len(xs))),
            tag_positions_m=tags,
            tag_normals=normals,
            params=params,
        )
        return max(abs(pg.graph.nodes[n]["position_m"][2]) for n in pg.graph)

    assert off_middle_m(SkeletonParams(facing_max_apart_m=0.0)) > 0.8  # one wall at a time
    assert off_middle_m(DEFAULT_SKELETON_PARAMS) < 0.5  # the walls that face each other


def test_tags_facing_each_other_across_a_junction_leave_it_where_it_was_walked() -> None:
    # A corridor along x with a branch north at x = 10. Two tags on the junction's corners face
    # each other diagonally across it (as tags 312 and 313 do on the real floor 2): their middle
    # line runs north-west through the junction, along neither corridor. Moved onto it, the
    # junction went 1.4 m off and the 90° turn north was told as 65°.
    positions = np.concatenate([walk((0, 0), (20, 0)), walk((20, 0), (10, 0), (10, 12))[1:]])
    d = 1 / math.sqrt(2)
    tags = [(2, 1.4, -1.6), (11.6, 1.4, 1.6), (8.4, 1.4, -1.6), (18, 1.4, 1.6), (8.4, 1.4, 11)]
    normals = [(0, 0, 1), (-d, 0, -d), (d, 0, d), (0, 0, -1), (1, 0, 0)]
    pg = build_skeleton_from_arrays(
        positions, tag_ids=[1, 2, 3, 4, 5], tag_positions_m=tags, tag_normals=normals
    )
    (junction,) = junctions(pg)
    assert np.hypot(junction[0] - 10.0, junction[2]) < 0.5
    (turn,) = announced_turns(plan_guided_route(pg, TagEnd(1), TagEnd(5)))
    assert -100 < turn.turn_deg < -80


def test_tag_normals_must_match_the_tags() -> None:
    with pytest.raises(ParameterError, match="tag_normals"):
        build_skeleton_from_arrays(
            walk((0, 0), (10, 0)), tag_ids=[1], tag_positions_m=[(5, 1.4, 1)], tag_normals=[]
        )


def test_a_lobby_walked_round_beside_a_junction_leaves_the_corridors_straight() -> None:
    # A T of corridors; at the junction the walker loops round a lobby of 2.5 m radius.
    angle = np.linspace(0.0, 2 * math.pi, 60)
    lobby = np.column_stack(
        [20 + 2.5 * np.sin(angle), np.full(60, PHONE_Y_M), 2.5 - 2.5 * np.cos(angle)]
    )
    positions = np.concatenate(
        [walk((0, 0), (20, 0)), lobby, walk((20, 0), (40, 0), (20, 0), (20, -20))]
    )
    pg = build_skeleton_from_arrays(
        positions, tag_ids=[1, 2, 3], tag_positions_m=[(2, 1.4, 1), (38, 1.4, 1), (21, 1.4, -18)]
    )
    assert not nx.cycle_basis(pg.graph)
    for a, b in ((1, 2), (2, 1)):  # straight along the corridor past the lobby
        assert announced_turns(plan_guided_route(pg, TagEnd(a), TagEnd(b))) == []
    route = plan_guided_route(pg, TagEnd(1), TagEnd(3))
    assert [t.turn_deg > 0 for t in announced_turns(route)] == [True]  # one left turn
    assert not has_turn_around(route)


def test_a_corridor_straight_through_a_widening_junction_runs_straight() -> None:
    # A T: the corridor z = 0 from x = 0 to 40, a stem down from x = 20; beside the junction, on
    # the far side from the stem, a lobby wandered through (a spiral out to 2.5 m, centred
    # 2.5 m off the corridor's line): the band bulges there, with no hole.
    angle = np.linspace(0.0, 6 * math.pi, 180)
    radius = np.linspace(0.2, 2.5, 180)
    lobby = np.column_stack(
        [20 + radius * np.sin(angle), np.full(180, PHONE_Y_M), 2.5 - radius * np.cos(angle)]
    )
    positions = np.concatenate(
        [walk((0, 0), (20, 0), (20, 2.3)), lobby, walk((20, 0), (40, 0), (20, 0), (20, -20))]
    )
    tags = [(2, 1.4, -1), (38, 1.4, -1), (21, 1.4, -18)]
    pg = build_skeleton_from_arrays(positions, tag_ids=[1, 2, 3], tag_positions_m=tags)
    for a, b in ((1, 2), (2, 1)):  # along the corridor, past the lobby: no turn, no bear
        assert announced_turns(plan_guided_route(pg, TagEnd(a), TagEnd(b)), min_deg=30.0) == []
    for a in (1, 2):  # into the stem: one turn
        assert len(announced_turns(plan_guided_route(pg, TagEnd(a), TagEnd(3)))) == 1


def _with_loop_at(positions: np.ndarray, k: int, radius_m: float) -> np.ndarray:
    """``positions`` with a walk round a circle of ``radius_m`` through row k inserted after it
    (to its left, z > row k's), back to where it began."""
    count = max(8, math.ceil(2 * math.pi * radius_m / 0.3))
    angle = -math.pi / 2 + np.linspace(0.0, 2 * math.pi, count + 1)[1:]
    centre = positions[k][[0, 2]] + [0.0, radius_m]
    loop = np.repeat(positions[k][None], count, axis=0)
    loop[:, 0] = centre[0] + radius_m * np.cos(angle)
    loop[:, 2] = centre[1] + radius_m * np.sin(angle)
    return np.concatenate([positions[: k + 1], loop, positions[k + 1 :]])


def test_a_walk_round_a_lobby_beside_a_corner_leaves_the_corner_where_it_is() -> None:
    """A walker who walks round a lobby (a 2.5 m circle) at a corner: the band fills the lobby
    and thinning ran the centreline across it, 1.5–2 m inside the corner (issue 26). The look
    round is left out of the band: the corner stays within 0.5 m of the walked one."""
    corner = walk((0, 0), (20, 0), (20, 20))
    k = int(np.argmin(np.hypot(corner[:, 0] - 20, corner[:, 2])))
    looped = _with_loop_at(corner, k, 2.5)
    for positions in (corner, looped):
        pg = build_skeleton_from_arrays(positions)
        xz = np.array([pg.graph.nodes[n]["position_m"] for n in pg.graph])[:, [0, 2]]
        assert np.hypot(xz[:, 0] - 20, xz[:, 1]).min() < 0.5
        route = plan_walk(pg, *(nearest_ends(pg, (0, 0), (20, 20))))
        assert not has_turn_around(route)


def nearest_ends(pg: PathGraph, *points_xz) -> list[NodeEnd]:
    G = pg.graph
    nodes = list(G)
    xz = np.array([G.nodes[n]["position_m"] for n in nodes])[:, [0, 2]]
    return [NodeEnd(nodes[int(np.argmin(np.hypot(*(xz - p).T)))]) for p in points_xz]


@pytest.mark.parametrize(
    ("label", "excursion"),
    [
        # a step to a tag on the wall and back: encloses nothing
        ("step to a tag", [(10, 0), (10.5, 1.4), (10.2, 0.1)]),
        # a dead end 8 m in and back 1 m to one side: a thin strip (4π area / perimeter² ≈ 0.3)
        ("dead end in and back", [(10, 0), (10, 8), (11, 8), (11, 0.3), (10.2, 0.2)]),
    ],
)
def test_an_out_and_back_is_no_look_round(label: str, excursion) -> None:
    positions = walk((0, 0), *excursion, (20, 0))
    out = _without_look_rounds(positions, [(0, len(positions))], DEFAULT_SKELETON_PARAMS)
    np.testing.assert_array_equal(out, positions, err_msg=label)


def test_only_a_round_loop_on_one_floor_is_collapsed() -> None:
    straight = walk((0, 0), (20, 0))
    k = 30
    looped = _with_loop_at(straight, k, 2.5)
    out = _without_look_rounds(looped, [(0, len(looped))], DEFAULT_SKELETON_PARAMS)
    inserted = slice(k + 1, len(looped) - (len(straight) - k - 1))
    # the loop reached 5 m out from the corridor (z = 0); collapsed, nothing is 0.5 m out (its
    # first rows may fold onto a point a little before row k, where the circle passes within
    # 0.5 m of the corridor)
    assert looped[inserted, 2].max() > 4.9
    assert np.abs(out[:, 2]).max() <= 0.5
    assert out[inserted, 2].min() >= 0.0
    np.testing.assert_array_equal(out[: k - 10], looped[: k - 10])  # the rest as walked
    np.testing.assert_array_equal(out[inserted.stop :], looped[inserted.stop :])
    # a loop too long to be a look round (a block walked round, 31 m), and the same loop rising
    # half a floor (a spiral stair), stay
    for positions in (
        _with_loop_at(straight, k, 5.0),
        looped
        + np.concatenate(
            [
                np.zeros(k + 1),
                np.linspace(0, 1.5, inserted.stop - k - 1),
                np.full(len(looped) - inserted.stop, 1.5),
            ]
        )[:, None]
        * [0, 1, 0],
    ):
        out = _without_look_rounds(positions, [(0, len(positions))], DEFAULT_SKELETON_PARAMS)
        np.testing.assert_array_equal(out, positions)
