"""Issue 39: alcoves and hooked corridor ends that the walks went into stay as short branches
with their tag at the end, so routes into them announce the turn; an oblique visit to a tag that
comes back to the corridor's line draws no bend."""

from __future__ import annotations

import math

import numpy as np
import pytest

from app.domain.evaluation.turn_metrics import announced_turns
from app.domain.navigation.instructions import plan_guided_route
from app.domain.navigation.routing import TagEnd
from app.domain.navigation.skeleton import (
    DEFAULT_SKELETON_PARAMS,
    SkeletonParams,
    build_skeleton_from_arrays,
)
from app.domain.navigation.tag_walls import without_tag_visits
from tests.unit.walks import PHONE_Y_M, walk

#: Without the issue's two changes.
BEFORE = SkeletonParams(spur_min_m=0.0, straighten_tag_visits=False)


def tag_at(x: float, z: float, normal_xz: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
    return np.array([x, PHONE_Y_M + 0.2, z]), np.array([normal_xz[0], 0.0, normal_xz[1]])


def alcove_walk() -> tuple[np.ndarray, list[int], np.ndarray, np.ndarray]:
    """A corridor along x (0 to 30 m); at x = 15 an alcove whose back wall is 3.6 m off the
    corridor's middle (2 m past its 1.6 m wall), tag 2 on it; tag 1 at the corridor's west
    end, tag 3 at its east end. The walk goes in to 0.6 m from the tag and back out."""
    positions = walk((0, 0), (15, 0), (15, 3.0), (15.2, 0), (30, 0))
    p1, n1 = tag_at(-0.6, 0.0, (1.0, 0.0))
    p2, n2 = tag_at(15.0, 3.6, (0.0, -1.0))
    p3, n3 = tag_at(30.6, 0.0, (-1.0, 0.0))
    return positions, [1, 2, 3], np.array([p1, p2, p3]), np.array([n1, n2, n3])


@pytest.mark.parametrize(("params", "told"), [(DEFAULT_SKELETON_PARAMS, True), (BEFORE, False)])
def test_a_route_into_an_alcove_announces_its_turn(params: SkeletonParams, told: bool) -> None:
    positions, ids, tag_p, tag_n = alcove_walk()
    pg = build_skeleton_from_arrays(
        positions, tag_ids=ids, tag_positions_m=tag_p, tag_normals=tag_n, params=params
    )
    anchor = np.asarray(pg.graph.nodes[pg.tags[2].node]["position_m"])
    route = plan_guided_route(pg, TagEnd(1), TagEnd(2))
    turns = announced_turns(route)
    if told:
        assert anchor[2] > 2.0  # the tag is at the alcove's end, not beside the corridor
        assert len(turns) == 1
        assert turns[0].turn_deg < -45  # into the alcove: a right turn walking +x with +z right
        assert math.dist(turns[0].position_xz_m, (15.0, 0.0)) < 1.0
    else:
        assert turns == []  # the alcove was a stub, pruned: the route ended on the corridor


def test_a_hooked_corridor_end_keeps_its_corner() -> None:
    """A corridor whose end hooks 3.5 m round a corner to its last tag, 3 m beside the
    corridor it leaves (the band of both is one blob that the thinning leaves nothing of)."""
    positions = walk((0, 0), (20, 0), (20, 3.2), (16.5, 3.2), (20, 3.0), (20, 0), (0, 0))
    p1, n1 = tag_at(-0.6, 0.0, (1.0, 0.0))
    p2, n2 = tag_at(15.9, 3.2, (1.0, 0.0))
    pg = build_skeleton_from_arrays(
        positions,
        tag_ids=[1, 2],
        tag_positions_m=np.array([p1, p2]),
        tag_normals=np.array([n1, n2]),
    )
    route = plan_guided_route(pg, TagEnd(1), TagEnd(2))
    turns = announced_turns(route)
    # walking +x, +z is on the right: right into the hook, right round its corner
    assert [round(math.copysign(1, t.turn_deg)) for t in turns] in ([-1], [-1, -1])
    end = np.asarray(pg.graph.nodes[pg.tags[2].node]["position_m"])
    assert end[0] < 18.0  # the route goes round the corner, not to the corridor's end
    before = build_skeleton_from_arrays(
        positions,
        tag_ids=[1, 2],
        tag_positions_m=np.array([p1, p2]),
        tag_normals=np.array([n1, n2]),
        params=BEFORE,
    )
    assert announced_turns(plan_guided_route(before, TagEnd(1), TagEnd(2))) == []


def test_an_oblique_visit_to_a_tag_is_straightened() -> None:
    """From 3 m before a tag on the wall 1.6 m off the line, straight to 0.4 m from it and back
    to the line 3 m after: the walk's line, not a V."""
    positions = walk((0, 0), (12, 0), (15, 1.2), (18, 0), (30, 0), step_m=0.3)
    p, n = tag_at(15.0, 1.6, (0.0, -1.0))
    moved = without_tag_visits(positions, [(0, len(positions))], p[None], n[None])
    assert float(np.abs(moved[:, 2]).max()) < 0.05
    pg = build_skeleton_from_arrays(
        positions,
        tag_ids=[1, 2, 3],
        tag_positions_m=np.array([[-0.5, 1.5, 0.0], p, [30.5, 1.5, 0.0]]),
        tag_normals=np.array([[1.0, 0.0, 0.0], n, [-1.0, 0.0, 0.0]]),
    )
    assert announced_turns(plan_guided_route(pg, TagEnd(1), TagEnd(3))) == []


def test_a_step_in_and_back_and_an_alcove_are_no_oblique_visit() -> None:
    positions = walk((0, 0), (15, 0), (15, 1.2), (15, 0), (30, 0), step_m=0.3)
    p, n = tag_at(15.0, 1.6, (0.0, -1.0))
    moved = without_tag_visits(positions, [(0, len(positions))], p[None], n[None])
    np.testing.assert_allclose(moved, positions, atol=1e-9)
    alcove, _, tag_p, tag_n = alcove_walk()
    moved = without_tag_visits(alcove, [(0, len(alcove))], tag_p, tag_n)
    np.testing.assert_allclose(moved, alcove, atol=1e-9)
