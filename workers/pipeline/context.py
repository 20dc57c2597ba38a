"""What a job's stages share: the :class:`JobContext` they read and fill, the :class:`Stage`
type, how an attempt ended (:class:`Outcome`, :class:`JobReport`), and the errors a stage
raises to stop it (:class:`PermanentJobError`, :class:`Interrupted`)."""

from __future__ import annotations

import enum
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, TypeVar

from app.domain.evaluation.table import Evaluation
from app.domain.evaluation.tuning import Trial, TuningTarget
from app.domain.frames import FloatArray
from app.domain.mapping.incremental import IsamState
from app.domain.mapping.joint import JointMap
from app.domain.mapping.map_result import MapResult
from app.domain.mapping.params import SlamParams
from app.domain.upload.session import Session
from app.storage import queue
from app.storage.db import Database
from app.storage.maps import VersionInfo
from app.storage.queue import Lease, LeaseLost
from workers.failures import log_failure
from workers.lease import JobControl

#: the package's one logger (its records keep the name they had before the split)
logger = logging.getLogger("workers.pipeline")

#: Least time between two progress writes from inside a stage, s (at most ~4 writes/s).
PROGRESS_INTERVAL_S = 0.25

T = TypeVar("T")


class PermanentJobError(Exception):
    """Raised by a stage when the job can never succeed as given (an input is missing or
    corrupt in storage); the job fails at once instead of being retried."""


class Interrupted(Exception):
    """Raised inside a stage (:meth:`JobContext.check_interrupted`, from an optimizer's iteration
    callback or between trials) when a cancel or a release was asked: the runner then cancels or
    releases the job at once instead of at the next stage boundary."""


class Outcome(enum.StrEnum):
    """How one attempt at a job ended (what the runner wrote to the job row)."""

    #: the result is stored and the job is ``succeeded``
    SUCCEEDED = "succeeded"
    #: the map changed while it was built: the result is not stored and the job is ``canceled``
    SUPERSEDED = "superseded"
    #: a transient error; the job is ``queued`` again, after a back-off
    RETRYING = "retrying"
    #: a permanent error, or the last attempt's transient one; the job is ``failed``
    FAILED = "failed"
    #: a cancel was requested; the job is ``canceled``
    CANCELED = "canceled"
    #: the worker is shutting down; the job is ``queued`` again, the attempt not counted
    RELEASED = "released"
    #: the lease was lost; nothing was written (another worker may be running the job)
    LEASE_LOST = "lease_lost"


@dataclass(frozen=True, slots=True, kw_only=True)
class JobReport:
    """The outcome of one attempt, for the worker's log."""

    outcome: Outcome
    error: str | None = None
    version: VersionInfo | None = None
    duration_s: float = 0.0
    #: each stage that ran to its end in this attempt, in order: (name, duration in s)
    stage_durations_s: tuple[tuple[str, float], ...] = ()


