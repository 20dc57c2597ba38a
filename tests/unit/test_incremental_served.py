"""The ISAM2 engine's map served as the batch build's JointMap (incremental/served_map.py, issue
38): read through the batch build's own report, it gives the batch build's figures; walks kept
from a stored state come without a map alone; and a change the batch build's later steps would
make (a walk rescaled, a walk down-weighted) is left to the batch build, the scale test made in
the tree as the batch build makes it."""

from __future__ import annotations

import dataclasses

import numpy as np

from app.domain.evaluation.simulate import SimulationConfig
from app.domain.evaluation.simulate_building import WalkStyle, simulate_building_sessions
from app.domain.mapping.incremental import IsamBuilding, IsamState, IsamWalkState, Walk
from app.domain.mapping.incremental.served_map import served_joint_map
from app.domain.mapping.joint import JointMap, optimize_sessions
from app.domain.upload.session import parse_session
from tests.unit.test_incremental_isam import (
    EVERYONE,
    PARAMS,
    POSE_BOUND_M,
    TAG_BOUND_M,
    batch,
    fits,
    walks,
)


def served_after_adding_the_fourth(building: IsamBuilding) -> JointMap:
    served = building.add(walks()[3])
    joint = served_joint_map(building, served, PARAMS)
    assert isinstance(joint, JointMap), joint
    return joint


def within_bounds(joint: JointMap, reference: JointMap) -> None:
    assert [p.dataset for p in joint.parts] == [p.dataset for p in reference.parts]
    np.testing.assert_array_equal(joint.map.tag_ids, reference.map.tag_ids)
    tag_m = np.linalg.norm(
        joint.map.world_T_tag[:, :3, 3] - reference.map.world_T_tag[:, :3, 3], axis=1
    )
    pose_m = np.linalg.norm(
        joint.map.world_T_phone[:, :3, 3] - reference.map.world_T_phone[:, :3, 3], axis=1
    )
    assert tag_m.max() <= TAG_BOUND_M
    assert pose_m.max() <= POSE_BOUND_M


def test_the_engines_map_is_reported_as_the_batch_build_reports_its_own():
    building, _ = IsamBuilding.build(walks()[:3], PARAMS, fits=fits())
    joint = served_after_adding_the_fourth(building)
    reference = batch(EVERYONE)
    assert all(p.disagreement_factor == 1.0 and not p.local_tags for p in reference.parts)
    within_bounds(joint, reference)
    np.testing.assert_allclose(joint.map.tag_covariance, reference.map.tag_covariance, atol=1e-3)
    np.testing.assert_array_equal(
        joint.map.residuals.keyframe_index, reference.map.residuals.keyframe_index
    )
    np.testing.assert_array_equal(
        joint.map.residuals.tag_detection_index, reference.map.residuals.tag_detection_index
    )
    for ours, theirs in [
        (joint.map.residuals.tag_chi2.sum(), reference.map.residuals.tag_chi2.sum()),
        (joint.map.residuals.odometry_chi2.sum(), reference.map.residuals.odometry_chi2.sum()),
    ]:
        assert abs(ours - theirs) <= 0.01 * theirs
    assert joint.map.warnings == reference.map.warnings
    assert joint.map.detections_used == reference.map.detections_used
    for ours, theirs in zip(joint.parts, reference.parts, strict=True):
        assert ours.pose_rows == theirs.pose_rows
        assert ours.detection_rows == theirs.detection_rows
        assert ours.tag_ids == theirs.tag_ids
        assert ours.detections_used == theirs.detections_used
        assert ours.alignment.shared_tags == theirs.alignment.shared_tags
        assert ours.alignment.inlier_tags == theirs.alignment.inlier_tags
        assert ours.redundancy_gain == theirs.redundancy_gain
        assert abs(ours.cost_joint - theirs.cost_joint) <= 0.01 * theirs.cost_joint
        assert ours.cost_alone == theirs.cost_alone
        assert ours.disagreement_factor == 1.0
        assert ours.weighting.startswith("weighed by its own noise")
        # every walk's fit was at hand (given to the build, the fourth's made by the add): its
        # map alone is the report's
        assert ours.fit is not None
        assert theirs.fit is not None
        assert ours.alone is ours.fit.alone
        assert ours.fit.cost == theirs.fit.cost


