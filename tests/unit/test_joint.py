"""Maps of several sessions (app/domain/mapping/joint.py): alignment, the joint graph, its
evaluation."""

from __future__ import annotations

import dataclasses
import itertools
import math
from functools import cache
from pathlib import Path

import numpy as np
import pytest

from app.domain.errors import InvisibleMapError
from app.domain.evaluation.ground_truth import load_ground_truth
from app.domain.evaluation.metrics import (
    joint_shift_metric,
    largest_tag_distance_m,
    shift_metric,
    tag_rmse_m,
)
from app.domain.evaluation.simulate import SimulationConfig
from app.domain.evaluation.simulate_building import (
    MIXED_WALKS,
    SimulatedBuilding,
    WalkStyle,
    simulate_building_sessions,
)
from app.domain.evaluation.table import evaluate_joint
from app.domain.frames import FloatArray, make_pose, rotation_about_y
from app.domain.mapping.joint import (
    MIN_SCALE_PARALLAX_M2,
    AlignmentError,
    JointMap,
    align_session,
    keep_poses,
    optimize_sessions,
    sighting_burst_sizes,
    tag_depth_fit,
    tag_depth_scale,
    yaw_of,
)
from app.domain.mapping.joint.alignment import _best_candidate
from app.domain.mapping.params import SlamParams
from app.domain.mapping.slam import optimize_session
from app.domain.upload.session import Session, load_session, parse_session

DATA_DIR = Path(__file__).parents[2] / "data"

#: A building frame turned by 0.7 rad about +y and moved.
MAP_T_WORLD = make_pose(rotation_about_y(0.7), [12.0, 0.3, -40.0])


def tags_at(positions: dict[int, tuple[float, float, float]], yaw: float = 0.0) -> dict:
    return {t: make_pose(rotation_about_y(yaw), p) for t, p in positions.items()}


SOME_TAGS = {1: (0.0, 1.4, 0.0), 2: (8.0, 1.5, 0.5), 3: (8.5, 1.3, 12.0), 4: (-3.0, 1.4, 9.0)}


# --------------------------------------------------------------------------- alignment


def test_yaw_of_a_turn_about_y():
    for angle in (-3.0, -0.5, 0.0, 1.2, 3.1):
        assert yaw_of(rotation_about_y(angle)) == pytest.approx(angle, abs=1e-12)


def test_alignment_recovers_a_turn_and_a_move():
    world_T_tag = tags_at(SOME_TAGS)
    map_T_tag = {t: MAP_T_WORLD @ pose for t, pose in world_T_tag.items()}
    alignment = align_session("b", world_T_tag, map_T_tag)
    np.testing.assert_allclose(alignment.map_T_world, MAP_T_WORLD, atol=1e-9)
    assert alignment.shared_tags == (1, 2, 3, 4)
    assert alignment.inlier_tags == (1, 2, 3, 4)
    assert alignment.outlier_tags == ()


def test_alignment_survives_a_moved_tag_and_names_it():
    world_T_tag = tags_at(SOME_TAGS)
    map_T_tag = {t: MAP_T_WORLD @ pose for t, pose in world_T_tag.items()}
    map_T_tag[3] = make_pose(rotation_about_y(2.0), map_T_tag[3][:3, 3] + [3.0, 0.0, -2.0])
    alignment = align_session("b", world_T_tag, map_T_tag)
    np.testing.assert_allclose(alignment.map_T_world, MAP_T_WORLD, atol=1e-9)
    assert alignment.outlier_tags == (3,)
    assert alignment.residual_m[2] == pytest.approx(math.hypot(3.0, 2.0), abs=1e-9)


