"""Hyperparameter tuning (§5): search spaces, trials on simulated and real sessions, the
sampler, the summary and the plots."""

from __future__ import annotations

import io
import json
import math
import re
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from app.domain.errors import ParameterError
from app.domain.evaluation import tuning
from app.domain.evaluation.ground_truth import load_ground_truth
from app.domain.evaluation.simulate import (
    SimulationConfig,
    simulate_along_trajectory,
    simulate_session,
)
from app.domain.evaluation.sweep_plan import SweepPlan
from app.domain.evaluation.table import evaluate_map
from app.domain.evaluation.tuning import (
    MAX_TRIALS,
    PAPER_GRID_AXES,
    TRIAL_MAX_ITERATIONS,
    Axis,
    SearchSpace,
    Trial,
    TuningTarget,
    best_trial,
    propose_trials,
    shift_gt_correlation,
    summarize,
    sweep_result,
)
from app.domain.mapping.params import SlamParams
from app.domain.mapping.slam import optimize_session
from app.domain.upload.session import Session, load_session, parse_session
from app.render.sweep_plots import heatmap_png, shift_vs_gt_png

DATA_DIR = Path(__file__).parents[2] / "data"
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
#: The sweep plots' marker colours (app/render/sweep_plots.py): shift-chosen / best ★, GT-chosen ★.
RED_RGB = (0xD5, 0x00, 0x00)
GREEN_RGB = (0x2E, 0x7D, 0x32)

LINEAR = "odom_linear_var_m2_per_s"
ANGULAR = "odom_angular_var_rad2_per_s"
ORIENTATION = "tag_orientation_var_rad2"
POSITION = "tag_position_var_m2"


def make_trial(
    values: dict[str, float] | None = None,
    *,
    shift: float,
    gt_metric: float = math.nan,
    tag_rmse_m: float = math.nan,
    iterations: int = 3,
    error: str | None = None,
) -> Trial:
    return Trial(
        values=values or {},
        shift=shift,
        gt_metric=gt_metric,
        tag_rmse_m=tag_rmse_m,
        iterations=iterations,
        duration_s=0.01,
        error=error,
    )


def axis(name: str = LINEAR, low: float = 1e-6, high: float = 1e-2, num: int = 5) -> Axis:
    return Axis(name, low, high, num)


# --------------------------------------------------------------------------- search space


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda: SearchSpace(()), "the search space is empty"),
        (lambda: axis(low=0.0), "low must be a positive variance, got 0.0"),
        (lambda: axis(low=-1e-3), "low must be a positive variance"),
        (lambda: axis(high=0.0), "high must be a positive variance"),
        (lambda: axis(high=math.inf), "high must be a positive variance, got inf"),
        (lambda: axis(low=math.nan), "low must be a positive variance, got nan"),
        # beyond what a build takes as a parameter (params.PARAM_RANGES): refused when swept too
        (lambda: axis(low=1e-30), "low must be 1e-12 to 1e+06 m²/s, got 1e-30"),
        (lambda: axis(high=1e9), "high must be 1e-12 to 1e+06 m²/s, got 1e+09"),
        (lambda: axis(name="huber_k"), "'huber_k' cannot be swept"),
        (lambda: axis(name="nonsense"), "tunable parameters: tag_position_var_m2"),
        (lambda: axis(low=1.0, high=1e-3), "low 1 is above high 0.001"),
        (lambda: axis(num=0), "num must be ≥ 1, got 0"),
        (lambda: axis(low=1e-3, high=1e-3, num=3), "3 values need low < high"),
        (lambda: SearchSpace((axis(), axis())), "a parameter appears twice"),
        (
            lambda: SearchSpace(tuple(axis(name, num=28) for name in PAPER_GRID_AXES)),
            f"the grid has 21952 points, more than the {MAX_TRIALS}",
        ),
    ],
)
def test_invalid_search_spaces_say_what_is_wrong(make, message) -> None:
    with pytest.raises(ParameterError, match=re.escape(message)):
        make()


def test_a_single_value_axis_of_equal_ends_is_allowed() -> None:
    assert axis(low=1e-3, high=1e-3, num=1).values().tolist() == [1e-3]


@pytest.mark.parametrize(
    ("document", "message"),
    [
        ({LINEAR: {"high": 1.0, "num": 3}}, f"{LINEAR}: missing 'low'"),
        ({LINEAR: {"low": 1e-6, "num": 3}}, f"{LINEAR}: missing 'high'"),
        ({LINEAR: 3}, f"{LINEAR}: expected an object with low, high and num"),
        ({LINEAR: [1e-6, 1.0]}, f"{LINEAR}: expected an object"),
        ({LINEAR: {"low": 1e-6, "high": 1.0, "step": 2}}, "unknown field(s) ['step']"),
        ({LINEAR: {"low": "small", "high": 1.0}}, f"{LINEAR}: could not convert"),
        ({LINEAR: {"low": 1e-6, "high": 1.0, "num": None}}, f"{LINEAR}: "),
        ({LINEAR: {"low": 0, "high": 1.0}}, "must be a positive variance"),
        ({"gravity": {"low": 1e-6, "high": 1.0}}, "'gravity' cannot be swept"),
        ({}, "the search space is empty"),
    ],
)
def test_from_dict_errors_name_the_parameter_and_the_problem(document, message) -> None:
    with pytest.raises(ParameterError, match=re.escape(message)):
        SearchSpace.from_dict(document)


def test_from_dict_round_trips_and_defaults_num_to_ten() -> None:
    space = SearchSpace.from_dict(
        {LINEAR: {"low": 1e-6, "high": 1e-2, "num": 3}, ANGULAR: {"low": "1e-8", "high": 1}}
    )
    assert space.names == (LINEAR, ANGULAR)
    assert [a.num for a in space.axes] == [3, 10]
    assert SearchSpace.from_dict(json.loads(json.dumps(space.to_dict()))) == space


