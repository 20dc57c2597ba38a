"""Each walk's noise from its own residuals (app/domain/mapping/noise.py and slam.py): the χ²
quantiles the robust kernel uses, the variance-component estimate, gravity folded into the
keyframes, and Levenberg–Marquardt stopping on a step in metres and radians."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from app.domain.evaluation.simulate import SimulationConfig, simulate_session
from app.domain.evaluation.simulate_building import WalkStyle
from app.domain.frames import make_pose, rotation_about_y
from app.domain.mapping import slam
from app.domain.mapping.noise import (
    NoiseEstimate,
    WalkNoise,
    chi2_cdf,
    chi2_quantile,
    noise_estimate_from_dict,
    robust_threshold,
    updated_scales,
)
from app.domain.mapping.params import HUBER_K, SlamParams
from app.domain.upload.session import load_session, parse_session

DATA = Path(__file__).parents[2] / "data"


# --------------------------------------------------------------------------- χ²


@pytest.mark.parametrize(
    ("probability", "dof", "expected"),
    [
        (0.95, 1, 3.841459),
        (0.95, 2, 5.991465),
        (0.95, 3, 7.814728),
        (0.95, 6, 12.591587),
        (0.99, 7, 18.475307),
        (0.999, 6, 22.457744),
        (0.5, 5, 4.351460),
    ],
)
def test_chi2_quantiles_are_scipys(probability: float, dof: int, expected: float) -> None:
    """scipy.stats.chi2.ppf's values (scipy is not a dependency of the domain)."""
    assert chi2_quantile(probability, dof) == pytest.approx(expected, abs=1e-5)
    assert chi2_cdf(expected, dof) == pytest.approx(probability, abs=1e-6)


def test_the_tag_kernel_threshold_is_the_6d_chi2_quantile() -> None:
    """1.345 is a one-dimensional constant; a 6-D whitened residual's norm is χ₆: its 95%
    quantile is 3.548, the default."""
    assert robust_threshold(dimension=6) == pytest.approx(math.sqrt(12.591587), abs=1e-6)
    assert SlamParams().huber_k == pytest.approx(robust_threshold(dimension=6), abs=1e-12)
    assert SlamParams().huber_k == HUBER_K


def test_chi2_refuses_what_it_cannot_compute() -> None:
    with pytest.raises(ValueError, match="dof"):
        chi2_cdf(1.0, 0)
    with pytest.raises(ValueError, match="probability"):
        chi2_quantile(1.0, 3)


# --------------------------------------------------------------------------- the estimate


def test_the_update_is_the_posterior_mode_with_the_prior_at_the_configured_variance() -> None:
    scales = np.array([[2.0, 1.0, 0.5, 1.0]])
    chi2 = np.array([[30.0, 0.0, 40.0, 10.0]])  # whitened with the current scales
    redundancy = np.array([[30.0, 0.0, 10.0, 10.0]])
    new = updated_scales(scales, chi2, redundancy, prior_dof=4.0, bounds=(1e-4, 1e4))
    # component 0: the data say 2.0 (vᵀPv / r = 1 at scale 2), the prior 1: (60 + 4) / 34
    assert new[0, 0] == pytest.approx((30 * 2 + 4) / 34)
    # component 1: no redundancy, nothing to say: the prior
    assert new[0, 1] == pytest.approx(1.0)
    assert new[0, 2] == pytest.approx((40 * 0.5 + 4) / 14)
    pure = updated_scales(scales, chi2, redundancy, prior_dof=0.0, bounds=(1e-4, 1e4))
    assert pure[0, 0] == pytest.approx(2.0)  # plain VCE: vᵀPv / r with the current scale
    assert pure[0, 1] == pytest.approx(1e-4)  # and collapses without redundancy (the bound)


