"""Request and response bodies of ``/v1/maps/{id}/sweeps`` and ``/v1/sweeps``."""

from __future__ import annotations

from datetime import datetime
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from app.domain.evaluation.tuning import SweepSummary, Trial
from app.storage.sweeps import SweepInfo

_SPACE_EXAMPLE: dict[str, Any] = {
    "tag_orientation_var_rad2": {"low": 1e-8, "high": 1.0, "num": 10},
    "odom_linear_var_m2_per_s": {"low": 1e-8, "high": 1.0, "num": 10},
    "odom_angular_var_rad2_per_s": {"low": 1e-8, "high": 1.0, "num": 10},
}
_VALUES_EXAMPLE: dict[str, Any] = {
    "tag_orientation_var_rad2": 0.0129,
    "odom_linear_var_m2_per_s": 0.00278,
    "odom_angular_var_rad2_per_s": 1e-4,
}


_SWEEP_EXAMPLE: dict[str, Any] = {
    "id": 4,
    "map_id": 12,
    "session_id": 9,
    "method": "grid",
    "objective": "shift",
    "state": "running",
    "error": None,
    "space": _SPACE_EXAMPLE,
    "base_params": {},
    "has_ground_truth": False,
    "trials_total": 1000,
    "trials_done": 420,
    "progress": 0.42,
    "summary": {
        "best_values": _VALUES_EXAMPLE,
        "best_shift": 0.0112,
        "shift_pre": 0.0139,
        "gt_metric_pre": None,
        "gt_metric_at_best_shift": None,
        "gt_metric_best": None,
        "best_gt_values": None,
        "tag_rmse_pre_m": None,
        "tag_rmse_at_best_shift_m": None,
        "tag_rmse_at_best_gt_m": None,
        "shift_gt_spearman": None,
    },
    "applied_job_id": None,
    "session_ids": [],
    "shift_metric_version": 2,
    "created_at": "2026-11-22T07:10:00Z",
    "finished_at": None,
    "runs": [],
}


class AxisSpec(BaseModel):
    """One swept parameter: ``num`` values log-spaced from ``low`` to ``high``."""

    model_config = ConfigDict(
        extra="forbid", json_schema_extra={"examples": [{"low": 1e-8, "high": 1.0, "num": 10}]}
    )

    low: float = Field(description="smallest value (a variance: > 0)")
    high: float = Field(description="largest value (≥ low)")
    num: int = Field(default=10, description="grid values (a sampler only uses low–high)")


class SweepRequest(BaseModel):
    """What to sweep and how to score it."""

    model_config = ConfigDict(
        extra="forbid",
        json_schema_extra={
            "examples": [
                {"method": "sampler", "trials": 100},
                {"method": "grid", "space": _SPACE_EXAMPLE},
                {
                    "method": "grid",
                    "objective": "ground_truth",
                    "space": {"odom_linear_var_m2_per_s": {"low": 1e-6, "high": 1e-1, "num": 6}},
                    "ground_truth": {
                        "poses": [
                            {"tag_id": 0, "pose": [0, 0, 0, 0, 0, 0, 1]},
                            {"tag_id": 1, "pose": [3.2, 0, 0, 0, 0, 0, 1]},
                        ]
                    },
                },
            ]
        },
    )

    method: Literal["grid", "sampler"] = Field(
        default="grid", description="every grid point, or Optuna's TPE sampler"
    )
    trials: int = Field(default=100, description="the sampler's number of trials (1–10000)")
    objective: Literal["shift", "ground_truth"] = Field(
        default="shift", description="what chooses the best trial (ground_truth needs it given)"
    )
    space: dict[str, AxisSpec] | None = Field(
        default=None,
        description="swept parameters (tag_position_var_m2, tag_orientation_var_rad2, "
        "odom_linear_var_m2_per_s, odom_angular_var_rad2_per_s, gravity_var_rad2); "
        "default: the paper grid, 10×10×10 over 1e-8…1",
    )
    params: dict[str, Any] = Field(
        default_factory=dict, description="other SLAM parameters, fixed for every trial"
    )
    ground_truth: dict[str, Any] | None = Field(
        default=None,
        description='tag poses in the ground-truth file form, {"poses": [{"tag_id", "pose": '
        "[x, y, z, qx, qy, qz, qw]}]}; every trial is then also scored against it",
    )
    seed: int = Field(default=0, ge=0, le=2**31 - 1, description="the sampler's seed")