def test_grid_order_and_size_last_axis_fastest() -> None:
    space = SearchSpace(
        (
            Axis(ORIENTATION, 1e-4, 1e-2, 3),
            Axis(LINEAR, 1e-6, 1e-5, 2),
            Axis(ANGULAR, 1e-3, 1e-3, 1),
        )
    )
    grid = space.grid()
    assert space.grid_size == len(grid) == 6
    as_exponents = [
        (round(math.log10(p[ORIENTATION])), round(math.log10(p[LINEAR])), p[ANGULAR]) for p in grid
    ]
    assert as_exponents == [
        (-4, -6, 1e-3),
        (-4, -5, 1e-3),
        (-3, -6, 1e-3),
        (-3, -5, 1e-3),
        (-2, -6, 1e-3),
        (-2, -5, 1e-3),
    ]
    assert all(list(point) == list(space.names) for point in grid)


def test_axis_values_are_log_spaced_and_include_both_ends() -> None:
    values = Axis(LINEAR, 2e-7, 2e-3, 9).values()
    assert (values[0], values[-1]) == (2e-7, 2e-3)  # exactly: the values a user asked for
    assert Axis(LINEAR, 1e-5, 1e-1, 2).values().tolist() == [1e-5, 1e-1]  # 10**-5 ≠ 1e-5
    np.testing.assert_allclose(np.diff(np.log10(values)), 0.5, atol=1e-12)
    # One value: the geometric mean of the range.
    assert Axis(LINEAR, 1e-6, 1e-2, 1).values() == pytest.approx([1e-4], rel=1e-12)


def test_the_paper_grid_is_ten_values_per_axis_from_1e8_to_1() -> None:
    space = SearchSpace.paper_grid()
    grid = space.grid()
    assert space.names == PAPER_GRID_AXES
    assert len(grid) == space.grid_size == 1000
    assert len({tuple(p.values()) for p in grid}) == 1000
    for name in PAPER_GRID_AXES:
        values = sorted({p[name] for p in grid})
        assert len(values) == 10
        assert values[0] == pytest.approx(1e-8, rel=1e-12)
        assert values[-1] == pytest.approx(1.0, rel=1e-12)
        np.testing.assert_allclose(np.diff(np.log10(values)), 8 / 9, atol=1e-12)


# --------------------------------------------------------------------------- exact truth


def assert_maps_equal(map_T_tag, truth, atol: float = 1e-9) -> None:
    assert map_T_tag
    for tag_id, pose in map_T_tag.items():
        np.testing.assert_allclose(pose, truth[tag_id], atol=atol, err_msg=f"tag {tag_id}")


#: Far corners of the paper grid and a middle point: a noiseless session is exact for all.
EXTREME_VALUES = [
    dict.fromkeys(PAPER_GRID_AXES, 1e-8),
    dict.fromkeys(PAPER_GRID_AXES, 1.0),
    {ORIENTATION: 1.0, LINEAR: 1e-8, ANGULAR: 1e-4, POSITION: 1e-2},
]


def test_a_noiseless_simulation_is_its_own_truth_before_and_after_optimizing() -> None:
    sim = simulate_session(SimulationConfig(num_poses=1200, seed=11).without_noise())
    session = parse_session(json.loads(json.dumps(sim.upload)))
    target = TuningTarget.prepare(session, SlamParams(), sim.world_T_tag_true)

    assert len(target.pre_map) >= 8
    assert_maps_equal(target.pre_map, sim.world_T_tag_true)
    shift, gt_metric, rmse_m = target.baseline()
    assert 0 <= shift < 1e-9
    assert 0 <= gt_metric < 1e-9
    assert 0 <= rmse_m < 1e-9
    for values in EXTREME_VALUES:
        trial = target.run(values)
        assert trial.converged, trial
        assert trial.shift < 1e-9
        assert trial.gt_metric < 1e-9
        assert trial.tag_rmse_m < 1e-9


def test_a_noiseless_replay_of_a_real_map_reproduces_it_exactly() -> None:
    """The paper's simulation: occam_room's optimized map and trajectory as the truth."""
    real = load_session(DATA_DIR / "sessions" / "occam_room.json")
    result = optimize_session(real, SlamParams(compute_marginals=False))
    used = result.residuals.tag_detection_index
    dt_s = float(np.median(np.diff(real.timestamp_s)))
    config = SimulationConfig(
        num_poses=real.num_poses,
        rate_hz=1 / dt_s,
        detection_rate_hz=1 / dt_s,
        num_points_of_interest=0,
    ).without_noise()
    truth = {int(t): result.world_T_tag[k] for k, t in enumerate(result.tag_ids)}
    sim = simulate_along_trajectory(
        config,
        result.world_T_phone,
        truth,
        real.detections.pose_index[used],
        real.detections.tag_id[used],
    )
    session = parse_session(json.loads(json.dumps(sim.upload)))

    assert len(session.detections) == len(used) > 100
    np.testing.assert_allclose(session.world_T_phone, result.world_T_phone, atol=1e-9)
    observed = session.world_T_tag_observed()
    for row, tag_id in enumerate(session.detections.tag_id):
        np.testing.assert_allclose(observed[row], truth[int(tag_id)], atol=1e-9)

    target = TuningTarget.prepare(session, SlamParams(), truth)
    assert sorted(target.pre_map) == sorted(truth)
    assert_maps_equal(target.pre_map, truth)
    assert max(target.baseline()) < 1e-9
    for values in EXTREME_VALUES:
        trial = target.run(values)
        assert trial.converged
        assert max(trial.shift, trial.gt_metric, trial.tag_rmse_m) < 1e-9


