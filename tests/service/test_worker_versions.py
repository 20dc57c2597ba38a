"""Versions always match their walks (issue 25, items 1 and 4), on SQLite and PostgreSQL, with
the real worker pipeline: a build overtaken by a change of the map's sessions stores no version
(its result would not be of the map's current sessions) and the build of the current sessions
becomes current; changes in quick succession coalesce into one build; a superseded build with no
build of the current sessions queues one."""

from __future__ import annotations

from typing import Any

import pytest

from app.config import Settings
from app.services.errors import InvalidInput
from app.services.maps import add_session_to_map, request_build
from app.storage import maps, queue
from app.storage.db import Database
from app.storage.orm import JobState
from tests.service.helpers import get_job, insert_session, session_bytes
from workers.main import Worker
from workers.pipeline import BUILD_MAP_STAGES, JobContext, Stage, store

pytestmark = pytest.mark.db

#: A small real walk (132 poses, 4 tags): uploaded several times, the copies share every tag.
WALK = "pgt_tester3"


def worker(db: Database, stages: tuple[Stage, ...] = BUILD_MAP_STAGES) -> Worker:
    settings = Settings(
        database_url=db.url.render_as_string(hide_password=False),
        lease_s=30.0,
        heartbeat_s=5.0,
        poll_s=0.05,
        retry_backoff_s=0.0,
    )
    return Worker(db, settings, pipelines={"build_map": stages})


def run_all(db: Database) -> None:
    """Run every queued job with the real pipeline."""
    runner = worker(db)
    while runner.run_once():
        pass


def built_map(db: Database) -> int:
    """A map of one walk with its first version built."""
    map_id = insert_session(db, session_bytes(WALK)).map_id
    run_all(db)
    return map_id


def another_walk(db: Database) -> int:
    """Another upload of the walk, its own map's build canceled (it is not what is tested)."""
    inserted = insert_session(db, session_bytes(WALK))
    with db.transaction() as db_session:
        queue.request_cancel(db_session, inserted.job_id)
    return inserted.session_id


def map_now(db: Database, map_id: int) -> maps.MapInfo:
    with db.read() as db_session:
        return maps.get_map(db_session, map_id)


def build_jobs(db: Database, map_id: int) -> list[queue.JobInfo]:
    with db.read() as db_session:
        return queue.jobs_of_map(db_session, map_id, kind="build_map")


def test_a_rebuild_overtaken_by_an_add_stores_no_version(db: Database) -> None:
    """The finding: a rebuild runs; a session is added and its build stores v2 from both walks;
    then the older rebuild reaches its store. It used to store v3 from one walk, which became
    current while the map listed both."""
    map_id = built_map(db)
    added = another_walk(db)
    with db.transaction() as db_session:
        rebuild = request_build(
            db_session, map_id, {"huber_k": 2.0}, max_attempts=3, change="rebuild requested"
        )

    changed: dict[str, Any] = {}

    def add_and_build_then_store(ctx: JobContext) -> None:
        with db.transaction() as db_session:
            changed["build"] = add_session_to_map(db_session, map_id, added, max_attempts=3)
        run_all(db)  # another worker builds the map of both walks: version 2
        assert map_now(db, map_id).current.number == 2  # type: ignore[union-attr]
        store(ctx)

    stages = (
        *BUILD_MAP_STAGES[:-1],
        Stage(name="store", weight=0.05, run=add_and_build_then_store),
    )
    assert worker(db, stages).run_once()

    info = map_now(db, map_id)
    assert info.current is not None
    assert (info.current.number, info.version_count) == (2, 2)
    assert info.current.session_ids == info.session_ids == [info.session_id, added]
    assert info.up_to_date
    assert info.pending_job_id is None
    overtaken = get_job(db, rebuild.job_id)
    assert overtaken.state == JobState.CANCELED
    add = changed["build"]
    assert add.generation == rebuild.generation + 1
    assert get_job(db, add.job_id).state == JobState.SUCCEEDED
    reason = (
        f"map {map_id} changed while it was built (generation {rebuild.generation} → "
        f"{add.generation}); its version is not stored: job {add.job_id} (succeeded) builds the "
        "map's current sessions"
    )
    assert overtaken.error == reason
    assert overtaken.log_tail.splitlines()[-1].endswith(f"superseded: {reason}")


