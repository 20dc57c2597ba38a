"""Running a sweep on this machine, over a pool of processes (the ``sweep`` command, benchmarks).

    trials = run_sweep(session, SweepPlan(method="grid", space=SearchSpace.paper_grid()),
                       ground_truth=gt, processes=2, on_progress=bar.update)

The server runs the same trials as jobs that any worker takes (``workers/sweep.py``); both use
:class:`SweepPlan` to decide which trials come next, so a sweep means the same thing everywhere.
The pool's processes are started fresh (``spawn``) so that they can preload jemalloc
(``app.allocator``: about 20% faster trials).
"""

from __future__ import annotations

import contextlib
import math
import multiprocessing
import os
from collections.abc import Callable, Iterator, Mapping, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass

from app.allocator import preloading_jemalloc
from app.domain.errors import ParameterError
from app.domain.frames import FloatArray
from app.domain.params import SlamParams
from app.domain.session import Session
from app.domain.tuning import SearchSpace, Trial, TuningTarget, check_objective, propose_trials

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


_target: TuningTarget | None = None


def _init_worker(
    session: Session, params: SlamParams, ground_truth: Mapping[int, FloatArray] | None
) -> None:
    global _target
    _target = TuningTarget.prepare(session, params, ground_truth)


def _run_chunk(chunk: Sequence[Mapping[str, float]]) -> list[Trial]:
    assert _target is not None, "pool worker not initialized"
    return [_target.run(values) for values in chunk]


@contextlib.contextmanager
def trial_pool(
    processes: int,
    session: Session,
    params: SlamParams,
    ground_truth: Mapping[int, FloatArray] | None,
) -> Iterator[ProcessPoolExecutor]:
    """``processes`` fresh processes (``spawn``, preloading jemalloc where the machine has it),
    each with ``session`` prepared for trials (:func:`_run_chunk`)."""
    with preloading_jemalloc():
        pool = ProcessPoolExecutor(
            processes,
            mp_context=multiprocessing.get_context("spawn"),
            initializer=_init_worker,
            initargs=(session, params, ground_truth),
        )
        with pool:  # processes start as tasks come, so the whole use is inside the preload
            yield pool


def run_sweep(
    session: Session,
    plan: SweepPlan,
    *,
    base_params: SlamParams | None = None,
    ground_truth: Mapping[int, FloatArray] | None = None,
    processes: int | None = None,
    on_progress: Callable[[int], None] | None = None,
) -> list[Trial]:
    """Every trial of ``plan``, in the plan's order; ``on_progress(n)`` after each n finish."""
    check_objective(plan.objective, has_ground_truth=bool(ground_truth))
    if processes is not None and processes < 1:
        raise ParameterError(f"processes must be ≥ 1, got {processes}")
    params = base_params or SlamParams()
    processes = processes or os.cpu_count() or 1
    trials: list[Trial] = []
    with trial_pool(processes, session, params, ground_truth) as pool:
        while batch := plan.next_batch(trials, len(trials)):
            # at most GRID_CHUNK per task, and every process gets a share of a small batch
            size = min(GRID_CHUNK, math.ceil(len(batch) / processes))
            chunks = [batch[i : i + size] for i in range(0, len(batch), size)]
            for chunk_trials in pool.map(_run_chunk, chunks):
                trials.extend(chunk_trials)
                if on_progress is not None:
                    on_progress(len(chunk_trials))
    return trials