@pytest.fixture(scope="module")
def same_walk_three_times_noisier() -> tuple[NoiseEstimate, NoiseEstimate]:
    """One walk recorded twice, the second with every noise σ 3× (variance 9×): the same route,
    detections and random draws, only scaled."""
    config = SimulationConfig(num_poses=1200, seed=1)
    estimates = []
    for noise_scale in (1.0, 3.0):
        sim = simulate_session(WalkStyle(noise_scale=noise_scale).apply(config))
        result = slam.optimize_session(parse_session(sim.upload))
        assert result.noise is not None
        assert result.noise.converged
        estimates.append(result.noise)
    return estimates[0], estimates[1]


def test_the_estimate_recovers_a_known_noise_ratio(
    same_walk_three_times_noisier: tuple[NoiseEstimate, NoiseEstimate],
) -> None:
    """The well-determined components (hundreds of redundant rows) see the 9× variance: tag
    position 9.1× (measured). The tag orientation (3.8×) and the odometry's translation (6.2×)
    grow less: screening drops the noisier walk's worst sightings (its corners disagree), and the
    odometry's redundancy is a few dozen rows, so the prior pulls. The odometry's yaw, with a
    handful of redundant rows, stays near its prior."""
    normal, noisy = same_walk_three_times_noisier
    ratio = noisy.scales / normal.scales
    assert 6.0 < ratio[2] < 14.0  # tag position
    assert ratio[3] > 2.0  # tag orientation
    assert ratio[0] > 2.0  # odometry linear
    assert normal.redundancy[2] > 100
    assert normal.redundancy[1] < 20  # the yaw: little to go on
    assert np.all(normal.redundancy <= normal.rows)


def test_the_estimate_is_reported_in_the_parameters_units() -> None:
    estimate = NoiseEstimate(
        scales=np.array([0.5, 2.0, 0.1, 0.01]),
        redundancy=np.array([10.0, 2.0, 50.0, 60.0]),
        rows=np.array([30.0, 10.0, 60.0, 60.0]),
        chi2_per_redundancy=np.array([1.0, math.nan, 1.0, 1.0]),
        rounds=4,
        converged=True,
    )
    params = SlamParams()
    noise = estimate.variances(params)
    assert noise.odom_linear_var_m2_per_s == pytest.approx(0.5 * params.odom_linear_var_m2_per_s)
    assert noise.tag_orientation_var_rad2 == pytest.approx(0.01 * params.tag_orientation_var_rad2)
    np.testing.assert_allclose(noise.scales(params), estimate.scales)
    as_dict = estimate.to_dict(params)
    assert as_dict["components"]["odom_angular"]["chi2_per_redundancy"] is None  # JSON: no NaN
    assert WalkNoise.of(params).scales(params) == pytest.approx(np.ones(4))


def test_the_estimate_as_json_is_exact_and_reads_back_as_it_was() -> None:
    """Every field of the document, exactly (a map's stored noise and the API show it), and the
    document read back field for field (NaN where JSON says null)."""
    estimate = NoiseEstimate(
        scales=np.array([0.5, 2.0, 0.25, 4.0]),
        redundancy=np.array([10.0, 2.0, 50.0, 60.0]),
        rows=np.array([30.0, 10.0, 60.0, 61.0]),
        chi2_per_redundancy=np.array([1.5, math.nan, 0.75, 1.0]),
        rounds=4,
        converged=False,
        note="the rounds ran out",
    )
    params = SlamParams()
    document = estimate.to_dict(params)
    assert document == {
        "variances": {
            "odom_linear_var_m2_per_s": 0.5 * params.odom_linear_var_m2_per_s,
            "odom_angular_var_rad2_per_s": 2.0 * params.odom_angular_var_rad2_per_s,
            "tag_position_var_m2": 0.25 * params.tag_position_var_m2,
            "tag_orientation_var_rad2": 4.0 * params.tag_orientation_var_rad2,
        },
        "components": {
            "odom_linear": {
                "scale": 0.5,
                "redundancy": 10.0,
                "rows": 30.0,
                "chi2_per_redundancy": 1.5,
            },
            "odom_angular": {
                "scale": 2.0,
                "redundancy": 2.0,
                "rows": 10.0,
                "chi2_per_redundancy": None,
            },
            "tag_position": {
                "scale": 0.25,
                "redundancy": 50.0,
                "rows": 60.0,
                "chi2_per_redundancy": 0.75,
            },
            "tag_orientation": {
                "scale": 4.0,
                "redundancy": 60.0,
                "rows": 61.0,
                "chi2_per_redundancy": 1.0,
            },
        },
        "rounds": 4,
        "converged": False,
        "note": "the rounds ran out",
    }
    again = noise_estimate_from_dict(document)
    for field in ("scales", "redundancy", "rows", "chi2_per_redundancy"):
        np.testing.assert_array_equal(getattr(again, field), getattr(estimate, field))
    assert (again.rounds, again.converged, again.note) == (4, False, "the rounds ran out")
    no_note = {k: v for k, v in document.items() if k != "note"}  # written before the note
    assert noise_estimate_from_dict(no_note).note == ""