@pytest.mark.parametrize("seed", range(20))
def test_the_candidate_turns_scored_at_once_choose_as_one_by_one(seed):
    """``_best_candidate`` against the plain loop it replaced: each turn placed by the median
    offset, most tags within 1 m first, then the smallest median residual, the first such; on
    noisy tags with outliers and with repeated candidates (ties)."""
    rng = np.random.default_rng(seed)
    world_p = rng.uniform(-20, 20, (9, 3))
    map_p = world_p @ rotation_about_y(0.7).T + [12.0, 0.3, -40.0]
    map_p += rng.normal(0, 0.1 + 0.1 * (seed % 10), map_p.shape)  # up to σ 1 m: inliers matter
    map_p[: seed % 4] += rng.uniform(-5, 5, (seed % 4, 3))  # moved tags
    candidates = [float(y) for y in rng.uniform(-math.pi, math.pi, 30)]
    candidates += [0.7, 0.7, *(0.7 + rng.normal(0, 0.05, 10))]
    best = None
    for k, yaw in enumerate(candidates):
        R = rotation_about_y(yaw)
        residual = np.linalg.norm(
            world_p @ R.T + np.median(map_p - world_p @ R.T, axis=0) - map_p, axis=1
        )
        score = (int(np.sum(residual <= 1.0)), -float(np.median(residual)))
        if best is None or score > best[0]:
            best = (score, k)
    assert best is not None
    assert _best_candidate(candidates, world_p, map_p, 1.0) == best[1]


@pytest.mark.parametrize(
    ("session_tags", "reason"),
    [({7: (0, 1, 0), 8: (5, 1, 0)}, "no_shared_tags"), ({1: (0, 1.4, 0)}, "too_few_shared_tags")],
)
def test_alignment_refuses_too_little_overlap(session_tags, reason):
    with pytest.raises(AlignmentError) as raised:
        align_session("b", tags_at(session_tags), tags_at(SOME_TAGS))
    assert raised.value.reason == reason
    assert raised.value.dataset == "b"
    assert "'b'" in str(raised.value)


def test_alignment_refuses_inconsistent_shared_tags():
    """Two shared tags, 8 m apart in the map and 20 m apart in the session: no placement fits
    both within 1 m, and the error lists each tag's distance."""
    session = tags_at({1: (0.0, 1.4, 0.0), 2: (20.0, 1.4, 0.0)})
    with pytest.raises(AlignmentError) as raised:
        align_session("b", session, tags_at(SOME_TAGS))
    assert raised.value.reason == "inconsistent_shared_tags"
    assert "1: " in raised.value.detail
    assert "2: " in raised.value.detail


# --------------------------------------------------------------------------- simulated walks


@cache
def building(count: int = 4) -> SimulatedBuilding:
    return simulate_building_sessions(SimulationConfig(num_poses=800, seed=5), count=count)


@cache
def walks() -> tuple[Session, ...]:
    return tuple(parse_session(s.upload) for s in building().sessions)


def test_simulated_walks_have_their_own_frames():
    sim = building()
    assert sim.world_T_building[0] == pytest.approx(np.eye(4))
    for frame in sim.world_T_building[1:]:
        assert frame[:3, 1] == pytest.approx([0, 1, 0])  # gravity-aligned
        assert np.linalg.norm(frame[:3, 3]) > 1.0
    assert len({s.config.seed for s in sim.sessions}) == len(sim.sessions)


def test_one_session_makes_the_map_optimize_session_makes():
    session = walks()[0]
    joint = optimize_sessions([session], names=["only"])
    alone = optimize_session(session)
    np.testing.assert_allclose(joint.map.world_T_tag, alone.world_T_tag, atol=1e-9)
    assert joint.parts[0].pose_rows == slice(0, session.num_poses)


def test_joint_map_of_simulated_walks_beats_each_walk_alone():
    sessions = walks()
    truth = building().world_T_tag_true
    joint = optimize_sessions(sessions)
    assert joint.map.world_T_phone.shape[0] == sum(s.num_poses for s in sessions)
    # no odometry across sessions: the boundary pairs carry no factor
    starts = [p.pose_rows.start for p in joint.parts[1:]]
    keyframes = joint.map.residuals.keyframe_index
    for start in starts:
        k = int(np.flatnonzero(keyframes == start)[0])
        assert joint.map.residuals.odometry_chi2[k - 1] == 0.0
    for part, session in zip(joint.parts, sessions, strict=True):
        alone = optimize_session(session).tag_poses()
        mine = joint.session_tag_poses(part.dataset)
        assert tag_rmse_m(mine, truth) < tag_rmse_m(alone, truth), part.dataset
    # the pose ids stay unique (the app's format keys vertices by them)
    assert np.unique(joint.map.pose_id).size == joint.map.pose_id.size


