"""``/admin/sweeps``: hyperparameter sweeps — the list (newest first, by map) with a form to start
one; a sweep's state and progress (live), its best parameters so far and summary metrics, the heat
map and the shift-vs-ground-truth scatter (PNG, with the best trials as a table), and the buttons
Apply best parameters and Cancel.

Each form does what the API does, through the same functions (``checked_plan``,
``sweeps.create_sweep``, ``apply_best``, ``sweeps.cancel_sweep``), in one transaction. A refused
start form is shown again with its values, the reason, and the field at fault focused (4xx).

    GET  /admin/sweeps?map_id=3&page=2          the list, and the start form (map 3 chosen)
    POST /admin/sweeps                          start (multipart: the ground truth may be a file)
    GET  /admin/sweeps/4                        a sweep; its live parts are /admin/live/sweeps/4
                                                (state, progress, best) and …/4/results (plots)
    GET  /admin/sweeps/4/heatmap.png, /admin/sweeps/4/shift-vs-gt.png
    POST /admin/sweeps/4/apply, /admin/sweeps/4/cancel
"""

from __future__ import annotations

import contextlib
import json
import math
from dataclasses import dataclass, field
from typing import Annotated, Any

from fastapi import Query, Request, Response
from sqlalchemy.orm import Session
from starlette.datastructures import FormData, UploadFile

from app.admin.auth import CheckedFormDep, DashboardUserDep
from app.admin.forms import REBUILD_PARAMS, changed_params
from app.admin.paging import PAGE_SIZE, Page, PageNumber
from app.admin.routing import admin_router, sentence
from app.admin.templating import redirect, render
from app.domain.evaluation.sweep_plan import SweepPlan
from app.domain.evaluation.tuning import (
    PAPER_GRID_AXES,
    PAPER_GRID_RANGE,
    PAPER_GRID_VALUES,
    TUNABLE_PARAMS,
    Trial,
    best_trial,
)
from app.services.errors import InvalidInput, NotFound, ServiceError
from app.services.sweeps import apply_best, checked_plan, heatmap_content, shift_vs_gt_content
from app.storage import maps, queue, sweeps
from app.storage.maps import MapInfo, MapNotFound
from app.storage.queue import JobInfo, JobNotFound
from app.storage.sweeps import SweepInfo
from app.web.deps import MAX_ID, DbDep, ReadDbSessionDep, SettingsDep, is_id, valid_id

router = admin_router()

#: Maps offered in the map lists (the newest; a map chosen by ``?map_id=`` is added).
MAP_CHOICES = 50
#: Trials in the table of best trials (the plots' text alternative).
BEST_SHOWN = 20
#: The largest ground-truth file the start form takes, bytes.
MAX_GROUND_TRUTH_BYTES = 2**20

MapFilter = Annotated[int | None, Query(ge=1, le=MAX_ID, description="only this map's sweeps")]

_PARAM_FIELDS = {param.name: param for param in REBUILD_PARAMS}
OBJECTIVE_NAMES = {"shift": "shift metric", "ground_truth": "ground-truth metric"}


# --------------------------------------------------------------------------- the start form


@dataclass(frozen=True, slots=True, kw_only=True)
class AxisField:
    """One tunable parameter in the start form, with the texts to show."""

    name: str
    label: str
    unit: str
    checked: bool
    low: str
    high: str
    num: str


def _default_axes() -> tuple[AxisField, ...]:
    low, high = PAPER_GRID_RANGE
    return tuple(
        AxisField(
            name=name,
            label=_PARAM_FIELDS[name].label,
            unit=_PARAM_FIELDS[name].unit,
            checked=name in PAPER_GRID_AXES,
            low=f"{low:g}",
            high=f"{high:g}",
            num=str(PAPER_GRID_VALUES),
        )
        for name in TUNABLE_PARAMS
    )


