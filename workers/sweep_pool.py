"""Running a sweep on this machine, over a pool of processes (the ``sweep`` command, benchmarks).

    trials = run_sweep(session, SweepPlan(method="grid", space=SearchSpace.paper_grid()),
                       ground_truth=gt, processes=2, on_progress=bar.update)

The server runs the same trials as jobs that any worker takes (``workers/sweep.py``); both use
:class:`SweepPlan` to decide which trials come next, so a sweep means the same thing everywhere.
The pool's processes are started fresh (``spawn``) so that they can preload jemalloc
(``workers.allocator``: about 20% faster trials).
"""

from __future__ import annotations

import contextlib
import math
import multiprocessing
import os
from collections.abc import Callable, Iterator, Mapping, Sequence
from concurrent.futures import ProcessPoolExecutor

from app.domain.errors import ParameterError
from app.domain.evaluation.sweep_plan import GRID_CHUNK, SweepPlan
from app.domain.evaluation.tuning import Trial, TuningTarget, check_objective
from app.domain.frames import FloatArray
from app.domain.mapping.params import SlamParams
from app.domain.upload.session import Session
from workers.allocator import preloading_jemalloc

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