@dataclass(slots=True, kw_only=True)
class JobContext:
    """A job's inputs, what its stages produced so far, and how a stage reports progress.

    Stages read and fill the fields in order: ``load`` sets ``params`` and ``session``;
    ``optimize`` sets ``result``; ``evaluate`` sets ``evaluation`` and ``plot_png``;
    ``path_graph`` sets ``path_graph``; ``store`` sets ``version`` and ``finished``.
    ``log_tail`` is the job's log as the worker will next write it (started from
    ``lease.log_tail``); add to it with :meth:`log`.
    """

    db: Database
    lease: Lease
    control: JobControl
    log_tail: str
    params: SlamParams | None = None
    session: Session | None = None
    result: MapResult | None = None
    evaluation: Evaluation | None = None
    plot_png: bytes | None = None
    #: ``app.domain.navigation.path_graph.path_graph_to_json`` of the map's path graph
    path_graph: dict[str, Any] | None = None
    #: the sessions the map is built from, in order (``SESSION_IDS``; else the job's one)
    session_ids: list[int] = field(default_factory=list)
    #: each of them parsed, when there are several (``session`` is then their joint session)
    sessions: list[Session] = field(default_factory=list)
    #: the joint optimization of several sessions (``app.domain.mapping.joint``)
    joint: JointMap | None = None
    #: what makes the next add to this building map incremental (issue 38), made from the
    #: joint optimum; stored with the version (``app.storage.isam_states``); None when the
    #: batch graph is not the tree's (``incremental.from_batch``)
    isam_state: IsamState | None = None
    #: ``workers.incremental_builds.mode_of(settings)``: "off"; "serve" (a change of one walk
    #: made in the stored state and served when the checks pass); "check" (made there too, and
    #: compared with the batch build, which is served)
    incremental_builds: str = "off"
    #: build_map with ``auto_tune_trials``: sampler trials by the shift metric before optimizing
    auto_tune_trials: int = 0
    #: build_map with ``ground_truth``: tag id → world_T_tag, for the ground-truth metric
    ground_truth: dict[int, FloatArray] | None = None
    #: sweep_trials jobs (``workers/sweep.py``): the prepared session and the finished trials
    tuning_target: TuningTarget | None = None
    trials: list[Trial] | None = None
    version: VersionInfo | None = None
    #: the map's generation the build was queued for (``lease.map_generation``): its version is
    #: stored only while it is still the map's (:func:`store`)
    map_generation: int = 0
    #: set by the stage that committed the job as succeeded (``queue.finish``), or as
    #: superseded (``superseded`` then)
    finished: bool = False
    superseded: bool = False
    stage: str = ""
    stage_start: float = 0.0
    stage_weight: float = 0.0
    _last_write_s: float = field(default=-math.inf, repr=False)
    #: time.monotonic() after which the attempt fails (``Settings.job_time_budget_s``)
    deadline_s: float = math.inf
    time_budget_s: float = 0.0

    def begin_stage(self, name: str, *, start: float, weight: float) -> None:
        """Set the stage that :meth:`report` reports within (its first report is always
        written): it starts at overall progress ``start`` and spans ``weight`` of it."""
        self.stage, self.stage_start, self.stage_weight = name, start, weight
        self._last_write_s = -math.inf

    def log(self, message: str) -> None:
        """Add a timestamped line to the job's log tail (written with the next progress write)."""
        self.log_tail = queue.append_log(self.log_tail, message)

    def check_interrupted(self) -> None:
        """Stop the stage now if the job must stop: :class:`Interrupted` for a cancel or a
        release, LeaseLost for a lost lease, PermanentJobError past the time budget. Stages call
        it where they can stop safely (each optimizer iteration, each trial): a cancel then
        takes effect within a heartbeat (``heartbeat_s``) and one iteration."""
        control = self.control
        if control.lease_lost:
            raise LeaseLost(self.lease.job_id)
        if control.cancel_requested or control.release_requested:
            raise Interrupted(self.stage)
        if time.monotonic() > self.deadline_s:
            raise PermanentJobError(
                f"the job ran longer than its time budget of {self.time_budget_s:g} s "
                "(INVISIBLE_MAP_JOB_TIME_BUDGET_S)"
            )

    def on_trial_iteration(self, _iteration: int, _error: float) -> None:
        """The iteration callback of a tuning or sweep trial (``TuningTarget.run``): a cancel
        stops the trial within one Levenberg–Marquardt iteration, not after the trial."""
        self.check_interrupted()

    def report(self, fraction_within_stage: float, message: str | None = None) -> None:
        """Report progress within the current stage (0–1), and optionally log ``message``.

        Writes at most every :data:`PROGRESS_INTERVAL_S` (the first report of a stage always);
        never raises. A cancel request it sees
        is recorded in ``control`` (carried out at the next stage boundary), as is a lost lease.
        """
        if message is not None:
            self.log(message)
        now_s = time.monotonic()
        if now_s - self._last_write_s < PROGRESS_INTERVAL_S or self.control.lease_lost:
            return
        self._last_write_s = now_s
        fraction = min(max(fraction_within_stage, 0.0), 1.0)
        try:
            if queue.report_progress(
                self.db,
                self.lease,
                progress=self.stage_start + self.stage_weight * fraction,
                stage=self.stage,
                log_tail=self.log_tail,
            ):
                self.control.cancel_requested = True
        except LeaseLost:
            self.control.lease_lost = True
        except Exception as err:
            log_failure(logger, f"job {self.lease.job_id}: progress write failed", err)


@dataclass(frozen=True, slots=True, kw_only=True)
class Stage:
    """One step of a job: ``run(context)`` does the work; ``weight`` is its share of progress."""

    name: str
    weight: float
    run: Callable[[JobContext], None]


def need(value: T | None, what: str) -> T:
    if value is None:
        raise RuntimeError(f"pipeline order: {what} is not set by an earlier stage")
    return value
