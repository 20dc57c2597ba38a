"""Graph SLAM: recovery of simulated truth, screening, noise models, residuals, marginals."""

from __future__ import annotations

import copy
import json
import math
from pathlib import Path

import numpy as np
import pytest

from app.domain.errors import NoTagsRecorded
from app.domain.evaluation.simulate import SimulationConfig, simulate_session
from app.domain.frames import make_pose, rotation_about_y, se3_inverse
from app.domain.mapping.params import SlamParams
from app.domain.mapping.slam import odometry_sigmas, optimize_session, tag_covariance_in_tag_frame
from app.domain.upload.session import NO_TAGS_REASON, load_session, parse_session

DATA = Path(__file__).parents[2] / "data"


def positions_error_m(world_T_a: np.ndarray, world_T_b: np.ndarray) -> float:
    """Largest position difference between two pose stacks, m."""
    return float(np.max(np.linalg.norm(world_T_a[:, :3, 3] - world_T_b[:, :3, 3], axis=1)))


def tag_errors_m(result, sim) -> tuple[float, float]:
    """RMS error of optimized and pre-optimized tag positions against the simulated truth, m."""
    truth = np.array([sim.world_T_tag_true[int(t)][:3, 3] for t in result.tag_ids])
    opt = np.sqrt(np.mean(np.sum((result.world_T_tag[:, :3, 3] - truth) ** 2, axis=1)))
    pre = np.sqrt(np.mean(np.sum((result.world_T_tag_pre[:, :3, 3] - truth) ** 2, axis=1)))
    return float(opt), float(pre)


@pytest.fixture(scope="module")
def noiseless():
    return simulate_session(SimulationConfig(num_poses=800, seed=3).without_noise())


def test_noiseless_truth_has_zero_residuals(noiseless):
    """Every factor's convention agrees with the simulated world: the truth costs nothing."""
    result = optimize_session(parse_session(noiseless.upload))
    assert result.stats.initial_error < 1e-12
    assert np.max(result.residuals.tag_chi2) < 1e-12
    assert np.max(result.residuals.gravity_chi2) < 1e-12
    assert positions_error_m(result.world_T_phone, noiseless.world_T_phone_true) < 1e-6


def test_noiseless_simulation_recovered_from_a_perturbed_start(noiseless):
    """LM starting 0.3 m / 3° off everywhere returns to the truth to 1e-6."""
    session = parse_session(noiseless.upload)
    rng = np.random.default_rng(0)
    n = session.num_poses
    # A smooth bend of the whole trajectory, growing along it: what drift looks like.
    yaw_rad = np.cumsum(rng.normal(0.0, 0.004, n))
    offset_m = np.cumsum(rng.normal(0.0, 0.01, (n, 3)), axis=0)
    offset_m[:, 1] *= 0.1
    perturbation = np.stack(
        [make_pose(rotation_about_y(yaw_rad[i]), offset_m[i]) for i in range(n)]
    )
    start = noiseless.world_T_phone_true @ perturbation
    assert positions_error_m(start, noiseless.world_T_phone_true) > 0.1

    result = optimize_session(session, initial_world_T_phone=start)

    assert result.stats.iterations >= 2
    assert positions_error_m(result.world_T_phone, noiseless.world_T_phone_true) < 1e-6
    truth = np.stack([noiseless.world_T_tag_true[int(t)] for t in result.tag_ids])
    assert positions_error_m(result.world_T_tag, truth) < 1e-6
    rotation_error = np.einsum("kji,kjl->kil", result.world_T_tag[:, :3, :3], truth[:, :3, :3])
    np.testing.assert_allclose(
        rotation_error, np.broadcast_to(np.eye(3), rotation_error.shape), atol=1e-6
    )


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_noisy_simulation_map_is_closer_to_truth_than_raw(seed):
    sim = simulate_session(SimulationConfig(num_poses=1500, seed=seed))
    result = optimize_session(parse_session(sim.upload))
    opt_m, pre_m = tag_errors_m(result, sim)
    assert opt_m < pre_m
    raw = parse_session(sim.upload).world_T_phone
    raw_error = np.linalg.norm(raw[:, :3, 3] - sim.world_T_phone_true[:, :3, 3], axis=1)
    opt_error = np.linalg.norm(
        result.world_T_phone[:, :3, 3] - sim.world_T_phone_true[:, :3, 3], axis=1
    )
    assert np.sqrt(np.mean(opt_error**2)) < np.sqrt(np.mean(raw_error**2))