@pytest.mark.slow
def test_a_component_the_walk_cannot_check_stays_near_its_prior() -> None:
    """floor_2_straight sees each tag about twice: its tag positions have ~9 redundant rows.
    Without the prior (plain VCE), that component collapses to almost nothing (the tags become
    rigid and the odometry absorbs every disagreement); with it, it stays within a few times the
    configured variance."""
    session = load_session(DATA / "sessions" / "floor_2_straight.json")
    with_prior = slam.optimize_session(session)
    without = slam.optimize_session(session, SlamParams(noise_prior_dof=0.0))
    assert with_prior.noise is not None
    assert without.noise is not None
    assert with_prior.noise.redundancy[2] < 20
    assert with_prior.noise.scales[2] > 0.2
    assert without.noise.scales[2] < 0.05


def test_the_variances_as_given_make_no_estimate() -> None:
    session = load_session(DATA / "sessions" / "desnat_straight_once.json")
    result = slam.optimize_session(session, SlamParams(estimate_noise=False))
    assert result.noise is None


# --------------------------------------------------------------------------- gravity


def test_gravity_of_the_poses_between_keyframes_is_folded_into_the_keyframes() -> None:
    """With no tilt noise in the odometry, the keyframes' gravity information is exactly the
    information of every pose's gravity (N / σ²), whatever the interval; with it, each folded
    pose counts less the further it is from its keyframe."""
    session = load_session(DATA / "sessions" / "straight_209_occam.json")
    n = session.num_poses
    for interval_s in (0.0, 2.0, 5.0):
        exact = SlamParams(keyframe_interval_s=interval_s, odom_angular_var_rad2_per_s=1e-300)
        inputs = slam.GraphInputs(session, exact)
        variances = slam.gravity_variances(
            inputs.gravity_offset_s,
            inputs.gravity_keyframe,
            len(inputs.keyframes),
            exact,
            np.ones(n),
        )
        assert np.sum(1.0 / variances) == pytest.approx(n / exact.gravity_var_rad2, rel=1e-9)
        if interval_s > 0:
            assert len(inputs.keyframes) < n
    params = SlamParams()
    inputs = slam.GraphInputs(session, params)
    variances = slam.gravity_variances(
        inputs.gravity_offset_s, inputs.gravity_keyframe, len(inputs.keyframes), params, np.ones(n)
    )
    total = float(np.sum(1.0 / variances))
    assert 0.5 * n / params.gravity_var_rad2 < total < n / params.gravity_var_rad2


def test_each_pose_folds_into_its_nearest_keyframe_of_its_own_walk() -> None:
    session = load_session(DATA / "sessions" / "desnat_straight_once.json")
    inputs = slam.GraphInputs(session, SlamParams())
    times = session.timestamp_s
    keyframe_times = times[inputs.keyframes]
    nearest = np.abs(times[:, None] - keyframe_times[None, :]).min(axis=1)
    np.testing.assert_allclose(inputs.gravity_offset_s, nearest, atol=1e-12)
    np.testing.assert_array_equal(
        inputs.gravity_keyframe[inputs.keyframes], np.arange(len(inputs.keyframes))
    )


