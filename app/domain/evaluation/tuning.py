"""Hyperparameter tuning (docs/architecture.md §5): search spaces, trials, the grid and a sampler.

    space = SearchSpace.paper_grid()                       # 10 × 10 × 10 log grid, 1000 trials
    target = TuningTarget.prepare(session, SlamParams(), ground_truth)   # once per sweep
    trial = target.run({"odom_linear_var_m2_per_s": 1e-3, …})            # one optimization
    trial.shift, trial.gt_metric, trial.tag_rmse_m
    propose_trials(space, done=[(values, score), …], count=8, seed=0)    # Optuna TPE, ask-only
    build = target.build(trial.values)        # the map `apply` makes with them: the trial's
    result = sweep_result(target, trials, "shift")   # the summary, its choices built again

A *trial* is one optimization of the session with some of the noise variances replaced, scored by
the shift metric (always) and the ground-truth metric and tag RMSE (when ground truth is given).
The session is screened and its graph measurements prepared once (``slam.GraphInputs``); a trial
rebuilds only the factors whose noise its setting changes (``slam.TrialGraph``, which also computes
the COLAMD ordering once), runs Levenberg–Marquardt without marginals, and scores the tags.

Why three axes by default: scaling every variance by the same factor leaves the least-squares
optimum unchanged (only the Huber threshold, in σ units, notices), so one of the four noise
variances only sets the scale. The paper's grid sweeps three of them over 10 log-spaced values from
1e-10 to 10; ours keeps ``tag_position_var_m2`` at its default (1 cm at 1 m) and sweeps the other
three over 10 values from 1e-8 to 1 — the physically meaningful part of the paper's range (σ from
0.1 mm to 1 m per √s of odometry; 0.006° to 57° of tag orientation). Beyond it the graph is so
stiff that LM needs 50–100 iterations to reach maps that score badly anyway. Any of the five
variances (gravity included) may be an axis of a custom space.

Every trial starts Levenberg–Marquardt from the same point, the optimum with the default noise
variances (computed once), which is where a build with any other setting starts its second stage
(``slam.optimize_session``). So a converged trial is the map ``apply`` makes with its setting, bit
for bit, and it does not depend on which trials ran before it. Starting there also halves the
iterations (mean 6 instead of 13 on floor_2_straight). A trial that hits
``TRIAL_MAX_ITERATIONS`` is recorded but marked unconverged, and never chosen as the best.
:func:`sweep_result` builds the chosen settings once more with ``optimize_session`` and checks
that their scores are the trials'.

The sampler keeps no state of its own: the history of finished trials (in our database) is replayed
into an in-memory Optuna study, which is then asked for the next trials. So any worker can propose
the next batch, and a restart loses nothing.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import time
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from app.domain.errors import ParameterError
from app.domain.evaluation.metrics import (
    ShiftPairs,
    ground_truth_metric,
    joint_shift_pairs,
    mean_shift_ratio,
    shift_pairs,
    tag_rmse_m,
)
from app.domain.frames import FloatArray
from app.domain.json_values import finite_or_none
from app.domain.mapping.joint import prepare_joint
from app.domain.mapping.params import NOISE_VARIANCE_FIELDS, PARAM_RANGES, SlamParams
from app.domain.mapping.slam import (
    GraphInputs,
    IterationCallback,
    TrialGraph,
    optimize_session,
    prepare_graph_inputs,
    values_from,
)
from app.domain.upload.session import Session, first_observation_tag_poses

if TYPE_CHECKING:
    import gtsam

#: The hyperparameters a sweep may vary: the paper's four noise variances, and gravity's.
TUNABLE_PARAMS = NOISE_VARIANCE_FIELDS
#: The paper's grid: these three axes, ``PAPER_GRID_VALUES`` values each, log-spaced over the range.
PAPER_GRID_AXES = (
    "tag_orientation_var_rad2",
    "odom_linear_var_m2_per_s",
    "odom_angular_var_rad2_per_s",
)
PAPER_GRID_RANGE = (1e-8, 1.0)
PAPER_GRID_VALUES = 10
#: Most trials one sweep may hold (a 10⁴ grid takes minutes; more is a mistake, not a sweep).
MAX_TRIALS = 20_000
#: Levenberg–Marquardt iteration cap in a trial: settings far from the optimum would otherwise
#: take 50–80 slow iterations to converge to a map that scores badly anyway.
TRIAL_MAX_ITERATIONS = 25

#: What a sweep minimizes.
OBJECTIVES = ("shift", "ground_truth")


@dataclass(frozen=True, slots=True)
class Axis:
    """One swept hyperparameter: ``num`` values log-spaced from ``low`` to ``high`` (inclusive)."""

    name: str
    low: float
    high: float
    num: int

    def __post_init__(self) -> None:
        if self.name not in TUNABLE_PARAMS:
            raise ParameterError(
                f"{self.name!r} cannot be swept; tunable parameters: {', '.join(TUNABLE_PARAMS)}"
            )
        for end, value in (("low", self.low), ("high", self.high)):
            if not (math.isfinite(value) and value > 0):
                raise ParameterError(
                    f"{self.name}: {end} must be a positive variance, got {value!r}"
                )
            if value not in PARAM_RANGES[self.name]:  # what a build would refuse as a parameter
                raise ParameterError(
                    f"{self.name}: {end} must be {PARAM_RANGES[self.name]}, got {value:g}"
                )
        if self.low > self.high:
            raise ParameterError(f"{self.name}: low {self.low:g} is above high {self.high:g}")
        if self.num < 1:
            raise ParameterError(f"{self.name}: num must be ≥ 1, got {self.num}")
        if self.num > 1 and self.low == self.high:
            raise ParameterError(f"{self.name}: {self.num} values need low < high")

    def values(self) -> FloatArray:
        """The grid values, low to high (``num`` = 1: the geometric mean of the range)."""
        if self.num == 1:
            return np.array([math.sqrt(self.low * self.high)])
        values = np.logspace(math.log10(self.low), math.log10(self.high), self.num)
        # 10 ** log10(x) is not always x (numpy 2.4: 1e-05 → 9.999999999999999e-06): the ends
        # are the values asked for, exactly.
        values[0], values[-1] = self.low, self.high
        return values

    def to_dict(self) -> dict[str, Any]:
        return {"low": self.low, "high": self.high, "num": self.num}


@dataclass(frozen=True, slots=True)
class SearchSpace:
    """The swept hyperparameters: a grid (every combination) or a sampler's box (``low``–``high``
    per axis; ``num`` is then unused)."""

    axes: tuple[Axis, ...]

    def __post_init__(self) -> None:
        if not self.axes:
            raise ParameterError("the search space is empty: give at least one parameter to sweep")
        names = [axis.name for axis in self.axes]
        if len(set(names)) != len(names):
            raise ParameterError(f"a parameter appears twice in the search space: {names}")
        if self.grid_size > MAX_TRIALS:
            raise ParameterError(
                f"the grid has {self.grid_size} points, more than the {MAX_TRIALS} a sweep may run"
            )

    @classmethod
    def paper_grid(cls) -> SearchSpace:
        low, high = PAPER_GRID_RANGE
        return cls(tuple(Axis(name, low, high, PAPER_GRID_VALUES) for name in PAPER_GRID_AXES))

    @classmethod
    def from_dict(cls, document: Mapping[str, Any]) -> SearchSpace:
        """From ``{name: {"low", "high", "num"}}`` (the API's and the CLI's form)."""
        axes = []
        for name, spec in document.items():
            if not isinstance(spec, Mapping):
                raise ParameterError(f"{name}: expected an object with low, high and num")
            unknown = set(spec) - {"low", "high", "num"}
            if unknown:
                raise ParameterError(f"{name}: unknown field(s) {sorted(unknown)}")
            if "low" not in spec or "high" not in spec:
                raise ParameterError(f"{name}: missing {'low' if 'low' not in spec else 'high'!r}")
            num = spec.get("num", PAPER_GRID_VALUES)
            if isinstance(num, bool) or not isinstance(num, int):
                raise ParameterError(f"{name}: num must be an integer, got {num!r}")
            low, high = _number(spec["low"], name), _number(spec["high"], name)
            axes.append(Axis(str(name), low, high, num))
        return cls(tuple(axes))

    def to_dict(self) -> dict[str, dict[str, Any]]:
        return {axis.name: axis.to_dict() for axis in self.axes}

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(axis.name for axis in self.axes)

    @property
    def grid_size(self) -> int:
        return math.prod(axis.num for axis in self.axes)

    def corners_and_centre(self) -> list[dict[str, float]]:
        """The 2^d corners of the box (every axis at ``low`` or ``high``, the last axis varying
        fastest), then its centre (each axis at the geometric mean of its ends)."""
        corners = [
            dict(zip(self.names, point, strict=True))
            for point in itertools.product(*((axis.low, axis.high) for axis in self.axes))
        ]
        centre = {axis.name: math.sqrt(axis.low * axis.high) for axis in self.axes}
        return [*corners, centre]

    def grid(self) -> list[dict[str, float]]:
        """Every combination, the last axis varying fastest."""
        columns = [axis.values() for axis in self.axes]
        return [
            dict(zip(self.names, (float(v) for v in point), strict=True))
            for point in itertools.product(*columns)
        ]


@dataclass(frozen=True, slots=True, kw_only=True)
class Trial:
    """One scored optimization: a sweep's trial, or the build of a chosen setting
    (:meth:`TuningTarget.build`). Metrics are NaN where undefined (no ground truth, too few tags);
    ``error`` says why it produced no map (its metrics are then NaN)."""

    values: dict[str, float]
    shift: float
    gt_metric: float
    tag_rmse_m: float
    iterations: int
    duration_s: float
    error: str | None = None
    #: LM's iteration cap: a trial's, or a build's (the base parameters'; also a trial's at the
    #: default variances, which is the build's first stage). One that reaches it is reported,
    #: marked unconverged.
    max_iterations: int = TRIAL_MAX_ITERATIONS

    @property
    def converged(self) -> bool:
        return self.error is None and self.iterations < self.max_iterations

    def score(self, objective: str) -> float:
        """The value minimized; +inf when undefined or unconverged, so such a trial is never
        the best."""
        if objective not in OBJECTIVES:
            raise ParameterError(f"unknown objective {objective!r}; one of {', '.join(OBJECTIVES)}")
        value = self.shift if objective == "shift" else self.gt_metric
        return value if math.isfinite(value) and self.converged else math.inf

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready (NaN becomes None)."""
        return {
            "values": self.values,
            "shift": finite_or_none(self.shift),
            "gt_metric": finite_or_none(self.gt_metric),
            "tag_rmse_m": finite_or_none(self.tag_rmse_m),
            "iterations": self.iterations,
            "converged": self.converged,
            "duration_s": self.duration_s,
            "error": self.error,
        }


