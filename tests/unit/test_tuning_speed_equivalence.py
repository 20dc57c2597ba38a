"""A sweep trial measures the map a build with its parameters makes (DESIGN §5).

A trial takes shortcuts a build does not: it reuses the session's screening, factor kinds and
COLAMD ordering, starts Levenberg–Marquardt from the optimum with the base parameters instead of
raw odometry, and computes no marginals. So it must converge to the build's solution, to within
LM's own convergence tolerance (``relative_error_tol``: stop when an iteration lowers the error
by less than 0.1%). Checked against ``optimize_session`` on a real session at the eight corners
of the paper grid (every variance at 1e-8 or 1) and at the defaults:

- everywhere, the trial's final error is the build's to within 0.5% (``ERROR_RTOL``): both solve
  the same least-squares problem equally well;
- where that pins the map down, its tags are within 1 mm of the build's (``POSITION_ATOL_M``) and
  its three scores within 1% (``SCORE_RTOL``). It does not at the three corners with odometry
  angular variance 1 rad²/s (σ 1 rad per √s) and a stiff tag orientation or odometry linear
  variance: the error is so flat along the heading between tag sightings that two LM runs from
  different starts stop 16–245 mm apart, a build from raw odometry and a trial alike.

That is why a sweep reports the settings it chose by their builds (``TuningTarget.build``): the
last test checks, at the same points, that those are the build's scores exactly.
"""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pytest

from app.domain.evaluation import evaluate_map
from app.domain.ground_truth import load_ground_truth
from app.domain.params import SlamParams
from app.domain.session import load_session
from app.domain.slam import optimize_session
from app.domain.tuning import PAPER_GRID_AXES, PAPER_GRID_RANGE, TuningTarget

DATA_DIR = Path(__file__).parents[2] / "data"
ERROR_RTOL = 5e-3
POSITION_ATOL_M = 1e-3
SCORE_RTOL = 1e-2

LOW, HIGH = PAPER_GRID_RANGE
CORNERS = [
    dict(zip(PAPER_GRID_AXES, c, strict=True)) for c in itertools.product((LOW, HIGH), repeat=3)
]
DEFAULTS = dict(zip(PAPER_GRID_AXES, (1e-1, 1e-3, 1e-4), strict=True))
#: (tag orientation, odometry linear) at the corners where the map is not pinned down when the
#: odometry angular variance is 1.
FLAT_HEADING = {(LOW, LOW), (LOW, HIGH), (HIGH, LOW)}


@pytest.fixture(scope="module")
def target() -> TuningTarget:
    session = load_session(DATA_DIR / "sessions" / "desnat_straight_once.json")
    truth = load_ground_truth(DATA_DIR / "ground_truth" / "rtabmap_mac_1_2.txt")
    return TuningTarget.prepare(session, SlamParams(), truth)


def is_flat(values: dict[str, float]) -> bool:
    orientation, linear, angular = (values[name] for name in PAPER_GRID_AXES)
    return angular == HIGH and (orientation, linear) in FLAT_HEADING


@pytest.mark.parametrize(
    "values",
    [*CORNERS, DEFAULTS],
    ids=lambda v: "/".join(f"{x:.0e}" for x in v.values()),
)
def test_a_trial_converges_to_the_build_with_its_parameters(
    target: TuningTarget, values: dict[str, float]
) -> None:
    build = optimize_session(
        target.session, target.base_params.with_overrides({**values, "compute_marginals": False})
    )
    build_map = {int(t): build.world_T_tag[k] for k, t in enumerate(build.tag_ids)}

    trial = target.run(values)
    params = target.trial_params(values)
    trial_map, _, solution = target.graph.optimize(params, initial=target.warm_start)
    trial_error = target.graph.graph(params).error(solution)

    assert trial.converged
    assert trial_error == pytest.approx(build.stats.final_error, rel=ERROR_RTOL)
    if is_flat(values):
        return
    assert sorted(trial_map) == sorted(build_map)
    for tag_id, world_T_tag in build_map.items():
        np.testing.assert_allclose(
            trial_map[tag_id][:3, 3], world_T_tag[:3, 3], atol=POSITION_ATOL_M
        )
    build_scores = target.score_map(build_map)
    trial_scores = (trial.shift, trial.gt_metric, trial.tag_rmse_m)
    assert trial_scores == pytest.approx(build_scores, rel=SCORE_RTOL)


@pytest.mark.parametrize(
    "values",
    [*CORNERS, DEFAULTS],
    ids=lambda v: "/".join(f"{x:.0e}" for x in v.values()),
)
def test_a_build_rescore_is_the_build_exactly(
    target: TuningTarget, values: dict[str, float]
) -> None:
    """Flat corners included: what a sweep reports is the map ``apply`` would make."""
    build = optimize_session(target.session, target.base_params.with_overrides(values))
    evaluation = evaluate_map(target.session, build, target.ground_truth)

    rescored = target.build(values)

    assert (rescored.shift, rescored.gt_metric, rescored.tag_rmse_m) == (
        evaluation.shift_opt,
        evaluation.gt_metric_opt,
        evaluation.tag_rmse_opt_m,
    )
    assert rescored.iterations == build.stats.iterations