# --------------------------------------------------------------------------- identifying noise

#: The generating noise of the identification test, in the simulator's terms (moderate: the
#: odometry drifts ~1 m over the walk, tags are seen to ~1 cm at 1 m).
TRANSLATION_DRIFT_M_PER_SQRT_S = 0.03
ROTATION_DRIFT_RAD_PER_SQRT_S = 0.005
TAG_POSITION_NOISE_M_AT_1M = 0.01
TAG_ROTATION_NOISE_RAD = 0.03
TAG_DEPTH_NOISE_RATIO = 3.0


def generating_variances() -> dict[str, float]:
    """The simulator's noise as our SlamParams variances (σ → σ²).

    translation drift σ m/√s → odom_linear_var m²/s; heading drift σ rad/√s →
    odom_angular_var rad²/s; face-on tag rotation σ rad → tag_orientation_var rad²; tag position
    σ at 1 m (across the line of sight) → tag_position_var m² (at 1 m).
    """
    return {
        LINEAR: TRANSLATION_DRIFT_M_PER_SQRT_S**2,
        ANGULAR: ROTATION_DRIFT_RAD_PER_SQRT_S**2,
        ORIENTATION: TAG_ROTATION_NOISE_RAD**2,
        POSITION: TAG_POSITION_NOISE_M_AT_1M**2,
    }


@pytest.fixture(scope="module")
def noisy_target() -> TuningTarget:
    config = SimulationConfig(
        num_poses=2000,
        seed=0,
        odom_translation_drift_m_per_sqrt_s=TRANSLATION_DRIFT_M_PER_SQRT_S,
        # Vertical drift as large as horizontal and no tilt error: the isotropic random walk our
        # odometry factor models (the simulator's defaults hold height and tilt better).
        odom_vertical_drift_m_per_sqrt_s=TRANSLATION_DRIFT_M_PER_SQRT_S,
        odom_tilt_error_rad=0.0,
        odom_rotation_drift_rad_per_sqrt_s=ROTATION_DRIFT_RAD_PER_SQRT_S,
        tag_position_noise_m_at_1m=TAG_POSITION_NOISE_M_AT_1M,
        tag_rotation_noise_rad=TAG_ROTATION_NOISE_RAD,
        tag_depth_noise_ratio=TAG_DEPTH_NOISE_RATIO,
    )
    sim = simulate_session(config)
    truth = generating_variances()
    base = SlamParams(
        tag_position_var_m2=truth[POSITION],
        tag_depth_var_ratio=TAG_DEPTH_NOISE_RATIO**2,  # a σ ratio, as a variance ratio
        odom_angular_var_rad2_per_s=truth[ANGULAR],
    )
    return TuningTarget.prepare(parse_session(sim.upload), base, sim.world_T_tag_true)


def decades_off(values: dict[str, float], name: str) -> float:
    return math.log10(values[name] / generating_variances()[name])


def test_on_a_simulation_the_best_parameters_are_near_the_generating_noise(
    noisy_target: TuningTarget,
) -> None:
    """A 5 × 5 grid ±2 decades around the generating variances, scored by the ground-truth metric
    (tag_position_var fixed at its truth: scaling every variance together changes nothing, so one
    of them must be fixed), and the odometry's angular variance on its own.

    What the data can identify, found by experiment (2000- and 3000-pose walks, seeds 0–5; the
    full 5 × 5 × 5 grid on six of them): the ground-truth metric is flat near the truth — a few %
    over ±1 decade — so a grid finds each variance to about a decade, not better. It is flattest
    along the common-scale direction (tag orientation and odometry variances all up or all down
    together: on this session 0.0274 at the truth, 0.0281 and 0.0296 at the two far corners of
    that diagonal), i.e. mostly their ratios are identified:

    - odom_linear_var: within one decade on 11 of 12 sessions (two decades high once);
    - tag_orientation_var: within one decade on 11 of 12, biased high (+1 decade on 5 of them):
      the simulator's tag rotation noise grows as 1/cos(view angle), E[1/cos²] ≈ 2.1 at its 60°
      limit, and our model has no such term, so the effective variance is above σ²;
    - odom_angular_var: the flattest (the tags' orientations pin the heading; a stiffer odometry
      rotation costs almost nothing): within one decade on 11 of 12 slices, two decades low once.
      In the joint 5 × 5 × 5 grid it wanders further (within one decade on 5 of 6), partly along
      the common-scale direction, so it is held at its truth in the grid and checked as a slice.

    The shift metric identifies none of them: its best is at the grid's stiff-odometry corner on
    most of those sessions (it compares maps with the raw, drifting observations).
    """
    target = noisy_target
    truth = generating_variances()
    space = SearchSpace(
        tuple(
            Axis(name, truth[name] * 1e-2, truth[name] * 1e2, 5) for name in (ORIENTATION, LINEAR)
        )
    )
    trials = [target.run({**values, ANGULAR: truth[ANGULAR]}) for values in space.grid()]
    assert all(t.converged for t in trials)

    best = best_trial(trials, "ground_truth")
    assert best is not None
    assert abs(decades_off(best.values, ORIENTATION)) <= 1 + 1e-9, best.values
    assert abs(decades_off(best.values, LINEAR)) <= 1 + 1e-9, best.values
    # The tuned map is much better than the raw one, and the weights matter: trusting tag
    # orientations 100× less and the odometry 100× more is clearly worse (the other diagonal,
    # both 100× more or less, is almost as good as the best: it keeps their ratio).
    _, gt_pre, _ = target.baseline()
    assert best.gt_metric < 0.5 * gt_pre
    assert max(t.gt_metric for t in trials) > 1.5 * best.gt_metric

    profile = [
        target.run({**truth, ANGULAR: truth[ANGULAR] * 10.0**k}).gt_metric
        for k in (-2, -1, 0, 1, 2)
    ]
    assert abs(int(np.argmin(profile)) - 2) <= 1, profile


