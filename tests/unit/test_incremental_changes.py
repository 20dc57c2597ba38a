"""Which change of a building map the ISAM2 engine makes from a stored state
(app/domain/mapping/incremental/changes.py, issue 38): one walk added last or one taken out, the
state current for the rest; anything else is the batch build's. And the state a batch build
makes of its optimum (from_batch.py): the tree it restores is the batch map, and a batch build
that changed a walk beyond the tree's graph makes none."""

from __future__ import annotations

import dataclasses

import pytest

from app.domain.mapping.incremental import IsamBuilding
from app.domain.mapping.incremental.changes import WalkChange, apply_change, one_walk_change
from app.domain.mapping.incremental.from_batch import state_from_batch
from tests.unit.test_incremental_isam import (
    EVERYONE,
    PARAMS,
    batch,
    three,
    walks,
    within_bounds,
)


def by_id() -> dict:
    return {w.walk_id: w for w in walks()}


def test_one_walk_added_last_is_the_engines_and_serves_the_batch_map() -> None:
    state = three()[0].state()
    change = one_walk_change(state, ["w1", "w2", "w3", "w4"], PARAMS, by_id())
    assert isinstance(change, WalkChange)
    assert change.summary == "w4 added"
    _, served, timings_ms = apply_change(state, change, PARAMS)
    within_bounds(served, ("w1", "w2", "w3", "w4"))
    assert set(timings_ms) == {"restore", "change"}


def test_one_walk_taken_out_is_the_engines_and_serves_the_batch_map() -> None:
    state = three()[0].state()
    change = one_walk_change(state, ["w1", "w3"], PARAMS, by_id())
    assert isinstance(change, WalkChange)
    assert change.removed == "w2"
    _, served, _ = apply_change(state, change, PARAMS)
    within_bounds(served, ("w1", "w3"))


@pytest.mark.parametrize(
    ("wanted", "why"),
    [
        (["w1", "w2", "w3"], "the same walks"),
        (["w1", "w2", "w4", "w3"], "not one walk added"),  # not added last
        (["w1", "w2"], None),  # fine: one taken out (checked below that it is not refused)
        (["w2", "w1", "w3", "w4"], "not one walk added"),
        (["w1"], "not one walk added"),  # two taken out
    ],
)
def test_other_changes_are_the_batch_builds(wanted: list[str], why: str | None) -> None:
    state = three()[0].state()
    change = one_walk_change(state, wanted, PARAMS, by_id())
    if why is None:
        assert isinstance(change, WalkChange)
    else:
        assert isinstance(change, str)
        assert why in change


def test_a_stale_state_is_the_batch_builds() -> None:
    building, _ = three()
    old = building.state()  # of w1–w3
    building.add(walks()[3])
    # a walk added behind the old state's back: the map is w1–w4 and w5 is asked for
    assert "not one walk added" in str(
        one_walk_change(old, ["w1", "w2", "w3", "w4", "w5"], PARAMS, by_id())
    )
    # a walk's data changed
    changed = walks()[1]
    moved = changed.session.world_T_phone.copy()
    moved[5, 0, 3] += 0.01
    edited = {
        **by_id(),
        "w2": dataclasses.replace(
            changed, session=dataclasses.replace(changed.session, world_T_phone=moved)
        ),
    }
    assert "data or the parameters changed" in str(
        one_walk_change(old, ["w1", "w2", "w3", "w4"], PARAMS, edited)
    )
    # other parameters
    other = dataclasses.replace(PARAMS, huber_k=2.0)
    assert "parameters changed" in str(
        one_walk_change(old, ["w1", "w2", "w3", "w4"], other, by_id())
    )
    # the walk taken out is not at hand (its session deleted)
    without = {k: v for k, v in by_id().items() if k != "w2"}
    assert "not at hand" in str(one_walk_change(old, ["w1", "w3"], PARAMS, without))


def test_the_state_of_a_batch_optimum_restores_the_batch_map() -> None:
    state, why_not = state_from_batch(batch(EVERYONE), walks(), PARAMS)
    assert state is not None, why_not
    assert state.walk_ids == EVERYONE
    _, restored = IsamBuilding.restore(state, walks(), PARAMS)
    within_bounds(restored, EVERYONE)


@pytest.mark.parametrize(
    ("change", "why"),
    [
        ({"disagreement_factor": 1.8}, "down-weighted ×1.80"),
        ({"local_tags": (3,)}, "tags [3] set apart"),
        ({"fit": None}, "no fit of its own"),
    ],
)
def test_a_batch_build_that_changed_a_walk_makes_no_state(change: dict, why: str) -> None:
    joint = batch(EVERYONE)
    parts = list(joint.parts)
    parts[2] = dataclasses.replace(parts[2], **change)
    state, why_not = state_from_batch(
        dataclasses.replace(joint, parts=tuple(parts)), walks(), PARAMS
    )
    assert state is None
    assert why_not == f"w3: {why}"


def test_a_rescaled_walk_and_the_variances_as_given_make_no_state() -> None:
    joint = batch(EVERYONE)
    parts = list(joint.parts)
    parts[1] = dataclasses.replace(
        parts[1], alignment=dataclasses.replace(parts[1].alignment, odometry_scale=0.98)
    )
    rescaled = dataclasses.replace(joint, parts=tuple(parts))
    assert state_from_batch(rescaled, walks(), PARAMS) == (None, "w2: its odometry rescaled ×0.980")
    as_given = dataclasses.replace(PARAMS, estimate_noise=False)
    assert state_from_batch(joint, walks(), as_given)[0] is None