def stored(building: IsamBuilding) -> IsamState:
    """``building``'s state as the database gives it back (rows and ``.npz`` bytes)."""
    state = building.state()
    rows = [w.to_dict() for w in state.walks]
    return IsamState.from_dict(state.to_dict(), [IsamWalkState.from_dict(r) for r in rows])


def test_walks_restored_from_the_state_are_served_without_their_maps_alone():
    built, _ = IsamBuilding.build(walks()[:3], PARAMS, fits=fits())
    state = stored(built)
    for ours, theirs in zip(state.walks, built.walks, strict=True):  # each walk's own tags kept
        assert ours.alone_tag_poses().keys() == theirs.alone_tags.keys()
        for t, pose in theirs.alone_tags.items():
            np.testing.assert_allclose(ours.alone_tag_poses()[t], pose, atol=1e-12)
    restored, _ = IsamBuilding.restore(state, walks()[:3], PARAMS)
    joint = served_after_adding_the_fourth(restored)
    within_bounds(joint, batch(EVERYONE))
    assert [p.alone is None for p in joint.parts] == [True, True, True, False]
    assert [p.noise is None for p in joint.parts] == [True, True, True, False]


def test_a_walk_the_batch_build_would_down_weight_is_left_to_it():
    """A walk whose cost in the map is far beyond what its own noise explains (here: its cost
    alone recorded 1,000 lower than it was) is down-weighted by the batch build's step 6, which
    the engine does not make: the version is the batch build's."""
    built, _ = IsamBuilding.build(walks()[:3], PARAMS, fits=fits())
    state = stored(built)
    lowered = tuple(
        dataclasses.replace(w, cost_alone=w.cost_alone - 1000.0) if w.walk_id == "w2" else w
        for w in state.walks
    )
    restored, _ = IsamBuilding.restore(dataclasses.replace(state, walks=lowered), walks()[:3])
    served = restored.add(walks()[3])
    reason = served_joint_map(restored, served, PARAMS)
    assert isinstance(reason, str)
    prefix = "w2 would be down-weighted ×"
    assert reason.startswith(prefix)
    # step 6's factor: its excess over its cost alone, over the redundancy it gained
    w2 = batch(EVERYONE).part("w2")
    expected = (w2.cost_joint - (w2.cost_alone - 1000.0)) / w2.redundancy_gain
    assert abs(float(reason.removeprefix(prefix)) - expected) <= 0.01 * expected


def test_the_scale_test_made_in_the_tree_keeps_a_scale_where_the_batch_build_keeps_it():
    """Five 2-minute walks, the last with odometry 2% long: its candidate ×0.983 is tested in
    the tree (its factors swapped for scaled ones and back), and the map's cost drops by what
    the batch build's own test measures, so the batch build makes the version (and rescales
    it); the tree is left where it was."""
    building = simulate_building_sessions(
        SimulationConfig(num_poses=1200, seed=0),
        count=5,
        styles=(WalkStyle(),) * 4 + (WalkStyle(odom_scale_error=0.02),),
    )
    five = [
        Walk(walk_id=f"v{k + 1}", session=parse_session(s.upload))
        for k, s in enumerate(building.sessions)
    ]
    engine, _ = IsamBuilding.build(five[:4], PARAMS)
    served = engine.add(five[4])
    reason = served_joint_map(engine, served, PARAMS)
    assert isinstance(reason, str)
    prefix = "v5's odometry would be rescaled ×0.983 (the map's χ² drops by "
    assert reason.startswith(prefix)
    drop = float(reason.removeprefix(prefix).removesuffix(")"))
    batch_map = optimize_sessions(
        [w.session for w in five],
        PARAMS,
        names=[w.walk_id for w in five],
        fits=[w.fit for w in engine.walks if w.fit is not None],
    )
    v5 = batch_map.part("v5")
    assert round(v5.alignment.odometry_scale, 3) == 0.983
    batch_drop = float(v5.weighting.split("the map's cost fell by ")[1].split(")")[0])
    assert abs(drop - batch_drop) <= 0.05 * batch_drop
    after = engine.served()
    assert np.abs(after.map_T_tag[:, :3, 3] - served.map_T_tag[:, :3, 3]).max() <= 1e-3
