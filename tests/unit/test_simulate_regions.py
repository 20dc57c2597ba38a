"""Issue 37: the simulator's switchable error sources, and the region analysis of a map.

The error sources are off by default (the simulator's other tests and every bench table keep
their numbers); each is checked to do what its docstring says and nothing else.
"""

from __future__ import annotations

import dataclasses
import itertools
import math

import numpy as np
import numpy.typing as npt
import pytest

from app.domain.errors import ParameterError
from app.domain.evaluation.regions import (
    Region,
    connecting_stretches,
    fitted_rmse_m,
    odometry_end_error,
    odometry_pair_error,
    region_errors,
    tag_regions,
    transfer_rmse_m,
    umeyama_similarity,
)
from app.domain.evaluation.simulate import (
    APPROACH_GAP_S,
    REGION_ERROR_SOURCES,
    SimulatedSession,
    SimulationConfig,
    approach_ids,
    simulate_session,
    stairs_traversals,
)
from app.domain.frames import FloatArray, make_pose, rotation_about_y, so3_log
from app.domain.upload.session import parse_session

TWO_FLOORS = SimulationConfig(num_poses=2400, two_floors=True, seed=3)
#: Every noise of the simulator off, so that only the source under test errs.
SILENT = {
    "odom_translation_drift_m_per_sqrt_s": 0.0,
    "odom_vertical_drift_m_per_sqrt_s": 0.0,
    "odom_rotation_drift_rad_per_sqrt_s": 0.0,
    "odom_tilt_error_rad": 0.0,
    "tag_position_noise_m_at_1m": 0.0,
    "tag_rotation_noise_rad": 0.0,
    "corner_noise_px": 0.0,
}


@pytest.fixture(scope="module")
def plain() -> SimulatedSession:
    return simulate_session(TWO_FLOORS)


def _steps_m(world_T_phone: FloatArray) -> FloatArray:
    return np.asarray(np.linalg.norm(np.diff(world_T_phone[:, :3, 3], axis=0), axis=1))


def _approaches(sim: SimulatedSession) -> npt.NDArray[np.int64]:
    gap = round(APPROACH_GAP_S * sim.config.rate_hz)
    return approach_ids(sim.detection_pose_index, sim.detection_tag_id, gap)


def test_the_sources_are_off_by_default() -> None:
    config = SimulationConfig(num_poses=10)
    for source in REGION_ERROR_SOURCES.values():
        for name, value in source.items():
            default = getattr(config, name)
            assert default != value, f"{name}: the source must change its default"
    assert config.max_floor_changes is None
    assert config.sightings_per_approach == 0


def test_stairs_errors_change_the_odometry_on_the_stairs_only(plain: SimulatedSession) -> None:
    config = dataclasses.replace(
        TWO_FLOORS, stairs_scale_error_sigma=0.05, stairs_yaw_error_rad=0.1
    )
    erring = simulate_session(config)
    # the walk and what it saw do not change, nor the odometry before the stairs
    np.testing.assert_array_equal(erring.world_T_phone_true, plain.world_T_phone_true)
    assert erring.upload["tag_data"] == plain.upload["tag_data"]
    traversals = stairs_traversals(config, plain.world_T_phone_true)
    assert traversals, "the walk must take the stairs"
    first = traversals[0].start
    np.testing.assert_array_equal(
        erring.world_T_phone_odometry[: first + 1], plain.world_T_phone_odometry[: first + 1]
    )
    # without the random walk, a step's length changes only on the stairs (the scale error); the
    # heading error turns the later steps without changing their lengths
    silent = dataclasses.replace(config, **SILENT)  # type: ignore[arg-type]
    before = _steps_m(silent_twin(silent).world_T_phone_odometry)
    after = _steps_m(simulate_session(silent).world_T_phone_odometry)
    on_stairs = np.zeros(config.num_poses - 1, dtype=bool)
    for run in traversals:
        on_stairs[run] = True
    np.testing.assert_allclose(after[~on_stairs], before[~on_stairs], atol=1e-9)
    assert np.max(np.abs(after[on_stairs] / before[on_stairs] - 1)) > 1e-3
    later = traversals[-1].stop + 1
    yaw = so3_log(
        erring.world_T_phone_odometry[later:, :3, :3]
        @ np.swapaxes(plain.world_T_phone_odometry[later:, :3, :3], 1, 2)
    )
    assert np.min(np.abs(yaw[:, 1])) > 1e-4  # turned about gravity after the stairs


