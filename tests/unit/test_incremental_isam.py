"""A building map in gtsam's ISAM2 (app/domain/mapping/incremental/isam.py, issue 38): its graph is
the batch build's, an add or a removal serves the batch map of the walks it holds, and the state
it keeps as data makes the same tree again, or is refused when it is stale."""

from __future__ import annotations

import dataclasses
import json
from functools import cache

import numpy as np
import pytest

from app.domain.errors import InvisibleMapError
from app.domain.evaluation.simulate import SimulationConfig
from app.domain.evaluation.simulate_building import simulate_building_sessions
from app.domain.mapping.incremental import (
    IncrementalMap,
    IsamBuilding,
    IsamState,
    IsamWalkState,
    StaleStateError,
    Walk,
)
from app.domain.mapping.joint import JointMap, WalkFit, optimize_sessions, prepare_joint
from app.domain.mapping.params import SlamParams
from app.domain.mapping.slam import GraphInputs, TrialGraph, chain_graph, values_from
from app.domain.upload.session import parse_session

#: The issue's bounds on what is served, against the batch build of the same walks, m.
TAG_BOUND_M = 0.01
POSE_BOUND_M = 0.05
PARAMS = SlamParams()
EVERYONE = ("w1", "w2", "w3", "w4")


@cache
def walks() -> tuple[Walk, ...]:
    """Four simulated walks of one building (400 poses each), each in its own world frame."""
    building = simulate_building_sessions(SimulationConfig(num_poses=400, seed=3), count=4)
    return tuple(
        Walk(walk_id=f"w{k + 1}", session=parse_session(s.upload))
        for k, s in enumerate(building.sessions)
    )


@cache
def batch(ids: tuple[str, ...]) -> JointMap:
    """The batch build of these walks with every walk's own noise, none down-weighted (what the
    tree holds: the module's docstring); each walk optimized alone once."""
    by_id = {w.walk_id: w.session for w in walks()}
    fits = [] if ids == EVERYONE else [p.fit for p in batch(EVERYONE).parts if p.fit is not None]
    return optimize_sessions(
        [by_id[i] for i in ids], PARAMS, names=list(ids), reweight=False, fits=fits
    )


def fits() -> list[WalkFit]:
    return [p.fit for p in batch(EVERYONE).parts if p.fit is not None]


def three() -> tuple[IsamBuilding, IncrementalMap]:
    """A tree of the first three walks, made anew (the tests change it)."""
    return IsamBuilding.build(walks()[:3], PARAMS, fits=fits())


def largest_differences_m(served: IncrementalMap, joint: JointMap) -> tuple[float, float]:
    """The largest tag and pose position differences, both in the first walk's world."""
    assert served.walk_ids == tuple(part.dataset for part in joint.parts)
    assert set(joint.map.tag_poses()) == set(served.tag_poses())
    return served.largest_differences_m(joint)


def within_bounds(served: IncrementalMap, ids: tuple[str, ...]) -> None:
    joint = batch(ids)
    assert all(p.disagreement_factor == 1.0 and not p.local_tags for p in joint.parts)
    tag_m, pose_m = largest_differences_m(served, joint)
    assert tag_m <= TAG_BOUND_M
    assert pose_m <= POSE_BOUND_M


def test_the_walks_graphs_together_are_the_batch_builds_graph() -> None:
    """Each walk's factors (``slam.chain_graph`` at its pose rows) are its chain's factors in
    the joint graph: the same number, the same error at the same values."""
    sessions = [w.session for w in walks()]
    joint = prepare_joint(sessions, PARAMS, names=list(EVERYONE), fits=fits())
    fixed = dataclasses.replace(PARAMS, estimate_noise=False)
    whole = TrialGraph(joint.inputs).graph(fixed)
    values = values_from(joint.inputs, joint.start_T_keyframe, joint.start_T_tag)
    parts = []
    for s, start in enumerate(joint.starts):
        inputs = GraphInputs(
            joint.plan.sessions[s],
            fixed,
            screening=joint.plan.screenings[s],
            noise_scales=joint.base_scales[s][None],
        )
        parts.append(chain_graph(inputs, fixed, key_offset=start, gauge=s == 0))
    assert sum(int(g.size()) for g in parts) == int(whole.size())
    error = sum(g.error(values) for g in parts)
    assert error == pytest.approx(whole.error(values), rel=1e-9)


def test_a_tree_built_and_a_walk_added_serve_the_batch_map() -> None:
    building, served = three()
    within_bounds(served, ("w1", "w2", "w3"))
    added = building.add(walks()[3], fit=fits()[3])
    assert added.walk_ids == EVERYONE
    within_bounds(added, EVERYONE)