# --------------------------------------------------------------------------- the sampler


def bowl(values: dict[str, float]) -> float:
    """A smooth test objective, minimum 1 at an off-grid point of the paper space."""
    centre = {ORIENTATION: -3.3, LINEAR: -5.6, ANGULAR: -1.7}
    return 1.0 + sum((math.log10(values[n]) - c) ** 2 for n, c in centre.items())


def some_history(count: int) -> list[tuple[dict[str, float], float]]:
    grid = SearchSpace.paper_grid().grid()
    points = [grid[(37 * k) % len(grid)] for k in range(count)]
    return [(p, bowl(p)) for p in points]


def test_propose_trials_is_deterministic_for_the_same_history_and_seed() -> None:
    space = SearchSpace.paper_grid()
    for history in ([], some_history(15)):
        first = propose_trials(space, history, count=6, seed=3)
        again = propose_trials(space, list(history), count=6, seed=3)
        other_seed = propose_trials(space, history, count=6, seed=4)
        assert first == again
        assert first != other_seed
        assert len(first) == 6


def test_proposals_stay_inside_the_bounds() -> None:
    space = SearchSpace(
        (Axis(ORIENTATION, 1e-4, 1e-3, 4), Axis(LINEAR, 3e-7, 2e-6, 4), Axis(ANGULAR, 0.5, 0.9, 4))
    )
    history = [(p, bowl(p)) for p in space.grid()[:30]]
    # A point from a wider, earlier space is clipped into this one, not refused.
    history.append(({ORIENTATION: 1e-9, LINEAR: 1.0, ANGULAR: 0.7}, 5.0))
    for done in ([], history):
        for proposal in propose_trials(space, done, count=12, seed=0):
            assert list(proposal) == list(space.names)
            for a in space.axes:
                assert a.low <= proposal[a.name] <= a.high, (a.name, proposal[a.name])


def test_proposals_do_not_repeat_the_history_or_each_other() -> None:
    space = SearchSpace.paper_grid()
    history = some_history(24)
    proposals = propose_trials(space, history, count=8, seed=0)
    seen = {tuple(values[n] for n in space.names) for values, _ in history}
    keys = [tuple(p[n] for n in space.names) for p in proposals]
    assert len(set(keys)) == len(keys) == 8
    assert not seen & set(keys)


def test_failed_trials_with_infinite_or_nan_scores_are_accepted() -> None:
    space = SearchSpace.paper_grid()
    history = some_history(12)
    failed = [(values, math.inf) for values, _ in history[:5]]
    failed += [(values, math.nan) for values, _ in history[5:7]]
    mixed = failed + history[7:]
    assert len(propose_trials(space, mixed, count=4, seed=1)) == 4
    assert len(propose_trials(space, failed, count=4, seed=1)) == 4
    # A failed trial is not a good one: the sampler does not treat inf as a score to approach.
    assert propose_trials(space, mixed, count=4, seed=1) != propose_trials(
        space, [(v, 1.0) for v, _ in failed] + history[7:], count=4, seed=1
    )


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_sampler_beats_the_paper_grid_on_a_smooth_bowl_in_80_trials(seed: int) -> None:
    """80 trials, 8% of the 1000-point grid's (9 of them the box's corners and centre), find a
    lower point of the bowl than the grid."""
    space = SearchSpace.paper_grid()
    grid_best = min(bowl(p) for p in space.grid())
    plan = SweepPlan(method="sampler", space=space, trials=80, seed=seed)
    done: list[Trial] = []
    while batch := plan.next_batch(done, len(done)):
        assert len(batch) <= plan.batch
        done += [make_trial(values, shift=bowl(values)) for values in batch]
    assert len(done) == 80
    assert min(t.shift for t in done) <= grid_best


def test_the_sampler_starts_at_the_corners_and_centre_of_its_box() -> None:
    """A best setting on the box's edge (as occam_room's, by the shift metric) is tried first."""
    space = SearchSpace((Axis(LINEAR, 1e-8, 1.0, 10), Axis(ANGULAR, 1e-6, 1e-2, 10)))
    plan = SweepPlan(method="sampler", space=space, trials=20, batch=4, seed=0)
    corners = [
        {LINEAR: 1e-8, ANGULAR: 1e-6},
        {LINEAR: 1e-8, ANGULAR: 1e-2},
        {LINEAR: 1.0, ANGULAR: 1e-6},
        {LINEAR: 1.0, ANGULAR: 1e-2},
    ]
    assert plan.initial_design() == [*corners, {LINEAR: 1e-4, ANGULAR: pytest.approx(1e-4)}]
    assert plan.next_batch([], 0) == corners
    done = [make_trial(values, shift=1.0) for values in corners]
    second = plan.next_batch(done, 4)
    assert second[0] == plan.initial_design()[4]
    assert len(second) == 4  # the centre, then the sampler's
    for values in second[1:]:
        assert 1e-8 <= values[LINEAR] <= 1.0
        assert 1e-6 <= values[ANGULAR] <= 1e-2
    # too few trials for 2^d + 1 of them: no fixed design
    assert SweepPlan(method="sampler", space=space, trials=9).initial_design() == []
    assert SweepPlan(method="grid", space=space).initial_design() == []