def silent_twin(config: SimulationConfig) -> SimulatedSession:
    """``config``'s walk with issue 37's odometry sources off."""
    return simulate_session(
        dataclasses.replace(
            config,
            stairs_scale_error_sigma=0.0,
            stairs_yaw_error_rad=0.0,
            fast_turn_yaw_error_ratio=0.0,
        )
    )


def test_a_link_errs_on_the_stairs_alone() -> None:
    """With every other noise off, the odometry is exact up to the stairs and its error across
    them is the stairs' own: the analysis finds it, and fits the start perfectly."""
    silent = dataclasses.replace(TWO_FLOORS, max_floor_changes=1, **SILENT)  # type: ignore[arg-type]
    for scale, yaw_rad in ((0.0, 0.0), (0.05, 0.08)):
        config = dataclasses.replace(
            silent, stairs_scale_error_sigma=scale, stairs_yaw_error_rad=yaw_rad
        )
        sim = simulate_session(config)
        session = parse_session(sim.upload)
        truth = sim.world_T_tag_true
        regions = tag_regions({t: truth[t] for t in sim.detected_tag_ids})
        links = connecting_stretches(session, regions, level="floor")
        assert len(links) == 1, "one change of floor, one link"
        end = odometry_end_error(session, links[0], truth)
        pair = odometry_pair_error(session, links[0], truth)
        assert end is not None
        assert end.fit_rms_m < 1e-6
        assert len(end.after_tags) >= 2
        if scale == 0.0:
            assert end.position_m < 1e-6
            assert abs(end.yaw_deg) < 1e-6
            assert pair.position_m < 1e-6
            assert pair.rotation_deg < 1e-4
        else:
            assert end.position_m > 0.01
            assert abs(end.yaw_deg) > 0.1
            assert pair.rotation_deg > 0.1


def test_max_floor_changes_limits_the_links() -> None:
    long_walk = dataclasses.replace(TWO_FLOORS, num_poses=6000)
    free = simulate_session(long_walk)
    once = simulate_session(dataclasses.replace(long_walk, max_floor_changes=1))
    assert len(stairs_traversals(long_walk, free.world_T_phone_true)) >= 2
    assert len(stairs_traversals(long_walk, once.world_T_phone_true)) == 1
    with pytest.raises(ParameterError, match="max_floor_changes"):
        SimulationConfig(num_poses=10, max_floor_changes=-1)


def test_sightings_per_approach_keeps_the_first_of_each(plain: SimulatedSession) -> None:
    glancing = simulate_session(dataclasses.replace(TWO_FLOORS, sightings_per_approach=2))
    approach = _approaches(glancing)
    assert np.bincount(approach).max() <= 2
    all_sightings = set(zip(plain.detection_pose_index.tolist(), plain.detection_tag_id.tolist(),
                            strict=True))  # fmt: skip
    kept = list(zip(glancing.detection_pose_index.tolist(), glancing.detection_tag_id.tolist(),
                    strict=True))  # fmt: skip
    assert set(kept) <= all_sightings
    # every approach is still there, with its first sightings
    assert approach.max() == _approaches(plain).max()
    assert len(kept) < len(all_sightings)