def test_outliers_are_contained_by_screening_and_huber():
    sim = simulate_session(SimulationConfig(num_poses=1500, seed=4, outlier_fraction=0.1))
    session = parse_session(sim.upload)
    protected = optimize_session(session)
    unprotected = optimize_session(
        session,
        SlamParams(huber_k=0.0, max_reprojection_px=1e6, max_view_angle_deg=90, max_distance_m=1e6),
    )
    protected_m, _ = tag_errors_m(protected, sim)
    unprotected_m, _ = tag_errors_m(unprotected, sim)
    assert protected_m < unprotected_m
    rejected = {r.detection_index for r in protected.rejections}
    outliers = set(np.flatnonzero(sim.detection_is_outlier).tolist())
    assert outliers, "the simulation should contain outliers"
    # Most deliberate outliers are caught by the reprojection test, with their reason.
    assert len(rejected & outliers) >= 0.5 * len(outliers)
    assert {r.reason for r in protected.rejections} <= {"reprojection", "view_angle", "distance"}


# --------------------------------------------------------------------------- screening


def _onetag_document() -> dict:
    return json.loads((DATA / "sessions" / "onetag.json").read_text())


def test_corners_that_disagree_with_the_pose_are_rejected_for_reprojection():
    document = _onetag_document()
    good = copy.deepcopy(document["tag_data"][0][0])
    bad = copy.deepcopy(good)
    corners = bad["tag_corners_pixel_coordinates"]
    bad["tag_corners_pixel_coordinates"] = [
        c + (40.0 if i % 2 == 0 else 0.0) for i, c in enumerate(corners[:2])
    ] + corners[2:]
    document["tag_data"] = [[good], [good], [bad]]
    result = optimize_session(parse_session(document))
    assert [(r.detection_index, r.reason) for r in result.rejections] == [(2, "reprojection")]
    assert result.rejections[0].value > result.params.max_reprojection_px
    assert "px" in result.rejections[0].detail
    assert result.detections_used == 2


def test_grazing_and_far_detections_are_rejected_with_their_reason():
    document = _onetag_document()
    result = optimize_session(parse_session(document), SlamParams(max_view_angle_deg=1.0))
    assert [r.reason for r in result.rejections] == ["view_angle"]
    result = optimize_session(parse_session(document), SlamParams(max_distance_m=0.1))
    assert [r.reason for r in result.rejections] == ["distance"]
    assert result.tag_ids.size == 0
    assert any("not in the map" in w for w in result.warnings)


def test_session_without_detections_makes_no_map_and_says_why():
    document = _onetag_document()
    document["tag_data"] = []
    session = parse_session(document)
    assert NO_TAGS_REASON in session.warnings
    with pytest.raises(NoTagsRecorded, match="no tags were recorded: a map needs at least one tag"):
        optimize_session(session)


def test_single_detection_session():
    session = load_session(DATA / "sessions" / "onetag.json")
    result = optimize_session(session)
    assert result.tag_ids.tolist() == session.tag_ids
    np.testing.assert_allclose(result.world_T_tag, result.world_T_tag_pre, atol=1e-6)


# --------------------------------------------------------------------------- noise models


def test_odometry_noise_grows_with_time_between_poses():
    params = SlamParams(odom_linear_var_m2_per_s=1e-3, odom_angular_var_rad2_per_s=1e-4)
    one_s, four_s = odometry_sigmas(1.0, params), odometry_sigmas(4.0, params)
    np.testing.assert_allclose(four_s, 2.0 * one_s)  # σ ∝ √dt
    np.testing.assert_allclose(one_s[:3], math.sqrt(1e-4))  # rotation first, rad
    np.testing.assert_allclose(one_s[3:], math.sqrt(1e-3))  # then translation, m


def test_tag_noise_is_largest_along_the_line_of_sight_and_grows_with_distance():
    params = SlamParams(tag_position_var_m2=1e-4, tag_depth_var_ratio=10.0)
    # A tag 2 m straight ahead, facing the camera (tag z toward the camera: camera z is forward).
    camera_T_tag = make_pose(np.diag([1.0, -1.0, -1.0]), [0.0, 0.0, 2.0])
    covariance = tag_covariance_in_tag_frame(camera_T_tag, params)
    position = covariance[3:, 3:]
    # Line of sight is the tag's z axis here; variance 1e-4 · 2² · 10.
    np.testing.assert_allclose(np.diag(position), [4e-4, 4e-4, 4e-3])
    np.testing.assert_allclose(covariance[:3, :3], np.eye(3) * params.tag_orientation_var_rad2)
    farther = tag_covariance_in_tag_frame(make_pose(np.eye(3), [0.0, 0.0, 4.0]), params)
    assert np.trace(farther[3:, 3:]) == pytest.approx(4 * np.trace(position))


# --------------------------------------------------------------------------- outputs