def test_the_sampler_matches_a_small_grid_on_a_real_session_with_the_same_budget() -> None:
    """occam_room, shift metric, odometry variances: 16 grid points against 16 sampler trials.
    The angular range stops at 1e-2 rad²/s: at 1 (σ 1 rad per √s, a heading free between tag
    sightings) with the stiffest linear variance the grid's corner is an isolated optimum that 16
    trials are not meant to find. (The paper-sized comparison is in ``bench/tuning.py``.)"""
    target = TuningTarget.prepare(load_session(DATA_DIR / "sessions" / "occam_room.json"))
    space = SearchSpace((Axis(LINEAR, 1e-8, 1.0, 4), Axis(ANGULAR, 1e-8, 1e-2, 4)))
    grid_best = best_trial([target.run(p) for p in space.grid()], "shift")
    assert grid_best is not None
    plan = SweepPlan(method="sampler", space=space, trials=16, seed=0)
    done: list[Trial] = []
    while batch := plan.next_batch(done, len(done)):
        done += [target.run(values) for values in batch]
    sampler_best = best_trial(done, "shift")
    assert sampler_best is not None
    assert sampler_best.shift <= 1.02 * grid_best.shift
    assert sampler_best.shift < target.baseline()[0]


# --------------------------------------------------------------------------- summaries


def hand_made_trials() -> list[Trial]:
    return [
        make_trial({"x": 1.0}, shift=0.30, gt_metric=0.10, tag_rmse_m=0.5),
        make_trial({"x": 2.0}, shift=0.10, gt_metric=0.20, tag_rmse_m=0.4),  # best shift
        make_trial({"x": 3.0}, shift=0.20, gt_metric=0.05, tag_rmse_m=0.3),  # best GT
        # Better on both, but LM hit its cap: never chosen, not in the correlation.
        make_trial(
            {"x": 4.0},
            shift=0.01,
            gt_metric=0.01,
            tag_rmse_m=0.1,
            iterations=TRIAL_MAX_ITERATIONS,
        ),
        make_trial({"x": 5.0}, shift=math.nan, iterations=0, error="optimization failed: x"),
        make_trial({"x": 6.0}, shift=0.40, gt_metric=0.30, tag_rmse_m=0.6),
    ]


def test_summarize_hand_worked() -> None:
    summary = summarize(hand_made_trials(), "shift", (0.5, 0.25, 0.7))
    assert summary.runs == 6
    assert summary.objective == "shift"
    assert summary.best_values == {"x": 2.0}
    assert summary.best_shift == 0.10
    assert summary.shift_pre == 0.5
    assert summary.gt_metric_pre == 0.25
    assert summary.gt_metric_at_best_shift == 0.20
    assert summary.gt_metric_best == 0.05
    assert summary.best_gt_values == {"x": 3.0}
    assert summary.tag_rmse_pre_m == 0.7
    assert summary.tag_rmse_at_best_shift_m == 0.4
    assert summary.tag_rmse_at_best_gt_m == 0.3
    # Converged trials with both metrics: shift ranks (A, B, C, F) = 3 1 2 4, GT ranks 2 3 1 4;
    # Σd² = 1 + 4 + 1 + 0 = 6, rho = 1 − 6·6 / (4·15) = 0.4.
    assert summary.shift_gt_spearman == pytest.approx(0.4, abs=1e-12)

    by_gt = summarize(hand_made_trials(), "ground_truth", (0.5, 0.25, 0.7))
    assert by_gt.best_values == {"x": 3.0}
    assert by_gt.best_shift == 0.20  # the shift metric of the trial the objective chose


def test_summary_of_nothing_is_json_ready_with_nulls() -> None:
    summary = summarize([], "shift", (0.2, math.nan, math.nan))
    document = json.loads(json.dumps(summary.to_dict(), allow_nan=False))
    assert document["runs"] == 0
    assert document["best_values"] is None
    assert document["best_shift"] is None
    assert document["shift_pre"] == 0.2
    assert document["gt_metric_pre"] is None
    assert document["shift_gt_spearman"] is None


def test_best_trial_ignores_unconverged_failed_and_nan_trials() -> None:
    trials = hand_made_trials()
    assert best_trial(trials, "shift") is trials[1]
    assert best_trial(trials, "ground_truth") is trials[2]
    assert best_trial(trials[3:5], "shift") is None
    no_gt = [make_trial({"x": 1.0}, shift=0.3), make_trial({"x": 2.0}, shift=0.2)]
    assert best_trial(no_gt, "ground_truth") is None
    assert best_trial(no_gt, "shift") is no_gt[1]
    # Ties: the first.
    tied = [make_trial({"x": 1.0}, shift=0.2), make_trial({"x": 2.0}, shift=0.2)]
    assert best_trial(tied, "shift") is tied[0]


def test_trial_score_and_json() -> None:
    at_cap = make_trial(shift=0.1, iterations=TRIAL_MAX_ITERATIONS)
    just_under = make_trial(shift=0.1, iterations=TRIAL_MAX_ITERATIONS - 1)
    assert not at_cap.converged
    assert at_cap.score("shift") == math.inf
    assert just_under.score("shift") == 0.1
    assert just_under.score("ground_truth") == math.inf  # NaN GT
    document = json.loads(json.dumps(just_under.to_dict(), allow_nan=False))
    assert document["gt_metric"] is None
    assert document["converged"] is True


@pytest.mark.parametrize(
    ("pairs", "expected"),
    [
        ([(0.1, 0.4), (0.2, 0.3), (0.3, 0.2), (0.4, 0.1)], -1.0),
        ([(1.0, 1.0), (2.0, 4.0), (3.0, 9.0)], 1.0),  # ranks, not values
        # d = 0 1 1 0 → rho = 1 − 6·2 / (4·15) = 0.8
        ([(1.0, 10.0), (2.0, 30.0), (3.0, 20.0), (4.0, 40.0)], 0.8),
        # d = 2 0 −2 → rho = 1 − 6·8 / (3·8) = −1
        ([(1.0, 3.0), (2.0, 2.0), (3.0, 1.0)], -1.0),
    ],
)
def test_shift_gt_correlation_hand_worked(pairs, expected) -> None:
    trials = [make_trial(shift=s, gt_metric=g) for s, g in pairs]
    assert shift_gt_correlation(trials) == pytest.approx(expected, abs=1e-12)
    assert shift_gt_correlation(trials[::-1]) == pytest.approx(expected, abs=1e-12)


