"""Which trials a sweep runs, and in which order: every point of a grid, or a sampler's batches.

    plan = SweepPlan(method="sampler", space=SearchSpace.paper_grid(), trials=100)
    batch = plan.next_batch(done_trials, started=len(done_trials))

The command line's pool (``workers/sweep_pool.py``) and the server's sweep jobs (any worker, on
any machine) both ask a plan what comes next, so a sweep means the same thing everywhere.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from app.domain.errors import ParameterError
from app.domain.evaluation.tuning import SearchSpace, Trial, propose_trials

#: Trials per task on the local pool, and per job on the server, for a grid.
GRID_CHUNK = 20
#: Trials the sampler proposes at once (then waits for their scores): small batches keep TPE
#: nearly sequential, which is what makes it efficient; 4 keeps two workers busy.
SAMPLER_BATCH = 4
METHODS = ("grid", "sampler")


@dataclass(frozen=True, slots=True, kw_only=True)
class SweepPlan:
    """Which trials a sweep runs: every grid point, or ``trials`` of the sampler in batches of
    ``batch``. The sampler's first trials are the corners and the centre of the box
    (:meth:`SearchSpace.corners_and_centre`, when they are at most half of its trials): the
    best setting often sits on the box's edge (the shift metric favours stiff odometry, and on
    occam_room the grid's best is a corner), where Optuna's proposals rarely go. The rest are
    Optuna's TPE's."""

    method: str
    space: SearchSpace
    trials: int = 100
    objective: str = "shift"
    seed: int = 0
    batch: int = SAMPLER_BATCH

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise ParameterError(f"unknown method {self.method!r}; one of {', '.join(METHODS)}")
        if self.method == "sampler" and not 1 <= self.trials <= 10_000:
            raise ParameterError(f"trials must be between 1 and 10000, got {self.trials}")
        if self.batch < 1:
            raise ParameterError(f"batch must be ≥ 1, got {self.batch}")

    @property
    def total(self) -> int:
        return self.space.grid_size if self.method == "grid" else self.trials

    def next_batch(self, done: Sequence[Trial], started: int) -> list[dict[str, float]]:
        """The values of trials ``started`` … for the sampler (after ``done`` finished), or of
        the whole grid when nothing has started; [] when the plan is complete."""
        if self.method == "grid":
            return self.space.grid() if started == 0 else []
        count = min(self.batch, self.trials - started)
        if count <= 0:
            return []
        fixed = self.initial_design()[started : started + count]
        if len(fixed) == count:
            return fixed
        history = [(t.values, t.score(self.objective)) for t in done]
        return fixed + propose_trials(self.space, history, count=count - len(fixed), seed=self.seed)

    def initial_design(self) -> list[dict[str, float]]:
        """The sampler's first trials: the box's corners and centre if they are at most half of
        its trials (none otherwise, and none for a grid)."""
        if self.method != "sampler":
            return []
        design = self.space.corners_and_centre()
        return design if 2 * len(design) <= self.trials else []