def test_a_running_build_is_stopped_by_a_change_and_the_new_set_built(db: Database) -> None:
    """The finding's race caught earlier: a rebuild with auto_tune_trials runs; a session is
    added, which asks the running build to stop (its result could not become current) before
    its trials; the add's own build makes the version of both walks."""
    map_id = built_map(db)
    added = another_walk(db)
    with db.transaction() as db_session:
        rebuild = request_build(
            db_session, map_id, {"auto_tune_trials": 20}, max_attempts=3, change="tune it"
        )
    changed: dict[str, Any] = {}

    def add(_ctx: JobContext) -> None:
        with db.transaction() as db_session:
            changed["build"] = add_session_to_map(db_session, map_id, added, max_attempts=3)

    stages = list(BUILD_MAP_STAGES)
    stages.insert(1, Stage(name="add", weight=0.0, run=add))  # after load, before tune
    assert worker(db, tuple(stages)).run_once()
    assert changed["build"].superseded == (rebuild.job_id,)
    stopped = get_job(db, rebuild.job_id)
    assert stopped.state == JobState.CANCELED
    assert stopped.error == (
        f"superseded by job {changed['build'].job_id}: session {added} added (its "
        "auto_tune_trials=20 dropped: it tunes a map of one session); "
        f"generation {changed['build'].generation} builds sessions "
        f"{map_now(db, map_id).session_ids}"
    )
    run_all(db)
    info = map_now(db, map_id)
    assert info.current is not None
    assert info.current.number == 2
    assert info.current.session_ids == info.session_ids
    assert info.up_to_date


def test_changes_coalesce_into_one_build_and_tuning_several_sessions_is_refused(
    db: Database,
) -> None:
    map_id = built_map(db)
    walks = [another_walk(db) for _ in range(5)]
    # a rebuild of the one-session map, tuned; then adds while it is queued fold into it,
    # keeping its parameters but the tuning (a map of several sessions is not tuned)
    with db.transaction() as db_session:
        rebuild = request_build(
            db_session,
            map_id,
            {"huber_k": 2.0, "auto_tune_trials": 5},
            max_attempts=3,
            change="rebuild requested",
        )
        builds = [add_session_to_map(db_session, map_id, s, max_attempts=3) for s in walks[:3]]
    assert [b.coalesced for b in builds] == [True, True, True]
    assert {b.job_id for b in builds} == {rebuild.job_id}
    assert [b.params for b in builds] == [{"huber_k": 2.0}] * 3
    job = get_job(db, rebuild.job_id)
    assert job.state == JobState.QUEUED
    assert job.params == {"huber_k": 2.0, "session_ids": map_now(db, map_id).session_ids}
    assert job.map_generation == builds[-1].generation
    assert job.log_tail.count("coalesced: session") == 3
    assert "auto_tune_trials=5 dropped: it tunes a map of one session" in job.log_tail
    info = map_now(db, map_id)
    assert not info.up_to_date
    assert info.pending_job_id == job.id

    # tuning a map of several sessions: refused, nothing queued or changed
    with db.transaction() as db_session, pytest.raises(InvalidInput) as refused:
        request_build(
            db_session, map_id, {"auto_tune_trials": 1000}, max_attempts=3, change="rebuild"
        )
    assert refused.value.field == "auto_tune_trials"
    assert get_job(db, job.id) == job

    # adds while it runs: it is asked to stop, one follow-up takes them all
    lease = queue.claim(db, worker_id="test", lease_s=30)
    assert lease is not None
    assert lease.job_id == job.id
    with db.transaction() as db_session:
        follow_up = add_session_to_map(db_session, map_id, walks[3], max_attempts=3)
        again = add_session_to_map(db_session, map_id, walks[4], max_attempts=3)
    assert (follow_up.coalesced, follow_up.superseded) == (False, (job.id,))
    assert (again.job_id, again.coalesced) == (follow_up.job_id, True)
    assert get_job(db, job.id).cancel_requested

    run_all(db)
    assert get_job(db, follow_up.job_id).state == JobState.SUCCEEDED
    info = map_now(db, map_id)
    assert info.current is not None
    assert info.current.number == 2  # one build of all six walks, not five
    assert info.current.session_ids == info.session_ids
    assert len(info.session_ids) == 6
    assert info.up_to_date
    assert info.current.params["huber_k"] == 2.0


def test_a_superseded_build_with_no_build_of_the_new_generation_queues_one(db: Database) -> None:
    """A generation bumped by something that queued no build (none of the API's changes does
    that, but a restore or a hand-made change might): the overtaken build queues the build."""
    map_id = built_map(db)

    def bump_then_store(ctx: JobContext) -> None:
        with db.transaction() as db_session:
            maps.lock_maps(db_session, [map_id])
            maps.bump_generation(db_session, map_id)
        store(ctx)

    with db.transaction() as db_session:
        rebuild = request_build(db_session, map_id, {"huber_k": 2.0}, max_attempts=3, change="x")
    stages = (*BUILD_MAP_STAGES[:-1], Stage(name="store", weight=0.05, run=bump_then_store))
    assert worker(db, stages).run_once()
    assert get_job(db, rebuild.job_id).state == JobState.CANCELED
    queued = [j for j in build_jobs(db, map_id) if j.state == JobState.QUEUED]
    assert len(queued) == 1
    assert queued[0].params == {"huber_k": 2.0}
    assert queued[0].map_generation == rebuild.generation + 1
    run_all(db)
    info = map_now(db, map_id)
    assert info.current is not None
    assert info.current.number == 2
    assert info.up_to_date
    assert info.current.params["huber_k"] == 2.0