def test_approach_bias_persists_through_an_approach() -> None:
    config = dataclasses.replace(
        TWO_FLOORS,
        approach_bias_rotation_rad=0.05,
        **SILENT,  # type: ignore[arg-type]
    )
    sim = simulate_session(config)
    approach = _approaches(sim)
    measured = np.array(
        [np.array(d["tag_pose"]).reshape(4, 4) for frame in sim.upload["tag_data"] for d in frame]
    )
    error = so3_log(measured[:, :3, :3] @ np.swapaxes(sim.camera_T_tag_true[:, :3, :3], 1, 2))
    spread_within, between = [], []
    for a in np.unique(approach):
        rows = np.flatnonzero(approach == a)
        spread_within.append(float(np.ptp(error[rows], axis=0).max()))
    for tag in np.unique(sim.detection_tag_id):
        firsts = [
            np.flatnonzero(approach == a)[0]
            for a in np.unique(approach[sim.detection_tag_id == tag])
        ]
        between += [
            float(np.linalg.norm(error[a] - error[b])) for a, b in itertools.pairwise(firsts)
        ]
    assert max(spread_within) < 1e-6  # one error per approach
    assert between, "some tag must be approached twice"
    assert np.median(between) > 0.02  # a fresh one on the next approach (σ 0.05 rad per axis)


def test_without_noise_silences_the_new_sources() -> None:
    on = {k: v for source in REGION_ERROR_SOURCES.values() for k, v in source.items()}
    quiet = dataclasses.replace(TWO_FLOORS, **on).without_noise()  # type: ignore[arg-type]
    assert quiet.stairs_scale_error_sigma == quiet.stairs_yaw_error_rad == 0.0
    assert quiet.fast_turn_yaw_error_ratio == 0.0
    assert quiet.approach_bias_rotation_rad == quiet.approach_bias_position_m_at_1m == 0.0
    # not noise: the walk and what it sees stay
    assert quiet.max_floor_changes == 1
    assert quiet.sightings_per_approach == 3


def test_fast_turn_errors_change_the_heading_where_the_phone_turns_fast() -> None:
    config = dataclasses.replace(TWO_FLOORS, fast_turn_yaw_error_ratio=0.05, **SILENT)  # type: ignore[arg-type]
    erring, twin = simulate_session(config), silent_twin(config)
    # lengths kept (no scale), heading changed
    np.testing.assert_allclose(
        _steps_m(erring.world_T_phone_odometry), _steps_m(twin.world_T_phone_odometry), atol=1e-9
    )
    yaw = so3_log(
        erring.world_T_phone_odometry[:, :3, :3]
        @ np.swapaxes(twin.world_T_phone_odometry[:, :3, :3], 1, 2)
    )[:, 1]
    assert np.max(np.abs(yaw)) > 1e-3
    np.testing.assert_allclose(twin.world_T_phone_odometry, twin.world_T_phone_true, atol=1e-9)


# --------------------------------------------------------------------------- regions


def _tag(x: float, y: float, z: float) -> FloatArray:
    return make_pose(np.eye(3), [x, y, z])


def two_floor_tags() -> dict[int, FloatArray]:
    """Eight tags along a corridor on each of two floors 3.5 m apart, and one on the landing."""
    tags = {k: _tag(0.0, 1.4, 4.0 * k) for k in range(8)}
    tags |= {10 + k: _tag(1.0, 4.9, 4.0 * k) for k in range(8)}
    tags[20] = _tag(2.0, 2.5, 0.0)  # nearer the lower floor
    return tags


def tags_with_a_landing() -> dict[int, FloatArray]:
    """:func:`two_floor_tags` with the landing's tag halfway up (1.75 m from either floor)."""
    tags = two_floor_tags()
    tags[20] = _tag(2.0, 3.15, 0.0)
    return tags


def test_tag_regions_floors_and_halves() -> None:
    regions = tag_regions(two_floor_tags())
    assert {regions[k].floor for k in range(8)} == {0}
    assert {regions[10 + k].floor for k in range(8)} == {1}
    assert regions[20].floor == 0  # a landing's lone tag joins the nearer floor
    assert [regions[k].half for k in range(8)] == [0, 0, 0, 0, 1, 1, 1, 1] or [
        regions[k].half for k in range(8)
    ] == [1, 1, 1, 1, 0, 0, 0, 0]


