"""Building maps that grow a walk at a time (app/domain/mapping/incremental, issue 38): an add or
a removal gives the batch build's map, the state survives a round trip through its rows, and a
state made from other walks or parameters is caught."""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable
from functools import cache

import gtsam
import numpy as np
import pytest
from gtsam.symbol_shorthand import L

from app.domain.evaluation.simulate import SimulationConfig
from app.domain.evaluation.simulate_building import simulate_building_sessions
from app.domain.mapping.incremental import (
    BuildingState,
    IncrementalMap,
    StaleStateError,
    Walk,
    WalkSummary,
    add_walk,
    build,
    remove_walk,
    require_current,
)
from app.domain.mapping.incremental import building as incremental_building
from app.domain.mapping.incremental.building import (
    se3_adjoint,
    se3_exp,
    se3_log,
    se3_log_derivative,
)
from app.domain.mapping.joint import JointMap, WalkFit, optimize_sessions, plan_sessions
from app.domain.mapping.params import SlamParams
from app.domain.mapping.slam import GraphInputs, TrialGraph, values_from
from app.domain.upload.session import Session, parse_session

#: The issue's bounds on what is served, against the batch build of the same walks, m.
TAG_BOUND_M = 0.01
POSE_BOUND_M = 0.05
PARAMS = SlamParams()


@cache
def walks() -> tuple[Walk, ...]:
    """Four simulated walks of one building (400 poses each), each in its own world frame."""
    building = simulate_building_sessions(SimulationConfig(num_poses=400, seed=3), count=4)
    return tuple(
        Walk(walk_id=f"w{k + 1}", session=parse_session(s.upload))
        for k, s in enumerate(building.sessions)
    )


def loader() -> Callable[[str], Session]:
    return {w.walk_id: w.session for w in walks()}.__getitem__


@cache
def batch(ids: tuple[str, ...]) -> JointMap:
    """The batch build of these walks, with every walk's own noise and no down-weighting (what
    the summaries reproduce: the package's docstring); each walk optimized alone once."""
    by_id = {w.walk_id: w.session for w in walks()}
    everyone = ("w1", "w2", "w3", "w4")
    fits = [] if ids == everyone else [p.fit for p in batch(everyone).parts if p.fit is not None]
    return optimize_sessions(
        [by_id[i] for i in ids], PARAMS, names=list(ids), reweight=False, fits=fits
    )


def fits() -> list[WalkFit]:
    return [p.fit for p in batch(("w1", "w2", "w3", "w4")).parts if p.fit is not None]


@cache
def three() -> tuple[BuildingState, IncrementalMap]:
    return build(walks()[:3], PARAMS, fits=fits())


@cache
def four_by_adding() -> tuple[BuildingState, IncrementalMap]:
    return add_walk(three()[0], walks()[3], PARAMS, load=loader(), fit=fits()[3])


def largest_differences_m(served: IncrementalMap, joint: JointMap) -> tuple[float, float]:
    """The largest tag and pose position differences, both in the first walk's world."""
    assert served.walk_ids == tuple(part.dataset for part in joint.parts)
    assert set(joint.map.tag_poses()) == set(served.tag_poses())
    return served.largest_differences_m(joint)


def test_adding_a_walk_gives_the_batch_map_of_all_of_them() -> None:
    state, served = four_by_adding()
    tag_m, pose_m = largest_differences_m(served, batch(("w1", "w2", "w3", "w4")))
    assert tag_m <= TAG_BOUND_M
    assert pose_m <= POSE_BOUND_M
    assert state.walk_ids == ("w1", "w2", "w3", "w4")
    # the walks it names as relinearized are those whose summaries were made again: the new
    # one, and each earlier one whose count of relinearizations went up
    counts_before = {w.walk_id: w.relinearized for w in three()[0].walks}
    again = {w.walk_id for w in state.walks[:3] if w.relinearized > counts_before[w.walk_id]}
    assert set(served.relinearized) == {"w4"} | again
    assert len(served.relinearized) == len(set(served.relinearized))
    before = three()[1]
    assert largest_differences_m(before, batch(("w1", "w2", "w3")))[0] <= TAG_BOUND_M


def test_removing_a_walk_gives_the_map_it_never_joined() -> None:
    _, served = remove_walk(four_by_adding()[0], "w4", PARAMS, load=loader())
    tag_m, pose_m = largest_differences_m(served, batch(("w1", "w2", "w3")))
    assert tag_m <= TAG_BOUND_M
    assert pose_m <= POSE_BOUND_M


def test_removing_the_first_walk_draws_the_map_in_the_next_ones_world() -> None:
    state, served = remove_walk(four_by_adding()[0], "w1", PARAMS, load=loader())
    np.testing.assert_allclose(state.map_T_world[0], np.eye(4), atol=1e-12)
    tag_m, pose_m = largest_differences_m(served, batch(("w2", "w3", "w4")))
    assert tag_m <= TAG_BOUND_M
    assert pose_m <= POSE_BOUND_M


