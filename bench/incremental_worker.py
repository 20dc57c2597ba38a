"""Incremental building maps through the real worker (issue 38): what one walk added to or taken
out of a map of N walks costs as a worker job, with ``Settings.incremental_builds`` (the ISAM2
state stored with the map's current version, the engine's map served without a batch solve)
against the batch build. One command, prints a table:

    .venv/bin/python bench/incremental_worker.py                      # N = 5, 10, 20, 30
    .venv/bin/python bench/incremental_worker.py --sizes 5 10 --json out.json

For each N, in a fresh SQLite database (a temporary directory, migrated to head), N + 1
simulated walks of one building (``simulate_building_sessions``, seed 7, 1,200 poses = 2 minutes
each) are uploaded as the API stores them (``parse_upload``, ``sessions.create_session``; each
upload's own build is canceled), then, each timed in wall seconds from the enqueue to the worker
(``workers.main.Worker`` with the ``build_map`` pipeline, in this process) finishing the job:

- *first build*: one map of the first N walks, one batch build (``enqueue_rebuild`` with their
  session ids, incremental builds off); it stores the ISAM2 state the next add starts from;
- *add, engine* and *remove, engine*: with incremental builds on ("serve"), walk N + 1 added
  (``add_session_to_map``) and taken out again (``remove_session_from_map``), three times; the
  worker's memory (its warm-start cache ``workers.pipeline.LAST_JOINT_MAPS`` and its parsed
  walks ``workers.pipeline.loading.PARSED_SESSIONS``) is cleared before every job (unless
  ``--keep-worker-memory``: a long-lived worker's jobs),
  so that each starts as a restarted worker's would (from the state in the database);
- *add, batch path*: once, the same add with incremental builds off (cache cleared too).

For each job: its wall and CPU time, its stage durations as the worker stored them
(``job_stage`` rows, ``app.storage.job_metrics``) and what its log says of the incremental path
(the ``optimize: incremental:`` line: "; served (" when the engine's map was served, else why
the batch build decided). A job that fails is printed with its error and the bench goes on.
Timings on a shared machine are noisy: OpenBLAS is held to one thread, as the other benches do.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import json
import logging
import statistics
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from sqlalchemy import select
from sqlalchemy.orm import Session as DbSession

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # run from a checkout without installing

from app.cli.tables import render_markdown_table  # noqa: E402
from app.config import Settings  # noqa: E402
from app.domain.evaluation.simulate import SimulationConfig  # noqa: E402
from app.domain.evaluation.simulate_building import simulate_building_sessions  # noqa: E402
from app.services.maps import (  # noqa: E402
    add_session_to_map,
    enqueue_rebuild,
    remove_session_from_map,
)
from app.services.uploads import parse_upload  # noqa: E402
from app.storage import queue, sessions  # noqa: E402
from app.storage.db import Database  # noqa: E402
from app.storage.migrate import upgrade_to_head  # noqa: E402
from app.storage.orm import JobStageRun, JobState  # noqa: E402
from app.storage.sessions import StoredUpload  # noqa: E402
from workers import pipeline  # noqa: E402
from workers.main import Worker  # noqa: E402
from workers.pipeline import BUILD_MAP_STAGES, loading  # noqa: E402

SIZES = (5, 10, 20, 30)
SIMULATED_POSES = 1_200
SEED = 7
REPETITIONS = 3
MAX_ATTEMPTS = 3
INCREMENTAL_MARK = "optimize: incremental: "
#: ``--keep-worker-memory``: the worker's caches kept between jobs (else cleared before each)
KEEP_WORKER_MEMORY = False
SERVED_MARK = "; served ("


class IncrementalLines(logging.Handler):
    """The worker's ``incremental_build`` log records, by job id: the job's log tail keeps its
    last lines only, the logger has them all."""

    def __init__(self) -> None:
        super().__init__(level=logging.INFO)
        self.notes: dict[int, str] = {}

    def emit(self, record: logging.LogRecord) -> None:
        if getattr(record, "action", None) == "incremental_build":
            job_id, note = record.args if isinstance(record.args, tuple) else (None, None)
            if isinstance(job_id, int):
                self.notes[job_id] = str(note)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--sizes", type=int, nargs="+", default=list(SIZES), help="map sizes N (5 10 20 30)"
    )
    parser.add_argument("--json", type=Path, help="also write the results here")
    parser.add_argument(
        "--keep-worker-memory",
        action="store_true",
        help="keep the worker's caches between jobs (a long-lived worker; default: cleared)",
    )
    args = parser.parse_args()
    global KEEP_WORKER_MEMORY
    KEEP_WORKER_MEMORY = args.keep_worker_memory
    handler = IncrementalLines()
    pipeline_logger = logging.getLogger("workers.pipeline")
    pipeline_logger.addHandler(handler)
    pipeline_logger.setLevel(logging.INFO)
    rows = []
    started_s = time.perf_counter()
    for n in args.sizes:
        size_started_s = time.perf_counter()
        try:
            row = one_size(n, handler)
        except Exception as err:  # the bench goes on with the next size
            row = {"n": n, "error": f"{type(err).__name__}: {err}"}
            print(f"N = {n}: {row['error']}", file=sys.stderr)
        row["total_s"] = time.perf_counter() - size_started_s
        rows.append(row)
        print(f"N = {n}: done in {row['total_s']:.0f} s", file=sys.stderr)
    total_s = time.perf_counter() - started_s
    print(
        f"\n## One walk added to / taken out of a map of N walks, a worker job each "
        f"(wall s; {SIMULATED_POSES} poses a walk)\n"
    )
    print(render_markdown_table(size_table(rows), justify="right"))
    notes = [note for row in rows for note in row_notes(row)]
    if notes:
        print()
        print("\n".join(f"- {note}" for note in notes))
    print(f"\ntotal {total_s:.0f} s")
    if args.json:
        args.json.write_text(json.dumps({"sizes": rows, "total_s": total_s}, indent=2))
    return 0


def one_size(n: int, handler: IncrementalLines) -> dict[str, Any]:
    building = simulate_building_sessions(
        SimulationConfig(num_poses=SIMULATED_POSES, seed=SEED), count=n + 1
    )
    uploads = [json.dumps(s.upload, separators=(",", ":")).encode() for s in building.sessions]
    del building
    row: dict[str, Any] = {"n": n}
    with tempfile.TemporaryDirectory(prefix="im-bench-incremental-worker-") as tmp:
        db = Database(f"sqlite:///{tmp}/bench.sqlite3")
        try:
            upgrade_to_head(db)
            batch, engine = worker(db, Path(tmp), "off"), worker(db, Path(tmp), "serve")
            started_s = time.perf_counter()
            session_ids, map_id = upload_all(db, uploads, max_poses=batch.settings.max_poses)
            row["upload_s"] = time.perf_counter() - started_s
            first, last = session_ids[:n], session_ids[n]

            def rebuild(tx: DbSession) -> int:
                return enqueue_rebuild(
                    tx, map_id, {}, max_attempts=MAX_ATTEMPTS, session_ids=first
                )[1]

            def add(tx: DbSession) -> int:
                return add_session_to_map(tx, map_id, last, max_attempts=MAX_ATTEMPTS).job_id

            def remove(tx: DbSession) -> int:
                return remove_session_from_map(tx, map_id, last, max_attempts=MAX_ATTEMPTS).job_id

            row["first_build"] = timed_job(db, batch, rebuild, handler)
            if row["first_build"]["state"] != JobState.SUCCEEDED:
                return row
            row["engine_adds"], row["engine_removes"] = [], []
            for _ in range(REPETITIONS):
                row["engine_adds"].append(timed_job(db, engine, add, handler))
                row["engine_removes"].append(timed_job(db, engine, remove, handler))
            row["batch_add"] = timed_job(db, batch, add, handler)
        finally:
            db.dispose()
            pipeline.LAST_JOINT_MAPS.clear()
            loading.PARSED_SESSIONS.clear()
    return row


def worker(db: Database, data_dir: Path, mode: str) -> Worker:
    """A worker of the ``build_map`` pipeline in this process; ``mode``: incremental builds
    "off" or "serve"."""
    settings = Settings(
        database_url=db.url.render_as_string(hide_password=False),
        data_dir=data_dir,
        lease_s=60.0,
        heartbeat_s=5.0,
        poll_s=0.05,
        retry_backoff_s=0.0,
        incremental_builds=mode != "off",
        incremental_check=False,
    )
    return Worker(db, settings, pipelines={"build_map": BUILD_MAP_STAGES})


def upload_all(db: Database, uploads: Sequence[bytes], *, max_poses: int) -> tuple[list[int], int]:
    """Each upload stored as ``POST /v1/sessions`` stores it (its session, its map, its build
    job, which is canceled: the bench builds the map of several); the session ids and the first
    upload's map."""
    session_ids, map_ids = [], []
    for raw in uploads:
        parsed = parse_upload([raw], max_poses=max_poses)
        with db.transaction() as tx:
            result = sessions.create_session(
                tx,
                parsed=parsed,
                upload=StoredUpload.of(raw),
                uploaded_by="bench",
                max_attempts=MAX_ATTEMPTS,
            )
            queue.request_cancel(tx, result.job_id)
        session_ids.append(result.session_id)
        map_ids.append(result.map_id)
    return session_ids, map_ids[0]


