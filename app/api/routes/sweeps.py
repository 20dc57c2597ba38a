"""Hyperparameter sweeps (admin): ``POST /v1/maps/{id}/sweeps``, ``/v1/sweeps/…``.

A sweep is split into ``sweep_trials`` jobs that any worker takes (a grid's all at once; the
sampler's a batch at a time), so adding workers makes it faster. ``GET /v1/sweeps/{id}`` shows the
progress, the best parameters so far and (``?runs=true``) every finished trial; the plots are PNG;
``apply`` queues a rebuild of the map with the base parameters and the best values, which adds a
version when it succeeds. Bad requests are a 422 naming the problem (an empty or unknown
parameter, a non-positive variance, ``objective: ground_truth`` without ground truth).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Annotated, Any

from fastapi import APIRouter, Query, Response
from sqlalchemy.orm import Session

from app.api.deps import (
    AdminPrincipal,
    MapDep,
    ReadSessionDep,
    SettingsDep,
    WriteSessionDep,
    valid_id,
)
from app.api.errors import ApiError, error_responses
from app.api.route_class import SessionEndingRoute
from app.api.routes.maps import checked_overrides, enqueue_rebuild
from app.api.schemas import RebuildAccepted
from app.api.sweep_schemas import SweepAccepted, SweepPublic, SweepRequest, SweepsPublic
from app.domain.errors import InvisibleMapError, ParameterError
from app.domain.ground_truth import parse_ground_truth_json
from app.domain.sweep_plan import SweepPlan
from app.domain.tuning import SearchSpace, best_trial, check_objective
from app.storage import sweeps
from app.storage.maps import MapInfo
from app.storage.sweeps import SweepInfo

router = APIRouter(tags=["sweeps"], route_class=SessionEndingRoute)

PNG: dict[int | str, dict[str, Any]] = {
    200: {
        "description": "the plot",
        "content": {
            "image/png": {"schema": {"type": "string", "format": "binary"}, "example": "(PNG)"}
        },
    }
}
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
        raise ApiError(422, "invalid_sweep", str(err), field="space") from err
    if ground_truth is not None:
        try:
            parse_ground_truth_json(ground_truth)
        except InvisibleMapError as err:
            raise ApiError(422, "invalid_ground_truth", str(err), field="ground_truth") from err
    try:
        check_objective(plan.objective, has_ground_truth=ground_truth is not None)
    except ParameterError as err:
        raise ApiError(422, "invalid_sweep", str(err), field="objective") from err
    return plan


def heatmap_content(session: Session, info: SweepInfo) -> bytes:
    """The sweep's heat map, PNG."""
    from app.render.sweep_plots import heatmap_png

    trials = sweeps.list_trials(session, info.id)
    return heatmap_png(SearchSpace.from_dict(info.space), trials, objective=info.objective)


def shift_vs_gt_content(session: Session, info: SweepInfo) -> bytes:
    """The sweep's shift-vs-ground-truth scatter, PNG; ApiError 409 without ground truth."""
    from app.render.sweep_plots import shift_vs_gt_png

    if not info.has_ground_truth:
        raise ApiError(409, NO_GROUND_TRUTH[0], f"sweep {info.id} has no ground truth")
    gt_metric_pre = (info.baseline or {}).get("gt_metric")
    trials = sweeps.list_trials(session, info.id)
    return shift_vs_gt_png(trials, gt_metric_pre=gt_metric_pre)


def apply_best(
    session: Session, info: SweepInfo, *, max_attempts: int
) -> tuple[MapInfo, int, dict[str, Any]]:
    """Queue a rebuild of the sweep's map with its base parameters and its best trial's values,
    and record it on the sweep: (the map, the job id, the parameters). ApiError 409 while no
    trial has converged."""
    best = best_trial(sweeps.list_trials(session, info.id), info.objective)
    if best is None:
        raise ApiError(409, NO_BEST[0], f"sweep {info.id} has no converged trial yet")
    overrides = checked_overrides({**info.base_params, **best.values})
    map_info, job_id = enqueue_rebuild(session, info.map_id, overrides, max_attempts=max_attempts)
    sweeps.set_applied(session, info.id, job_id)
    return map_info, job_id, overrides


@router.post(
    "/maps/{map_id}/sweeps",  # noqa: FAST003 (map_id is read by MapDep)
    status_code=202,
    summary="Start a sweep",
    description="Sweep the SLAM noise variances of the map's session over a log grid (default: "
    "the paper-sized 10×10×10 grid) or with Optuna's sampler, scoring every trial by the shift "
    "metric and, with `ground_truth`, the ground-truth metric and tag RMSE (admin).",
    responses=error_responses(401, 403, 404, 422),
)
def start_sweep(
    info: MapDep,
    body: SweepRequest,
    _admin: AdminPrincipal,
    session: WriteSessionDep,
    settings: SettingsDep,
    response: Response,
) -> SweepAccepted:
    base_params = checked_overrides(body.params)
    plan = checked_plan(
        method=body.method,
        trials=body.trials,
        objective=body.objective,
        seed=body.seed,
        space=None if body.space is None else {k: v.model_dump() for k, v in body.space.items()},
        ground_truth=body.ground_truth,
    )
    sweep_id = sweeps.create_sweep(
        session,
        map_id=info.id,
        session_id=info.session_id,
        plan=plan,
        base_params=base_params,
        ground_truth=body.ground_truth,
        max_attempts=settings.max_attempts,
    )
    response.headers["Location"] = f"/v1/sweeps/{sweep_id}"
    return SweepAccepted(
        sweep_id=sweep_id,
        map_id=info.id,
        trials_total=plan.total,
        sweep_url=f"/v1/sweeps/{sweep_id}",
    )


