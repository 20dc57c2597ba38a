"""One row of the evaluation table: a map against the pre-optimized baseline and ground truth.

    row = evaluate_map(session, result, ground_truth)     # ground_truth may be None
    row.to_dict()                                         # the ``evaluate --json`` object
    evaluate_joint(joint, alone, ground_truth)            # a map of several sessions (joint.py)
    compare_walk(joint, part, alone, ground_truth)        # one walk alone against the building

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
from app.domain.mapping.joint import JointMap, SessionPart
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
class TagComparison:
    """One walk's map alone against the building map on a set of its tags, each against the
    ground truth (NaN without ground truth or with fewer than 2 such tags), and without ground
    truth the RMS distance between the two after a rigid fit: how far joining moved them.

    tags: the tags compared; with_truth: how many of them the ground truth has (the metrics are
    over those); moved_rms_m: (alone → building, after a best rigid fit, over all), m."""

    tags: tuple[int, ...]
    with_truth: int
    gt_metric_alone: float
    gt_metric_joint: float
    tag_rmse_alone_m: float
    tag_rmse_joint_m: float
    moved_rms_m: float

    def to_dict(self) -> dict[str, Any]:
        out = _finite_dict(dataclasses.asdict(self))
        out["tags"] = list(self.tags)
        out["tags_compared"] = len(self.tags)
        return out


@dataclass(frozen=True, slots=True, kw_only=True)
class SessionComparison:
    """One session of a joint map, honestly: its map alone against the building map on *all* its
    tags (the flat fields, as issue 15 named them; before issue 25 a walk was compared only on
    the tags that placed it, and regressions elsewhere read as improvements), and apart on its
    ``shared`` tags (other walks placed them too) and its ``own`` tags (no other walk saw
    them: what the building map did to the part of the map only this walk knows). Also what it
    weighs in the map and why (``weighting``, the disagreement factor, its noise)."""

    gt_metric_alone: float
    gt_metric_joint: float
    tag_rmse_alone_m: float
    tag_rmse_joint_m: float
    tags_compared: int
    all_tags: TagComparison
    shared: TagComparison
    own: TagComparison
    disagreement_factor: float = 1.0
    odometry_scale: float = 1.0
    weighting: str = ""

    def to_dict(self) -> dict[str, Any]:
        return {
            "gt_metric_alone": _finite_or_none(self.gt_metric_alone),
            "gt_metric_joint": _finite_or_none(self.gt_metric_joint),
            "tag_rmse_alone_m": _finite_or_none(self.tag_rmse_alone_m),
            "tag_rmse_joint_m": _finite_or_none(self.tag_rmse_joint_m),
            "tags_compared": self.tags_compared,
            "moved_rms_m": _finite_or_none(self.all_tags.moved_rms_m),
            "shared": self.shared.to_dict(),
            "own": self.own.to_dict(),
            "disagreement_factor": self.disagreement_factor,
            "odometry_scale": self.odometry_scale,
            "weighting": self.weighting,
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
    alone: Mapping[str, MapResult] | None = None,
    ground_truth: Mapping[int, FloatArray] | None = None,
) -> JointEvaluation:
    """The joint map against its pre-optimized baseline (first sightings, sessions placed by
    their alignments) and ground truth, and each session's map alone (``alone``, by dataset;
    default: each part's own map, ``SessionPart.alone``) against the joint map on all that
    session's tags, its shared ones and its own ones (:func:`compare_walk`). The shift metrics
    are over every session's own detections (:func:`joint_shift_metric`)."""
    row = evaluate_map(joint.combined, joint.map, ground_truth, dataset="joint")
    row = dataclasses.replace(
        row,
        shift_pre=joint_shift_metric(joint, joint.map.tag_poses_pre()),
        shift_opt=joint_shift_metric(joint),
    )
    by_session = {}
    for part in joint.parts:
        walk = alone[part.dataset] if alone is not None else part.alone
        if walk is None:
            raise ValueError(f"no map alone of {part.dataset!r} to compare with")
        by_session[part.dataset] = compare_walk(joint, part, walk, ground_truth)
    return JointEvaluation(row=row, by_session=by_session)