def test_shift_gt_correlation_uses_converged_trials_with_both_metrics_only() -> None:
    rising = [make_trial(shift=s, gt_metric=s) for s in (0.1, 0.2, 0.3, 0.4)]
    spoilers = [
        make_trial(shift=0.05, gt_metric=0.9, iterations=TRIAL_MAX_ITERATIONS),
        make_trial(shift=0.01, gt_metric=math.nan),
        make_trial(shift=math.nan, iterations=0, error="optimization failed"),
    ]
    assert shift_gt_correlation(rising + spoilers) == pytest.approx(1.0, abs=1e-12)
    assert math.isnan(shift_gt_correlation(rising[:2] + spoilers))  # fewer than 3
    constant_gt = [make_trial(shift=s, gt_metric=0.2) for s in (0.1, 0.2, 0.3)]
    assert math.isnan(shift_gt_correlation(constant_gt))


# --------------------------------------------------------------------------- plots


def png_image(data: bytes) -> Image.Image:
    assert data[:8] == PNG_MAGIC
    image = Image.open(io.BytesIO(data))
    image.load()
    return image.convert("RGB")


def has_colour(image: Image.Image, rgb: tuple[int, int, int], tolerance: int = 12) -> bool:
    pixels = np.asarray(image, dtype=np.int64)
    return bool(np.any(np.all(np.abs(pixels - np.array(rgb)) <= tolerance, axis=-1)))


def grid_trials(space: SearchSpace) -> list[Trial]:
    """Scores rising with distance from the grid's middle point (finite shift and GT)."""
    trials = []
    for values in space.grid():
        spread = sum(abs(math.log10(v) + 4) for v in values.values())
        trials.append(make_trial(values, shift=0.1 + spread, gt_metric=0.05 + 0.5 * spread))
    return trials


PAPER_SMALL = SearchSpace(tuple(Axis(name, 1e-8, 1.0, 5) for name in PAPER_GRID_AXES))


@pytest.mark.parametrize(
    ("space", "size"),
    [
        (PAPER_SMALL, (1242, 360)),  # three pairs of axes: one row of three panels
        (SearchSpace(PAPER_SMALL.axes[:2]), (414, 360)),  # one pair
        (SearchSpace(PAPER_SMALL.axes[:1]), (414, 360)),  # one axis: score against value
        (  # four axes: six pairs, two rows
            SearchSpace((*PAPER_SMALL.axes, Axis(POSITION, 1e-6, 1e-2, 3))),
            (1242, 720),
        ),
    ],
)
def test_heatmap_of_a_grid_is_a_png_with_a_panel_per_pair(space, size) -> None:
    image = png_image(heatmap_png(space, grid_trials(space), objective="shift"))
    assert image.size == size
    if len(space.axes) > 1:
        assert has_colour(image, RED_RGB)  # the best trial's star


def test_heatmap_of_sampler_trials_bins_off_grid_values() -> None:
    rng = np.random.default_rng(0)
    trials = [
        make_trial(
            {n: float(10 ** rng.uniform(-8, 0)) for n in PAPER_GRID_AXES},
            shift=float(rng.uniform(0.01, 0.2)),
        )
        for _ in range(40)
    ]
    image = png_image(heatmap_png(PAPER_SMALL, trials, objective="shift"))
    assert image.size == (1242, 360)
    assert has_colour(image, RED_RGB)


@pytest.mark.parametrize("space", [PAPER_SMALL, SearchSpace(PAPER_SMALL.axes[:1])])
def test_heatmap_without_usable_trials_is_still_a_png(space) -> None:
    failed = [make_trial(v, shift=math.nan, error="optimization failed") for v in space.grid()]
    for trials in ([], failed):
        image = png_image(heatmap_png(space, trials, objective="shift"))
        assert image.size[0] > 0
        assert not has_colour(image, RED_RGB)  # no best trial, no star


def test_shift_vs_gt_marks_both_choices() -> None:
    image = png_image(shift_vs_gt_png(grid_trials(PAPER_SMALL)))
    assert image.size == (540, 432)
    assert has_colour(image, RED_RGB)
    assert has_colour(image, GREEN_RGB)


@pytest.mark.parametrize(
    "trials",
    [
        [],
        [make_trial({LINEAR: 1e-3}, shift=0.1), make_trial({LINEAR: 1e-2}, shift=0.2)],  # no GT
        [make_trial({LINEAR: 1e-3}, shift=math.nan, error="optimization failed")],
    ],
)
def test_shift_vs_gt_without_ground_truth_is_an_empty_plot(trials) -> None:
    image = png_image(shift_vs_gt_png(trials))
    assert image.size == (540, 432)
    assert not has_colour(image, RED_RGB)
    assert not has_colour(image, GREEN_RGB)


# --------------------------------------------------------------------------- real sessions


def test_a_real_session_trial_scores_all_three_metrics() -> None:
    session: Session = load_session(DATA_DIR / "sessions" / "occam_room.json")
    truth = load_ground_truth(DATA_DIR / "ground_truth" / "occam_room_tape.json")
    target = TuningTarget.prepare(session, SlamParams(), truth)
    shift_pre, gt_pre, rmse_pre = target.baseline()
    assert gt_pre == pytest.approx(0.0553, abs=5e-4)  # data/README.md's reference
    assert shift_pre > 0
    assert rmse_pre > 0
    trial = target.run({LINEAR: 1e-3, ANGULAR: 1e-4, ORIENTATION: 1e-1})  # the defaults
    assert trial.converged
    assert trial.values == {LINEAR: 1e-3, ANGULAR: 1e-4, ORIENTATION: 1e-1}
    assert 0 < trial.gt_metric < gt_pre
    assert 0 < trial.shift < shift_pre
    with pytest.raises(ParameterError, match="cannot sweep"):
        target.run({"huber_k": 1.0})