def test_umeyama_similarity_recovers_a_similarity() -> None:
    rng = np.random.default_rng(0)
    source = rng.normal(size=(10, 3))
    R = rotation_about_y(0.7) @ make_pose(np.eye(3), [0, 0, 0])[:3, :3]
    target = 1.3 * source @ R.T + np.array([1.0, -2.0, 3.0])
    T = umeyama_similarity(source, target)
    np.testing.assert_allclose(source @ T[:3, :3].T + T[:3, 3], target, atol=1e-9)


def test_region_errors_tell_inside_from_between() -> None:
    truth = two_floor_tags()
    regions = tag_regions(truth)
    # the upper floor turned by 3° about its first tag: each floor is exact, their relation not
    turn = make_pose(rotation_about_y(math.radians(3.0)), [0, 0, 0])
    pivot = make_pose(np.eye(3), truth[10][:3, 3])
    mapped = {
        t: (pivot @ turn @ np.linalg.inv(pivot) @ T if regions[t].floor == 1 else T)
        for t, T in truth.items()
    }
    errors = region_errors(mapped, truth, regions)
    assert errors.inside_rigid_m("floor") < 1e-9
    assert errors.inside_rigid_m("half") < 1e-9
    assert errors.between_floors_m > 0.5  # 28 m of floor turned by 3°
    assert errors.all_rigid_m > 0.1
    upper = [t for t, r in regions.items() if r.floor == 1]
    lower = [t for t, r in regions.items() if r.floor == 0]
    assert transfer_rmse_m(mapped, truth, upper, lower) > 0.5
    # a map 2% too large: a similarity fit removes it, a rigid one does not
    scaled = {t: make_pose(np.eye(3), 1.02 * T[:3, 3]) for t, T in truth.items()}
    assert fitted_rmse_m(scaled, truth, list(truth), scale=True) < 1e-9
    assert fitted_rmse_m(scaled, truth, list(truth), scale=False) > 0.05
    assert Region(1, 0).label == "floor 1 a"


def test_a_landing_tag_can_be_a_region_of_its_own() -> None:
    assert tag_regions(tags_with_a_landing())[20].floor in (0, 1)  # joins a floor
    regions = tag_regions(tags_with_a_landing(), landings=True)
    assert regions[20].floor == 1
    assert {regions[10 + k].floor for k in range(8)} == {2}
    assert {regions[k].floor for k in range(8)} == {0}


def test_loosening_a_walks_links_resolves_the_same_graph_otherwise() -> None:
    from app.domain.evaluation.simulate_building import WalkStyle, simulate_building_sessions
    from app.domain.mapping.joint import optimize_sessions
    from app.domain.mapping.stretch_trust import resolve_with_loose_stretches

    stairs = REGION_ERROR_SOURCES["stairs"]
    config = dataclasses.replace(TWO_FLOORS, max_floor_changes=1, **stairs)  # type: ignore[arg-type]
    building = simulate_building_sessions(config, count=2, styles=(WalkStyle(), WalkStyle()))
    sessions = [parse_session(s.upload) for s in building.sessions]
    joint = optimize_sessions(sessions, names=["a", "b"])
    again = resolve_with_loose_stretches(joint, {}, variance_factor=100.0)
    moved_m = [np.linalg.norm(again[t][:3, 3] - T[:3, 3]) for t, T in joint.map.tag_poses().items()]
    assert max(moved_m) < 0.02  # the map's own graph, solved again from its optimum
    regions = tag_regions(building.world_T_tag_true)
    used = joint.detection_mask[joint.parts[1].detection_rows]
    links = connecting_stretches(sessions[1], regions, used, level="floor")
    assert links
    seen_by_a = {regions[t].floor for t in joint.parts[0].tag_ids}
    assert seen_by_a == {0, 1}, "both walks must see both floors for their links to disagree"
    loose = resolve_with_loose_stretches(
        joint, {"b": [(s.from_pose, s.to_pose) for s in links]}, variance_factor=1e4
    )
    moved_m = [np.linalg.norm(loose[t][:3, 3] - again[t][:3, 3]) for t in again]
    # the two walks' links disagree (their stairs err): b's no longer pulls the floors its way
    assert max(moved_m) > 0.01