def compare_walk(
    joint: JointMap,
    part: SessionPart,
    alone: MapResult,
    ground_truth: Mapping[int, FloatArray] | None = None,
) -> SessionComparison:
    """One walk's own map against the building map: on all the tags it mapped (those in the
    building map), on its shared ones (other walks saw them too) and on its own ones."""
    alone_T_tag = alone.tag_poses()
    joint_T_tag = joint.map.tag_poses()
    mapped = sorted(set(alone_T_tag) & set(joint_T_tag))
    others = _tags_of_other_walks(joint, part)
    everything = _compared(mapped, alone_T_tag, joint_T_tag, ground_truth)
    return SessionComparison(
        gt_metric_alone=everything.gt_metric_alone,
        gt_metric_joint=everything.gt_metric_joint,
        tag_rmse_alone_m=everything.tag_rmse_alone_m,
        tag_rmse_joint_m=everything.tag_rmse_joint_m,
        tags_compared=len(_with_truth(mapped, ground_truth)),
        all_tags=everything,
        shared=_compared(
            [t for t in mapped if t in others], alone_T_tag, joint_T_tag, ground_truth
        ),
        own=_compared(
            [t for t in mapped if t not in others], alone_T_tag, joint_T_tag, ground_truth
        ),
        disagreement_factor=part.disagreement_factor,
        odometry_scale=part.alignment.odometry_scale,
        weighting=part.weighting,
    )


def _tags_of_other_walks(joint: JointMap, part: SessionPart) -> set[int]:
    """The tags any other walk of the map used (its split-off sightings included)."""
    out: set[int] = set()
    for other in joint.parts:
        if other.dataset != part.dataset:
            out |= set(other.tag_ids) | set(other.local_tags)
    return out


def _with_truth(tags: list[int], ground_truth: Mapping[int, FloatArray] | None) -> list[int]:
    return [t for t in tags if ground_truth is not None and t in ground_truth]


def _compared(
    tags: list[int],
    alone_T_tag: Mapping[int, FloatArray],
    joint_T_tag: Mapping[int, FloatArray],
    ground_truth: Mapping[int, FloatArray] | None,
) -> TagComparison:
    nan = math.nan
    moved = (
        tag_rmse_m({t: alone_T_tag[t] for t in tags}, {t: joint_T_tag[t] for t in tags})
        if len(tags) >= 3
        else nan
    )
    truth_tags = _with_truth(tags, ground_truth)
    if ground_truth is None or len(truth_tags) < 2:
        return TagComparison(
            tags=tuple(tags),
            with_truth=len(truth_tags),
            gt_metric_alone=nan,
            gt_metric_joint=nan,
            tag_rmse_alone_m=nan,
            tag_rmse_joint_m=nan,
            moved_rms_m=moved,
        )
    alone_tags = {t: alone_T_tag[t] for t in truth_tags}
    joint_tags = {t: joint_T_tag[t] for t in truth_tags}
    return TagComparison(
        tags=tuple(tags),
        with_truth=len(truth_tags),
        gt_metric_alone=ground_truth_metric(alone_tags, ground_truth),
        gt_metric_joint=ground_truth_metric(joint_tags, ground_truth),
        tag_rmse_alone_m=tag_rmse_m(alone_tags, ground_truth),
        tag_rmse_joint_m=tag_rmse_m(joint_tags, ground_truth),
        moved_rms_m=moved,
    )


def _finite_or_none(value: float) -> float | None:
    return None if math.isnan(value) else value


def _finite_dict(values: dict[str, Any]) -> dict[str, Any]:
    return {k: (None if isinstance(v, float) and math.isnan(v) else v) for k, v in values.items()}