def test_the_map_does_not_depend_on_the_session_order_beyond_its_frame():
    """Uniform walks, forward and backward: the same tags to 1 cm after a rigid fit (the frame is
    the first walk's)."""
    sessions = walks()[:3]
    forward = optimize_sessions(sessions, names=["a", "b", "c"])
    backward = optimize_sessions(sessions[::-1], names=["c", "b", "a"])
    assert next(p.dataset for p in backward.parts) == "c"
    assert largest_tag_distance_m(forward.map.tag_poses(), backward.map.tag_poses()) < 0.01


def test_a_session_that_shares_nothing_is_refused_with_its_reason():
    other_building = simulate_building_sessions(SimulationConfig(num_poses=300, seed=9), count=1)
    stranger = parse_session(other_building.sessions[0].upload)
    stranger = _renumbered_tags(stranger, offset=10_000)
    with pytest.raises(AlignmentError) as raised:
        optimize_sessions([walks()[0], stranger], names=["home", "stranger"])
    assert (raised.value.dataset, raised.value.reason) == ("stranger", "no_shared_tags")


def test_a_moved_tag_in_one_session_does_not_drag_the_map():
    """Walk b saw one shared tag 2.5 m from where walk a saw it (moved between the walks): after
    the joint optimization b's sightings of it disagree beyond b's noise, so they get a landmark
    of their own (named in the warnings), in either order, and the map keeps a's tag."""
    sessions = list(walks()[:2])
    truth = building().world_T_tag_true
    shared = sorted(set(sessions[0].tag_ids) & set(sessions[1].tag_ids))
    moved_tag = shared[0]
    sessions[1] = _moved_tag(sessions[1], moved_tag, offset_m=(2.5, 0.0, 0.0))
    # the corners were not moved with the pose: keep screening from rejecting the sightings
    params = SlamParams(max_reprojection_px=1e6, max_distance_m=100.0)
    joint = optimize_sessions(sessions, params, names=["a", "b"])
    assert joint.parts[1].local_tags == (moved_tag,)
    assert joint.parts[0].local_tags == ()
    assert moved_tag not in joint.parts[1].tag_ids
    assert any(f"tags {moved_tag} (" in w for w in joint.map.warnings)
    backward = optimize_sessions(sessions[::-1], params, names=["b", "a"])
    assert backward.part("b").local_tags == (moved_tag,)
    assert largest_tag_distance_m(joint.map.tag_poses(), backward.map.tag_poses()) < 0.01
    clean = optimize_sessions(list(walks()[:2]), params, names=["a", "b"])
    error_m = np.linalg.norm(
        joint.map.tag_poses()[moved_tag][:3, 3] - clean.map.tag_poses()[moved_tag][:3, 3]
    )
    assert error_m < 0.2
    assert tag_rmse_m(joint.map.tag_poses(), truth) < 0.2


def test_a_session_in_the_map_twice_is_refused():
    with pytest.raises(InvisibleMapError, match="twice"):
        optimize_sessions([walks()[0], walks()[0]], names=["a", "a"])
    with pytest.raises(InvisibleMapError, match="at least one"):
        optimize_sessions([])


def test_depth_scale_is_one_when_the_sizes_are_right_and_found_when_wrong():
    session = walks()[0]
    assert tag_depth_scale(session) == 1.0
    shrunk = _scaled_depths(session, 0.8)  # as if the app had assumed a smaller tag
    assert tag_depth_scale(shrunk) == pytest.approx(1 / 0.8, rel=0.05)