def test_a_state_read_back_from_its_rows_makes_the_same_next_add() -> None:
    state = three()[0]
    row = json.loads(json.dumps({k: v for k, v in state.to_dict().items() if k != "arrays"}))
    row["arrays"] = state.to_dict()["arrays"]
    rows = [WalkSummary.from_dict(w.to_dict()) for w in reversed(state.walks)]
    restored = BuildingState.from_dict(row, rows)
    assert restored.fingerprint == state.fingerprint
    require_current(restored, walks()[:3], PARAMS)
    _, again = add_walk(restored, walks()[3], PARAMS, load=loader(), fit=fits()[3])
    _, first = four_by_adding()
    np.testing.assert_allclose(again.map_T_tag, first.map_T_tag, atol=1e-9)
    for a, b in zip(again.world_T_phone, first.world_T_phone, strict=True):
        np.testing.assert_allclose(a, b, atol=1e-9)


def test_a_walk_added_behind_the_states_back_is_caught() -> None:
    state = three()[0]
    require_current(state, walks()[:3], PARAMS)
    with pytest.raises(StaleStateError, match=r"holds walks \['w1', 'w2', 'w3'\]"):
        require_current(state, walks(), PARAMS)
    with pytest.raises(StaleStateError):  # the same walks in another order: another map frame
        require_current(state, [walks()[1], walks()[0], walks()[2]], PARAMS)
    with pytest.raises(StaleStateError):
        require_current(state, walks()[:3], dataclasses.replace(PARAMS, huber_k=2.0))
    with pytest.raises(StaleStateError):
        add_walk(state, walks()[3], dataclasses.replace(PARAMS, huber_k=2.0), fit=fits()[3])


def test_a_walk_whose_data_changed_is_caught() -> None:
    state = three()[0]
    changed = walks()[1].session
    moved = changed.world_T_phone.copy()
    moved[5, 0, 3] += 0.01
    edited = Walk(walk_id="w2", session=dataclasses.replace(changed, world_T_phone=moved))
    with pytest.raises(StaleStateError, match="data or the parameters changed"):
        require_current(state, [walks()[0], edited, walks()[2]], PARAMS)

    def load(walk_id: str) -> Session:
        return edited.session if walk_id == "w2" else loader()(walk_id)

    # relinearizing w2 from other data than its summary's is refused too
    with pytest.raises(StaleStateError, match="w2"):
        remove_walk(state, "w3", PARAMS, load=load, tolerance=(0.0, 0.0))


def test_rows_of_another_state_are_refused() -> None:
    state = three()[0]
    other = four_by_adding()[0]
    with pytest.raises(StaleStateError):
        BuildingState.from_dict(state.to_dict(), [*other.walks[:2], other.walks[3]])
    rows = list(other.walks[:3])  # the same walks, relinearized since: their rows changed
    if any(a.relinearized != b.relinearized for a, b in zip(rows, state.walks, strict=True)):
        changed = dict(state.to_dict(), walk_fingerprints=["x", "y", "z"])
        with pytest.raises(StaleStateError):
            BuildingState.from_dict(changed, rows)


def test_a_summary_is_the_marginal_information_of_the_walks_tags() -> None:
    walk = walks()[0]
    plan = plan_sessions([walk.session], PARAMS, names=[walk.walk_id], fits=fits()[:1])
    summary = three()[0].walk("w1")
    fixed = dataclasses.replace(PARAMS, estimate_noise=False)
    inputs = GraphInputs(
        plan.sessions[0],
        fixed,
        screening=plan.screenings[0],
        noise_scales=summary.noise_scales[None],
    )
    graph = TrialGraph(inputs).graph(fixed)
    world_T_tag = {
        int(t): pose for t, pose in zip(summary.tag_ids, summary.world_T_tag, strict=True)
    }
    values = values_from(inputs, summary.world_T_phone[inputs.keyframes], world_T_tag)
    keys = gtsam.KeyVector([L(int(t)) for t in summary.tag_ids])
    information = gtsam.Marginals(graph, values).jointMarginalInformation(keys).fullMatrix()
    np.testing.assert_allclose(summary.information, information, rtol=1e-6, atol=1e-6)


def test_a_singular_system_is_solved_by_least_squares() -> None:
    """A building's normal equations without full rank (a tag seen by no walk's summary in a
    direction): Cholesky refuses them, and the minimum-norm least-squares answer is used."""
    singular = np.array([[1.0, 1.0], [1.0, 1.0]])
    np.testing.assert_allclose(incremental_building._solve(singular, np.array([2.0, 2.0])), [1, 1])
    definite = np.array([[4.0, 1.0], [1.0, 3.0]])
    rhs = np.array([1.0, 2.0])
    np.testing.assert_allclose(
        incremental_building._solve(definite, rhs), np.linalg.solve(definite, rhs)
    )


def test_se3_helpers_are_gtsams() -> None:
    rng = np.random.default_rng(0)
    for scale in (1e-9, 1e-3, 0.05, 0.5):
        xi = rng.normal(size=6) * scale
        pose = gtsam.Pose3.Expmap(xi)
        np.testing.assert_allclose(se3_exp(xi), pose.matrix(), atol=1e-12)
        np.testing.assert_allclose(se3_log(pose.matrix()), gtsam.Pose3.Logmap(pose), atol=1e-12)
        np.testing.assert_allclose(se3_adjoint(pose.matrix()), pose.AdjointMap(), atol=1e-12)
        np.testing.assert_allclose(
            se3_log_derivative(xi),
            gtsam.Pose3.LogmapDerivative(pose),
            atol=max(1e-12, 10 * scale**3),
        )