@dataclass(frozen=True, slots=True, kw_only=True)
class StartForm:
    """What the start form shows: the defaults (the paper grid, by the shift metric), or the
    texts of a refused form."""

    map_id: int | None = None
    method: str = "grid"
    trials: str = "100"
    objective: str = "shift"
    ground_truth_text: str = ""
    file_given: bool = False
    axes: tuple[AxisField, ...] = field(default_factory=_default_axes)

    @classmethod
    def submitted(cls, form: FormData) -> StartForm:
        def text(name: str, default: str = "") -> str:
            value = form.get(name)
            return value.strip() if isinstance(value, str) else default

        chosen = set(form.getlist("sweep"))
        map_text = text("map_id")
        file = form.get("ground_truth_file")
        return cls(
            map_id=int(map_text) if map_text.isdecimal() and len(map_text) < 19 else None,
            method=text("method", "grid"),
            trials=text("trials"),
            objective=text("objective", "shift"),
            ground_truth_text=text("ground_truth_text"),
            file_given=isinstance(file, UploadFile) and bool(file.filename),
            axes=tuple(
                AxisField(
                    name=axis.name,
                    label=axis.label,
                    unit=axis.unit,
                    checked=axis.name in chosen,
                    low=text(f"{axis.name}_low"),
                    high=text(f"{axis.name}_high"),
                    num=text(f"{axis.name}_num"),
                )
                for axis in _default_axes()
            ),
        )


@dataclass(frozen=True, slots=True, kw_only=True)
class StartRequest:
    """A start form read into what :func:`checked_plan` takes."""

    map_id: int
    method: str
    trials: int
    objective: str
    space: dict[str, dict[str, Any]]
    ground_truth: dict[str, Any] | None


def _form_error(element_id: str, detail: str, status_code: int = 422) -> ServiceError:
    """An error of the start form; ``field`` is the id of the element to focus."""
    error_type = NotFound if status_code == 404 else InvalidInput
    return error_type("invalid_sweep", detail, field=element_id)


def _number(text: str, element_id: str, what: str) -> float:
    try:
        return float(text)
    except ValueError:
        raise _form_error(element_id, f"{what}: not a number ({text!r})") from None