def test_depth_fit_reads_the_factor_and_the_parallax_it_rests_on():
    """The fit behind ``tag_depth_scale``: what it reads whatever its size, and the parallax
    (Σ‖Δ camera-to-tag vector‖² over the pairs of sightings, m²), which scales with the depths'
    square; one sighting per tag gives no pair and no parallax."""
    session = walks()[0]
    fit, parallax_m2 = tag_depth_fit(session)
    shrunk_fit, shrunk_parallax_m2 = tag_depth_fit(_scaled_depths(session, 0.8))
    assert parallax_m2 > MIN_SCALE_PARALLAX_M2
    assert shrunk_fit == pytest.approx(fit / 0.8, rel=1e-9)
    assert shrunk_parallax_m2 == pytest.approx(parallax_m2 * 0.8**2, rel=1e-9)
    tag_ids = session.detections.tag_id
    once = np.zeros(len(tag_ids), dtype=bool)
    once[np.unique(tag_ids, return_index=True)[1]] = True  # each tag's first sighting only
    assert tag_depth_fit(session, once) == (1.0, 0.0)
    assert tag_depth_scale(session, once) == 1.0


def test_joint_shift_metric_uses_each_session_in_its_own_frame():
    sessions = walks()[:2]
    joint = optimize_sessions(sessions, names=["a", "b"])
    moved = dataclasses.replace(sessions[1], world_T_phone=MAP_T_WORLD @ sessions[1].world_T_phone)
    again = optimize_sessions([sessions[0], moved], names=["a", "b"])
    # the same map up to LM's tolerance, and the same metric
    assert joint_shift_metric(again) == pytest.approx(joint_shift_metric(joint), rel=1e-4)
    per_session = [
        shift_metric(s, joint.map.tag_poses(), detection_mask=m)
        for s, m in zip(sessions, joint.session_masks(), strict=True)
    ]
    assert min(per_session) <= joint_shift_metric(joint) <= max(per_session)


def test_evaluate_joint_reports_each_session_and_the_whole():
    sessions = walks()[:3]
    names = ["a", "b", "c"]
    truth = building().world_T_tag_true
    alone = {n: optimize_session(s) for n, s in zip(names, sessions, strict=True)}
    joint = optimize_sessions(sessions, names=names)
    evaluation = evaluate_joint(joint, alone, truth)
    out = evaluation.to_dict()
    assert out["dataset"] == "joint"
    assert out["tags"] == len(joint.map.tag_ids)
    assert out["poses"] == sum(s.num_poses for s in sessions)
    assert set(out["by_session"]) == set(names)
    for name in names:
        row = out["by_session"][name]
        assert set(row) >= {
            "gt_metric_alone",
            "gt_metric_joint",
            "tag_rmse_alone_m",
            "tag_rmse_joint_m",
        }
        assert row["tag_rmse_joint_m"] < row["tag_rmse_alone_m"]
    assert out["shift_opt"] == pytest.approx(joint_shift_metric(joint))


def test_simulated_joint_error_falls_as_walks_are_added():
    sim = simulate_building_sessions(SimulationConfig(num_poses=1200), count=5)
    sessions = [parse_session(s.upload) for s in sim.sessions]
    five = optimize_sessions(sessions)
    fits = [part.fit for part in five.parts if part.fit is not None]  # each walk alone, once
    errors = [
        tag_rmse_m(optimize_sessions(sessions[:n], fits=fits).map.tag_poses(), sim.world_T_tag_true)
        for n in (1, 2)
    ]
    errors.append(tag_rmse_m(five.map.tag_poses(), sim.world_T_tag_true))
    assert errors[0] > errors[1] > errors[2]


# ------------------------------------------------------------------ each walk its own noise


@cache
def clean_and_noisy() -> tuple[tuple[Session, ...], JointMap]:
    """Two short walks of one building (500 poses each, tags 11–13 seen by both): one as
    configured, one with every noise σ 3× larger; their joint map."""
    sim = simulate_building_sessions(
        SimulationConfig(num_poses=500, seed=0),
        count=2,
        styles=(WalkStyle(), WalkStyle(noise_scale=3.0)),
    )
    sessions = tuple(parse_session(s.upload) for s in sim.sessions)
    return sessions, optimize_sessions(sessions, names=["clean", "noisy"])