class TuningTarget:
    """A session prepared for many trials: screened once, its shift pairs taken once, and its
    baseline (pre-optimized) metrics computed once."""

    def __init__(
        self,
        session: Session,
        base_params: SlamParams,
        ground_truth: Mapping[int, FloatArray] | None,
        inputs: GraphInputs,
        pairs: ShiftPairs,
    ) -> None:
        self.session = session
        self.base_params = base_params
        self.ground_truth = dict(ground_truth) if ground_truth else None
        self.inputs = inputs
        self.pairs = pairs
        self.graph = TrialGraph(inputs)
        #: whether a trial with the default variances is the warm start itself (as a build at
        #: the default variances is one LM stage, for one walk or, as given, for several)
        self.first_stage_is_map = True
        self._warm_start: gtsam.Values | None = None
        self._start_map: dict[int, FloatArray] = {}
        self._start_iterations = 0
        pre_all = first_observation_tag_poses(session)
        self.pre_map = {tag_id: pre_all[tag_id] for tag_id in inputs.tag_rows}

    @classmethod
    def prepare(
        cls,
        session: Session,
        base_params: SlamParams | None = None,
        ground_truth: Mapping[int, FloatArray] | None = None,
    ) -> TuningTarget:
        params = base_params or SlamParams()
        inputs = prepare_graph_inputs(session, params)
        pairs = shift_pairs(session, detection_mask=inputs.screening.used)
        return cls(session, params, ground_truth, inputs, pairs)

    @classmethod
    def prepare_joint(
        cls,
        sessions: Sequence[Session],
        base_params: SlamParams | None = None,
        ground_truth: Mapping[int, FloatArray] | None = None,
        *,
        names: Sequence[str] | None = None,
    ) -> TuningTarget:
        """A map of several sessions prepared for trials (``app.domain.mapping.joint``): the shift
        metric over every session's own detections, and each trial the joint graph with the
        trial's variances as given for every walk, from the optimum of the default variances:
        the map ``optimize_sessions`` makes with ``estimate_noise`` off (what ``apply`` builds),
        bit for bit. (Tuning a building map with each walk's own noise as the starting point is
        issue 25's item 4, not this.)"""
        params = base_params or SlamParams()
        # a trial is its variances as given, for every walk (as optimize_sessions builds them
        # with estimate_noise off, which is what apply does)
        joint = prepare_joint(
            sessions, dataclasses.replace(params, estimate_noise=False), names=names
        )
        masks = [
            joint.screening.used[start : start + len(session.detections)]
            for start, session in zip(joint.detection_starts, joint.plan.sessions, strict=True)
        ]
        pairs = joint_shift_pairs(joint.plan.sessions, masks)
        target = cls(joint.combined, params, ground_truth, joint.inputs, pairs)
        target.inputs.initial = values_from(joint.inputs, joint.start_T_keyframe, joint.start_T_tag)
        target.graph = TrialGraph(joint.inputs)
        pre_all = first_observation_tag_poses(joint.combined)
        target.pre_map = {tag_id: pre_all[tag_id] for tag_id in joint.inputs.tag_rows}
        return target

    @property
    def warm_start(self) -> gtsam.Values:
        """Where every trial starts LM: the optimum with the base parameters' default variances
        (computed once), which is the first stage of a build (``slam.optimize_session``)."""
        return self._warm_start_values(None)

    def _warm_start_values(self, on_iteration: IterationCallback | None) -> gtsam.Values:
        if self._warm_start is None:
            start = self.base_params.with_default_variances().with_overrides(
                {"compute_marginals": False}
            )
            self._start_map, self._start_iterations, self._warm_start = self.graph.optimize(
                start, on_iteration=on_iteration
            )
        return self._warm_start

    @property
    def has_ground_truth(self) -> bool:
        return self.ground_truth is not None

    def trial_params(self, values: Mapping[str, float]) -> SlamParams:
        """The base parameters with ``values`` swapped in, as a trial optimizes with them."""
        _check_tunable(values)
        return self.base_params.with_overrides(
            {
                **values,
                "compute_marginals": False,
                "estimate_noise": False,
                "max_iterations": min(self.base_params.max_iterations, TRIAL_MAX_ITERATIONS),
            }
        )

    def score_map(self, map_T_tag: Mapping[int, FloatArray]) -> tuple[float, float, float]:
        """(shift, ground-truth metric, tag RMSE in m) of a map of this session."""
        shift = mean_shift_ratio(self.pairs, map_T_tag)
        if self.ground_truth is None:
            return shift, math.nan, math.nan
        return (
            shift,
            ground_truth_metric(map_T_tag, self.ground_truth),
            tag_rmse_m(map_T_tag, self.ground_truth),
        )

    def baseline(self) -> tuple[float, float, float]:
        """:meth:`score_map` of the pre-optimized map: each tag's first observation, for the tags
        in the graph (as ``evaluate``'s ``gt_metric_pre``)."""
        return self.score_map(self.pre_map)

    def run(
        self, values: Mapping[str, float], *, on_iteration: IterationCallback | None = None
    ) -> Trial:
        """Optimize with ``values`` and score the result; never raises on a solver failure.
        ``on_iteration(iteration, error)`` after each LM iteration (of the warm start too, the
        first time): what it raises (a job's cancel) stops the trial there and propagates."""
        started = time.perf_counter()
        values = {name: float(value) for name, value in values.items()}
        params = self.trial_params(values)
        max_iterations = params.max_iterations
        try:
            start = self._warm_start_values(on_iteration)
            if params.has_default_variances and self.first_stage_is_map:
                # a build makes the first stage its map
                map_T_tag, iterations = self._start_map, self._start_iterations
                max_iterations = self.base_params.max_iterations
            else:
                map_T_tag, iterations, _ = self.graph.refine(
                    params, start, on_iteration=on_iteration
                )
        except RuntimeError as err:  # gtsam: an indeterminant system at extreme settings
            return Trial(
                values=values,
                shift=math.nan,
                gt_metric=math.nan,
                tag_rmse_m=math.nan,
                iterations=0,
                duration_s=time.perf_counter() - started,
                error=f"optimization failed: {err}",
            )
        shift, gt_metric, rmse_m = self.score_map(map_T_tag)
        return Trial(
            values=values,
            shift=shift,
            gt_metric=gt_metric,
            tag_rmse_m=rmse_m,
            iterations=iterations,
            max_iterations=max_iterations,
            duration_s=time.perf_counter() - started,
        )

    def build_params(self, values: Mapping[str, float]) -> SlamParams:
        """The base parameters with ``values`` swapped in, as a build uses them (``apply``'s
        rebuild, ``process --param``): the base iteration cap, no marginals, which do not move
        the map, and the variances as given (a trial is that setting, not a noise estimate
        started from it)."""
        _check_tunable(values)
        return self.base_params.with_overrides(
            {**values, "compute_marginals": False, "estimate_noise": False}
        )

    def build(self, values: Mapping[str, float]) -> Trial:
        """Build the map with ``values`` (:func:`slam.optimize_session` from raw odometry, in two
        stages, as ``apply`` does) and score it as a trial is scored (:meth:`score_map`); never
        raises on a solver failure. Its tags are those of the trials: ``values`` change no
        rejection threshold, so the build screens the session as :meth:`prepare` did."""
        started = time.perf_counter()
        values = {name: float(value) for name, value in values.items()}
        params = self.build_params(values)
        try:
            result = optimize_session(self.session, params)
        except RuntimeError as err:  # gtsam: an indeterminant system at extreme settings
            return Trial(
                values=values,
                shift=math.nan,
                gt_metric=math.nan,
                tag_rmse_m=math.nan,
                iterations=0,
                max_iterations=params.max_iterations,
                duration_s=time.perf_counter() - started,
                error=f"optimization failed: {err}",
            )
        shift, gt_metric, rmse_m = self.score_map(result.tag_poses())
        return Trial(
            values=values,
            shift=shift,
            gt_metric=gt_metric,
            tag_rmse_m=rmse_m,
            iterations=result.stats.iterations,
            max_iterations=params.max_iterations,
            duration_s=time.perf_counter() - started,
        )