def test_marginal_covariances_are_symmetric_positive_definite():
    session = load_session(DATA / "sessions" / "occam_room.json")
    result = optimize_session(session)
    assert result.tag_covariance.shape == (len(result.tag_ids), 6, 6)
    for covariance in result.tag_covariance:
        np.testing.assert_allclose(covariance, covariance.T, atol=1e-12)
        assert np.linalg.eigvalsh(covariance).min() > 0


def test_residuals_cover_every_factor():
    session = load_session(DATA / "sessions" / "occam_room.json")
    result = optimize_session(session)
    residuals = result.residuals
    keyframes = residuals.keyframe_index.size
    assert 2 <= keyframes < session.num_poses
    assert residuals.odometry_chi2.shape == (keyframes - 1,)
    assert residuals.gravity_chi2.shape == (keyframes,)
    assert residuals.tag_chi2.shape == (result.detections_used,)
    assert len(result.rejections) + result.detections_used == len(session.detections)
    assert np.all(residuals.tag_chi2 >= 0)
    # The pose each tag factor hangs on is the detection's pose.
    np.testing.assert_array_equal(
        residuals.tag_pose_index, session.detections.pose_index[residuals.tag_detection_index]
    )
    assert result.stats.final_error < result.stats.initial_error


def test_optimized_map_keeps_the_first_pose_fixed():
    session = load_session(DATA / "sessions" / "desnat_straight_once.json")
    result = optimize_session(session)
    np.testing.assert_allclose(
        se3_inverse(session.world_T_phone[0]) @ result.world_T_phone[0], np.eye(4), atol=1e-6
    )


def test_warm_start_with_wrong_shape_is_refused():
    session = load_session(DATA / "sessions" / "onetag.json")
    with pytest.raises(ValueError, match="initial_world_T_phone"):
        optimize_session(session, initial_world_T_phone=np.zeros((3, 4, 4)))


def test_tag_marginals_equal_gtsams_marginals_of_the_whole_graph():
    """The covariances are those of the graph at the solution (rebuilt independently here)."""
    import gtsam
    from gtsam.symbol_shorthand import L, X

    from app.domain.mapping import slam

    session = load_session(DATA / "sessions" / "occam_room.json")
    params = SlamParams()
    result = optimize_session(session, params)
    inputs = slam.prepare_graph_inputs(session, params)
    assert result.noise is not None
    inputs.noise_scales = result.noise.scales[None, :]  # the variances the map was made with
    problem = slam.build_problem(inputs, params)
    values = gtsam.Values()
    for i in range(session.num_poses):
        values.insert(X(i), gtsam.Pose3(result.world_T_phone[i]))
    for k, tag_id in enumerate(result.tag_ids):
        values.insert(L(int(tag_id)), gtsam.Pose3(result.world_T_tag[k]))
    reference = gtsam.Marginals(problem.graph, values)
    for k, tag_id in enumerate(result.tag_ids):
        np.testing.assert_allclose(
            result.tag_covariance[k], reference.marginalCovariance(L(int(tag_id))), atol=1e-10
        )


#: SlamParams' noise fields (its docstring's "Noise" group): everything a factor's noise is made of.
NOISE_FIELDS = {
    "tag_position_var_m2",
    "tag_depth_var_ratio",
    "tag_orientation_var_rad2",
    "odom_linear_var_m2_per_s",
    "odom_angular_var_rad2_per_s",
    "gravity_var_rad2",
    "huber_k",
}


def test_a_trial_graph_is_the_builds_graph_for_every_noise_setting():
    """TrialGraph keeps each kind of factor until one of its fields changes: after any sequence
    of settings, its graph must be the one the build makes (same factors in the same order, the
    same error at any values)."""
    from app.domain.mapping import slam

    assert (
        set(slam.ODOMETRY_NOISE_FIELDS + slam.GRAVITY_NOISE_FIELDS + slam.TAG_NOISE_FIELDS)
        == NOISE_FIELDS
    )
    session = load_session(DATA / "sessions" / "desnat_straight_once.json")  # 16 step durations
    inputs = slam.prepare_graph_inputs(session)
    trial_graph = slam.TrialGraph(inputs)
    default = SlamParams()
    settings = [default]
    for name in sorted(NOISE_FIELDS):
        changed = 2.0 if name == "huber_k" else 10.0 * getattr(default, name)
        settings += [default.with_overrides({name: changed}), default]
    settings.append(default.with_overrides({"huber_k": 0.0}))
    for params in settings:
        built = slam.build_problem(inputs, params).graph
        graph = trial_graph.graph(params)
        assert graph.size() == built.size()
        assert [list(graph.at(i).keys()) for i in range(graph.size())] == [
            list(built.at(i).keys()) for i in range(built.size())
        ]
        assert graph.error(inputs.initial) == pytest.approx(built.error(inputs.initial), rel=1e-12)