#: The walks' noise estimates alone (``noise.COMPONENTS`` order: odometry linear, angular, tag
#: position, orientation), as measured on this building (gtsam 4.3.0).
CLEAN_NOISE_SCALES = [0.42560, 0.77789, 0.45281, 0.031650]
NOISY_NOISE_SCALES = [1.64352, 1.11438, 3.92413, 0.087889]


def test_each_walk_is_weighed_by_its_own_noise():
    """Issue 25's rule, fast (the real-data test is @slow): each walk's variances in the
    building map are its own noise estimate, from its own residuals alone, so the noisy walk
    weighs less than the clean one where they share tags; neither is down-weighted, because its
    own noise explains its disagreement with the other."""
    sessions, joint = clean_and_noisy()
    clean, noisy = joint.part("clean"), joint.part("noisy")
    assert sorted(set(clean.tag_ids) & set(noisy.tag_ids)) == [11, 12, 13]
    np.testing.assert_allclose(clean.noise_scales, CLEAN_NOISE_SCALES, rtol=1e-4)
    np.testing.assert_allclose(noisy.noise_scales, NOISY_NOISE_SCALES, rtol=1e-4)
    assert np.all(noisy.noise_scales > clean.noise_scales)  # every σ larger: a smaller weight
    for part, session in zip((clean, noisy), sessions, strict=True):
        # its own estimate: the same as in a map of that walk alone
        (alone,) = optimize_sessions([session], names=[part.dataset]).parts
        assert alone.noise is not None
        assert part.noise is not None
        np.testing.assert_allclose(part.noise.scales, alone.noise.scales, rtol=1e-9)
        assert part.fit is not None
        np.testing.assert_array_equal(part.noise_scales, part.fit.noise_scales)
        assert part.disagreement_factor == 1.0
    assert clean.weighting == (
        "weighed by its own noise: its cost grew by 1.8 on joining, for 1.0 degrees of freedom "
        "gained, which that noise explains"
    )
    assert noisy.weighting == (
        "weighed by its own noise: its cost grew by 5.3 on joining, for 14.2 degrees of freedom "
        "gained, which that noise explains"
    )


# --------------------------------------------------------------------------- walks that differ


@cache
def mixed() -> SimulatedBuilding:
    """Issue 25's building: a walk as configured, one 3× noisier, one whose odometry runs 2%
    long, one walked obliquely to the tags (2 minutes each)."""
    return simulate_building_sessions(
        SimulationConfig(num_poses=1200, seed=0), count=4, styles=MIXED_WALKS
    )


@cache
def mixed_maps() -> tuple[JointMap, ...]:
    """The mixed building's joint map with each walk first (cold builds; the walks' own fits,
    which depend on nothing but the walk, made once)."""
    sessions = [parse_session(s.upload) for s in mixed().sessions]
    names = [style.label for style in mixed().styles]
    first = optimize_sessions(sessions, names=names)
    fits = [part.fit for part in first.parts if part.fit is not None]
    maps = [first]
    for k in range(1, 4):
        order = [*range(k, 4), *range(k)]
        maps.append(
            optimize_sessions(
                [sessions[i] for i in order], names=[names[i] for i in order], fits=fits
            )
        )
    return tuple(maps)


def test_walks_that_differ_make_one_map_whichever_comes_first():
    """Issue 25's permutation test: the same map (tags within 1 cm after a rigid fit) with each
    walk first; before issue 25 this building's maps differed by 7 mm to 18 cm by order
    (seeds 0–3), and which walk's sightings of a shared tag were set apart depended on it."""
    maps = mixed_maps()
    assert [m.parts[0].dataset for m in maps] == [s.label for s in mixed().styles]
    for other in maps[1:]:
        assert largest_tag_distance_m(maps[0].map.tag_poses(), other.map.tag_poses()) < 0.01
        for part in other.parts:
            first = maps[0].part(part.dataset)
            assert part.local_tags == first.local_tags
            assert part.alignment.odometry_scale == pytest.approx(
                first.alignment.odometry_scale, rel=1e-9
            )


