"""Hyperparameter sweeps (admin): ``POST /v1/maps/{id}/sweeps``, ``/v1/sweeps/…``.

A sweep is split into ``sweep_trials`` jobs that any worker takes (a grid's all at once; the
sampler's a batch at a time), so adding workers makes it faster. ``GET /v1/sweeps/{id}`` shows the
progress, the best parameters so far and (``?runs=true``) every finished trial; the plots are PNG;
``apply`` queues a rebuild of the map with the base parameters and the best values, which adds a
version when it succeeds. Bad requests are a 422 naming the problem (an empty or unknown
parameter, a non-positive variance, ``objective: ground_truth`` without ground truth).
"""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Query, Response

from app.api.schemas.maps import RebuildAccepted
from app.api.schemas.sweeps import SweepAccepted, SweepPublic, SweepRequest, SweepsPublic
from app.services.maps import checked_overrides
from app.services.sweeps import (
    NO_BEST,
    NO_GROUND_TRUTH,
    apply_best,
    checked_plan,
    heatmap_content,
    shift_vs_gt_content,
)
from app.storage import sweeps
from app.storage.sweeps import SweepInfo
from app.web.deps import (
    AdminPrincipal,
    MapDep,
    MapFilter,
    ReadDbSessionDep,
    SettingsDep,
    SweepId,
    WriteDbSessionDep,
    is_id,
    valid_id,
)
from app.web.errors import error_responses
from app.web.route_class import SessionEndingRoute

router = APIRouter(tags=["sweeps"], route_class=SessionEndingRoute)

PNG: dict[int | str, dict[str, Any]] = {
    200: {
        "description": "the plot",
        "content": {
            "image/png": {"schema": {"type": "string", "format": "binary"}, "example": "(PNG)"}
        },
    }
}


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
    db_session: WriteDbSessionDep,
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
        db_session,
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
    db_session: ReadDbSessionDep,
    map_id: MapFilter = None,
    limit: Annotated[int, Query(ge=1, le=200)] = 50,
    offset: Annotated[int, Query(ge=0, le=2**31)] = 0,
) -> SweepsPublic:
    if map_id is not None and not is_id(map_id):  # no map has it
        infos: list[SweepInfo] = []
        total = 0
    else:
        infos, total = sweeps.list_sweeps(db_session, map_id=map_id, limit=limit, offset=offset)
    return SweepsPublic(
        data=[SweepPublic.from_domain(i, sweeps.summary(db_session, i), None) for i in infos],
        count=total,
        limit=limit,
        offset=offset,
    )


def _sweep(db_session: ReadDbSessionDep, sweep_id: SweepId) -> SweepInfo:
    return sweeps.get_sweep(db_session, valid_id(sweep_id, "sweep"))


@router.get(
    "/sweeps/{sweep_id}",
    summary="Get a sweep",
    description="State, progress, the best parameters so far with their metrics, and with "
    "`?runs=true` every finished trial (admin).",
    responses=error_responses(401, 403, 404, 422),
)
def get_sweep(
    sweep_id: SweepId,
    _admin: AdminPrincipal,
    db_session: ReadDbSessionDep,
    runs: Annotated[bool, Query(description="include every finished trial")] = False,
) -> SweepPublic:
    info = _sweep(db_session, sweep_id)
    trials = sweeps.numbered_trials(db_session, info.id) if runs else None
    return SweepPublic.from_domain(info, sweeps.summary(db_session, info), trials)


@router.get(
    "/sweeps/{sweep_id}/heatmap.png",
    summary="Heat map of a sweep",
    description="The best score (by the sweep's objective) per cell, for every pair of swept "
    "parameters (admin).",
    response_class=Response,
    responses={**PNG, **error_responses(401, 403, 404, 422)},
)
def get_heatmap(
    sweep_id: SweepId, _admin: AdminPrincipal, db_session: ReadDbSessionDep
) -> Response:
    info = _sweep(db_session, sweep_id)
    return Response(content=heatmap_content(db_session, info), media_type="image/png")


@router.get(
    "/sweeps/{sweep_id}/shift-vs-gt.png",
    summary="Shift metric against ground-truth metric",
    description="Every converged trial's shift and ground-truth metric, with their Spearman "
    "correlation (the paper's Fig. 3). 409 when the sweep has no ground truth (admin).",
    response_class=Response,
    responses={**PNG, **error_responses(401, 403, 404, 409, 422, examples={409: NO_GROUND_TRUTH})},
)
def get_shift_vs_gt(
    sweep_id: SweepId, _admin: AdminPrincipal, db_session: ReadDbSessionDep
) -> Response:
    info = _sweep(db_session, sweep_id)
    return Response(content=shift_vs_gt_content(db_session, info), media_type="image/png")


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
    sweep_id: SweepId,
    _admin: AdminPrincipal,
    db_session: WriteDbSessionDep,
    settings: SettingsDep,
    response: Response,
) -> RebuildAccepted:
    info = _sweep(db_session, sweep_id)
    map_info, job_id, overrides = apply_best(db_session, info, max_attempts=settings.max_attempts)
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
def cancel_sweep(
    sweep_id: SweepId, _admin: AdminPrincipal, db_session: WriteDbSessionDep
) -> SweepPublic:
    info = sweeps.cancel_sweep(db_session, valid_id(sweep_id, "sweep"))
    return SweepPublic.from_domain(info, sweeps.summary(db_session, info), None)
