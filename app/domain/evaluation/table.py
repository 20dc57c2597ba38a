"""One row of the evaluation table: a map against the pre-optimized baseline and ground truth.

    row = evaluate_map(session, result, ground_truth)     # ground_truth may be None
    row.to_dict()                                         # the ``evaluate --json`` object
    evaluate_joint(joint, alone, ground_truth)            # a map of several sessions (joint.py)

The pre-optimized and optimized maps are compared on the *same* tags: the tags in the optimized
map (a tag whose every detection was rejected is in neither). ``gt_metric_pre_all_tags`` is the
baseline over every tag the session saw, as the reference numbers in the data README define it.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from app.domain.evaluation.metrics import (
    compare_tag_sets,
    ground_truth_metric,
    joint_shift_metric,
    shift_metric,
    tag_rmse_m,
)
from app.domain.frames import FloatArray
from app.domain.mapping.joint import JointMap
from app.domain.mapping.map_result import MapResult
from app.domain.upload.session import Session, first_observation_tag_poses


@dataclass(frozen=True, slots=True, kw_only=True)
class Evaluation:
    """Metrics of one map. NaN where a metric is undefined (no ground truth, too few tags)."""

    dataset: str
    poses: int
    tags: int
    detections_used: int
    detections_rejected: int
    optimize_ms: float
    iterations: int
    gt_metric_pre: float
    gt_metric_opt: float
    gt_metric_pre_all_tags: float
    tag_rmse_pre_m: float
    tag_rmse_opt_m: float
    shift_pre: float
    shift_opt: float
    tags_with_ground_truth: int
    ground_truth_ids_ignored: tuple[int, ...]

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready (NaN becomes None)."""
        out = dataclasses.asdict(self)
        out["ground_truth_ids_ignored"] = list(self.ground_truth_ids_ignored)
        return {k: (None if isinstance(v, float) and math.isnan(v) else v) for k, v in out.items()}


def evaluate_map(
    session: Session,
    result: MapResult,
    ground_truth: Mapping[int, FloatArray] | None = None,
    *,
    dataset: str | None = None,
) -> Evaluation:
    """Compare ``result`` with the first-observation baseline, and with ``ground_truth``."""
    optimized = result.tag_poses()
    pre_same_tags = result.tag_poses_pre()
    pre_all_tags = first_observation_tag_poses(session)
    used = _used_mask(session, result)
    nan = math.nan
    if ground_truth:
        comparison = compare_tag_sets(optimized, ground_truth)
        gt_pre, gt_opt = (
            ground_truth_metric(pre_same_tags, ground_truth),
            ground_truth_metric(optimized, ground_truth),
        )
        gt_pre_all = ground_truth_metric(pre_all_tags, ground_truth)
        rmse_pre, rmse_opt = (
            tag_rmse_m(pre_same_tags, ground_truth),
            tag_rmse_m(optimized, ground_truth),
        )
        with_truth, ignored = len(comparison.common), comparison.only_in_ground_truth
    else:
        gt_pre = gt_opt = gt_pre_all = rmse_pre = rmse_opt = nan
        with_truth, ignored = 0, ()
    return Evaluation(
        dataset=dataset or session.map_id,
        poses=session.num_poses,
        tags=len(result.tag_ids),
        detections_used=result.detections_used,
        detections_rejected=len(result.rejections),
        optimize_ms=result.stats.optimize_ms,
        iterations=result.stats.iterations,
        gt_metric_pre=gt_pre,
        gt_metric_opt=gt_opt,
        gt_metric_pre_all_tags=gt_pre_all,
        tag_rmse_pre_m=rmse_pre,
        tag_rmse_opt_m=rmse_opt,
        shift_pre=shift_metric(session, pre_same_tags, detection_mask=used),
        shift_opt=shift_metric(session, optimized, detection_mask=used),
        tags_with_ground_truth=with_truth,
        ground_truth_ids_ignored=tuple(ignored),
    )


def _used_mask(session: Session, result: MapResult) -> npt.NDArray[np.bool_]:
    """(M,) True for the detections that entered the graph."""
    used = np.zeros(len(session.detections), dtype=bool)
    used[result.residuals.tag_detection_index] = True
    return used


# --------------------------------------------------------------------------- several sessions


@dataclass(frozen=True, slots=True, kw_only=True)
class SessionComparison:
    """One session of a joint map: its map alone against the joint map, each on the tags of
    that session that the ground truth has (NaN without ground truth or with < 2 such tags)."""

    gt_metric_alone: float
    gt_metric_joint: float
    tag_rmse_alone_m: float
    tag_rmse_joint_m: float
    tags_compared: int

    def to_dict(self) -> dict[str, Any]:
        return {
            k: (None if isinstance(v, float) and math.isnan(v) else v)
            for k, v in dataclasses.asdict(self).items()
        }


@dataclass(frozen=True, slots=True, kw_only=True)
class JointEvaluation:
    """The joint map's row (``dataset`` ``"joint"``, over all its tags) and each session's
    comparison, by dataset name."""

    row: Evaluation
    by_session: dict[str, SessionComparison]

    def to_dict(self) -> dict[str, Any]:
        """The ``evaluate --joint --json`` object: the usual fields and ``by_session``."""
        return {
            **self.row.to_dict(),
            "by_session": {name: c.to_dict() for name, c in self.by_session.items()},
        }


def evaluate_joint(
    joint: JointMap,
    alone: Mapping[str, MapResult],
    ground_truth: Mapping[int, FloatArray] | None = None,
) -> JointEvaluation:
    """The joint map against its pre-optimized baseline (first sightings, sessions placed by
    their alignments) and ground truth, and each session's map alone (``alone``, by dataset)
    against the joint map on that session's tags. The shift metrics are over every session's own
    detections (:func:`joint_shift_metric`)."""
    row = evaluate_map(joint.combined, joint.map, ground_truth, dataset="joint")
    row = dataclasses.replace(
        row,
        shift_pre=joint_shift_metric(joint, joint.map.tag_poses_pre()),
        shift_opt=joint_shift_metric(joint),
    )
    nan = math.nan
    by_session = {}
    for part in joint.parts:
        alone_T_tag = alone[part.dataset].tag_poses()
        joint_T_tag = joint.map.tag_poses()
        tags = sorted(set(part.tag_ids) & set(alone_T_tag) & set(ground_truth or {}))
        if ground_truth and len(tags) >= 2:
            alone_tags = {t: alone_T_tag[t] for t in tags}
            joint_tags = {t: joint_T_tag[t] for t in tags}
            comparison = SessionComparison(
                gt_metric_alone=ground_truth_metric(alone_tags, ground_truth),
                gt_metric_joint=ground_truth_metric(joint_tags, ground_truth),
                tag_rmse_alone_m=tag_rmse_m(alone_tags, ground_truth),
                tag_rmse_joint_m=tag_rmse_m(joint_tags, ground_truth),
                tags_compared=len(tags),
            )
        else:
            comparison = SessionComparison(
                gt_metric_alone=nan,
                gt_metric_joint=nan,
                tag_rmse_alone_m=nan,
                tag_rmse_joint_m=nan,
                tags_compared=len(tags),
            )
        by_session[part.dataset] = comparison
    return JointEvaluation(row=row, by_session=by_session)