#: Why each walk of the mixed building weighs what it does (measured; gtsam 4.3.0).
MIXED_WEIGHTING = {
    "as configured": (
        "weighed by its own noise: its cost grew by 24.1 on joining, for 54.6 degrees of freedom "
        "gained, which that noise explains"
    ),
    "3× noisier": (
        "weighed by its own noise: its cost grew by 61.2 on joining, for 81.0 degrees of freedom "
        "gained, which that noise explains; its odometry scale against the other walks' (1.0120) "
        "was tested and not used: the map's cost rose by 1.6, which a drift explains as well"
    ),
    "odometry +2%": (
        "weighed by its own noise: its cost grew by 22.1 on joining, for 45.2 degrees of freedom "
        "gained, which that noise explains; its odometry lengths ×0.9840 (they ran 1.6% long "
        "against the other walks'; the map's cost fell by 66.6)"
    ),
    "oblique to the tags": (
        "weighed by its own noise: its cost grew by 27.5 on joining, for 53.2 degrees of freedom "
        "gained, which that noise explains"
    ),
}
#: Their noise estimates (``noise.COMPONENTS`` order), each from the walk alone: the 3× noisier
#: walk's odometry and tag position variances the largest.
MIXED_NOISE_SCALES = [
    [0.382009, 0.332796, 0.442888, 0.0162109],
    [7.20805, 0.577895, 3.54407, 0.0740272],
    [0.474817, 0.412661, 0.372108, 0.0162474],
    [0.563211, 0.462994, 0.476186, 0.0296446],
]


def test_no_walk_of_the_mixed_building_is_worse_in_the_building_map():
    """Every walk's own tags, against the truth: no worse than alone (before issue 25 the walk as
    configured got 8% worse); the walk whose odometry runs 2% long is found and rescaled; the
    reasons are there to read."""
    joint = mixed_maps()[0]
    truth = mixed().world_T_tag_true
    for part in joint.parts:
        assert part.alone is not None
        alone = part.alone.tag_poses()
        mine = {t: pose for t, pose in joint.map.tag_poses().items() if t in alone}
        assert tag_rmse_m(mine, truth) < tag_rmse_m(alone, truth), part.dataset
        # weighed by its own noise (estimated alone), none down-weighted
        assert part.noise is not None
        np.testing.assert_array_equal(part.noise_scales, part.noise.scales)
        assert part.disagreement_factor == 1.0
    assert {part.dataset: part.weighting for part in joint.parts} == MIXED_WEIGHTING
    np.testing.assert_allclose(
        [part.noise_scales for part in joint.parts], MIXED_NOISE_SCALES, rtol=1e-4
    )
    long_walk = joint.part("odometry +2%")
    assert long_walk.alignment.odometry_scale == pytest.approx(1 / 1.02, abs=0.005)
    assert joint.part("as configured").alignment.odometry_scale == 1.0
    assert set(joint.timings_ms) >= {"walks_alone", "placing", "joint_optimize", "marginals"}


def test_five_walks_of_one_floor_are_each_better_than_alone():
    """Issue 25's target for five walks of one floor (at least 4 of 5 better than alone), with
    known truth, as only three real walks of floor 2 ship: the mixed building and a fifth walk
    as configured (bench/multi_session.py table 3b: 5 of 5 on seeds 0–2). This building makes
    5 of 5, and the test holds it to that."""
    building = simulate_building_sessions(
        SimulationConfig(num_poses=1200, seed=0), count=5, styles=MIXED_WALKS
    )
    sessions = [parse_session(s.upload) for s in building.sessions]
    joint = optimize_sessions(sessions, names=[f"walk {k}" for k in range(5)])
    not_better = []
    for part in joint.parts:
        assert part.alone is not None
        alone = part.alone.tag_poses()
        mine = {t: pose for t, pose in joint.map.tag_poses().items() if t in alone}
        if tag_rmse_m(mine, building.world_T_tag_true) >= tag_rmse_m(
            alone, building.world_T_tag_true
        ):
            not_better.append(part.dataset)
    assert not_better == []  # 5 of 5 (measured: 0.047–0.039 m joint against 0.076–0.35 m alone)


