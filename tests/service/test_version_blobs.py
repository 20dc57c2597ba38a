"""A version's bulk data as content-addressed blobs written outside its fenced transaction
(issue 19, finding 4), on SQLite and PostgreSQL: chunks, reuse, half-written blobs, orphans
collected, and a worker stalled while writing them stops no other writer (on SQLite the store
stage used to hold the only write lock for its whole 2.5 s)."""

from __future__ import annotations

import gzip
import json
import threading
from datetime import timedelta
from typing import Any

import pytest
from api_support import ADMIN, ONETAG, running_api
from sqlalchemy import select, update

from app.storage import blobs, maps, queue
from app.storage.blobs import BlobMissing
from app.storage.db import Database
from app.storage.navigation import path_graph_document
from app.storage.orm import Blob, BlobChunk, Job, JobState, MapVersion, utc_now
from app.storage.queue import LeaseLost
from tests.service.helpers import get_job, insert_session, session_bytes, version_count
from tests.service.test_worker import worker_with

pytestmark = pytest.mark.db

LATER = timedelta(seconds=blobs.ORPHAN_GRACE_S + 60)


def chunk_rows(db: Database, sha256: str) -> list[bytes]:
    with db.read() as tx:
        query = select(BlobChunk.data).where(BlobChunk.sha256 == sha256).order_by(BlobChunk.number)
        return [bytes(data) for data in tx.scalars(query)]


def blob_shas(db: Database) -> set[str]:
    with db.read() as tx:
        return set(tx.scalars(select(Blob.sha256)))


def version_blob_shas(db: Database) -> set[str]:
    with db.read() as tx:
        rows = tx.execute(
            select(
                MapVersion.map_json_sha256,
                MapVersion.plot_png_sha256,
                MapVersion.path_graph_sha256,
                MapVersion.app_map_sha256,
                MapVersion.overview_sha256,
            )
        ).all()
    return {sha for row in rows for sha in row if sha is not None}


