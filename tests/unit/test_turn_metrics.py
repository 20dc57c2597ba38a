"""Scoring of announced turns (app.domain.evaluation.turn_metrics): matching, zigzags,
turn-arounds."""

from __future__ import annotations

import numpy as np

from app.domain.evaluation.turn_metrics import (
    Decisions,
    Turn,
    decisions_agree,
    decisions_agreement,
    has_turn_around,
    has_zigzag,
    match_turns,
    sides_agreement,
)
from app.domain.navigation.routing import Route, Step


def turn(x: float, z: float, turn_deg: float, along_m: float = 0.0) -> Turn:
    return Turn(position_xz_m=(x, z), turn_deg=turn_deg, along_m=along_m)


def route(points, steps=()) -> Route:
    return Route(
        polyline_m=[(float(x), 0.0, float(z)) for x, z in points],
        length_m=0.0,
        floors=[0],
        nodes=[],
        steps=list(steps),
    )


def test_matching_is_one_to_one_same_side_and_near() -> None:
    truth = [turn(0, 0, 90), turn(20, 0, -90)]
    told = [turn(1, 1, 80), turn(0.5, 0, 85), turn(20, 3, 90), turn(40, 0, -90)]
    # (1, 1) and (0.5, 0) both match the first real turn, only one counts; (20, 3) is the wrong
    # side; (40, 0) is too far.
    assert match_turns(told, truth) == (1, 1)
    assert match_turns([], truth) == (0, 0)
    assert match_turns(truth, truth) == (2, 2)


def test_zigzags_are_opposite_turns_close_together() -> None:
    assert has_zigzag([turn(0, 0, 60, 10.0), turn(0, 0, -60, 14.0)])
    assert not has_zigzag([turn(0, 0, 60, 10.0), turn(0, 0, -60, 17.0)])
    assert not has_zigzag([turn(0, 0, 60, 10.0), turn(0, 0, 60, 12.0)])


def test_a_reversal_mid_route_is_a_turn_around() -> None:
    out_and_back = route([(0, 0), (10, 0), (5, 0.1), (5, 8)])
    assert has_turn_around(out_and_back)
    corner = route([(0, 0), (10, 0), (10, 8)])
    assert not has_turn_around(corner)
    # A reversal right at the start (stepping off a tag) is not mid-route.
    assert not has_turn_around(route([(0, 0), (0.5, 0), (0, 0.01), (0, 9)]))
    told = Step(
        instruction="turn around",
        position_m=(10.0, 0.0, 0.0),
        kind="turn",
        distance_m=0.0,
        turn_deg=180.0,
        floor=0,
    )
    assert has_turn_around(route([(0, 0), (10, 0), (10, 8)], [told]))


def test_a_switchback_staircase_is_no_turn_around() -> None:
    # up the first flight along +x, round at the landing, up the second flight back along −x
    stairs = Route(
        polyline_m=[(0, 0, 0), (5, 0, 0), (8, 1.6, 0), (5, 3.2, 0.3), (0, 3.2, 0.3)],
        length_m=0.0,
        floors=[0, 1],
        nodes=[],
        steps=[],
    )
    assert not has_turn_around(stairs)
    flat = Route(
        polyline_m=[(0, 0, 0), (5, 0, 0), (8, 0, 0), (5, 0, 0.3), (0, 0, 0.3)],
        length_m=0.0,
        floors=[0],
        nodes=[],
        steps=[],
    )
    assert has_turn_around(flat)  # the same bends on one floor are a reversal


def test_two_maps_agree_within_the_band_and_not_beyond() -> None:
    corner_47 = Decisions(turns=(turn(10, 0, -47),), bends=(turn(10, 0, -47),))
    corner_43 = Decisions(turns=(), bends=(turn(10.5, 0, -43),))  # told by neither as a turn
    straight = Decisions(turns=(), bends=())
    other_side = Decisions(turns=(turn(10, 0, 50),), bends=(turn(10, 0, 50),))
    elsewhere = Decisions(turns=(turn(30, 0, -47),), bends=(turn(30, 0, -47),))
    assert decisions_agree(corner_47, corner_43)  # a 45° corner measured either side of 45°
    assert decisions_agree(corner_43, corner_47)
    assert not decisions_agree(corner_47, straight)  # a turn where the other goes straight
    assert not decisions_agree(corner_47, other_side)
    assert not decisions_agree(corner_47, elsewhere)  # 20 m apart: not the same decision
    first = {(1, 2): corner_47, (2, 1): straight, (1, 3): straight}
    second = {(1, 2): corner_43, (2, 1): other_side}
    assert decisions_agreement(first, second) == 0.5  # (1, 3): routed by one map only
    assert sides_agreement({k: d.sides for k, d in first.items()}, {(1, 2): "", (2, 1): ""}) == 0.5
    assert np.isnan(decisions_agreement(first, {}))