def timed_job(
    db: Database,
    runner: Worker,
    enqueue: Callable[[DbSession], int],
    handler: IncrementalLines,
) -> dict[str, Any]:
    """Enqueue a job (``enqueue``, in one transaction) and run the worker until the queue is
    empty, the warm-start cache cleared first; the job's timings and what its log says."""
    if not KEEP_WORKER_MEMORY:  # a restarted worker: nothing of the map in memory
        pipeline.LAST_JOINT_MAPS.clear()
        loading.PARSED_SESSIONS.clear()
    started_s, started_cpu_s = time.perf_counter(), time.process_time()
    try:
        with db.transaction() as tx:
            job_id = enqueue(tx)
    except Exception as err:
        return {"state": "not queued", "error": f"{type(err).__name__}: {err}"}
    while runner.run_once():
        pass
    wall_s, cpu_s = time.perf_counter() - started_s, time.process_time() - started_cpu_s
    with db.read() as tx:
        job = queue.get_job(tx, job_id)
        stages = tx.execute(
            select(JobStageRun.stage, JobStageRun.duration_s)
            .where(JobStageRun.job_id == job_id, JobStageRun.attempt == job.attempts)
            .order_by(JobStageRun.id)
        ).all()
    line = next((ln for ln in reversed(job.log_tail.splitlines()) if INCREMENTAL_MARK in ln), None)
    note = line.split(INCREMENTAL_MARK, 1)[1] if line is not None else handler.notes.get(job_id)
    out: dict[str, Any] = {
        "job_id": job_id,
        "state": str(job.state),
        "error": job.error,
        "attempts": job.attempts,
        "wall_s": wall_s,
        "cpu_s": cpu_s,
        "stages_s": {stage: float(duration_s) for stage, duration_s in stages},
        "incremental": note,
        "served": note is not None and SERVED_MARK in note,
    }
    if job.state != JobState.SUCCEEDED:
        print(f"job {job_id} {job.state}: {job.error}", file=sys.stderr)
    return out


