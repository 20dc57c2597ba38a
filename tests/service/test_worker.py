"""The worker (``workers/``) on SQLite and PostgreSQL, in process: real sessions built into map
versions, progress and logs, permanent and transient errors, cancel, lost leases, stopping.

The tests that run worker *processes* (kill -9, SIGTERM, many processes) are in
``test_worker_processes.py``.
"""

from __future__ import annotations

import gzip
import json
import logging
import threading
import time
from collections.abc import Callable, Sequence
from datetime import timedelta

import numpy as np
import pytest
from sqlalchemy import select, update

from app.config import Settings
from app.domain.frames import pose_to_xyz_quat_xyzw
from app.domain.mapping.params import SlamParams
from app.domain.mapping.slam import optimize_session
from app.domain.upload.session import decode_json_bytes, parse_session
from app.storage import maps, queue, sessions
from app.storage.db import Database
from app.storage.orm import Job, JobState, MapVersion, WorkerRow, utc_now
from app.storage.queue import LeaseLost
from tests.service.helpers import (
    get_job,
    insert_session,
    replace_stored_upload,
    session_bytes,
    version_count,
    wait_for,
)
from workers import pipeline
from workers.lease import JobControl
from workers.main import Worker, main
from workers.pipeline import BUILD_MAP_STAGES, JobContext, Outcome, Stage

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def settings_for(db: Database, **overrides: float) -> Settings:
    values: dict[str, float] = {
        "lease_s": 30.0,
        "heartbeat_s": 5.0,
        "poll_s": 0.05,
        "retry_backoff_s": 0.0,
    }
    values.update(overrides)
    return Settings(database_url=db.url.render_as_string(hide_password=False), **values)


def worker_with(
    db: Database, stages: Sequence[Stage] = BUILD_MAP_STAGES, **settings: float
) -> Worker:
    return Worker(db, settings_for(db, **settings), pipelines={"build_map": tuple(stages)})


def with_stage_before(name: str, extra: Stage) -> list[Stage]:
    """The build-map stages with ``extra`` inserted before the stage called ``name``."""
    stages = list(BUILD_MAP_STAGES)
    stages.insert(next(k for k, stage in enumerate(stages) if stage.name == name), extra)
    return stages


def action(name: str, run: Callable[[JobContext], None]) -> Stage:
    """A weightless test stage."""
    return Stage(name=name, weight=0.0, run=run)


# --------------------------------------------------------------------------- success


def test_worker_builds_a_real_session_into_a_map_version(db: Database) -> None:
    raw = session_bytes("occam_room")
    overrides = {"max_reprojection_px": "6.0"}
    inserted = insert_session(db, raw, params=overrides)
    worker = worker_with(db)

    assert worker.run_once() is True
    assert worker.run_once() is False  # nothing left

    info = get_job(db, inserted.job_id)
    assert info.state == JobState.SUCCEEDED, info.error
    assert (info.attempts, info.progress, info.error, info.lease_owner) == (1, 1.0, None, None)
    expected = optimize_session(
        parse_session(decode_json_bytes(raw)), SlamParams().with_overrides(overrides)
    )
    with db.read() as tx:
        version = maps.get_version(tx, inserted.map_id)
        tags = maps.tag_poses(tx, version.id)
        plot = maps.plot_png(tx, inserted.map_id)
    assert (version.number, version.job_id) == (1, inserted.job_id)
    assert version.params["max_reprojection_px"] == 6.0
    assert version.tag_count == len(expected.tag_ids) == len(tags) > 1
    assert [t.tag_id for t in tags] == [int(t) for t in expected.tag_ids]
    stored = np.array([[*t.position_m, *t.quat_xyzw] for t in tags])
    direct = np.array([pose_to_xyz_quat_xyzw(pose) for pose in expected.world_T_tag])
    np.testing.assert_allclose(stored, direct, atol=1e-9)
    assert version.detections_rejected == len(expected.rejections)
    assert version.metrics["shift_opt"] is not None
    assert plot is not None
    assert plot.startswith(PNG_MAGIC)
    assert worker.jobs_done == 1


def test_log_tail_has_a_line_per_stage(db: Database) -> None:
    inserted = insert_session(db, session_bytes("onetag"))

    worker_with(db).run_once()

    lines = get_job(db, inserted.job_id).log_tail.splitlines()
    messages = [line.split(" ", 1)[1] for line in lines]
    assert messages[0] == "queued"
    assert messages[1].startswith("attempt 1 of 3 started by ")
    assert [m.split(":")[0] for m in messages[2:7]] == [
        "load",
        "optimize",
        "evaluate",
        "path graph",
        "store",
    ]
    assert "junctions" in messages[5]
    assert "poses" in messages[2]
    assert "iterations" in messages[3]
    assert "ms" in messages[3]
    assert "shift metric" in messages[4]
    assert messages[7:] == ["succeeded"]