# --------------------------------------------------------------------------- builds


#: floor_2_straight's shift-chosen setting on the paper grid: its trial (warm-started from the
#: base optimum) stops far from where the build (from raw odometry) stops, GT 0.0428 against 0.0471.
#: LM does not converge there within 100 iterations (steps of millimetres each, issue 25).
_GRID = SearchSpace.paper_grid().axes[0].values()
FLAT_SETTING = {ORIENTATION: float(_GRID[2]), LINEAR: float(_GRID[2]), ANGULAR: float(_GRID[0])}


@pytest.fixture(scope="module")
def floor_2() -> TuningTarget:
    session = load_session(DATA_DIR / "sessions" / "floor_2_straight.json")
    truth = load_ground_truth(DATA_DIR / "ground_truth" / "rtabmap_mac_1_2.txt")
    return TuningTarget.prepare(session, SlamParams(), truth)


@pytest.fixture(scope="module")
def occam() -> TuningTarget:
    session = load_session(DATA_DIR / "sessions" / "occam_room.json")
    truth = load_ground_truth(DATA_DIR / "ground_truth" / "occam_room_tape.json")
    return TuningTarget.prepare(session, SlamParams(), truth)


def scores(build: Trial) -> tuple[object, ...]:
    """Everything of a build but its duration."""
    return (build.values, build.shift, build.gt_metric, build.tag_rmse_m, build.iterations)


@pytest.mark.parametrize("values", [FLAT_SETTING, {}], ids=["flat", "defaults"])
def test_a_build_is_the_map_optimize_session_makes_scored_as_evaluate_scores_it(
    floor_2: TuningTarget, values: dict[str, float]
) -> None:
    """Independently: the map ``apply`` makes (``optimize_session`` with the base parameters and
    the values as given, marginals and all) and the metrics ``invisible-map evaluate`` reports
    of it."""
    result = optimize_session(
        floor_2.session, SlamParams(estimate_noise=False).with_overrides(values)
    )
    evaluation = evaluate_map(floor_2.session, result, floor_2.ground_truth)

    build = floor_2.build(values)

    assert build.values == values
    assert build.shift == evaluation.shift_opt
    assert build.gt_metric == evaluation.gt_metric_opt
    assert build.tag_rmse_m == evaluation.tag_rmse_opt_m
    assert build.iterations == result.stats.iterations
    # the flat setting crawls: still moving tags by millimetres at the cap, and says so
    assert build.converged == (values == {})
    assert build.error is None
    assert math.isfinite(build.gt_metric)
    # Same inputs, same numbers: a second build is the first, bit for bit.
    assert scores(floor_2.build(values)) == scores(build)


def test_build_params_are_the_base_parameters_with_the_values() -> None:
    base = SlamParams(huber_k=0.0, max_iterations=40)
    target = TuningTarget.prepare(load_session(DATA_DIR / "sessions" / "onetag.json"), base)
    params = target.build_params({LINEAR: 1e-2})
    assert params == base.with_overrides(
        {LINEAR: 1e-2, "compute_marginals": False, "estimate_noise": False}
    )
    assert params.max_iterations == 40  # not the trials' cap
    with pytest.raises(ParameterError, match="cannot sweep"):
        target.build({"huber_k": 1.0})


def test_a_build_that_fails_is_reported_not_raised(monkeypatch, occam: TuningTarget) -> None:
    def fail(*_args, **_kwargs):
        raise RuntimeError("Indeterminant linear system")

    monkeypatch.setattr(tuning, "optimize_session", fail)
    build = occam.build({LINEAR: 1.0})
    assert build.error == "optimization failed: Indeterminant linear system"
    assert not build.converged
    assert math.isnan(build.gt_metric)
    assert build.to_dict()["gt_metric"] is None


def chosen_trials() -> list[Trial]:
    """Made-up trial scores, far from any build's, so a figure shows where it came from."""
    return [
        make_trial({LINEAR: 1e-2, ANGULAR: 1e-4}, shift=0.1, gt_metric=0.3, tag_rmse_m=3.0),
        make_trial({LINEAR: 1e-4, ANGULAR: 1e-6}, shift=0.2, gt_metric=0.05, tag_rmse_m=5.0),
        make_trial({LINEAR: 1.0, ANGULAR: 1.0}, shift=0.01, iterations=TRIAL_MAX_ITERATIONS),
    ]


def test_a_sweep_result_builds_the_chosen_settings(occam: TuningTarget) -> None:
    trials = chosen_trials()
    shift_build = occam.build(trials[0].values)
    gt_build = occam.build(trials[1].values)

    result = sweep_result(occam, trials, "shift")

    assert result.summary == summarize(trials, "shift", occam.baseline())
    assert result.shift_chosen is not None
    assert result.gt_chosen is not None
    assert scores(result.shift_chosen) == scores(shift_build)
    assert scores(result.gt_chosen) == scores(gt_build)
    assert result.best is result.shift_chosen
    report = json.loads(json.dumps(result.to_dict(), allow_nan=False))
    assert report["best_values"] == trials[0].values
    assert report["best_gt_values"] == trials[1].values
    # The summary: the trials'.
    assert report["best_shift"] == 0.1
    assert report["gt_metric_at_best_shift"] == 0.3
    assert report["tag_rmse_at_best_shift_m"] == 3.0
    assert report["gt_metric_best"] == 0.05
    assert report["tag_rmse_at_best_gt_m"] == 5.0
    # Beside it, the builds: made-up trials are not their builds, and the report says so.
    assert report["builds"]["shift_chosen"]["gt_metric"] == shift_build.gt_metric
    assert report["builds"]["gt_chosen"]["values"] == trials[1].values
    assert report["builds_equal_trials"] is False
    # And the baseline as before.
    shift_pre, gt_pre, rmse_pre = occam.baseline()
    assert (report["shift_pre"], report["gt_metric_pre"], report["tag_rmse_pre_m"]) == (
        shift_pre,
        gt_pre,
        rmse_pre,
    )

    by_gt = sweep_result(occam, trials, "ground_truth")
    assert by_gt.best is by_gt.gt_chosen
    assert by_gt.to_dict()["best_values"] == trials[1].values