def test_a_new_version_started_from_the_last_is_the_map_a_cold_build_makes():
    """The warm start (issue 25, item 5): the walks of the last version are not optimized alone
    again and LM starts from its optimum; the map is the cold build's."""
    sessions = [parse_session(s.upload) for s in mixed().sessions]
    names = [style.label for style in mixed().styles]
    cold = mixed_maps()[0]
    fits = [part.fit for part in cold.parts if part.fit is not None]
    previous = optimize_sessions(sessions[:3], names=names[:3], fits=fits)
    warm = optimize_sessions(sessions, names=names, initial=previous)
    assert largest_tag_distance_m(cold.map.tag_poses(), warm.map.tag_poses()) < 0.01
    for old, new in zip(previous.parts, warm.parts, strict=False):
        assert new.fit is old.fit  # not optimized alone again
    assert warm.parts[3].fit is not None
    assert warm.parts[3].fit is not fits[3]  # a walk new to the map is
    assert warm.map.stats.iterations <= cold.map.stats.iterations + 1


# --------------------------------------------------------------------------- real sessions


@pytest.mark.slow
def test_mac_building_sessions_are_never_made_worse_in_the_joint_map():
    """The three mac-building walks (straight_209_occam whole, both floors): no walk's own tags
    more than 5% worse than alone, on both measures (issue 25's target; measured: floor_2 −2%,
    desnat −54%, 209 +2.8% in tag RMSE); desnat_straight_once, whose odometry runs 3% long
    against the others and whose disagreement its own noise does not explain, is rescaled and
    down-weighted, and says why; floor_2_straight weighs as its own noise says."""
    names = ["floor_2_straight", "desnat_straight_once", "straight_209_occam"]
    sessions = [load_session(DATA_DIR / "sessions" / f"{n}.json") for n in names]
    truth = load_ground_truth(DATA_DIR / "ground_truth" / "rtabmap_mac_1_2.txt")
    alone = {n: optimize_session(s) for n, s in zip(names, sessions, strict=True)}
    joint = optimize_sessions(sessions, SlamParams(), names=names)
    evaluation = evaluate_joint(joint, alone, truth)
    for name, row in evaluation.by_session.items():
        assert row.gt_metric_joint <= 1.05 * row.gt_metric_alone, name
        assert row.tag_rmse_joint_m <= 1.05 * row.tag_rmse_alone_m, name
    desnat = joint.part("desnat_straight_once")
    assert desnat.disagreement_factor > 2
    assert desnat.alignment.odometry_scale == pytest.approx(0.97, abs=0.01)
    assert "down-weighted" in desnat.weighting
    assert "odometry lengths ×0.96" in desnat.weighting
    floor_2 = joint.part("floor_2_straight")
    assert floor_2.disagreement_factor == 1.0
    assert floor_2.weighting.startswith("weighed by its own noise")
    assert all(part.weighting for part in joint.parts)


@cache
def floor_2_walks() -> dict[str, Session]:
    """The shipped walks of the mac building's floor 2: floor_2_straight, desnat_straight_once,
    and the floor-2 part of straight_209_occam (the poses above −1 m of its world; the floor-1
    loop between leaves it, and the composed odometry across the gap is held as loosely as its
    500 s ask)."""
    occam = load_session(DATA_DIR / "sessions" / "straight_209_occam.json")
    return {
        "floor_2_straight": load_session(DATA_DIR / "sessions" / "floor_2_straight.json"),
        "desnat_straight_once": load_session(DATA_DIR / "sessions" / "desnat_straight_once.json"),
        "straight_209_occam floor 2": keep_poses(occam, occam.world_T_phone[:, 1, 3] > -1.0),
    }