def median(jobs: Sequence[dict[str, Any]], key: Callable[[dict[str, Any]], float | None]) -> str:
    """The median of ``key`` over the jobs that succeeded (where it is known), s."""
    done = [key(job) for job in jobs if job.get("state") == JobState.SUCCEEDED]
    values = [v for v in done if v is not None]
    return f"{statistics.median(values):.2f}" if values else "—"


def size_table(rows: Sequence[dict[str, Any]]) -> list[list[str]]:
    lines = [
        ["N", "first build (batch) s", "add, batch path s", "add, engine s (median of 3)",
         "remove, engine s (median of 3)", "served by the engine",
         "optimize stage of an engine add s", "slowest other stage (name, s)"],
    ]  # fmt: skip
    for r in rows:
        adds, removes = r.get("engine_adds", []), r.get("engine_removes", [])
        changes = [*adds, *removes]
        lines.append(
            [
                str(r["n"]),
                job_cell(r.get("first_build")),
                job_cell(r.get("batch_add")),
                median(adds, lambda job: job["wall_s"]) + failed(adds),
                median(removes, lambda job: job["wall_s"]) + failed(removes),
                f"adds {sum(1 for j in adds if j.get('served'))}/{len(adds)}, removes "
                f"{sum(1 for j in removes if j.get('served'))}/{len(removes)}"
                if changes
                else "—",
                median(adds, lambda job: job["stages_s"].get("optimize")),
                slowest_other_stage(adds),
            ]
        )
    return lines


def job_cell(job: dict[str, Any] | None) -> str:
    if job is None:
        return "—"
    if job["state"] != JobState.SUCCEEDED:
        return str(job["state"])
    return f"{job['wall_s']:.2f}"


def failed(jobs: Sequence[dict[str, Any]]) -> str:
    bad = sum(1 for job in jobs if job.get("state") != JobState.SUCCEEDED)
    return f" ({bad} failed)" if bad else ""


def slowest_other_stage(jobs: Sequence[dict[str, Any]]) -> str:
    """The stage other than ``optimize`` with the largest median duration over ``jobs``."""
    done = [job for job in jobs if job.get("state") == JobState.SUCCEEDED]
    names = {name for job in done for name in job["stages_s"] if name != "optimize"}
    if not names:
        return "—"
    medians = {
        name: statistics.median(job["stages_s"][name] for job in done if name in job["stages_s"])
        for name in names
    }
    name = max(medians, key=medians.__getitem__)
    return f"{name} {medians[name]:.2f}"


def row_notes(row: dict[str, Any]) -> list[str]:
    """What the table does not say: errors, and the changes the engine did not serve (why)."""
    n = row["n"]
    notes = []
    if "error" in row:
        notes.append(f"N = {n}: {row['error']}")
    jobs = [("first build", row.get("first_build")), ("add, batch path", row.get("batch_add"))]
    jobs += [(f"add {k + 1}", job) for k, job in enumerate(row.get("engine_adds", []))]
    jobs += [(f"remove {k + 1}", job) for k, job in enumerate(row.get("engine_removes", []))]
    for what, job in jobs:
        if job is None:
            continue
        if job["state"] != JobState.SUCCEEDED:
            notes.append(f"N = {n}, {what}: {job['state']}: {job['error']}")
        elif what.startswith(("add ", "remove ")) and not job["served"]:
            notes.append(f"N = {n}, {what}, not served by the engine: {job['incremental']}")
    return notes


if __name__ == "__main__":
    sys.exit(main())