def test_removing_a_walk_gives_the_map_it_never_joined() -> None:
    building, before = three()
    building.add(walks()[3], fit=fits()[3])
    removed = building.remove("w4")
    within_bounds(removed, ("w1", "w2", "w3"))
    np.testing.assert_array_equal(removed.tag_ids, before.tag_ids)
    np.testing.assert_allclose(removed.map_T_tag, before.map_T_tag, atol=TAG_BOUND_M / 10)
    for a, b in zip(removed.world_T_phone, before.world_T_phone, strict=True):
        assert float(np.max(np.linalg.norm(a[:, :3, 3] - b[:, :3, 3], axis=1))) <= POSE_BOUND_M


def test_removing_the_first_walk_draws_the_map_in_the_next_ones_world() -> None:
    building, _ = three()
    building.add(walks()[3], fit=fits()[3])
    removed = building.remove("w1")
    within_bounds(removed, ("w2", "w3", "w4"))
    # the next walk holds the gauge now: the walk after it can go too
    within_bounds(building.remove("w3"), ("w2", "w4"))


def test_a_state_read_back_from_its_rows_makes_the_tree_again() -> None:
    building, served = three()
    state = building.state()
    row = state.to_dict()
    plain = json.loads(json.dumps({k: v for k, v in row.items() if k != "arrays"}))
    walk_rows = [IsamWalkState.from_dict(w.to_dict()) for w in reversed(state.walks)]
    restored_state = IsamState.from_dict({**plain, "arrays": row["arrays"]}, walk_rows)
    assert restored_state.fingerprint == state.fingerprint
    restarted, again = IsamBuilding.restore(restored_state, walks()[:3], PARAMS)
    np.testing.assert_allclose(again.map_T_tag, served.map_T_tag, atol=1e-3)
    for a, b in zip(again.world_T_phone, served.world_T_phone, strict=True):
        np.testing.assert_allclose(a[:, :3, 3], b[:, :3, 3], atol=1e-3)
    # … and the next add is incremental again, and still the batch map
    within_bounds(restarted.add(walks()[3], fit=fits()[3]), EVERYONE)


def test_a_state_after_the_first_walk_left_restores_in_the_next_ones_world() -> None:
    building, _ = three()
    building.remove("w1")
    state = building.state()
    assert state.walk_ids == ("w2", "w3")
    _, again = IsamBuilding.restore(state, walks()[1:3], PARAMS)
    within_bounds(again, ("w2", "w3"))


def test_a_walk_added_behind_the_states_back_is_caught() -> None:
    state = three()[0].state()
    state.require_current(walks()[:3], PARAMS)
    with pytest.raises(StaleStateError, match=r"holds walks \['w1', 'w2', 'w3'\]"):
        IsamBuilding.restore(state, walks(), PARAMS)
    with pytest.raises(StaleStateError, match="holds walks"):  # one taken out behind its back
        IsamBuilding.restore(state, walks()[:2], PARAMS)
    with pytest.raises(StaleStateError):  # the same walks in another order: another map frame
        IsamBuilding.restore(state, [walks()[1], walks()[0], walks()[2]], PARAMS)
    with pytest.raises(StaleStateError, match="parameters changed"):
        IsamBuilding.restore(state, walks()[:3], dataclasses.replace(PARAMS, huber_k=2.0))


def test_a_walk_whose_data_changed_is_caught() -> None:
    state = three()[0].state()
    changed = walks()[1].session
    moved = changed.world_T_phone.copy()
    moved[5, 0, 3] += 0.01
    edited = Walk(walk_id="w2", session=dataclasses.replace(changed, world_T_phone=moved))
    with pytest.raises(StaleStateError, match="data or the parameters changed"):
        IsamBuilding.restore(state, [walks()[0], edited, walks()[2]], PARAMS)


def test_rows_of_another_state_are_refused() -> None:
    building, _ = three()
    state = building.state()
    building.add(walks()[3], fit=fits()[3])
    other = building.state()
    with pytest.raises(StaleStateError):  # another state's walk rows
        IsamState.from_dict(state.to_dict(), [*other.walks[:2], other.walks[3]])
    with pytest.raises(StaleStateError):
        IsamState.from_dict({**state.to_dict(), "walk_fingerprints": ["x", "y", "z"]}, state.walks)
    with pytest.raises(StaleStateError, match="format"):
        IsamState.from_dict({**state.to_dict(), "format": "isam-building/0"}, state.walks)


def test_a_walk_cannot_be_added_twice_nor_the_last_removed() -> None:
    building, _ = three()
    with pytest.raises(InvisibleMapError, match="already"):
        building.add(walks()[0], fit=fits()[0])
    building.remove("w3")
    building.remove("w2")
    with pytest.raises(InvisibleMapError, match="at least one session"):
        building.remove("w1")