def test_the_builds_of_real_trials_equal_them(occam: TuningTarget) -> None:
    trials = [occam.run({LINEAR: value}) for value in (1e-5, 1e-3, 1e-1)]
    result = sweep_result(occam, trials, "shift")
    assert result.builds_equal_trials
    by_shift = min(trials, key=lambda t: t.shift)
    assert result.shift_chosen is not None
    assert scores(result.shift_chosen) == scores(by_shift)


def test_a_sweep_result_builds_a_setting_both_metrics_chose_once(occam: TuningTarget) -> None:
    trials = [
        make_trial({LINEAR: 1e-2}, shift=0.1, gt_metric=0.05),
        make_trial({LINEAR: 1e-4}, shift=0.2, gt_metric=0.3),
    ]
    result = sweep_result(occam, trials, "shift")
    assert result.gt_chosen is result.shift_chosen
    report = result.to_dict()
    assert report["gt_metric_best"] == report["gt_metric_at_best_shift"]


def test_a_sweep_result_without_ground_truth_or_trials_has_nulls(occam: TuningTarget) -> None:
    no_truth = TuningTarget.prepare(occam.session, occam.base_params)
    result = sweep_result(no_truth, [make_trial({LINEAR: 1e-2}, shift=0.1)], "shift")
    assert result.gt_chosen is None
    report = json.loads(json.dumps(result.to_dict(), allow_nan=False))
    assert result.shift_chosen is not None
    assert report["best_shift"] == 0.1
    assert report["gt_metric_at_best_shift"] is None
    assert report["gt_metric_best"] is None
    assert report["builds"]["gt_chosen"] is None

    nothing = json.loads(json.dumps(sweep_result(occam, [], "shift").to_dict(), allow_nan=False))
    assert nothing["best_values"] is None
    assert nothing["best_shift"] is None
    assert nothing["builds_equal_trials"] is True  # nothing to check
    assert nothing["builds"] == {"shift_chosen": None, "gt_chosen": None}


def test_spearman_gives_tied_values_their_mean_rank_whatever_the_order() -> None:
    """Hand-worked: shifts (1, 1, 2, 3) against GT (4, 3, 2, 1). Shift ranks with the tie
    averaged are (0.5, 0.5, 2, 3), GT ranks (3, 2, 1, 0); Pearson of those is −0.9487."""

    def trial(shift: float, gt: float) -> Trial:
        return Trial(
            values={}, shift=shift, gt_metric=gt, tag_rmse_m=0.0, iterations=3, duration_s=0.0
        )

    points = [(1.0, 4.0), (1.0, 3.0), (2.0, 2.0), (3.0, 1.0)]
    expected = -0.9 / math.sqrt(0.9)  # cov(x, y) / (σx σy) with the mean ranks, written out
    forward = shift_gt_correlation([trial(*p) for p in points])
    backward = shift_gt_correlation([trial(*p) for p in reversed(points)])
    assert forward == pytest.approx(backward)
    assert forward == pytest.approx(expected, abs=1e-12)


def test_unknown_objectives_and_non_integer_counts_are_refused() -> None:
    trial = Trial(values={}, shift=0.1, gt_metric=0.2, tag_rmse_m=0.0, iterations=3, duration_s=0)
    with pytest.raises(ParameterError, match="unknown objective 'gt'"):
        trial.score("gt")
    with pytest.raises(ParameterError, match="num must be an integer"):
        SearchSpace.from_dict({"gravity_var_rad2": {"low": 1e-6, "high": 1.0, "num": 2.7}})
    with pytest.raises(ParameterError, match="expected a number"):
        SearchSpace.from_dict({"gravity_var_rad2": {"low": True, "high": 1.0}})


def test_run_sweep_refuses_zero_processes() -> None:
    from workers.sweep_pool import run_sweep

    session = load_session(DATA_DIR / "sessions" / "onetag.json")
    plan = SweepPlan(method="grid", space=SearchSpace((Axis("gravity_var_rad2", 1e-4, 1e-2, 2),)))
    with pytest.raises(ParameterError, match="processes must be ≥ 1"):
        run_sweep(session, plan, processes=0)


def test_plots_drawn_from_many_threads_at_once_all_succeed() -> None:
    """The API renders plots in its thread pool; pyplot is not thread-safe (without the lock
    about half of 40 parallel renders failed)."""
    from concurrent.futures import ThreadPoolExecutor

    space = SearchSpace(PAPER_SMALL.axes[:2])  # one panel: quick to draw, still pyplot
    trials = grid_trials(space)
    with_gt = [make_trial(t.values, shift=t.shift, gt_metric=t.shift * 2) for t in trials]

    def render(k: int) -> bytes:
        if k % 2:
            return shift_vs_gt_png(with_gt, gt_metric_pre=0.5)
        return heatmap_png(space, trials, objective="shift")

    with ThreadPoolExecutor(8) as pool:
        images = list(pool.map(render, range(16)))
    assert all(png.startswith(b"\x89PNG") for png in images)
    assert len(set(images[::2])) == 1  # the same heat map every time