# --------------------------------------------------------------------------- stopping


def test_the_largest_step_is_measured_in_metres_and_radians() -> None:
    before = np.stack([make_pose(rotation_about_y(0.0), [0.0, 0.0, 0.0])] * 3)
    after = before.copy()
    after[1] = make_pose(rotation_about_y(0.02), [0.0, 0.003, 0.004])
    step_m, step_rad = slam.largest_step(_extracted(before), _extracted(after))
    assert step_m == pytest.approx(0.005, abs=1e-12)
    assert step_rad == pytest.approx(0.02, rel=1e-9)


def test_lm_stops_near_the_optimum_not_on_a_small_relative_drop() -> None:
    """desnat_straight_once at stiff odometry: stopping when an iteration lowers the cost by less
    than 0.1% (the former criterion) leaves tags centimetres from where the metric criterion
    ends; tightening that criterion a hundredfold moves them by a fraction of a millimetre."""
    session = load_session(DATA / "sessions" / "desnat_straight_once.json")
    stiff = SlamParams(
        estimate_noise=False,
        odom_linear_var_m2_per_s=1e-6,
        odom_angular_var_rad2_per_s=1e-7,
        compute_marginals=False,
    )
    metric = slam.optimize_session(session, stiff).tag_poses()
    tighter = slam.optimize_session(
        session,
        dataclasses.replace(stiff, converged_step_m=1e-6, converged_step_rad=1e-7),
    ).tag_poses()
    former = slam.optimize_session(
        session,
        dataclasses.replace(
            stiff, converged_step_m=1e3, converged_step_rad=1e3, relative_error_tol=1e-3
        ),
    ).tag_poses()

    def largest_m(a: dict, b: dict) -> float:
        return max(float(np.linalg.norm(a[t][:3, 3] - b[t][:3, 3])) for t in a)

    assert largest_m(metric, tighter) < 1e-3
    assert largest_m(former, tighter) > 10 * largest_m(metric, tighter)


def _extracted(poses: np.ndarray) -> np.ndarray:
    """``gtsam.utilities.extractPose3``'s layout: each pose's rotation (9), then translation."""
    return np.concatenate([poses[:, :3, :3].reshape(-1, 9), poses[:, :3, 3]], axis=1)


def test_a_maps_document_keeps_its_noise_and_older_documents_read_without() -> None:
    from app.domain.formats.map_io import map_from_json, map_to_json

    session = load_session(DATA / "sessions" / "desnat_straight_once.json")
    result = slam.optimize_session(session)
    assert result.noise is not None
    document = map_to_json(result)
    again = map_from_json(document)
    assert again.noise is not None
    np.testing.assert_allclose(again.noise.scales, result.noise.scales)
    np.testing.assert_allclose(again.noise.redundancy, result.noise.redundancy)
    assert again.noise.rounds == result.noise.rounds
    older = {k: v for k, v in document.items() if k != "noise"}  # written before issue 25
    assert map_from_json(older).noise is None


def test_a_walk_too_large_to_estimate_uses_its_configured_variances_and_says_so(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    session = load_session(DATA / "sessions" / "desnat_straight_once.json")
    monkeypatch.setattr(slam, "MAX_NOISE_ESTIMATE_ENTRIES", 10)
    result = slam.optimize_session(session)
    given = slam.optimize_session(session, SlamParams(estimate_noise=False))
    assert result.noise is not None
    assert not result.noise.converged
    assert result.noise.rounds == 0
    np.testing.assert_array_equal(result.noise.scales, np.ones(4))
    assert any("not estimated" in w for w in result.warnings)
    np.testing.assert_allclose(result.world_T_tag, given.world_T_tag, atol=1e-9)