@pytest.mark.slow
def test_the_floor_2_walks_make_one_map_in_any_order_and_no_walk_worse():
    """Every subset of two or three of the shipped floor-2 walks: no walk's own tags more than 5%
    worse than alone against the ground truth (tag RMSE; measured: worst +1.5%, floor_2_straight
    next to desnat_straight_once); and the three in another order (each walk in another place)
    give the same tags to 1 cm (measured 0.0 mm; every subset in every order:
    bench/multi_session.py, section 1)."""
    walks = floor_2_walks()
    names = list(walks)
    truth = load_ground_truth(DATA_DIR / "ground_truth" / "rtabmap_mac_1_2.txt")
    first = optimize_sessions([walks[n] for n in names], names=names)
    fits = [part.fit for part in first.parts if part.fit is not None]
    rotated = [*names[1:], names[0]]
    other = optimize_sessions([walks[n] for n in rotated], names=rotated, fits=fits)
    assert largest_tag_distance_m(first.map.tag_poses(), other.map.tag_poses()) < 0.01
    for size in (2, 3):
        for subset in itertools.combinations(walks, size):
            forward = (
                first
                if size == 3
                else optimize_sessions([walks[n] for n in subset], names=subset, fits=fits)
            )
            for part in forward.parts:
                assert part.alone is not None
                alone = {t: p for t, p in part.alone.tag_poses().items() if t in truth}
                joint = {t: p for t, p in forward.map.tag_poses().items() if t in alone}
                assert tag_rmse_m(joint, truth) <= 1.05 * tag_rmse_m(alone, truth), (
                    subset,
                    part.dataset,
                )


# --------------------------------------------------------------------------- helpers


def _renumbered_tags(session: Session, *, offset: int) -> Session:
    detections = dataclasses.replace(session.detections, tag_id=session.detections.tag_id + offset)
    return dataclasses.replace(session, detections=detections)


def _moved_tag(session: Session, tag_id: int, *, offset_m: tuple[float, float, float]) -> Session:
    """``session`` as if tag ``tag_id`` had hung ``offset_m`` away (world frame) when it was
    walked."""
    detections = session.detections
    rows = detections.tag_id == tag_id
    world_T_phone = session.world_T_phone[detections.pose_index[rows]]
    phone_t_offset = np.einsum("nji,j->ni", world_T_phone[:, :3, :3], np.asarray(offset_m))
    phone_T_tag = detections.phone_T_tag.copy()
    phone_T_tag[rows, :3, 3] += phone_t_offset
    camera_T_tag = detections.camera_T_tag.copy()
    camera_T_tag[rows, :3, 3] += phone_t_offset * [1.0, -1.0, -1.0]
    return dataclasses.replace(
        session,
        detections=dataclasses.replace(
            detections, phone_T_tag=phone_T_tag, camera_T_tag=camera_T_tag
        ),
    )


def _scaled_depths(session: Session, scale: float) -> Session:
    detections = session.detections
    phone_T_tag: FloatArray = detections.phone_T_tag.copy()
    camera_T_tag: FloatArray = detections.camera_T_tag.copy()
    phone_T_tag[:, :3, 3] *= scale
    camera_T_tag[:, :3, 3] *= scale
    return dataclasses.replace(
        session,
        detections=dataclasses.replace(
            detections, phone_T_tag=phone_T_tag, camera_T_tag=camera_T_tag
        ),
    )


def test_sighting_bursts_by_hand():
    session = walks()[0]
    used = np.ones(len(session.detections), dtype=bool)
    used[::7] = False
    sizes = sighting_burst_sizes(session, used)
    assert np.all(sizes[~used] == 1)
    detections = session.detections
    for tag_id in np.unique(detections.tag_id):
        rows = [r for r in np.argsort(detections.timestamp_s, kind="stable") if used[r]]
        rows = [r for r in rows if detections.tag_id[r] == tag_id]
        bursts: list[list[int]] = []
        for r in rows:
            if bursts and detections.timestamp_s[r] - detections.timestamp_s[bursts[-1][-1]] <= 3.0:
                bursts[-1].append(r)
            else:
                bursts.append([r])
        for burst in bursts:
            assert all(sizes[r] == len(burst) for r in burst)
    assert sizes[used].max() > 1  # the simulated phone sees a tag several times in a row