def _check_tunable(values: Mapping[str, float]) -> None:
    unknown = set(values) - set(TUNABLE_PARAMS)
    if unknown:
        raise ParameterError(f"cannot sweep {sorted(unknown)}; tunable: {TUNABLE_PARAMS}")


def check_objective(objective: str, *, has_ground_truth: bool) -> None:
    if objective not in OBJECTIVES:
        raise ParameterError(f"unknown objective {objective!r}; one of {', '.join(OBJECTIVES)}")
    if objective == "ground_truth" and not has_ground_truth:
        raise ParameterError("objective 'ground_truth' needs ground truth")


def best_trial(trials: Sequence[Trial], objective: str) -> Trial | None:
    """The trial with the lowest score (ties: the first); None if none has a finite score."""
    scored = [t for t in trials if math.isfinite(t.score(objective))]
    return min(scored, key=lambda t: t.score(objective)) if scored else None


def propose_trials(
    space: SearchSpace,
    done: Sequence[tuple[Mapping[str, float], float]],
    *,
    count: int,
    seed: int,
) -> list[dict[str, float]]:
    """The next ``count`` points to try, from Optuna's TPE sampler given the finished trials
    ``done`` ((values, score) pairs; a non-finite score is recorded as a failed trial).

    Deterministic for the same inputs: the sampler is seeded with ``seed`` and the number of
    trials done, and each proposal of a batch is asked with the earlier ones pending (the
    "constant liar"), so a batch spreads out instead of repeating one point.
    """
    import optuna  # imported here: only sweeps with a sampler need it (≈0.5 s to import)

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    distributions: dict[str, optuna.distributions.BaseDistribution] = {
        axis.name: optuna.distributions.FloatDistribution(axis.low, axis.high, log=True)
        for axis in space.axes
    }
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
        sampler = optuna.samplers.TPESampler(
            seed=seed + len(done),
            n_startup_trials=10,
            multivariate=True,
            constant_liar=True,
        )
        study = optuna.create_study(direction="minimize", sampler=sampler)
        for values, score in done:
            params = {name: _clip(float(values[name]), space, name) for name in space.names}
            finite = math.isfinite(score)
            study.add_trial(
                optuna.trial.create_trial(
                    params=params,
                    distributions=distributions,
                    value=score if finite else None,
                    state=(
                        optuna.trial.TrialState.COMPLETE if finite else optuna.trial.TrialState.FAIL
                    ),
                )
            )
        proposals = []
        for _ in range(count):
            trial = study.ask(distributions)
            proposals.append({name: float(trial.params[name]) for name in space.names})
    return proposals