# --------------------------------------------------------------------------- each check alone
# store() checks the map's generation twice: before the bulk data is written (a read, then the
# same under the map's lock) and in the transaction that stores the version (under the lock).
# The tests below each reach one check with the other passing, so that either check taken out
# fails a test (the mutation audit of issue 40: only both taken out was caught).


def counting_bulk_writes(monkeypatch: pytest.MonkeyPatch, before: Any = None) -> list[int]:
    """Count store()'s bulk writes; ``before()`` runs just before each (the real one follows)."""
    writes: list[int] = []
    real = maps.write_version_bulk

    def write_version_bulk(*args: Any, **kwargs: Any) -> Any:
        writes.append(1)
        if before is not None:
            before()
        return real(*args, **kwargs)

    monkeypatch.setattr(maps, "write_version_bulk", write_version_bulk)
    return writes


def bump(db: Database, map_id: int) -> int:
    """What a change of the map does to it (add a session, a rebuild): a new generation."""
    with db.transaction() as db_session:
        maps.lock_maps(db_session, [map_id])
        return maps.bump_generation(db_session, map_id)


def test_a_change_during_the_bulk_write_is_caught_by_the_locked_check(
    db: Database, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The generation moves after the first check passed, while the bulk data is written: only
    the check in the storing transaction can see it. Without it the build stored version 2 of
    an older generation."""
    map_id = built_map(db)
    with db.transaction() as db_session:
        rebuild = request_build(db_session, map_id, {"huber_k": 2.0}, max_attempts=3, change="x")
    generations: list[int] = []
    writes = counting_bulk_writes(monkeypatch, before=lambda: generations.append(bump(db, map_id)))

    assert worker(db).run_once()

    assert writes == [1]  # the first check passed: the bulk data was written
    assert generations == [rebuild.generation + 1]
    overtaken = get_job(db, rebuild.job_id)
    assert overtaken.state == JobState.CANCELED
    info = map_now(db, map_id)
    assert info.current is not None
    assert (info.current.number, info.version_count) == (1, 1)
    assert overtaken.error == (
        f"map {map_id} changed while it was built (generation {rebuild.generation} → "
        f"{rebuild.generation + 1}); its version is not stored: job "
        f"{build_jobs(db, map_id)[-1].id} (queued now) builds the map's current sessions"
    )


def test_a_change_before_the_store_writes_no_bulk_data(
    db: Database, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The generation moved before store() began: the first check supersedes the build before
    any bulk data is written (the second check would also refuse the version, so what tells the
    first is at work is that nothing was written)."""
    map_id = built_map(db)
    with db.transaction() as db_session:
        rebuild = request_build(db_session, map_id, {"huber_k": 2.0}, max_attempts=3, change="x")
    writes = counting_bulk_writes(monkeypatch)

    def bump_then_store(ctx: JobContext) -> None:
        bump(db, map_id)
        store(ctx)

    stages = (*BUILD_MAP_STAGES[:-1], Stage(name="store", weight=0.05, run=bump_then_store))
    assert worker(db, stages).run_once()

    assert writes == []
    overtaken = get_job(db, rebuild.job_id)
    assert overtaken.state == JobState.CANCELED
    assert overtaken.error is not None
    assert overtaken.error.startswith(
        f"map {map_id} changed while it was built (generation {rebuild.generation} → "
        f"{rebuild.generation + 1}); its version is not stored"
    )
    assert map_now(db, map_id).version_count == 1


def test_an_unchanged_map_stores_its_version(db: Database, monkeypatch: pytest.MonkeyPatch) -> None:
    """The other side of both checks: a build of the current generation writes its bulk data
    once and stores its version (a check that refused every build fails here)."""
    map_id = built_map(db)
    with db.transaction() as db_session:
        rebuild = request_build(db_session, map_id, {"huber_k": 2.0}, max_attempts=3, change="x")
    writes = counting_bulk_writes(monkeypatch)

    assert worker(db).run_once()

    assert writes == [1]
    assert get_job(db, rebuild.job_id).state == JobState.SUCCEEDED
    info = map_now(db, map_id)
    assert info.current is not None
    assert (info.current.number, info.version_count) == (2, 2)
    assert info.current.params["huber_k"] == 2.0