class SweepAccepted(BaseModel):
    """The answer to a new sweep (202): where to follow it."""

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {"sweep_id": 4, "map_id": 12, "trials_total": 1000, "sweep_url": "/v1/sweeps/4"}
            ]
        }
    )

    sweep_id: int
    map_id: int
    trials_total: int
    sweep_url: str


class TrialPublic(BaseModel):
    """One finished trial: the values tried and the map's metrics (null where undefined)."""

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "number": 7,
                    "values": _VALUES_EXAMPLE,
                    "shift": 0.0112,
                    "gt_metric": 0.0541,
                    "tag_rmse_m": 0.262,
                    "iterations": 4,
                    "converged": True,
                    "duration_s": 0.061,
                    "error": None,
                }
            ]
        }
    )

    number: int
    values: dict[str, float]
    shift: float | None
    gt_metric: float | None
    tag_rmse_m: float | None
    iterations: int
    converged: bool
    duration_s: float
    error: str | None

    @classmethod
    def from_domain(cls, number: int, trial: Trial) -> TrialPublic:
        return cls(number=number, **trial.to_dict())


class SummaryPublic(BaseModel):
    """The best so far; metrics are null where undefined (no ground truth, no trial yet). A
    chosen trial has converged, so its figures are those of the map ``apply`` builds with its
    setting, exactly (README, "What a trial measures")."""

    model_config = ConfigDict(json_schema_extra={"examples": [_SWEEP_EXAMPLE["summary"]]})

    best_values: dict[str, float] | None
    best_shift: float | None
    shift_pre: float | None
    gt_metric_pre: float | None
    gt_metric_at_best_shift: float | None
    gt_metric_best: float | None
    best_gt_values: dict[str, float] | None
    tag_rmse_pre_m: float | None
    tag_rmse_at_best_shift_m: float | None
    tag_rmse_at_best_gt_m: float | None
    shift_gt_spearman: float | None

    @classmethod
    def from_domain(cls, summary: SweepSummary) -> SummaryPublic:
        values = summary.to_dict()
        return cls(**{name: values[name] for name in cls.model_fields})


class SweepPublic(BaseModel):
    """A sweep: its progress, the best parameters so far and (``?runs=true``) every trial."""

    model_config = ConfigDict(json_schema_extra={"examples": [_SWEEP_EXAMPLE]})

    id: int
    map_id: int
    session_id: int
    method: str
    objective: str
    state: Literal["running", "succeeded", "failed", "canceled"]
    error: str | None
    space: dict[str, Any]
    base_params: dict[str, Any]
    has_ground_truth: bool
    trials_total: int
    trials_done: int
    progress: float = Field(ge=0, le=1)
    summary: SummaryPublic
    applied_job_id: int | None = Field(description="the rebuild that applied the best parameters")
    session_ids: list[int] = Field(
        description="the map's sessions its trials optimize together (empty: session_id alone)"
    )
    shift_metric_version: int = Field(
        description="the shift metric's definition its trials were scored with: 2 is "
        "docs/architecture.md §4's (origin-invariant); 1 the earlier, origin-dependent form"
    )
    created_at: datetime
    finished_at: datetime | None
    runs: list[TrialPublic] | None = Field(description="every finished trial (with ?runs=true)")

    @classmethod
    def from_domain(
        cls, info: SweepInfo, summary: SweepSummary, trials: list[tuple[int, Trial]] | None
    ) -> SweepPublic:
        return cls(
            id=info.id,
            map_id=info.map_id,
            session_id=info.session_id,
            method=info.method,
            objective=info.objective,
            state=info.state,
            error=info.error,
            space=info.space,
            base_params=info.base_params,
            has_ground_truth=info.has_ground_truth,
            trials_total=info.trials_total,
            trials_done=info.trials_done,
            progress=min(1.0, info.progress),
            summary=SummaryPublic.from_domain(summary),
            applied_job_id=info.applied_job_id,
            session_ids=info.session_ids,
            shift_metric_version=info.shift_metric_version,
            created_at=info.created_at,
            finished_at=info.finished_at,
            runs=None if trials is None else [TrialPublic.from_domain(k, t) for k, t in trials],
        )


class SweepsPublic(BaseModel):
    """A page of sweeps, newest first."""

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {"data": [{**_SWEEP_EXAMPLE, "runs": None}], "count": 1, "limit": 50, "offset": 0}
            ]
        }
    )

    data: list[SweepPublic]
    count: int
    limit: int
    offset: int
