"""A sweep trial is the map a build with its parameters makes (architecture §5), bit for bit.

A trial takes shortcuts a build does not: it reuses the session's screening, factor kinds and
COLAMD ordering, starts Levenberg–Marquardt from the optimum with the default variances (computed
once per sweep) and computes no marginals. A build (``optimize_session``) optimizes any setting
but the defaults in two stages: first with the default variances from raw odometry, then with its
own from there. So the trial's LM run is the build's second stage: same graph, same start, same
ordering. Checked on real sessions at the eight corners of the paper grid (every variance at 1e-8
or 1), at the defaults, and at the setting whose build from raw odometry did not converge in 100
iterations on floor_2_straight before builds started from the defaults' optimum.

A trial is a setting of the variances *as given* (``estimate_noise`` off): a build that estimates
the walk's noise from its residuals starts from the setting and ends elsewhere, so ``apply``
rebuilds with ``estimate_noise`` off, and so do these builds.
"""

from __future__ import annotations

import itertools
import math
from pathlib import Path

import numpy as np
import pytest

from app.domain.evaluation.ground_truth import load_ground_truth
from app.domain.evaluation.table import evaluate_map
from app.domain.evaluation.tuning import PAPER_GRID_AXES, PAPER_GRID_RANGE, TuningTarget
from app.domain.mapping.params import SlamParams
from app.domain.mapping.slam import optimize_session
from app.domain.upload.session import load_session

DATA_DIR = Path(__file__).parents[2] / "data"

LOW, HIGH = PAPER_GRID_RANGE
CORNERS = [
    dict(zip(PAPER_GRID_AXES, c, strict=True)) for c in itertools.product((LOW, HIGH), repeat=3)
]
DEFAULTS = dict(zip(PAPER_GRID_AXES, (1e-1, 1e-3, 1e-4), strict=True))
#: floor_2_straight's best grid point by ground truth: from raw odometry LM took 284 iterations
#: (and stopped at the 100-iteration cap with a map 42% worse than the first observations).
FLOOR_2_STIFF = dict(zip(PAPER_GRID_AXES, (1.0, 1e-8, 1.0), strict=True))


def prepared(name: str) -> TuningTarget:
    session = load_session(DATA_DIR / "sessions" / f"{name}.json")
    truth = load_ground_truth(DATA_DIR / "ground_truth" / "rtabmap_mac_1_2.txt")
    return TuningTarget.prepare(session, SlamParams(), truth)


@pytest.fixture(scope="module")
def desnat() -> TuningTarget:
    return prepared("desnat_straight_once")


@pytest.fixture(scope="module")
def floor_2() -> TuningTarget:
    return prepared("floor_2_straight")


def assert_trial_is_build(target: TuningTarget, values: dict[str, float]) -> bool:
    """A converged trial is its build, bit for bit; a trial that did not converge (LM still
    moving a pose or tag by more than ``converged_step_m`` / ``converged_step_rad`` at the trial
    cap) says so, and is never chosen. Returns whether the trial converged."""
    build = optimize_session(target.session, target.build_params(values))
    build_map = build.tag_poses()

    trial = target.run(values)
    if not trial.converged:
        assert trial.iterations == trial.max_iterations
        assert trial.score("ground_truth") == math.inf
        return False
    trial_map, _, _ = target.graph.refine(target.trial_params(values), target.warm_start)

    assert trial.iterations == build.stats.iterations
    assert sorted(trial_map) == sorted(build_map)
    if not target.trial_params(values).has_default_variances:
        for tag_id, world_T_tag in build_map.items():
            np.testing.assert_array_equal(trial_map[tag_id], world_T_tag)
    assert (trial.shift, trial.gt_metric, trial.tag_rmse_m) == target.score_map(build_map)
    return True


@pytest.mark.parametrize(
    "values",
    [*CORNERS, DEFAULTS],
    ids=lambda v: "/".join(f"{x:.0e}" for x in v.values()),
)
def test_a_converged_trial_is_its_build(desnat: TuningTarget, values: dict[str, float]) -> None:
    converged = assert_trial_is_build(desnat, values)
    # the stiff-odometry corners crawl (steps of mm per iteration at 25 iterations); the others,
    # and the defaults, converge
    stiff = (
        values["odom_angular_var_rad2_per_s"] == LOW and values["tag_orientation_var_rad2"] == LOW
    )
    assert converged or stiff


def test_the_stiff_setting_that_broke_a_build_from_raw_odometry(floor_2: TuningTarget) -> None:
    """floor_2_straight at (1, 1e-8, 1): before issue 25 its trial stopped after a few iterations
    on the 0.1% cost tolerance and was called converged; LM was still moving tags by a centimetre
    per iteration there. It is now reported as not converged (and so never chosen), and its
    build runs to the iteration cap, still moving."""
    assert not assert_trial_is_build(floor_2, FLOOR_2_STIFF)
    build = floor_2.build(FLOOR_2_STIFF)
    assert not build.converged
    assert build.iterations == floor_2.base_params.max_iterations


def test_a_build_at_the_defaults_is_one_stage() -> None:
    session = load_session(DATA_DIR / "sessions" / "desnat_straight_once.json")
    given = SlamParams(huber_k=2.0, estimate_noise=False)
    at_defaults = optimize_session(session, given)
    stiff = optimize_session(session, given.with_overrides({"odom_linear_var_m2_per_s": 1e-6}))

    assert at_defaults.stats.start_iterations == 0
    assert stiff.stats.start_iterations == at_defaults.stats.iterations


@pytest.mark.parametrize(
    "values",
    [*CORNERS, DEFAULTS],
    ids=lambda v: "/".join(f"{x:.0e}" for x in v.values()),
)
def test_a_build_rescore_is_the_build_exactly(
    desnat: TuningTarget, values: dict[str, float]
) -> None:
    """What a sweep reports is the map ``apply`` would make, marginals and all."""
    build = optimize_session(
        desnat.session, desnat.base_params.with_overrides({**values, "estimate_noise": False})
    )
    evaluation = evaluate_map(desnat.session, build, desnat.ground_truth)

    rescored = desnat.build(values)

    assert (rescored.shift, rescored.gt_metric, rescored.tag_rmse_m) == (
        evaluation.shift_opt,
        evaluation.gt_metric_opt,
        evaluation.tag_rmse_opt_m,
    )
    assert rescored.iterations == build.stats.iterations