def test_stage_and_progress_are_written_at_each_stage(db: Database) -> None:
    inserted = insert_session(db, session_bytes("onetag"))
    seen: list[tuple[str | None, float]] = []
    within: list[float] = []

    def probe(real: Stage) -> Stage:
        def run(ctx: JobContext) -> None:
            row = get_job(db, ctx.lease.job_id)  # another transaction: what the API would see
            seen.append((row.stage, row.progress))
            real.run(ctx)

        return Stage(name=real.name, weight=real.weight, run=run)

    def report_within_stage(ctx: JobContext) -> None:
        ctx.report(0.5)
        within.append(get_job(db, ctx.lease.job_id).progress)
        ctx.report(1.0)  # too soon after the last write: not written
        within.append(get_job(db, ctx.lease.job_id).progress)

    stages = [probe(stage) for stage in BUILD_MAP_STAGES]
    evaluate = [stage.name for stage in BUILD_MAP_STAGES].index("evaluate")
    stages[evaluate] = Stage(
        name="evaluate",
        weight=stages[evaluate].weight,
        run=lambda ctx: (report_within_stage(ctx), BUILD_MAP_STAGES[evaluate].run(ctx))[1],
    )
    worker_with(db, stages).run_once()

    starts = np.cumsum([0.0] + [stage.weight for stage in BUILD_MAP_STAGES])[:-1]
    assert [name for name, _ in seen] == ["load", "tune", "optimize", "path_graph", "store"]
    # Progress is stored rounded to 4 decimals.
    np.testing.assert_allclose([p for _, p in seen], starts[[0, 1, 2, 4, 5]], atol=1e-4)
    evaluate_start, evaluate_weight = starts[evaluate], BUILD_MAP_STAGES[evaluate].weight
    np.testing.assert_allclose(within, [evaluate_start + 0.5 * evaluate_weight] * 2, atol=1e-4)
    assert get_job(db, inserted.job_id).state == JobState.SUCCEEDED


# --------------------------------------------------------------------------- errors


def test_corrupt_stored_uploads_fail_permanently_and_the_next_job_succeeds(db: Database) -> None:
    corruptions = {
        b"this is not gzip at all": ["corrupt", "not valid gzip"],
        gzip.compress(session_bytes("occam_room"))[:5000]: ["corrupt", "not valid gzip"],  # cut
        gzip.compress(b"{not json"): ["stored upload of session", "not valid JSON"],
        gzip.compress(json.dumps({"map_id": "x"}).encode()): ["pose_data"],
    }
    bad = []
    for stored in corruptions:
        inserted = insert_session(db, session_bytes("onetag"))
        replace_stored_upload(db, inserted.session_id, stored)
        bad.append(inserted)
    good = insert_session(db, session_bytes("onetag"))
    worker = worker_with(db)

    for _ in range(len(bad) + 1):
        assert worker.run_once()

    for inserted, words in zip(bad, corruptions.values(), strict=True):
        info = get_job(db, inserted.job_id)
        assert (info.state, info.attempts) == (JobState.FAILED, 1), info.error
        assert info.error is not None
        assert info.error.startswith("load: ")
        for word in words:
            assert word in info.error
        assert "permanent error" in info.log_tail
        assert version_count(db, job_id=inserted.job_id) == 0
    assert get_job(db, good.job_id).state == JobState.SUCCEEDED
    assert version_count(db) == 1