def _whole_number(text: str, element_id: str, what: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise _form_error(element_id, f"{what}: not a whole number ({text!r})") from None


def _ground_truth(form: FormData, submitted: StartForm) -> dict[str, Any] | None:
    """The ground truth from the uploaded file or the text box (None if neither), decoded but
    not yet checked (``checked_plan`` does that)."""
    file = form.get("ground_truth_file")
    content: bytes | str | None = None
    element_id = "start-gt-text"
    if isinstance(file, UploadFile) and file.filename:
        if submitted.ground_truth_text:
            raise _form_error(
                element_id, "Ground truth: give a file or paste it in the text box, not both"
            )
        content, element_id = file.file.read(MAX_GROUND_TRUTH_BYTES + 1), "start-gt-file"
        if len(content) > MAX_GROUND_TRUTH_BYTES:
            raise _form_error(
                element_id,
                f"Ground truth: the file is larger than {MAX_GROUND_TRUTH_BYTES // 2**20} MiB",
                413,
            )
    elif submitted.ground_truth_text:
        content = submitted.ground_truth_text
    if content is None:
        return None
    try:
        document = json.loads(content)
    except json.JSONDecodeError as err:
        raise _form_error(
            element_id,
            f"Ground truth: not valid JSON ({err.msg}, line {err.lineno} column {err.colno})",
        ) from None
    except UnicodeDecodeError:
        raise _form_error(element_id, "Ground truth: the file is not UTF-8 text") from None
    if not isinstance(document, dict):
        raise _form_error(element_id, 'Ground truth: expected a JSON object like {"poses": [...]}')
    return document


def start_request(form: FormData, submitted: StartForm) -> StartRequest:
    """The start form read (numbers parsed, ground truth decoded); ServiceError naming the element
    at fault. What the numbers mean is checked by :func:`checked_plan`."""
    if submitted.map_id is None:
        raise _form_error("start-map", "Map: choose the map whose session to sweep")
    if submitted.method not in ("grid", "sampler"):
        raise _form_error("start-method-grid", "Method: choose grid or sampler")
    trials = 100
    if submitted.method == "sampler":
        trials = _whole_number(submitted.trials, "start-trials", "Trials")
    space = {}
    for axis in submitted.axes:
        if axis.checked:
            element = f"start-{axis.name}"
            space[axis.name] = {
                "low": _number(axis.low, f"{element}-low", f"{axis.label}, low"),
                "high": _number(axis.high, f"{element}-high", f"{axis.label}, high"),
                "num": _whole_number(axis.num, f"{element}-num", f"{axis.label}, values"),
            }
    return StartRequest(
        map_id=submitted.map_id,
        method=submitted.method,
        trials=trials,
        objective=submitted.objective,
        space=space,
        ground_truth=_ground_truth(form, submitted),
    )


def _plan_error(err: ServiceError, submitted: StartForm) -> ServiceError:
    """:func:`checked_plan`'s error (named by its API field) as the start form's: about the
    form element at fault, a parameter named by its label."""
    detail = err.detail
    if err.field == "objective":
        return _form_error("start-objective", detail)
    if err.field == "ground_truth":
        element = "start-gt-file" if submitted.file_given else "start-gt-text"
        return _form_error(element, f"Ground truth: {detail}")
    if detail.startswith("trials"):
        return _form_error("start-trials", detail)
    if detail.startswith("unknown method"):
        return _form_error("start-method-grid", detail)
    checked = [axis for axis in submitted.axes if axis.checked]
    for axis in checked:
        if detail.startswith(f"{axis.name}:"):
            rest = detail.removeprefix(f"{axis.name}:")
            found = {part: rest.find(part) for part in ("low", "high", "num") if part in rest}
            part = min(found, key=found.__getitem__) if found else "low"
            return _form_error(f"start-{axis.name}-{part}", f"{axis.label} ({axis.name}):{rest}")
    if detail.startswith("the grid has") and checked:
        return _form_error(f"start-{checked[0].name}-num", detail)
    return _form_error(f"start-{checked[0].name if checked else TUNABLE_PARAMS[0]}", detail)


# --------------------------------------------------------------------------- the list


def _map_choices(db_session: Session, chosen: int | None) -> list[MapInfo]:
    """The maps offered in the lists: the newest, and the chosen one if it is older (a refused
    form's number that can be no map's id is none: it never reaches the database)."""
    infos, _ = maps.list_maps(db_session, limit=MAP_CHOICES)
    if chosen is not None and is_id(chosen) and all(info.id != chosen for info in infos):
        with contextlib.suppress(MapNotFound):  # a refused form's map may be gone
            infos.append(maps.get_map(db_session, chosen))
    return infos


def _sweeps_page(
    request: Request,
    db_session: Session,
    *,
    map_id: int | None,
    page: int = 1,
    form: StartForm | None = None,
    error: ServiceError | None = None,
) -> Response:
    if map_id is not None:
        maps.get_map(db_session, valid_id(map_id, "map"))  # 404 for an unknown map
    infos, total = sweeps.list_sweeps(
        db_session, map_id=map_id, limit=PAGE_SIZE, offset=(page - 1) * PAGE_SIZE
    )
    start = form or StartForm(map_id=map_id)
    choices = _map_choices(db_session, start.map_id)
    names = {info.id: info.name for info in choices}
    for info in infos:
        if info.map_id not in names:
            names[info.map_id] = maps.get_map(db_session, info.map_id).name
    return render(
        request,
        "sweeps.html",
        status_code=error.status_code if error else 200,
        section="sweeps",
        title="Sweeps",
        sweeps=infos,
        summaries={info.id: sweeps.summary(db_session, info) for info in infos},
        map_names=names,
        map_id=map_id,
        map_choices=choices,
        page=Page.of(
            number=page,
            size=PAGE_SIZE,
            total=total,
            url="/admin/sweeps",
            query={"map_id": str(map_id) if map_id else ""},
        ),
        form=start,
        error=sentence(error.detail) if error else None,
        error_id=error.field if error else None,
    )


@router.get("/sweeps")
def sweep_list(
    request: Request,
    _user: DashboardUserDep,
    db_session: ReadDbSessionDep,
    map_id: MapFilter = None,
    page: PageNumber = 1,
) -> Response:
    return _sweeps_page(request, db_session, map_id=map_id, page=page)


def _plan(asked: StartRequest, submitted: StartForm) -> SweepPlan:
    """:func:`checked_plan` of the form, its error naming the form's element at fault."""
    try:
        return checked_plan(
            method=asked.method,
            trials=asked.trials,
            objective=asked.objective,
            seed=0,
            space=asked.space,
            ground_truth=asked.ground_truth,
        )
    except ServiceError as err:
        raise _plan_error(err, submitted) from None


def _chosen_map(db_session: Session, map_id: int) -> MapInfo:
    try:
        return maps.get_map(db_session, valid_id(map_id, "map"))
    except (MapNotFound, ServiceError):
        raise _form_error("start-map", f"Map {map_id} not found", 404) from None


@router.post("/sweeps")
def start_sweep(
    request: Request, form: CheckedFormDep, db: DbDep, settings: SettingsDep
) -> Response:
    submitted = StartForm.submitted(form)
    try:
        asked = start_request(form, submitted)
        plan = _plan(asked, submitted)
        with db.transaction() as db_session:
            info = _chosen_map(db_session, asked.map_id)
            sweep_id = sweeps.create_sweep(
                db_session,
                map_id=info.id,
                session_id=info.session_id,
                plan=plan,
                base_params={},
                ground_truth=asked.ground_truth,
                max_attempts=settings.max_attempts,
            )
    except ServiceError as err:
        with db.read() as db_session:
            return _sweeps_page(request, db_session, map_id=None, form=submitted, error=err)
    finally:  # the uploaded file, read or not
        for value in form.values():
            if isinstance(value, UploadFile):
                value.file.close()
    return redirect(
        request,
        f"/admin/sweeps/{sweep_id}",
        flash=f"Sweep {sweep_id} of map {info.id} started: {plan.total} trials ({plan.method}).",
    )


# --------------------------------------------------------------------------- a sweep


@dataclass(frozen=True, slots=True, kw_only=True)
class ComparisonRow:
    """One map in the summary table: its metrics (NaN where unknown)."""

    label: str
    shift: float
    gt_metric: float
    tag_rmse_m: float


@dataclass(frozen=True, slots=True, kw_only=True)
class RankedTrial:
    rank: int
    number: int
    trial: Trial


def _applied(db_session: Session, info: SweepInfo) -> tuple[JobInfo | None, int | None]:
    """The rebuild job that applied the sweep's best parameters, and the version it made."""
    if info.applied_job_id is None:
        return None, None
    try:
        job = queue.get_job(db_session, info.applied_job_id)
    except JobNotFound:
        return None, None
    made = [v.number for v in maps.list_versions(db_session, info.map_id) if v.job_id == job.id]
    return job, made[-1] if made else None


def _live_context(db_session: Session, info: SweepInfo) -> dict[str, Any]:
    """What the sweep's live part shows: state, progress, the best values and metrics."""
    trials = sweeps.list_trials(db_session, info.id)
    summary = sweeps.summary(db_session, info)
    by_shift = best_trial(trials, "shift")
    by_gt = best_trial(trials, "ground_truth") if info.has_ground_truth else None
    nan = math.nan
    comparison = [
        ComparisonRow(
            label="Pre-optimized (each tag where first seen)",
            shift=summary.shift_pre,
            gt_metric=summary.gt_metric_pre,
            tag_rmse_m=summary.tag_rmse_pre_m,
        ),
        ComparisonRow(
            label="Chosen by the shift metric",
            shift=by_shift.shift if by_shift else nan,
            gt_metric=summary.gt_metric_at_best_shift,
            tag_rmse_m=summary.tag_rmse_at_best_shift_m,
        ),
    ]
    if info.has_ground_truth:
        comparison.append(
            ComparisonRow(
                label="Chosen by the ground-truth metric",
                shift=by_gt.shift if by_gt else nan,
                gt_metric=summary.gt_metric_best,
                tag_rmse_m=summary.tag_rmse_at_best_gt_m,
            )
        )
    applied_job, applied_version = _applied(db_session, info)
    return {
        "info": info,
        "summary": summary,
        "best_by_shift": by_shift.values if by_shift else None,
        "best_by_gt": by_gt.values if by_gt else None,
        "comparison": comparison,
        "applied_job": applied_job,
        "applied_version": applied_version,
        "params": [_PARAM_FIELDS[name] for name in info.space],
        "objective_name": OBJECTIVE_NAMES.get(info.objective, info.objective),
    }


def _results_context(db_session: Session, info: SweepInfo) -> dict[str, Any]:
    """What the sweep's results part shows: the plots and the best trials."""
    numbered = sweeps.numbered_trials(db_session, info.id)
    ranked = sorted(numbered, key=lambda pair: (pair[1].score(info.objective), pair[0]))
    trials = [trial for _, trial in numbered]
    usable = [
        t for t in trials if t.converged and math.isfinite(t.shift) and math.isfinite(t.gt_metric)
    ]
    by_shift = best_trial(usable, "shift")
    by_gt = best_trial(usable, "ground_truth")
    return {
        "info": info,
        "summary": sweeps.summary(db_session, info),
        "best_trials": [
            RankedTrial(rank=k + 1, number=number, trial=trial)
            for k, (number, trial) in enumerate(ranked[:BEST_SHOWN])
        ],
        "best": best_trial(trials, info.objective),
        "usable_count": len(usable),
        "gt_pre_known": (info.baseline or {}).get("gt_metric") is not None,
        "gt_at_shift_choice": by_shift.gt_metric if by_shift else None,
        "gt_at_gt_choice": by_gt.gt_metric if by_gt else None,
        "params": [_PARAM_FIELDS[name] for name in info.space],
        "objective_name": OBJECTIVE_NAMES.get(info.objective, info.objective),
    }


def _sweep(db_session: Session, sweep_id: int) -> SweepInfo:
    return sweeps.get_sweep(db_session, valid_id(sweep_id, "sweep"))


def _sweep_page(
    request: Request, db_session: Session, sweep_id: int, *, apply_error: ServiceError | None = None
) -> Response:
    info = _sweep(db_session, sweep_id)
    map_info = maps.get_map(db_session, info.map_id)
    return render(
        request,
        "sweep.html",
        status_code=apply_error.status_code if apply_error else 200,
        section="sweeps",
        title=f"Sweep {info.id}",
        map_info=map_info,
        base_changes=changed_params(info.base_params),
        apply_error=sentence(apply_error.detail) if apply_error else None,
        **_live_context(db_session, info),
        results=_results_context(db_session, info),
    )


@router.get("/sweeps/{sweep_id}")
def sweep_detail(
    request: Request, _user: DashboardUserDep, db_session: ReadDbSessionDep, sweep_id: int
) -> Response:
    return _sweep_page(request, db_session, sweep_id)


@router.get("/live/sweeps/{sweep_id}")
def sweep_live(
    request: Request, _user: DashboardUserDep, db_session: ReadDbSessionDep, sweep_id: int
) -> Response:
    """The sweep page's live part: state, progress, best values and metrics, the buttons."""
    info = _sweep(db_session, sweep_id)
    return render(request, "_sweep_live.html", **_live_context(db_session, info))


@router.get("/live/sweeps/{sweep_id}/results")
def sweep_results_live(
    request: Request, _user: DashboardUserDep, db_session: ReadDbSessionDep, sweep_id: int
) -> Response:
    """The sweep page's plots and best trials (their image URLs change with the trial count, so
    the images are fetched again only when there are new trials)."""
    info = _sweep(db_session, sweep_id)
    return render(request, "_sweep_results.html", results=_results_context(db_session, info))


@router.get("/sweeps/{sweep_id}/heatmap.png")
def heatmap(_user: DashboardUserDep, db_session: ReadDbSessionDep, sweep_id: int) -> Response:
    info = _sweep(db_session, sweep_id)
    return Response(content=heatmap_content(db_session, info), media_type="image/png")


@router.get("/sweeps/{sweep_id}/shift-vs-gt.png")
def shift_vs_gt(_user: DashboardUserDep, db_session: ReadDbSessionDep, sweep_id: int) -> Response:
    info = _sweep(db_session, sweep_id)
    return Response(content=shift_vs_gt_content(db_session, info), media_type="image/png")


@router.post("/sweeps/{sweep_id}/apply")
def apply(
    request: Request, _form: CheckedFormDep, db: DbDep, settings: SettingsDep, sweep_id: int
) -> Response:
    try:
        with db.transaction() as db_session:
            info = _sweep(db_session, sweep_id)
            map_info, job_id, overrides = apply_best(
                db_session, info, max_attempts=settings.max_attempts
            )
    except ServiceError as err:
        with db.read() as db_session:
            return _sweep_page(request, db_session, sweep_id, apply_error=err)
    values = ", ".join(f"{name} = {value:g}" for name, value in overrides.items())
    return redirect(
        request,
        f"/admin/sweeps/{info.id}",
        flash=f"Rebuild of map {map_info.id} with sweep {info.id}'s best parameters queued as "
        f"job {job_id} ({values}).",
        flash_link=(f"/admin/jobs/{job_id}", f"Follow job {job_id}"),
    )


@router.post("/sweeps/{sweep_id}/cancel")
def cancel(request: Request, _form: CheckedFormDep, db: DbDep, sweep_id: int) -> Response:
    with db.transaction() as db_session:
        before = _sweep(db_session, sweep_id)
        info = sweeps.cancel_sweep(db_session, before.id)
    message = (
        f"Sweep {info.id} canceled: its queued trials will not run; the "
        f"{info.trials_done} trials stored are kept."
        if before.state == "running"
        else f"Sweep {info.id} is {info.state}: nothing to cancel."
    )
    return redirect(request, f"/admin/sweeps/{info.id}", flash=message)
