"""Sweeps: a checked plan, their plots, applying the best trial.

What the API routers and the dashboard pages both do; errors are :mod:`app.services.errors`.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from sqlalchemy.orm import Session

from app.domain.errors import InvisibleMapError, ParameterError
from app.domain.evaluation.ground_truth import parse_ground_truth_json
from app.domain.evaluation.sweep_plan import SweepPlan
from app.domain.evaluation.tuning import SearchSpace, best_trial, check_objective
from app.domain.upload.fields import json_text_fault
from app.services.errors import Conflict, InvalidInput
from app.services.maps import checked_overrides, enqueue_rebuild
from app.storage import sweeps
from app.storage.maps import MapInfo
from app.storage.sweeps import SweepInfo

NO_GROUND_TRUTH = ("no_ground_truth", "sweep 4 has no ground truth to plot against")


NO_BEST = ("no_best_trial", "sweep 4 has no converged trial yet: nothing to apply")


def checked_plan(
    *,
    method: str,
    trials: int,
    objective: str,
    seed: int,
    space: Mapping[str, Mapping[str, Any]] | None,
    ground_truth: dict[str, Any] | None,
) -> SweepPlan:
    """The sweep a request asks for (``space`` None: the paper grid), checked: ApiError 422
    naming the field at fault (``space``, which also covers the method and trial count,
    ``ground_truth`` or ``objective``)."""
    try:
        search = SearchSpace.paper_grid() if space is None else SearchSpace.from_dict(space)
        plan = SweepPlan(method=method, space=search, trials=trials, objective=objective, seed=seed)
    except ParameterError as err:
        raise InvalidInput("invalid_sweep", str(err), field="space") from err
    if ground_truth is not None:
        try:
            parse_ground_truth_json(ground_truth)
        except InvisibleMapError as err:
            raise InvalidInput("invalid_ground_truth", str(err), field="ground_truth") from err
        if (fault := json_text_fault(ground_truth)) is not None:  # it is stored as it came
            raise InvalidInput(
                "invalid_ground_truth", f"{fault[0]} {fault[1]}", field="ground_truth"
            )
    try:
        check_objective(plan.objective, has_ground_truth=ground_truth is not None)
    except ParameterError as err:
        raise InvalidInput("invalid_sweep", str(err), field="objective") from err
    return plan


def heatmap_content(db_session: Session, info: SweepInfo) -> bytes:
    """The sweep's heat map, PNG."""
    from app.render.sweep_plots import heatmap_png

    trials = sweeps.list_trials(db_session, info.id)
    return heatmap_png(SearchSpace.from_dict(info.space), trials, objective=info.objective)


def shift_vs_gt_content(db_session: Session, info: SweepInfo) -> bytes:
    """The sweep's shift-vs-ground-truth scatter, PNG; ApiError 409 without ground truth."""
    from app.render.sweep_plots import shift_vs_gt_png

    if not info.has_ground_truth:
        raise Conflict(NO_GROUND_TRUTH[0], f"sweep {info.id} has no ground truth")
    gt_metric_pre = (info.baseline or {}).get("gt_metric")
    trials = sweeps.list_trials(db_session, info.id)
    return shift_vs_gt_png(trials, gt_metric_pre=gt_metric_pre)


def apply_best(
    db_session: Session, info: SweepInfo, *, max_attempts: int
) -> tuple[MapInfo, int, dict[str, Any]]:
    """Queue a rebuild of the sweep's map with its base parameters and its best trial's values
    (as given: ``estimate_noise`` off), and record it on the sweep: (the map, the job id, the
    parameters). ApiError 409 while no
    trial has converged."""
    best = best_trial(sweeps.list_trials(db_session, info.id), info.objective)
    if best is None:
        raise Conflict(NO_BEST[0], f"sweep {info.id} has no converged trial yet")
    # a trial is its setting of the variances as given, not a noise estimate started from it
    overrides = checked_overrides({**info.base_params, **best.values, "estimate_noise": False})
    map_info, job_id = enqueue_rebuild(
        db_session,
        info.map_id,
        overrides,
        max_attempts=max_attempts,
        session_ids=info.session_ids or [info.session_id],
    )
    sweeps.set_applied(db_session, info.id, job_id)
    return map_info, job_id, overrides