def test_the_stored_upload_is_parsed_as_it_streams_never_whole(
    db: Database, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The load stage reads the stored upload a piece at a time (here 1,000 bytes) and parses it
    as it is inflated; two gzip members (as a resumed upload may store) are one document."""
    raw = session_bytes("occam_room")
    inserted = insert_session(db, raw)
    replace_stored_upload(
        db, inserted.session_id, gzip.compress(raw[:300_000]) + gzip.compress(raw[300_000:])
    )

    def whole_file(*_: object) -> bytes:
        raise AssertionError("the whole stored upload was read")

    monkeypatch.setattr(sessions, "raw_upload", whole_file)
    monkeypatch.setattr(sessions, "raw_upload_gzip", whole_file)
    monkeypatch.setattr(pipeline.loading, "STORED_PIECE_BYTES", 1000)
    assert worker_with(db).run_once()
    job = get_job(db, inserted.job_id)
    assert job.state == JobState.SUCCEEDED, job.error
    expected = parse_session(decode_json_bytes(raw))
    assert f"load: {expected.num_poses} poses" in job.log_tail
    assert f"{len(raw) / 1e6:.2f} MB" in job.log_tail  # the JSON's size, counted as inflated


@pytest.mark.parametrize(
    ("params", "named"),
    [
        ({"no_such_param": 1}, "no_such_param"),
        ({"tag_position_var_m2": "lots"}, "tag_position_var_m2"),
        ({"tag_position_var_m2": -1.0}, "tag_position_var_m2"),
    ],
)
def test_bad_params_fail_permanently(db: Database, params: dict[str, object], named: str) -> None:
    inserted = insert_session(db, session_bytes("onetag"), params=params)

    worker_with(db).run_once()

    info = get_job(db, inserted.job_id)
    assert (info.state, info.attempts) == (JobState.FAILED, 1)
    assert info.error is not None
    assert info.error.startswith("load: ParameterError")
    assert named in info.error
    assert version_count(db) == 0


def test_a_map_whose_every_detection_is_rejected_fails_and_keeps_no_version(
    db: Database,
) -> None:
    inserted = insert_session(db, session_bytes("occam_room"), params={"max_distance_m": 0.01})

    worker_with(db).run_once()

    info = get_job(db, inserted.job_id)
    assert (info.state, info.attempts) == (JobState.FAILED, 1)
    assert info.error is not None
    assert info.error.startswith("optimize: PermanentJobError")
    assert "every one of the session's 200 tag detections was rejected" in info.error
    assert "distance" in info.error
    assert version_count(db) == 0


def test_transient_errors_are_retried_until_max_attempts(db: Database) -> None:
    calls = {"flaky": 0}

    def flaky_once(_ctx: JobContext) -> None:
        calls["flaky"] += 1
        if calls["flaky"] == 1:
            raise RuntimeError("database hiccup")

    def always_broken(ctx: JobContext) -> None:
        if ctx.lease.params.get("huber_k") == 0:
            raise OSError("disk full")

    flaky = insert_session(db, session_bytes("onetag"))
    broken = insert_session(db, session_bytes("onetag"), params={"huber_k": 0}, max_attempts=2)
    stages = [action("flaky", flaky_once), action("broken", always_broken), *BUILD_MAP_STAGES]
    worker = worker_with(db, stages)

    worker.run_once()  # flaky, attempt 1: transient error
    info = get_job(db, flaky.job_id)
    assert (info.state, info.attempts) == (JobState.QUEUED, 1)
    assert info.error == "flaky: RuntimeError: database hiccup"
    assert "retrying in 0 s" in info.log_tail

    for _ in range(3):  # broken attempt 1, flaky attempt 2 (oldest first), broken attempt 2
        assert worker.run_once()

    info = get_job(db, flaky.job_id)
    assert (info.state, info.attempts, info.error) == (JobState.SUCCEEDED, 2, None)
    info = get_job(db, broken.job_id)
    assert (info.state, info.attempts) == (JobState.FAILED, 2)
    assert info.error == "broken: OSError: disk full"
    assert version_count(db, job_id=flaky.job_id) == 1
    assert version_count(db, job_id=broken.job_id) == 0


def test_a_failure_to_store_rolls_back_the_finish(
    db: Database, monkeypatch: pytest.MonkeyPatch
) -> None:
    inserted = insert_session(db, session_bytes("onetag"))
    real_store_version = maps.store_version

    def store_then_break(*args: object, **kwargs: object) -> maps.VersionInfo:
        real_store_version(*args, **kwargs)  # type: ignore[arg-type]
        raise RuntimeError("connection reset while storing")

    monkeypatch.setattr(pipeline.build_map.maps, "store_version", store_then_break)
    worker_with(db).run_once()

    info = get_job(db, inserted.job_id)
    assert (info.state, info.attempts) == (JobState.QUEUED, 1)
    assert info.error == "store: RuntimeError: connection reset while storing"
    assert version_count(db) == 0


# --------------------------------------------------------------------------- cancel


def test_cancel_requested_while_running_stops_at_the_next_stage(db: Database) -> None:
    inserted = insert_session(db, session_bytes("onetag"))
    ran: list[str] = []

    def api_cancels(ctx: JobContext) -> None:
        with db.transaction() as tx:
            queue.request_cancel(tx, ctx.lease.job_id)

    stages = [
        Stage(name=s.name, weight=s.weight, run=lambda ctx, s=s: (ran.append(s.name), s.run(ctx)))
        for s in with_stage_before("evaluate", action("api_cancels", api_cancels))
    ]
    worker_with(db, stages).run_once()

    info = get_job(db, inserted.job_id)
    assert info.state == JobState.CANCELED
    assert ran == ["load", "tune", "optimize", "api_cancels"]
    assert info.log_tail.splitlines()[-2].endswith("cancel requested: stopping before evaluate")
    assert info.log_tail.endswith("canceled\n")
    assert version_count(db) == 0


def test_a_long_stage_keeps_its_lease_and_hears_of_a_cancel(db: Database) -> None:
    """Between two stage boundaries only the heartbeat thread talks to the database: it must
    renew the lease (the stage outlasts it) and bring in the cancel request."""
    lease_s = 0.6
    inserted = insert_session(db, session_bytes("onetag"))
    heard: list[bool] = []

    def long_stage(ctx: JobContext) -> None:
        started_s = time.monotonic()
        with db.transaction() as tx:
            queue.request_cancel(tx, ctx.lease.job_id)
        heard.append(
            bool(wait_for(lambda: ctx.control.cancel_requested, timeout_s=5, what="heartbeat"))
        )
        wait_for(lambda: time.monotonic() - started_s > 2 * lease_s, timeout_s=5, what="time")

    stages = with_stage_before("optimize", Stage(name="long", weight=0.5, run=long_stage))
    worker_with(db, stages, lease_s=lease_s, heartbeat_s=0.1).run_once()

    assert heard == [True]
    info = get_job(db, inserted.job_id)
    assert info.state == JobState.CANCELED  # not LeaseLost: the lease held
    assert info.stage == "optimize"


# --------------------------------------------------------------------------- lost leases


def test_a_lost_lease_abandons_the_job_and_writes_nothing(
    db: Database, caplog: pytest.LogCaptureFixture
) -> None:
    inserted = insert_session(db, session_bytes("onetag"))
    thief: list[queue.Lease] = []

    def lease_expires_and_another_worker_claims(ctx: JobContext) -> None:
        with db.transaction() as tx:
            tx.execute(
                update(Job).where(Job.id == ctx.lease.job_id).values(lease_expires_at=utc_now())
            )
        assert queue.reap_expired(db, backoff_s=0) == 1
        stolen = queue.claim(db, worker_id="other", lease_s=60)
        assert stolen is not None
        thief.append(stolen)

    stages = with_stage_before("store", action("steal", lease_expires_and_another_worker_claims))
    worker = worker_with(db, stages)
    with caplog.at_level(logging.WARNING, logger="workers"):
        worker.run_once()

    info = get_job(db, inserted.job_id)
    assert (info.state, info.lease_owner, info.attempts) == (JobState.RUNNING, "other", 2)
    assert info.log_tail == thief[0].log_tail  # nothing of the first worker's after the theft
    assert "store:" not in info.log_tail
    assert version_count(db) == 0
    assert [r.action for r in caplog.records if hasattr(r, "action")] == ["job_lease_lost"]  # type: ignore[attr-defined]
    assert worker.jobs_done == 0


def test_store_with_a_lost_lease_writes_no_version(db: Database) -> None:
    inserted = insert_session(db, session_bytes("onetag"))
    lease = queue.claim(db, worker_id="w", lease_s=30)
    assert lease is not None
    ctx = JobContext(db=db, lease=lease, control=JobControl(), log_tail=lease.log_tail)
    for stage in BUILD_MAP_STAGES[:-1]:
        stage.run(ctx)
    queue.reap_expired(db, backoff_s=0, now=utc_now() + timedelta(seconds=31))

    with pytest.raises(LeaseLost):
        pipeline.store(ctx)

    assert not ctx.finished
    assert version_count(db) == 0
    assert get_job(db, inserted.job_id).state == JobState.QUEUED


# --------------------------------------------------------------------------- the loop, stopping


def test_run_registers_the_worker_runs_jobs_and_unregisters(db: Database) -> None:
    jobs = [insert_session(db, session_bytes("onetag")).job_id for _ in range(2)]
    worker = worker_with(db)
    stop = threading.Event()
    thread = threading.Thread(target=worker.run, args=(stop,))
    thread.start()
    try:
        wait_for(
            lambda: all(get_job(db, j).state == JobState.SUCCEEDED for j in jobs),
            timeout_s=30,
            what="both jobs to succeed",
        )

        def worker_row() -> tuple[str, int | None, int] | None:
            with db.read() as tx:
                row = tx.get(WorkerRow, worker.worker_id)
                return None if row is None else (row.state, row.current_job_id, row.jobs_done)

        wait_for(
            lambda: worker_row() == ("idle", None, 2),
            timeout_s=5,
            what=f"the worker row to show 2 jobs done and idle (it is {worker_row()})",
        )
    finally:
        stop.set()
        thread.join(timeout=10)
    assert not thread.is_alive()
    with db.read() as tx:
        assert tx.get(WorkerRow, worker.worker_id) is None
    assert worker.worker_id.count(":") == 2


def test_a_stop_request_lets_the_current_job_finish_then_stops(db: Database) -> None:
    first = insert_session(db, session_bytes("onetag")).job_id
    second = insert_session(db, session_bytes("onetag")).job_id
    worker = worker_with(db)
    worker.pipelines["build_map"] = with_stage_before(
        "optimize", action("sigterm", lambda _ctx: worker.request_stop())
    )

    worker.run(threading.Event())  # returns: the stop request ends the loop

    assert get_job(db, first).state == JobState.SUCCEEDED
    assert get_job(db, second).state == JobState.QUEUED
    assert get_job(db, second).attempts == 0


def test_a_second_stop_request_releases_the_job_at_the_next_stage(db: Database) -> None:
    job_id = insert_session(db, session_bytes("onetag"), max_attempts=1).job_id
    worker = worker_with(db)

    def twice(_ctx: JobContext) -> None:
        worker.request_stop()
        worker.request_stop()

    worker.pipelines["build_map"] = with_stage_before("optimize", action("sigterm x2", twice))
    worker.run(threading.Event())

    info = get_job(db, job_id)
    assert (info.state, info.attempts, info.lease_owner) == (JobState.QUEUED, 0, None)
    assert "released by" in info.log_tail
    assert "optimize:" not in info.log_tail
    assert version_count(db) == 0
    with db.read() as tx:
        assert tx.scalar(select(MapVersion.id)) is None


def test_run_job_reports_each_outcome_once(db: Database) -> None:
    inserted = insert_session(db, session_bytes("onetag"))
    lease = queue.claim(db, worker_id="w", lease_s=30)
    assert lease is not None

    report = pipeline.run_job(
        db, lease, stages=BUILD_MAP_STAGES, control=JobControl(), retry_backoff_s=0
    )

    assert report.outcome == Outcome.SUCCEEDED
    assert report.version is not None
    assert report.version.job_id == inserted.job_id
    # the job is over: the same lease can do nothing more
    again = pipeline.run_job(
        db, lease, stages=BUILD_MAP_STAGES, control=JobControl(), retry_backoff_s=0
    )
    assert again.outcome == Outcome.LEASE_LOST
    assert version_count(db) == 1


def test_main_rejects_zero_processes() -> None:
    with pytest.raises(SystemExit) as exit_info:
        main(["--processes", "0"])
    assert exit_info.value.code == 2


def test_a_walk_that_falls_apart_is_said_on_the_version(
    db: Database, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The app-map keeps the largest part of a walk that falls apart; the version says so."""
    import networkx as nx

    from app.domain.navigation.path_graph import PathGraph
    from app.domain.navigation.skeleton import build_skeleton

    def cut_in_two(result, **options):  # the real graph, its edges across x = its median removed
        graph = build_skeleton(result, **options)
        G = graph.graph.copy()
        x_median = float(np.median([G.nodes[n]["position_m"][0] for n in G]))
        side = {n: G.nodes[n]["position_m"][0] < x_median for n in G}
        G.remove_edges_from([(u, v) for u, v in list(G.edges) if side[u] != side[v]])
        assert nx.number_connected_components(G) > 1
        return PathGraph(graph=G, floor_levels_m=graph.floor_levels_m)

    monkeypatch.setattr(pipeline.build_map, "build_skeleton", cut_in_two)
    inserted = insert_session(db, session_bytes("occam_room"))

    assert worker_with(db).run_once() is True

    info = get_job(db, inserted.job_id)
    assert info.state == JobState.SUCCEEDED, info.error
    with db.read() as tx:
        version = maps.get_version(tx, inserted.map_id)
    notes = [w for w in version.warnings if w.startswith("app map: ")]
    assert notes
    assert "unconnected parts: only the largest" in notes[0]
    assert "app map: the walk falls apart" in info.log_tail