def _number(value: Any, name: str) -> float:
    """A number, or a string of one ("1e-8", as the CLI and forms give them); not a boolean."""
    if isinstance(value, bool) or not isinstance(value, int | float | str):
        raise ParameterError(f"{name}: expected a number, got {value!r}")
    try:
        return float(value)
    except ValueError as err:
        raise ParameterError(f"{name}: {err}") from err


def _clip(value: float, space: SearchSpace, name: str) -> float:
    axis = next(a for a in space.axes if a.name == name)
    return min(max(value, axis.low), axis.high)


@dataclass(frozen=True, slots=True, kw_only=True)
class SweepSummary:
    """What a sweep's trials found (the API's ``summary``). A chosen trial has converged, so its
    figures are those of the map a build with its setting makes (``apply``, ``process --param``).

    best_values: the best trial's values by ``objective``; best_shift its shift metric.
    gt_metric_pre: the pre-optimized map's ground-truth metric (same tags as the optimized maps);
    gt_metric_at_best_shift: the ground-truth metric of the trial the shift metric chose;
    gt_metric_best: the lowest ground-truth metric of any trial (the ground-truth-chosen trial).
    """

    runs: int
    objective: str
    best_values: dict[str, float] | None
    best_shift: float
    shift_pre: float
    gt_metric_pre: float
    gt_metric_at_best_shift: float
    gt_metric_best: float
    best_gt_values: dict[str, float] | None
    tag_rmse_pre_m: float
    tag_rmse_at_best_shift_m: float
    tag_rmse_at_best_gt_m: float
    shift_gt_spearman: float

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for name in self.__slots__:
            value = getattr(self, name)
            out[name] = finite_or_none(value) if isinstance(value, float) else value
        return out