@router.get(
    "/sweeps",
    summary="List sweeps",
    description="Newest first, optionally of one map, without their trials (admin).",
    responses=error_responses(401, 403, 422),
)
def list_sweeps(
    _admin: AdminPrincipal,
    session: ReadSessionDep,
    map_id: Annotated[int | None, Query(ge=1, le=2**63 - 1, description="only this map's")] = None,
    limit: Annotated[int, Query(ge=1, le=200)] = 50,
    offset: Annotated[int, Query(ge=0, le=2**31)] = 0,
) -> SweepsPublic:
    infos, total = sweeps.list_sweeps(session, map_id=map_id, limit=limit, offset=offset)
    return SweepsPublic(
        data=[SweepPublic.from_domain(i, sweeps.summary(session, i), None) for i in infos],
        count=total,
        limit=limit,
        offset=offset,
    )


def _sweep(session: ReadSessionDep, sweep_id: int) -> SweepInfo:
    return sweeps.get_sweep(session, valid_id(sweep_id, "sweep"))


@router.get(
    "/sweeps/{sweep_id}",
    summary="Get a sweep",
    description="State, progress, the best parameters so far with their metrics, and with "
    "`?runs=true` every finished trial (admin).",
    responses=error_responses(401, 403, 404, 422),
)
def get_sweep(
    sweep_id: int,
    _admin: AdminPrincipal,
    session: ReadSessionDep,
    runs: Annotated[bool, Query(description="include every finished trial")] = False,
) -> SweepPublic:
    info = _sweep(session, sweep_id)
    trials = sweeps.numbered_trials(session, info.id) if runs else None
    return SweepPublic.from_domain(info, sweeps.summary(session, info), trials)


@router.get(
    "/sweeps/{sweep_id}/heatmap.png",
    summary="Heat map of a sweep",
    description="The best score (by the sweep's objective) per cell, for every pair of swept "
    "parameters (admin).",
    response_class=Response,
    responses={**PNG, **error_responses(401, 403, 404, 422)},
)
def get_heatmap(sweep_id: int, _admin: AdminPrincipal, session: ReadSessionDep) -> Response:
    info = _sweep(session, sweep_id)
    return Response(content=heatmap_content(session, info), media_type="image/png")


@router.get(
    "/sweeps/{sweep_id}/shift-vs-gt.png",
    summary="Shift metric against ground-truth metric",
    description="Every converged trial's shift and ground-truth metric, with their Spearman "
    "correlation (the paper's Fig. 3). 409 when the sweep has no ground truth (admin).",
    response_class=Response,
    responses={**PNG, **error_responses(401, 403, 404, 409, 422, examples={409: NO_GROUND_TRUTH})},
)
def get_shift_vs_gt(sweep_id: int, _admin: AdminPrincipal, session: ReadSessionDep) -> Response:
    info = _sweep(session, sweep_id)
    return Response(content=shift_vs_gt_content(session, info), media_type="image/png")


@router.post(
    "/sweeps/{sweep_id}/apply",
    status_code=202,
    summary="Apply a sweep's best parameters",
    description="Queue a rebuild of the map with the sweep's base parameters and its best "
    "trial's values (by its objective; the best so far if it is still running). The new "
    "version becomes current when the job succeeds (admin).",
    responses=error_responses(401, 403, 404, 409, 422, examples={409: NO_BEST}),
)
def apply_sweep(
    sweep_id: int,
    _admin: AdminPrincipal,
    session: WriteSessionDep,
    settings: SettingsDep,
    response: Response,
) -> RebuildAccepted:
    info = _sweep(session, sweep_id)
    map_info, job_id, overrides = apply_best(session, info, max_attempts=settings.max_attempts)
    accepted = RebuildAccepted.queued(map_info, job_id, overrides)
    response.headers["Location"] = accepted.job_url
    return accepted


@router.post(
    "/sweeps/{sweep_id}/cancel",
    summary="Cancel a sweep",
    description="Cancel its queued jobs and ask its running ones to stop; the trials stored so "
    "far are kept (admin).",
    responses=error_responses(401, 403, 404, 422),
)
def cancel_sweep(sweep_id: int, _admin: AdminPrincipal, session: WriteSessionDep) -> SweepPublic:
    info = sweeps.cancel_sweep(session, valid_id(sweep_id, "sweep"))
    return SweepPublic.from_domain(info, sweeps.summary(session, info), None)