def test_a_blob_is_written_in_chunks_read_back_and_reused(
    db: Database, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(blobs, "CHUNK_BYTES", 10)
    data = bytes(range(35))
    sha256 = blobs.put_blob(db, data)
    assert sha256 == blobs.blob_sha256(data)
    assert chunk_rows(db, sha256) == [data[0:10], data[10:20], data[20:30], data[30:35]]
    with db.read() as tx:
        assert blobs.read_blob(tx, sha256) == data
        first = tx.get(Blob, sha256)
        assert first is not None
        assert first.complete
        touched_at = first.touched_at

    assert blobs.put_blob(db, data) == sha256  # the same content: reused, only touched
    with db.read() as tx:
        again = tx.get(Blob, sha256)
        assert again is not None
        assert again.touched_at >= touched_at
    assert len(chunk_rows(db, sha256)) == 4
    assert blobs.put_blob(db, b"") == blobs.blob_sha256(b"")  # empty: complete without chunks
    with db.read() as tx:
        assert blobs.read_blob(tx, blobs.blob_sha256(b"")) == b""
        with pytest.raises(BlobMissing):
            blobs.read_blob(tx, "0" * 64)


def test_a_half_written_blob_is_never_read_and_the_next_writer_completes_it(
    db: Database, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(blobs, "CHUNK_BYTES", 10)
    data = b"x" * 25
    write_chunk = blobs.write_blob_chunk

    def dies_at_chunk_1(db: Database, sha256: str, number: int, chunk: bytes, **kw: Any) -> None:
        if number == 1:
            raise RuntimeError("the worker died here")
        write_chunk(db, sha256, number, chunk, **kw)

    monkeypatch.setattr(blobs, "write_blob_chunk", dies_at_chunk_1)
    with pytest.raises(RuntimeError):
        blobs.put_blob(db, data)
    sha256 = blobs.blob_sha256(data)
    assert len(chunk_rows(db, sha256)) == 1
    with db.read() as tx:
        with pytest.raises(BlobMissing):
            blobs.read_blob(tx, sha256)
        with pytest.raises(BlobMissing):
            blobs.require_blobs(tx, [sha256])

    monkeypatch.setattr(blobs, "write_blob_chunk", write_chunk)
    monkeypatch.setattr(blobs, "CHUNK_BYTES", 7)  # another size: the old pieces are dropped
    assert blobs.put_blob(db, data) == sha256
    assert chunk_rows(db, sha256) == [data[0:7], data[7:14], data[14:21], data[21:25]]
    with db.read() as tx:
        assert blobs.read_blob(tx, sha256) == data
        blobs.require_blobs(tx, [sha256])


def test_a_build_stores_its_bulk_data_as_blobs_and_the_reads_are_unchanged(db: Database) -> None:
    inserted = insert_session(db, session_bytes("occam_room"))
    worker_with(db).run_once()
    assert get_job(db, inserted.job_id).state == JobState.SUCCEEDED
    with db.read() as tx:
        row = tx.scalars(select(MapVersion)).one()
        assert (row.map_json_gzip, row.plot_png, row.path_graph_gzip) == (None, None, None)
        assert row.map_json_sha256
        assert row.plot_png_sha256
        assert row.path_graph_sha256
        document = maps.map_document(tx, inserted.map_id)
        plot = maps.plot_png(tx, inserted.map_id)
        stored = blobs.read_blob(tx, row.map_json_sha256)
        graph = path_graph_document(tx, row.id)
    assert document == json.loads(gzip.decompress(stored))
    assert plot is not None
    assert plot.startswith(b"\x89PNG")
    assert graph is not None
    assert graph["nodes"]
    assert version_blob_shas(db) == blob_shas(db)


def test_orphans_are_collected_after_the_grace_period_and_referenced_blobs_kept(
    db: Database,
) -> None:
    inserted = insert_session(db, session_bytes("onetag"))
    worker_with(db).run_once()
    referenced = version_blob_shas(db)
    orphan = blobs.put_blob(db, b"a failed attempt's plot")

    assert blobs.collect_orphan_blobs(db) == 0  # too young: a worker may be about to use it
    assert blobs.collect_orphan_blobs(db, now=utc_now() + LATER) == 1
    assert blob_shas(db) == referenced
    assert chunk_rows(db, orphan) == []
    with db.read() as tx:
        assert maps.map_document(tx, inserted.map_id)["tags"]

    with db.transaction() as tx:  # a deleted map's blobs are orphans too
        maps.delete_map(tx, inserted.map_id)
    assert blobs.collect_orphan_blobs(db, now=utc_now() + LATER) == len(referenced)
    assert blob_shas(db) == set()


def test_an_attempt_that_loses_its_lease_while_storing_leaves_only_collectable_orphans(
    db: Database, monkeypatch: pytest.MonkeyPatch
) -> None:
    inserted = insert_session(db, session_bytes("onetag"))

    def lease_lost(_tx: Any, lease: queue.Lease, **_kw: Any) -> None:
        raise LeaseLost(lease.job_id)

    monkeypatch.setattr(queue, "finish", lease_lost)
    worker_with(db).run_once()
    assert version_count(db, map_id=inserted.map_id) == 0  # the fenced write rolled back
    written = blob_shas(db)
    assert len(written) == 5  # document, plot, path graph, app-map, overview: nobody refers to them
    assert blobs.collect_orphan_blobs(db, now=utc_now() + LATER) == 5
    assert blob_shas(db) == set()


def test_a_worker_stalled_while_writing_its_bulk_data_stops_no_other_writer(
    database_url: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The worker stops between two chunk transactions of its map document (as a SIGSTOP or a
    page-in storm would stop it); uploads, cancels and reads of everyone else are answered at
    once, not after SQLite's 30 s busy timeout with a 503. Then it goes on and stores."""
    monkeypatch.setattr(blobs, "CHUNK_BYTES", 2048)
    stalled, go_on = threading.Event(), threading.Event()
    write_chunk = blobs.write_blob_chunk

    def stalls_after_chunk_0(
        db: Database, sha256: str, number: int, chunk: bytes, **kw: Any
    ) -> None:
        write_chunk(db, sha256, number, chunk, **kw)
        if number == 0 and not stalled.is_set():
            stalled.set()
            assert go_on.wait(60)

    monkeypatch.setattr(blobs, "write_blob_chunk", stalls_after_chunk_0)
    with running_api(database_url, db_lock_timeout_s=1.0) as api:
        building = api.uploaded(ONETAG)
        queued = api.uploaded(ONETAG, idempotency_key="another")
        worker = threading.Thread(target=worker_with(api.db, heartbeat_s=0.5).run_once)
        worker.start()
        try:
            assert stalled.wait(60), "the worker never reached its store stage"
            assert get_job(api.db, building["job_id"]).stage == "store"

            uploaded = api.upload(ONETAG, idempotency_key="during-the-stall")
            canceled = api.client.post(f"/v1/jobs/{queued['job_id']}/cancel", headers=ADMIN)
            listed = api.client.get("/v1/maps", headers=ADMIN)
            assert uploaded.status_code == 202, uploaded.text
            assert canceled.status_code == 200, canceled.text
            assert canceled.json()["state"] == "canceled"
            assert listed.status_code == 200, listed.text
            assert version_count(api.db, map_id=building["map_id"]) == 0  # not visible yet
        finally:
            go_on.set()
            worker.join(60)
        job = get_job(api.db, building["job_id"])
        assert job.state == JobState.SUCCEEDED, job.error
        answer = api.client.get(f"/v1/maps/{building['map_id']}/app-map", headers=ADMIN)
        assert answer.status_code == 200, answer.text
        assert answer.json()["tag_vertices"]


def test_the_reaper_acts_on_a_worker_stalled_in_its_store_and_fences_its_late_write(
    db: Database, monkeypatch: pytest.MonkeyPatch
) -> None:
    """On SQLite the reaper needs the write lock too: it used to wait for a worker stalled in
    its store transaction. Now it requeues the stalled worker's job at once (here: its lease
    taken as expired), the late worker's fenced write is refused when it wakes, and another
    worker builds the map; the late worker's blobs are reused or collected."""
    monkeypatch.setattr(blobs, "CHUNK_BYTES", 2048)
    stalled, go_on = threading.Event(), threading.Event()
    write_chunk = blobs.write_blob_chunk

    def stalls_once(db: Database, sha256: str, number: int, chunk: bytes, **kw: Any) -> None:
        write_chunk(db, sha256, number, chunk, **kw)
        if number == 0 and not stalled.is_set():
            stalled.set()
            assert go_on.wait(60)

    monkeypatch.setattr(blobs, "write_blob_chunk", stalls_once)
    inserted = insert_session(db, session_bytes("onetag"))
    late = threading.Thread(target=worker_with(db).run_once)
    late.start()
    try:
        assert stalled.wait(60), "the worker never reached its store stage"
        with db.transaction() as tx:  # as if it had stalled past its lease (SIGSTOP)
            tx.execute(
                update(Job)
                .where(Job.id == inserted.job_id)
                .values(lease_expires_at=utc_now() - timedelta(seconds=1))
            )
        assert queue.reap_expired(db, backoff_s=0.0) == 1
        assert get_job(db, inserted.job_id).state == JobState.QUEUED
    finally:
        go_on.set()
        late.join(60)
    assert version_count(db, map_id=inserted.map_id) == 0  # the late write was fenced off
    assert worker_with(db).run_once()
    job = get_job(db, inserted.job_id)
    assert (job.state, job.attempts) == (JobState.SUCCEEDED, 2), job.error
    late_orphans = blob_shas(db) - version_blob_shas(db)  # what content did not reuse
    assert blobs.collect_orphan_blobs(db, now=utc_now() + LATER) == len(late_orphans)
    assert blob_shas(db) == version_blob_shas(db)
