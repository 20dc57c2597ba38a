"""Jobs as lists of stages, and the runner that carries one out under a lease.

    stages = PIPELINES["build_map"]     # load → tune → optimize → evaluate → path_graph → store
    report = run_job(db, lease, stages=stages, control=JobControl(), retry_backoff_s=2.0)
    report.outcome                            # Outcome.SUCCEEDED, FAILED, RETRYING, …

A :class:`Stage` is a name, a weight (its share of the progress bar) and a function of the
:class:`JobContext`, which carries the job's inputs and what earlier stages produced. To extend a
job, add a stage (and, if it produces something, a field of the context); the last stage must end
the job with ``queue.finish`` in the transaction that stores its result (see :func:`store`).

Between stages the runner writes the stage and the overall progress (``queue.report_progress``,
which also returns whether a cancel was requested) and carries out what was asked meanwhile:
a cancel (``queue.mark_canceled``), a release by a worker shutting down (``queue.release``), or a
lost lease (abandon: write nothing). Errors decide between retrying and failing:

- :class:`~app.domain.errors.InvisibleMapError` (the core refusing its input: a malformed upload,
  a bad parameter) and :class:`PermanentJobError` (a missing or corrupt stored input) can never
  succeed, so the job fails at once with the error's message;
- any other ``Exception`` (out of memory, a bug, the database unreachable for longer than the
  lease) is transient: the job is queued again after a back-off that doubles per attempt, until
  ``max_attempts``.

A database outage shorter than the lease does not cost the attempt: a stage or a job-state write
that fails with a database fault (``app.storage.db.database_fault``: unreachable, restarting,
full, read-only) is tried again, waiting 0.5 s, 1 s, 2 s, 4 s, 4 s … while the lease holds
(``JobControl.lease_deadline_s``, kept by the heartbeat thread). Stages are idempotent (``store``
commits all or nothing and is fenced), so trying one again is safe; and once the database is back
the job carries on where it was, in the same attempt, and runs once.

The modules, in the order a job meets them:

context.py    what the stages share: :class:`JobContext`, :class:`Stage`, :class:`Outcome`,
              :class:`JobReport`, the errors a stage raises (:class:`PermanentJobError`,
              :class:`Interrupted`)
loading.py    the ``load`` stage, and :func:`load_session_upload` (a stored upload read back)
joint.py      a map of several sessions (``optimize``'s joint half) and its warm start
build_map.py  the other build_map stages (tune, optimize, evaluate, path_graph, store),
              :data:`BUILD_MAP_STAGES` and :data:`PIPELINES`
runner.py     :func:`run_job` and the database-outage retries (:func:`through_outages`)

Each module looks up the names it calls in its own namespace: a test patching one (the optimizer,
the skeleton, ``OUTAGE_FIRST_WAIT_S``) patches it in the module that calls it
(``workers.pipeline.build_map``, ``workers.pipeline.runner``), not here.
"""

from __future__ import annotations

from .build_map import (
    BUILD_MAP_STAGES,
    PIPELINES,
    derived_documents,
    evaluate,
    optimize,
    path_graph,
    store,
    tune,
)
from .context import (
    PROGRESS_INTERVAL_S,
    Interrupted,
    JobContext,
    JobReport,
    Outcome,
    PermanentJobError,
    Stage,
    logger,
)
from .joint import LAST_JOINT_MAPS, WARM_START_MAPS, remember_joint_map, warm_start
from .loading import load, load_session_upload
from .runner import OUTAGE_FIRST_WAIT_S, OUTAGE_MAX_WAIT_S, is_permanent, run_job, through_outages

__all__ = [
    "BUILD_MAP_STAGES",
    "LAST_JOINT_MAPS",
    "OUTAGE_FIRST_WAIT_S",
    "OUTAGE_MAX_WAIT_S",
    "PIPELINES",
    "PROGRESS_INTERVAL_S",
    "WARM_START_MAPS",
    "Interrupted",
    "JobContext",
    "JobReport",
    "Outcome",
    "PermanentJobError",
    "Stage",
    "derived_documents",
    "evaluate",
    "is_permanent",
    "load",
    "load_session_upload",
    "logger",
    "optimize",
    "path_graph",
    "remember_joint_map",
    "run_job",
    "store",
    "through_outages",
    "tune",
    "warm_start",
]