def summarize(
    trials: Sequence[Trial], objective: str, baseline: tuple[float, float, float]
) -> SweepSummary:
    """The summary of ``trials`` (``baseline``: :meth:`TuningTarget.baseline`)."""
    nan = math.nan
    best = best_trial(trials, objective)
    by_shift = best_trial(trials, "shift")
    by_gt = best_trial(trials, "ground_truth")
    return SweepSummary(
        runs=len(trials),
        objective=objective,
        best_values=dict(best.values) if best else None,
        best_shift=best.shift if best else nan,
        shift_pre=baseline[0],
        gt_metric_pre=baseline[1],
        gt_metric_at_best_shift=by_shift.gt_metric if by_shift else nan,
        gt_metric_best=by_gt.gt_metric if by_gt else nan,
        best_gt_values=dict(by_gt.values) if by_gt else None,
        tag_rmse_pre_m=baseline[2],
        tag_rmse_at_best_shift_m=by_shift.tag_rmse_m if by_shift else nan,
        tag_rmse_at_best_gt_m=by_gt.tag_rmse_m if by_gt else nan,
        shift_gt_spearman=shift_gt_correlation(trials),
    )


@dataclass(frozen=True, slots=True, kw_only=True)
class SweepResult:
    """What a sweep reports as its result (the ``sweep --json`` object): the trials' summary, and
    the settings it chose built again from raw odometry, as ``apply`` builds them
    (:meth:`TuningTarget.build`), a check that the chosen trials are the maps a user gets.

    summary: the trials' :class:`SweepSummary`; shift_chosen: the build of the setting the shift
    metric chose; gt_chosen: the build of the setting the ground-truth metric chose (None without
    ground truth or a converged trial).
    """

    summary: SweepSummary
    shift_chosen: Trial | None
    gt_chosen: Trial | None

    @property
    def best(self) -> Trial | None:
        """The build of the setting the objective chose (``summary.best_values``)."""
        return self.shift_chosen if self.summary.objective == "shift" else self.gt_chosen

    @property
    def builds_equal_trials(self) -> bool:
        """Whether each build scores exactly as the trial that chose it (it always should: a
        converged trial is its build)."""
        summary = self.summary
        pairs: list[tuple[tuple[float, ...], tuple[float, ...]]] = []
        if self.shift_chosen is not None:
            pairs.append(
                (
                    (self.shift_chosen.gt_metric, self.shift_chosen.tag_rmse_m),
                    (summary.gt_metric_at_best_shift, summary.tag_rmse_at_best_shift_m),
                )
            )
        if self.gt_chosen is not None:
            pairs.append(
                (
                    (self.gt_chosen.gt_metric, self.gt_chosen.tag_rmse_m),
                    (summary.gt_metric_best, summary.tag_rmse_at_best_gt_m),
                )
            )
        if self.best is not None:
            pairs.append(((self.best.shift,), (summary.best_shift,)))
        return all(_same_scores(build, trial) for build, trial in pairs)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready (NaN becomes None): the summary's fields, ``builds`` (each build in full)
        and ``builds_equal_trials``."""
        out = self.summary.to_dict()
        out["builds"] = {
            "shift_chosen": None if self.shift_chosen is None else self.shift_chosen.to_dict(),
            "gt_chosen": None if self.gt_chosen is None else self.gt_chosen.to_dict(),
        }
        out["builds_equal_trials"] = self.builds_equal_trials
        return out


def _same_scores(a: Sequence[float], b: Sequence[float]) -> bool:
    """Equal, NaN equal to NaN (an undefined metric is undefined in both)."""
    return all(x == y or (math.isnan(x) and math.isnan(y)) for x, y in zip(a, b, strict=True))


def sweep_result(target: TuningTarget, trials: Sequence[Trial], objective: str) -> SweepResult:
    """:func:`summarize` ``trials``, then build the settings the shift metric and (with ground
    truth) the ground-truth metric chose, and score the builds: one or two optimizations from raw
    odometry (one when both metrics chose the same setting)."""
    summary = summarize(trials, objective, target.baseline())
    by_shift = best_trial(trials, "shift")
    by_gt = best_trial(trials, "ground_truth")
    shift_chosen = target.build(by_shift.values) if by_shift else None
    gt_chosen: Trial | None = None
    if by_gt is not None:
        same = by_shift is not None and by_gt.values == by_shift.values
        gt_chosen = shift_chosen if same else target.build(by_gt.values)
    return SweepResult(summary=summary, shift_chosen=shift_chosen, gt_chosen=gt_chosen)


def shift_gt_correlation(trials: Sequence[Trial]) -> float:
    """Spearman rank correlation of shift and ground-truth metric over the converged trials with
    both defined (NaN with fewer than 3 such trials or a constant metric)."""
    pairs = np.array(
        [
            (t.shift, t.gt_metric)
            for t in trials
            if t.converged and math.isfinite(t.shift) and math.isfinite(t.gt_metric)
        ]
    )
    if len(pairs) < 3 or np.any(np.ptp(pairs, axis=0) == 0):
        return math.nan
    return float(np.corrcoef(_average_ranks(pairs[:, 0]), _average_ranks(pairs[:, 1]))[0, 1])


def _average_ranks(values: FloatArray) -> FloatArray:
    """Ranks 0…n−1, tied values sharing the mean of their ranks (as Spearman's needs)."""
    order = np.argsort(values, kind="stable")
    ranks = np.empty(len(values))
    ranks[order] = np.arange(len(values), dtype=float)
    unique, inverse = np.unique(values, return_inverse=True)
    sums = np.bincount(inverse, weights=ranks, minlength=len(unique))
    counts = np.bincount(inverse, minlength=len(unique))
    return np.asarray(sums[inverse] / counts[inverse], dtype=float)
