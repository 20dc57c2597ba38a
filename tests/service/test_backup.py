"""Backups (``app/storage/backup.py``): a deployment exported to an archive and imported into
SQLite and PostgreSQL. A restore keeps every id and every upload byte for byte, a merge gives new
ids, and a broken archive or a refused import writes nothing.

One source deployment (SQLite) is built once per module from real sessions: versions with plots
and path graphs, keys, an idempotency key, a failed build, a build running at export, a deleted
map, a finished sweep and a running one. Most tests import its archive.
"""

from __future__ import annotations

import gzip
import hashlib
import json
import math
import shutil
import struct
import zipfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import func, select
from sqlalchemy import update as sqlalchemy_update

from app.domain.evaluation.sweep_plan import SweepPlan
from app.domain.evaluation.tuning import Axis, SearchSpace, Trial
from app.domain.formats.derived_documents import APP_MAP_EXPORT
from app.domain.navigation.corridor_edits import edit_from_json
from app.domain.navigation.path_graph import path_graph_from_json
from app.domain.upload.session import decode_json_bytes, parse_session
from app.storage import backup, corridor_edits, images, keys, maps, queue, sessions, sweeps
from app.storage.backup import ArchiveIncompatible, ArchiveInvalid, ImportRefused
from app.storage.db import Database
from app.storage.migrate import head_revision
from app.storage.navigation import path_graph_document
from app.storage.orm import Base, Job, JobState, MapRow, Role
from tests.service.api_support import ADMIN, run_next_job, running_api
from tests.service.helpers import session_bytes

#: The source's sessions by id: (data file, uploader) — "device" is its device key.
SOURCE_SESSIONS = {
    1: ("onetag", "device"),  # idempotency key "walk-1"; map 1 has versions 1 and 2
    2: ("pgt_tester3", keys.ENVIRONMENT_ADMIN),  # its map has the sweeps
    3: ("occam_room", "device"),
    4: ("singletag3times", "device"),  # its build failed
    5: ("singletag3times", keys.ENVIRONMENT_ADMIN),  # its build is running at export
    6: ("onetag", keys.ENVIRONMENT_ADMIN),  # its map (the newest) is deleted
}
BUILT_MAPS = (1, 2, 3)
#: Columns left out of comparisons: ids of rows nobody refers to.
UNCOMPARED = {"map_tag": {"id"}, "sweep_trial": {"id"}}


@dataclass(frozen=True)
class Source:
    """The source deployment and its archives."""

    url: str
    archive: Path
    archive_with_keys: Path
    device_key_id: int
    device_key: str
    device_prefix: str
    #: (map id, version number or None) → the app-map the source served
    app_maps: dict[tuple[int, int | None], bytes]


# --------------------------------------------------------------------------- helpers


def upload(
    db: Database, name: str, *, uploaded_by: str, idempotency_key: str | None = None
) -> sessions.UploadResult:
    raw = session_bytes(name)
    with db.transaction() as tx:
        return sessions.create_session(
            tx,
            parsed=parse_session(decode_json_bytes(raw)),
            upload=sessions.StoredUpload.of(raw),
            uploaded_by=uploaded_by,
            idempotency_key=idempotency_key,
        )


def add_sweep(db: Database, map_id: int, *, trials_done: int) -> int:
    """A 3-point grid sweep of ``map_id`` with ``trials_done`` of its trials stored."""
    space = SearchSpace((Axis("odom_linear_var_m2_per_s", 1e-6, 1e-2, 3),))
    with db.transaction() as tx:
        sweep_id = sweeps.create_sweep(
            tx,
            map_id=map_id,
            session_id=maps.get_map(tx, map_id).session_id,
            plan=SweepPlan(method="grid", space=space),
            base_params={},
            ground_truth=None,
            max_attempts=3,
        )
        job_id = tx.scalars(select(Job.id).where(Job.sweep_id == sweep_id)).one()
        trials = [
            Trial(values=values, shift=0.1 * k, gt_metric=float("nan"),
                  tag_rmse_m=float("nan"), iterations=5, duration_s=0.01)
            for k, values in enumerate(space.grid()[:trials_done])
        ]  # fmt: skip
        sweeps.store_trials(
            tx, sweep_id, first_number=0, trials=trials, job_id=job_id, max_attempts=3
        )
    return sweep_id


SOURCE_PICTURE = b"\xff\xd8\xff\xe0" + bytes(range(200)) + b"\xff\xd9"


def build_source(db: Database) -> tuple[int, str, str]:
    """Fill ``db`` as :data:`SOURCE_SESSIONS` says; returns the device key's id, secret, prefix."""
    with db.transaction() as tx:
        device, secret = keys.create_key(tx, name="lab iPhone", role=Role.DEVICE)
        keys.create_key(tx, name="spare", role=Role.ADMIN)
    subject = {"device": f"key:{device.id}"}
    for session_id in (1, 2, 3):
        name, uploader = SOURCE_SESSIONS[session_id]
        key = "walk-1" if session_id == 1 else None
        upload(db, name, uploaded_by=subject.get(uploader, uploader), idempotency_key=key)
    with db.transaction() as tx:  # the app's picture of session 1's map
        images.put_session_image(tx, session_id=1, jpeg=SOURCE_PICTURE)
    run_next_job(db, plot=True, path_graph=True)
    run_next_job(db, path_graph=True)
    run_next_job(db, path_graph=True)
    with db.transaction() as tx:  # a rebuild with other parameters: version 2 of map 1
        queue.enqueue(
            tx, kind="build_map", map_id=1, session_id=1, params={"max_reprojection_px": 6.0}
        )
    run_next_job(db, path_graph=True)
    for session_id in (4, 5, 6):
        name, uploader = SOURCE_SESSIONS[session_id]
        upload(db, name, uploaded_by=subject.get(uploader, uploader))
    failed = queue.claim(db, worker_id="test-worker", lease_s=60)
    assert failed is not None
    queue.fail(db, failed, error="refused", permanent=True, backoff_s=0, log_tail="")
    running = queue.claim(db, worker_id="test-worker", lease_s=600)
    assert running is not None
    assert running.map_id == 5
    with db.transaction() as tx:
        maps.delete_map(tx, 6)
    add_corridor_edits(db, 3)
    add_sweep(db, 2, trials_done=3)
    add_sweep(db, 2, trials_done=1)
    return device.id, secret, device.prefix


def add_corridor_edits(db: Database, map_id: int) -> None:
    """Two points of interest added by an operator at a node of the map, one deleted again:
    the map's edit revision is 3, one edit is left (which the app-map shows)."""
    with db.transaction() as tx:
        version = maps.get_map(tx, map_id).current
        assert version is not None
        document = path_graph_document(tx, version.id)
        assert document is not None
        at = path_graph_from_json(document).graph.nodes[0]["position_m"]
        added = []
        for name in ("Desk", "Door"):
            corridor_edits.lock_edits(tx, map_id)
            edit = edit_from_json({"op": "add_poi", "name": name, "at": list(at)})
            added.append(
                corridor_edits.add_edit(
                    tx, map_id, edit, created_by=keys.ENVIRONMENT_ADMIN, created_by_name=None
                )
            )
        corridor_edits.lock_edits(tx, map_id)
        corridor_edits.delete_edit(tx, map_id, added[1].id)


def app_maps_of(url: str) -> dict[tuple[int, int | None], bytes]:
    """The app-maps the API serves for the built maps (current version, and map 1's first)."""
    with running_api(url) as api:
        return {
            (map_id, number): app_map(api.client, map_id, number)
            for map_id, number in [(m, None) for m in BUILT_MAPS] + [(1, 1)]
        }


def app_map(client: TestClient, map_id: int, number: int | None) -> bytes:
    query = "" if number is None else f"?version={number}"
    response = client.get(f"/v1/maps/{map_id}/app-map{query}", headers=ADMIN)
    assert response.status_code == 200, response.text
    return response.content


def dump(db: Database) -> dict[str, list[dict[str, Any]]]:
    """Every exported table's rows in key order, bytes as their SHA-256."""
    tables: dict[str, list[dict[str, Any]]] = {}
    with db.read() as tx:
        for spec in backup.TABLES:
            query = select(spec.table).order_by(spec.table.c[spec.key])
            if spec.only is not None:
                query = query.where(spec.only())
            tables[spec.name] = [
                {
                    name: hashlib.sha256(value).hexdigest() if isinstance(value, bytes) else value
                    for name, value in row.items()
                    if name not in UNCOMPARED.get(spec.name, set())
                }
                for row in tx.execute(query).mappings()
            ]
    return tables


def row_counts(db: Database) -> dict[str, int]:
    """Rows in every table of the schema."""
    with db.read() as tx:
        return {
            table.name: tx.scalar(select(func.count()).select_from(table)) or 0
            for table in Base.metadata.sorted_tables
        }


def raw_uploads(db: Database) -> dict[int, tuple[bytes, bytes]]:
    """session id → (the upload as sent, the stored gzip)."""
    with db.read() as tx:
        ids = [info.id for info in sessions.list_sessions(tx, limit=100)[0]]
        return {
            i: (sessions.raw_upload(tx, i), sessions.raw_upload_gzip(tx, i)) for i in sorted(ids)
        }


def next_upload_map_id(db: Database) -> int:
    map_id: int = upload(db, "onetag", uploaded_by=keys.ENVIRONMENT_ADMIN).map_id
    return map_id


@pytest.fixture(scope="module")
def source(sqlite_template: Path, tmp_path_factory: pytest.TempPathFactory) -> Source:
    folder = tmp_path_factory.mktemp("backup-source")
    shutil.copyfile(sqlite_template, folder / "source.sqlite3")
    url = f"sqlite:///{folder / 'source.sqlite3'}"
    db = Database(url)
    key_id, secret, prefix = build_source(db)
    archive, with_keys = folder / "source.zip", folder / "source-keys.zip"
    backup.export_archive(db, archive)
    backup.export_archive(db, with_keys, include_key_hashes=True)
    db.dispose()
    return Source(
        url=url,
        archive=archive,
        archive_with_keys=with_keys,
        device_key_id=key_id,
        device_key=secret,
        device_prefix=prefix,
        app_maps=app_maps_of(url),
    )


@pytest.fixture
def source_db(source: Source) -> Iterator[Database]:
    """The source, to read (never to change: other tests share it)."""
    database = Database(source.url)
    yield database
    database.dispose()


@pytest.fixture
def sqlite_copy(sqlite_template: Path, tmp_path: Path) -> Callable[[str], str]:
    """A fresh migrated SQLite database per call: its URL."""

    def make(name: str) -> str:
        path = tmp_path / f"{name}.sqlite3"
        shutil.copyfile(sqlite_template, path)
        return f"sqlite:///{path}"

    return make


# --------------------------------------------------------------------------- round trip


def test_round_trip_sqlite_postgresql_sqlite_keeps_everything(
    source: Source, source_db: Database, postgres_url: str, sqlite_copy: Callable[[str], str],
    tmp_path: Path,
) -> None:  # fmt: skip
    middle, last = Database(postgres_url), Database(sqlite_copy("last"))
    try:
        report = backup.import_archive(middle, source.archive_with_keys, include_keys=True)
        assert not report.merged
        assert report.map_ids == {m: m for m in (1, 2, 3, 4, 5)}
        assert report.queued_job_ids == [6]  # map 5's build, running at export
        again = tmp_path / "from-postgresql.zip"
        manifest = backup.export_archive(middle, again, include_key_hashes=True)
        assert manifest.source_backend == "postgresql"
        backup.import_archive(last, again, include_keys=True)

        first, second, third = dump(source_db), dump(middle), dump(last)
        assert second == third  # a restored deployment exports and restores losslessly
        # What the export changes on purpose: the running build is queued again, the running
        # sweep is canceled, and trials no longer name their (not exported) jobs.
        requeued = next(job for job in second["job"] if job["id"] == 6)
        assert (requeued["state"], requeued["attempts"], requeued["lease_owner"]) == (
            JobState.QUEUED.value, 0, None,
        )  # fmt: skip
        assert requeued["log_tail"].endswith("running at export: queued again\n")
        canceled = next(sweep for sweep in second["sweep"] if sweep["id"] == 2)
        assert canceled["state"] == "canceled"
        assert "not finished when the deployment was exported" in canceled["error"]
        first["job"] = [requeued if job["id"] == 6 else job for job in first["job"]]
        first["sweep"] = [canceled if sweep["id"] == 2 else sweep for sweep in first["sweep"]]
        for trial in first["sweep_trial"]:
            trial["job_id"] = None
        # and the import makes what a worker derives from each version (the source's versions,
        # stored without a worker, have none)
        derived = ("app_map_sha256", "app_map_export", "overview_sha256")
        assert all(version["app_map_export"] == APP_MAP_EXPORT for version in second["map_version"])
        assert all(version["overview_sha256"] for version in second["map_version"])
        first["map_version"] = [
            {**version, **{name: made[name] for name in derived}}
            for version, made in zip(first["map_version"], second["map_version"], strict=True)
        ]
        assert first == second

        originals = raw_uploads(source_db)
        for database in (middle, last):
            restored = raw_uploads(database)
            assert restored == originals  # the stored gzip and the JSON, byte for byte
            for session_id, (name, _) in SOURCE_SESSIONS.items():
                assert restored[session_id][0] == session_bytes(name)
        uploads = {n: m for n, m in manifest.members.items() if n.startswith("uploads/")}
        original = backup.read_manifest(source.archive_with_keys).members
        assert uploads == {n: m for n, m in original.items() if n.startswith("uploads/")}

        assert "images/1.jpg" in manifest.members
        for database in (middle, last):
            with database.read() as tx:
                picture = images.map_image(tx, 1)
            assert picture is not None
            assert picture.jpeg == SOURCE_PICTURE

        for database in (middle, last):  # the corridor edits and the map's edit revision
            with database.read() as tx:
                revision, edits = corridor_edits.list_edits(tx, 3)
            assert revision == 3
            assert [(e.edit.op, e.edit.name) for e in edits] == [("add_poi", "Desk")]
        assert b'"id":"Desk"' in source.app_maps[(3, None)]
        assert app_maps_of(postgres_url) == source.app_maps
        assert app_maps_of(last.url.render_as_string(hide_password=False)) == source.app_maps
    finally:
        middle.dispose()
        last.dispose()


def test_a_restore_with_keys_lets_the_phone_go_on(source: Source, database_url: str) -> None:
    """The device key authenticates as before, sees its sessions, and an upload retried with
    its idempotency key replays the first one (its session, map and build job)."""
    db = Database(database_url)
    backup.import_archive(db, source.archive_with_keys, include_keys=True)
    with db.read() as tx:
        principal = keys.authenticate(tx, source.device_key)
        assert principal is not None
        assert principal.subject == f"key:{source.device_key_id}"
        mine, _ = sessions.list_sessions(tx, uploaded_by=principal.subject)
    assert sorted(info.id for info in mine) == [1, 3, 4]
    replay = upload(db, "onetag", uploaded_by=principal.subject, idempotency_key="walk-1")
    assert (replay.replayed, replay.session_id, replay.map_id, replay.job_id) == (True, 1, 1, 1)
    db.dispose()


# --------------------------------------------------------------------------- restore


def test_a_restore_keeps_ids_and_never_gives_out_a_deleted_one(
    source: Source, database_url: str
) -> None:
    db = Database(database_url)
    backup.import_archive(db, source.archive)
    with db.read() as tx:
        assert [info.id for info in maps.list_maps(tx)[0]] == [5, 4, 3, 2, 1]
        assert [v.number for v in maps.list_versions(tx, 1)] == [1, 2]
        assert maps.get_version(tx, 1, 1).job_id == 1
        assert sweeps.get_sweep(tx, 1).map_id == 2
    assert next_upload_map_id(db) == 7  # the source's map 6 was deleted: 6 is never used again
    db.dispose()


def test_unfinished_work_goes_on_and_finished_work_stays_finished(
    source: Source, database_url: str
) -> None:
    db = Database(database_url)
    backup.import_archive(db, source.archive)
    with db.read() as tx:
        jobs = {job.id: job for job in queue.list_jobs(tx, limit=100)[0]}
        failed = maps.get_map(tx, 4)
        finished, canceled = sweeps.get_sweep(tx, 1), sweeps.get_sweep(tx, 2)
        trials = sweeps.list_trials(tx, 1)
    assert {i: (j.kind, j.state) for i, j in jobs.items()} == {
        1: ("build_map", JobState.SUCCEEDED),
        2: ("build_map", JobState.SUCCEEDED),
        3: ("build_map", JobState.SUCCEEDED),
        4: ("build_map", JobState.SUCCEEDED),
        5: ("build_map", JobState.FAILED),
        6: ("build_map", JobState.QUEUED),
        7: ("build_map", JobState.CANCELED),
    }  # the sweeps' jobs are not in the archive; map 6's is kept, canceled, with no map
    assert jobs[7].map_deleted
    assert jobs[5].error == "refused"
    assert failed.current is None
    assert (finished.state, finished.trials_done, len(trials)) == ("succeeded", 3, 3)
    assert (canceled.state, canceled.trials_done) == ("canceled", 1)

    assert run_next_job(db) == 6  # a worker of the new deployment builds map 5
    with db.read() as tx:
        current = maps.get_map(tx, 5).current
    assert current is not None
    assert current.job_id == 6
    db.dispose()


def test_without_keys_no_key_is_imported_and_uploaders_are_named_by_prefix(
    source: Source, database_url: str
) -> None:
    db = Database(database_url)
    report = backup.import_archive(db, source.archive)
    assert report.counts["api_key"] == 0
    with db.transaction() as tx:
        new_key, _ = keys.create_key(tx, name="new phone", role=Role.DEVICE)
    with db.read() as tx:
        uploaders = {info.id: info.uploaded_by for info in sessions.list_sessions(tx)[0]}
        theirs, _ = sessions.list_sessions(tx, uploaded_by=f"key:{new_key.id}")
    imported = f"imported:im_{source.device_prefix}"
    assert uploaders == {
        i: imported if who == "device" else who for i, (_, who) in SOURCE_SESSIONS.items()
    }
    assert new_key.id == 3  # above the source's key ids too
    assert theirs == []
    db.dispose()


def test_a_restore_into_a_database_with_data_is_refused(source: Source, database_url: str) -> None:
    db = Database(database_url)
    upload(db, "onetag", uploaded_by=keys.ENVIRONMENT_ADMIN)
    before = dump(db)
    with pytest.raises(
        ImportRefused, match=r"not empty \(1 session rows, 1 map rows, 1 job rows\)"
    ):
        backup.import_archive(db, source.archive)
    assert dump(db) == before
    db.dispose()


def test_keys_asked_of_an_archive_without_them_are_refused(
    source: Source, database_url: str
) -> None:
    db = Database(database_url)
    with pytest.raises(ImportRefused, match="no API key hashes"):
        backup.import_archive(db, source.archive, include_keys=True)
    assert set(row_counts(db).values()) == {0}
    db.dispose()


def test_an_empty_deployment_round_trips(database_url: str, tmp_path: Path) -> None:
    db = Database(database_url)
    manifest = backup.export_archive(db, tmp_path / "empty.zip")
    assert set(manifest.counts.values()) == {0}
    assert manifest.schema_revision == head_revision()
    report = backup.import_archive(db, tmp_path / "empty.zip")  # an empty database may restore
    assert set(report.counts.values()) == {0}
    db.dispose()


# --------------------------------------------------------------------------- merge


def test_a_merge_gives_new_ids_and_keeps_the_uploads(
    source: Source, source_db: Database, database_url: str
) -> None:
    db = Database(database_url)
    with db.transaction() as tx:
        local_key, _ = keys.create_key(tx, name="local", role=Role.ADMIN)
    own = upload(db, "pgt_tester3", uploaded_by=f"key:{local_key.id}")

    report = backup.import_archive(db, source.archive_with_keys, include_keys=True, merge=True)

    assert report.merged
    assert report.map_ids == {1: 2, 2: 3, 3: 4, 4: 5, 5: 6}
    assert report.session_ids == {1: 2, 2: 3, 3: 4, 4: 5, 5: 6, 6: 7}
    originals = raw_uploads(source_db)
    merged = raw_uploads(db)
    assert {report.session_ids[i]: u for i, u in originals.items()} == {
        i: u for i, u in merged.items() if i != own.session_id
    }
    with db.read() as tx:
        for old, new in report.map_ids.items():
            assert maps.get_map(tx, new).session_id == report.session_ids[old]
        versions = maps.list_versions(tx, report.map_ids[1])
        assert [v.number for v in versions] == [1, 2]
        with source_db.read() as source_tx:
            expected = maps.tag_poses(source_tx, maps.get_version(source_tx, 1, 2).id)
        assert maps.tag_poses(tx, versions[1].id) == expected
        principal = keys.authenticate(tx, source.device_key)
        assert principal is not None
        mine, _ = sessions.list_sessions(tx, uploaded_by=principal.subject)
    assert principal.subject != f"key:{local_key.id}"
    assert sorted(info.id for info in mine) == [report.session_ids[i] for i in (1, 3, 4)]

    before = dump(db)
    with pytest.raises(ImportRefused, match=r"'walk-1'.*imported before"):
        backup.import_archive(db, source.archive_with_keys, include_keys=True, merge=True)
    assert dump(db) == before
    db.dispose()


# --------------------------------------------------------------------------- broken archives


def rewrite(
    archive: Path,
    out: Path,
    *,
    member: Callable[[str, bytes], bytes | None] = lambda _name, data: data,
    manifest: Callable[[dict[str, Any]], None] = lambda _document: None,
    refresh_checksums: bool = True,
    extra: dict[str, bytes] | None = None,
) -> Path:
    """A copy of ``archive`` with members changed (or dropped: None) and the manifest changed;
    the manifest's sizes and checksums follow the members when ``refresh_checksums``."""
    with zipfile.ZipFile(archive) as source:
        document = json.loads(source.read(backup.MANIFEST))
        changed = {
            name: member(name, source.read(name))
            for name in source.namelist()
            if name != backup.MANIFEST
        }
    contents = {name: data for name, data in changed.items() if data is not None}
    contents.update(extra or {})
    if refresh_checksums:
        document["members"] = {
            name: {"size_bytes": len(data), "sha256": hashlib.sha256(data).hexdigest()}
            for name, data in contents.items()
        }
    manifest(document)
    with zipfile.ZipFile(out, "w") as target:
        for name, data in contents.items():
            target.writestr(name, data)
        target.writestr(backup.MANIFEST, json.dumps(document))
    return out


def jsonl_edit(
    table: str, change: Callable[[dict[str, Any]], None]
) -> Callable[[str, bytes], bytes]:
    """A member edit changing every row of ``tables/<table>.jsonl``."""

    def edit(name: str, data: bytes) -> bytes:
        if name != f"tables/{table}.jsonl":
            return data
        rows = [json.loads(line) for line in data.splitlines()]
        for row in rows:
            change(row)
        return b"".join(json.dumps(row).encode() + b"\n" for row in rows)

    return edit


def flipped_byte_inside(archive: Path, out: Path, member: str) -> Path:
    """``archive`` with one byte of ``member``'s stored data changed (its CRC no longer fits)."""
    data = bytearray(archive.read_bytes())
    with zipfile.ZipFile(archive) as source:
        info = source.getinfo(member)
    header_bytes = 30 + len(info.filename.encode()) + len(info.extra)
    data[info.header_offset + header_bytes + info.compress_size // 2] ^= 0xFF
    out.write_bytes(bytes(data))
    return out


def other_upload(name: str, data: bytes) -> bytes:
    return gzip.compress(session_bytes("pgt_tester3")) if name == "uploads/1.json.gz" else data


def set_in(document: dict[str, Any], **values: Any) -> None:
    document.update(values)


BROKEN: dict[str, tuple[Callable[[Path, Path], Path], type[BaseException], str]] = {
    "missing file": (lambda _a, out: out / "nothing.zip", FileNotFoundError, "nothing.zip"),
    "not a zip file": (
        lambda _a, out: _write(out / "x.zip", session_bytes("onetag")),
        ArchiveInvalid,
        "not a zip file",
    ),
    "truncated": (
        lambda a, out: _write(out / "x.zip", a.read_bytes()[: a.stat().st_size * 2 // 3]),
        ArchiveInvalid,
        "truncated",
    ),
    "no manifest": (
        lambda _a, out: _zip_of(out / "x.zip", {"hello.txt": b"hi"}),
        ArchiveInvalid,
        "no manifest.json",
    ),
    "not our format": (
        lambda a, out: rewrite(a, out / "x.zip", manifest=lambda d: set_in(d, format="tarball")),
        ArchiveInvalid,
        "not an invisible-map backup",
    ),
    "corrupt member (CRC)": (
        lambda a, out: flipped_byte_inside(a, out / "x.zip", "uploads/3.json.gz"),
        ArchiveInvalid,
        "uploads/3.json.gz is corrupt",
    ),
    "checksum mismatch": (
        lambda a, out: rewrite(a, out / "x.zip", member=other_upload, refresh_checksums=False),
        ArchiveInvalid,
        "uploads/1.json.gz does not match the manifest (checksum mismatch",
    ),
    "upload of another session": (
        lambda a, out: rewrite(a, out / "x.zip", member=other_upload),
        ArchiveInvalid,
        "the upload does not match its session",
    ),
    "member missing": (
        lambda a, out: rewrite(
            a,
            out / "x.zip",
            member=lambda n, d: None if n.endswith("plot.png") else d,
            refresh_checksums=False,
        ),
        ArchiveInvalid,
        "versions/1/plot.png is in the manifest but not in the archive",
    ),
    "member not in the manifest": (
        lambda a, out: rewrite(
            a, out / "x.zip", extra={"uploads/99.json.gz": b"x"}, refresh_checksums=False
        ),
        ArchiveInvalid,
        "uploads/99.json.gz is not in the manifest",
    ),
    "row of the wrong type": (
        lambda a, out: rewrite(
            a, out / "x.zip", member=jsonl_edit("session", lambda r: set_in(r, pose_count="many"))
        ),
        ArchiveInvalid,
        "tables/session.jsonl line 1 (id 1): pose_count: expected integer, got 'many'",
    ),
    "row count differs": (
        lambda a, out: rewrite(
            a, out / "x.zip", manifest=lambda d: d["counts"].update(map_tag=999)
        ),
        ArchiveInvalid,
        "tables/map_tag.jsonl has",
    ),
    "a reference in the last table": (
        lambda a, out: rewrite(
            a, out / "x.zip", member=jsonl_edit("sweep_trial", lambda r: set_in(r, sweep_id=99))
        ),
        ArchiveInvalid,
        "sweep_id: sweep 99 is not in the archive",
    ),
    "newer format version": (
        lambda a, out: rewrite(a, out / "x.zip", manifest=lambda d: set_in(d, format_version=2)),
        ArchiveIncompatible,
        "format version 2 is newer",
    ),
    "older schema": (
        lambda a, out: rewrite(
            a, out / "x.zip", manifest=lambda d: set_in(d, schema_revision="255ed7c85f58")
        ),
        ArchiveIncompatible,
        "migrate the source deployment",
    ),
    "newer schema": (
        lambda a, out: rewrite(
            a, out / "x.zip", manifest=lambda d: set_in(d, schema_revision="0123456789ab")
        ),
        ArchiveIncompatible,
        "newer invisible-map",
    ),
}


#: Archives no database holds, each refused naming its row (issue 28, finding 4: each was a
#: traceback of the driver, or was stored, and `import --check` called the archive valid).
VALUE_CASES: dict[str, tuple[Callable[[Path, Path], Path], type[BaseException], str]] = {
    "an id beyond 64 bits": (
        lambda a, out: rewrite(
            a, out / "x.zip", member=jsonl_edit("map", lambda r: set_in(r, id=2**63))
        ),
        ArchiveInvalid,
        "tables/map.jsonl line 1 (id 9223372036854775808): id: 9223372036854775808 is beyond the "
        "column's 32-bit integers",
    ),
    "an id beyond 32 bits (PostgreSQL's integer)": (
        lambda a, out: rewrite(
            a, out / "x.zip", member=jsonl_edit("sweep_trial", lambda r: set_in(r, number=2**31))
        ),
        ArchiveInvalid,
        "number: 2147483648 is beyond the column's 32-bit integers",
    ),
    "a lone surrogate in a name": (
        lambda a, out: rewrite(
            a, out / "x.zip", member=jsonl_edit("map", lambda r: set_in(r, display_name="\ud800"))
        ),
        ArchiveInvalid,
        "tables/map.jsonl line 1 (id 1): display_name holds a lone surrogate (U+D800)",
    ),
    "a NUL in a JSON column": (
        lambda a, out: rewrite(
            a,
            out / "x.zip",
            member=jsonl_edit("map_version", lambda r: set_in(r, warnings=["ok", "a\x00b"])),
        ),
        ArchiveInvalid,
        "tables/map_version.jsonl line 1 (id 1): warnings[1] holds a NUL character",
    ),
    "a name longer than its column": (
        lambda a, out: rewrite(
            a, out / "x.zip", member=jsonl_edit("map", lambda r: set_in(r, display_name="x" * 201))
        ),
        ArchiveInvalid,
        "display_name: 201 characters, more than the column's 200",
    ),
    "a datetime beyond the year 9999 in UTC": (
        lambda a, out: rewrite(
            a,
            out / "x.zip",
            member=jsonl_edit("map", lambda r: set_in(r, created_at="9999-12-31T23:59:59-23:59")),
        ),
        ArchiveInvalid,
        "created_at: '9999-12-31T23:59:59-23:59' is not a datetime with a UTC offset",
    ),
    "an upload larger than the server takes": (
        lambda a, out: rewrite(
            a,
            out / "x.zip",
            member=jsonl_edit("session", lambda r: set_in(r, raw_size_bytes=2**31 - 1)),
        ),
        ArchiveInvalid,
        "raw_size_bytes 2147483647 is not from 0 to the 268435456 bytes an upload may inflate to",
    ),
    "a row nested too deeply": (
        lambda a, out: rewrite(
            a,
            out / "x.zip",
            member=lambda n, d: b"[" * 200_000 + b"]" * 200_000 if n.endswith("/map.jsonl") else d,
        ),
        ArchiveInvalid,
        "tables/map.jsonl line 1: not JSON",
    ),
    "a high-water mark beyond 32 bits": (
        lambda a, out: rewrite(
            a, out / "x.zip", manifest=lambda d: d["id_high_water"].update(map=2**63)
        ),
        ArchiveInvalid,
        "id_high_water.map is 9223372036854775808, not an integer from 0 to 2147483647",
    ),
}


def twice(
    table: str, change: Callable[[dict[str, Any]], None] = lambda _row: None
) -> Callable[[Path, Path], Path]:
    """An archive whose ``tables/<table>.jsonl`` has its first row again at its end (with
    ``change`` made to the copy), the manifest's count of the table one larger."""

    def again(name: str, data: bytes) -> bytes:
        if name != f"tables/{table}.jsonl":
            return data
        copy = json.loads(data.splitlines()[0])
        change(copy)
        return data + json.dumps(copy).encode() + b"\n"

    return lambda a, out: rewrite(
        a,
        out / "x.zip",
        member=again,
        manifest=lambda d: d["counts"].update({table: d["counts"][table] + 1}),
    )


#: Archives that a database refuses, or stores altered, for a constraint of its own or a number
#: JSON has not, that `import --check` called valid (issue 40, finding 3).
CONSTRAINT_CASES: dict[str, tuple[Callable[[Path, Path], Path], type[BaseException], str]] = {
    "a corridor edit's id twice": (
        twice("corridor_edit"),
        ArchiveInvalid,
        "tables/corridor_edit.jsonl line 2 (id 1): id 1: an earlier row of "
        "tables/corridor_edit.jsonl has it too",
    ),
    "a tag twice in one map version": (
        twice("map_tag"),
        ArchiveInvalid,
        "map_tag.jsonl line 15: map_version_id 1, tag_id 306: an earlier row of "
        "tables/map_tag.jsonl has them too",
    ),
    "a map's version number twice": (
        twice("map_version", lambda r: r.update(id=99, job_id=None)),
        ArchiveInvalid,
        "(id 99): map_id 1, number 1: an earlier row of tables/map_version.jsonl has them too",
    ),
    "NaN in a JSON column": (
        lambda a, out: rewrite(
            a,
            out / "x.zip",
            member=jsonl_edit("map_version", lambda r: r["params"].update(huber_k=math.nan)),
        ),
        ArchiveInvalid,
        "tables/map_version.jsonl line 1: holds NaN, which is no JSON number",
    ),
    "Infinity in a float column": (
        lambda a, out: rewrite(
            a,
            out / "x.zip",
            member=jsonl_edit("sweep_trial", lambda r: set_in(r, shift=-math.inf)),
        ),
        ArchiveInvalid,
        "tables/sweep_trial.jsonl line 1: holds -Infinity, which is no JSON number",
    ),
    "1e999 in a float column": (
        lambda a, out: rewrite(
            a,
            out / "x.zip",
            member=lambda n, d: (
                d.replace(b'"duration_s":', b'"duration_s":1e999,"x":', 1)
                if n == "tables/sweep_trial.jsonl"
                else d
            ),
        ),
        ArchiveInvalid,
        "tables/sweep_trial.jsonl line 1: holds 1e999, a number beyond a float's range",
    ),
    "a job state no job has": (
        lambda a, out: rewrite(
            a, out / "x.zip", member=jsonl_edit("job", lambda r: set_in(r, state="paused"))
        ),
        ArchiveInvalid,
        "tables/job.jsonl line 1 (id 1): state 'paused' is not one of ['canceled', 'failed'",
    ),
    "a job's progress beyond 1": (
        lambda a, out: rewrite(
            a, out / "x.zip", member=jsonl_edit("job", lambda r: set_in(r, progress=1.5))
        ),
        ArchiveInvalid,
        "tables/job.jsonl line 1 (id 1): progress 1.5 is not from 0.0 to 1.0",
    ),
    "an API key's role no key has": (
        lambda a, out: rewrite(
            a, out / "x.zip", member=jsonl_edit("api_key", lambda r: set_in(r, role="root"))
        ),
        ArchiveInvalid,
        "tables/api_key.jsonl line 1 (id 1): role 'root' is not one of ['admin', 'device']",
    ),
}


def _write(path: Path, data: bytes) -> Path:
    path.write_bytes(data)
    return path


def _zip_of(path: Path, members: dict[str, bytes]) -> Path:
    with zipfile.ZipFile(path, "w") as archive:
        for name, data in members.items():
            archive.writestr(name, data)
    return path


@pytest.mark.parametrize("case", BROKEN)
def test_a_broken_archive_is_refused_and_nothing_is_written(
    case: str, source: Source, database_url: str, tmp_path: Path
) -> None:
    make, error, message = BROKEN[case]
    broken = make(source.archive, tmp_path)
    db = Database(database_url)
    with pytest.raises(error) as raised:
        backup.import_archive(db, broken)
    assert message in str(raised.value)
    assert set(row_counts(db).values()) == {0}
    assert next_upload_map_id(db) == 1  # no id sequence moved either
    db.dispose()


#: What only an import into a database refuses (`import --check` compares the schema revision
#: with this code's, in the command).
NEEDS_A_DATABASE = {"older schema", "newer schema"}


def test_every_value_no_database_holds_is_refused_naming_its_row(
    source: Source, database_url: str, tmp_path: Path
) -> None:
    """One database for all the cases (each import is refused whole, so it stays empty)."""
    db = Database(database_url)
    for case, (make, error, message) in VALUE_CASES.items():
        with pytest.raises(error) as raised:
            backup.import_archive(db, make(source.archive, tmp_path))
        assert message in str(raised.value), case
    assert set(row_counts(db).values()) == {0}
    assert next_upload_map_id(db) == 1
    db.dispose()


@pytest.mark.parametrize("case", CONSTRAINT_CASES)
def test_the_check_and_the_import_refuse_what_a_database_would_alike(
    case: str, source: Source, database_url: str, tmp_path: Path
) -> None:
    """Issue 40, finding 3: a corridor edit's id twice or NaN in a JSON column passed
    `import --check`, and the import then failed on the database's constraint (or, on SQLite,
    stored NaN as it came). One validator now refuses each, with and without a database."""
    make, error, message = CONSTRAINT_CASES[case]
    hostile = make(source.archive_with_keys, tmp_path)
    with pytest.raises(error) as checked:
        backup.check_archive(hostile)
    assert message in str(checked.value)
    db = Database(database_url)
    with pytest.raises(error) as imported:
        backup.import_archive(db, hostile, include_keys=True)
    assert str(imported.value) == str(checked.value)
    assert set(row_counts(db).values()) == {0}
    assert next_upload_map_id(db) == 1
    db.dispose()


def test_every_check_constraint_of_an_exported_table_is_checked_without_a_database() -> None:
    from sqlalchemy import CheckConstraint

    from app.storage.backup.restore import ALLOWED_RANGES, ALLOWED_VALUES

    constrained = {
        (spec.name, column.name)
        for spec in backup.TABLES
        for constraint in spec.table.constraints
        if isinstance(constraint, CheckConstraint)
        for column in spec.table.columns
        if column.name in str(constraint.sqltext)
    }
    assert constrained == set(ALLOWED_VALUES) | set(ALLOWED_RANGES)


CHECKED = {**BROKEN, **VALUE_CASES}


@pytest.mark.parametrize("case", sorted(set(CHECKED) - NEEDS_A_DATABASE))
def test_the_check_refuses_what_an_import_refuses(
    case: str, source: Source, tmp_path: Path
) -> None:
    make, error, message = CHECKED[case]
    with pytest.raises(error) as raised:
        backup.check_archive(make(source.archive, tmp_path))
    assert message in str(raised.value)


def test_the_check_passes_a_good_archive(source: Source) -> None:
    for archive in (source.archive, source.archive_with_keys):
        assert backup.check_archive(archive) == backup.read_manifest(archive)


def with_member(
    archive: Path, out: Path, name: str, inflated: Callable[[], Iterator[bytes]]
) -> Path:
    """``archive`` with member ``name`` replaced by the bytes ``inflated`` yields, deflated in the
    zip (so a member of many MiB takes a few KiB), the manifest's size and SHA-256 of it set."""
    with zipfile.ZipFile(archive) as source:
        document = json.loads(source.read(backup.MANIFEST))
        members = {n: source.read(n) for n in source.namelist() if n != backup.MANIFEST}
    digest, size = hashlib.sha256(), 0
    with zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as target:
        for other, data in members.items():
            if other != name:
                target.writestr(other, data)
        with target.open(name, "w") as member:
            for chunk in inflated():
                member.write(chunk)
                digest.update(chunk)
                size += len(chunk)
        document["members"][name] = {"size_bytes": size, "sha256": digest.hexdigest()}
        target.writestr(backup.MANIFEST, json.dumps(document))
    return out


def zeros(mib: int) -> Callable[[], Iterator[bytes]]:
    return lambda: (bytes(2**20) for _ in range(mib))


def opened_members(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """The names of the members the archive reader opens from now on."""
    opened: list[str] = []
    real_open = backup.archive.ArchiveReader._open

    def recording_open(reader: backup.archive.ArchiveReader, name: str) -> Any:
        opened.append(name)
        return real_open(reader, name)

    monkeypatch.setattr(backup.archive.ArchiveReader, "_open", recording_open)
    return opened


def test_a_member_inflating_beyond_the_limit_is_refused_before_it_is_read(
    source: Source, database_url: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Issue 28, finding 4: a member inflating to 1.5 GB was read whole (3.2 GB, 32 s) before it
    was refused. Here 8 MiB against a limit of 1 MiB, as `import` and `import --check` run."""
    hostile = with_member(source.archive, tmp_path / "x.zip", "uploads/1.json.gz", zeros(8))
    opened = opened_members(monkeypatch)
    db = Database(database_url)
    for check in (
        lambda: backup.check_archive(hostile, max_member_bytes=2**20),
        lambda: backup.import_archive(db, hostile, max_member_bytes=2**20),
    ):
        with pytest.raises(ArchiveInvalid) as raised:
            check()
        assert "uploads/1.json.gz inflates to 8388608 bytes, more than the 1048576" in str(
            raised.value
        )
        assert "uploads/1.json.gz" not in opened
    assert set(row_counts(db).values()) == {0}
    db.dispose()


def inflated_bytes(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """The sizes of the pieces of uploads the import inflates from now on (one per read)."""
    from app.storage.backup import restore

    pieces: list[int] = []

    class CountedGzipFile(gzip.GzipFile):
        def read(self, size: int | None = -1) -> bytes:
            data = super().read(size)
            pieces.append(len(data))
            return data

    monkeypatch.setattr(restore, "gzip", SimpleNamespace(GzipFile=CountedGzipFile))
    return pieces


def test_an_upload_is_inflated_no_further_than_its_session_says(
    source: Source, database_url: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A gzip bomb as an upload, its session claiming the size it inflates to (within the limit,
    and the checksums right): refused for that size, before a byte of it is inflated; with a
    small claim, refused after inflating one byte more than the claim, and no further (issue 40,
    finding 5: only the message was checked, and an upload inflated whole passed)."""
    bomb = gzip.compress(bytes(4 * 2**20))

    def claims(size: int) -> Callable[[str, bytes], bytes]:
        def edit(name: str, data: bytes) -> bytes:
            if name == "uploads/1.json.gz":
                return bomb
            return jsonl_edit(
                "session", lambda r: r.update(raw_size_bytes=size) if r["id"] == 1 else None
            )(name, data)

        return edit

    db = Database(database_url)
    big = rewrite(source.archive, tmp_path / "big.zip", member=claims(4 * 2**20))
    small = rewrite(source.archive, tmp_path / "small.zip", member=claims(1000))
    for check in (
        lambda archive: backup.check_archive(archive, max_member_bytes=2**20),
        lambda archive: backup.import_archive(db, archive, max_member_bytes=2**20),
    ):
        pieces = inflated_bytes(monkeypatch)
        with pytest.raises(ArchiveInvalid) as raised:
            check(big)
        assert "uploads/1.json.gz" not in str(raised.value)
        assert "(id 1): raw_size_bytes 4194304 is not from 0 to the 1048576" in str(raised.value)
        assert pieces == []  # not a byte inflated
        with pytest.raises(ArchiveInvalid) as raised:
            check(small)
        assert str(raised.value).endswith(
            "tables/session_upload.jsonl line 1 (session_id 1): the upload does not match its "
            "session (sha256 or size differs)"
        )
        assert sum(pieces) == 1001  # the claim and one byte more
    assert set(row_counts(db).values()) == {0}
    assert next_upload_map_id(db) == 1
    db.dispose()


def test_a_member_inflating_beyond_what_its_zip_says_fails_its_crc(
    source: Source, tmp_path: Path
) -> None:
    """The zip's headers claim 1 KiB of an upload that inflates to 8 MiB: the reader stops at
    the size claimed, and the CRC fails."""
    hostile = with_member(source.archive, tmp_path / "x.zip", "uploads/1.json.gz", zeros(8))
    data = bytearray(hostile.read_bytes())
    with zipfile.ZipFile(hostile) as archive:
        info = archive.getinfo("uploads/1.json.gz")
    # the uncompressed size: at 22 in the local header, at 24 in the central directory's entry
    struct.pack_into("<I", data, info.header_offset + 22, 1024)
    central = _central_entries(bytes(data), "uploads/1.json.gz")
    assert len(central) == 1
    struct.pack_into("<I", data, central[0] + 24, 1024)
    lying = tmp_path / "lying.zip"
    lying.write_bytes(bytes(data))
    with zipfile.ZipFile(lying) as archive:
        assert archive.getinfo("uploads/1.json.gz").file_size == 1024
    with pytest.raises(ArchiveInvalid, match=r"uploads/1\.json\.gz is corrupt"):
        backup.check_archive(lying, max_member_bytes=2**20)


def _central_entries(data: bytes, name: str) -> list[int]:
    """Offsets of the central directory's entries for ``name``."""
    offsets, start = [], 0
    while (found := data.find(b"PK\x01\x02", start)) >= 0:
        name_length = struct.unpack_from("<H", data, found + 28)[0]
        if data[found + 46 : found + 46 + name_length] == name.encode():
            offsets.append(found)
        start = found + 4
    return offsets


def test_text_no_database_holds_in_an_old_sqlite_database_is_named_on_its_way_out(
    sqlite_copy: Callable[[str], str], database_url: str, tmp_path: Path
) -> None:
    """Issue 28, finding 1: a SQLite database that stored a NUL in a display name before the
    API refused it could not be moved to PostgreSQL, and the error named no row."""
    old = Database(sqlite_copy("old"))
    upload(old, "onetag", uploaded_by=keys.ENVIRONMENT_ADMIN)
    with old.transaction() as tx:
        tx.execute(update_display_name(1, "Lab\x003"))
    backup.export_archive(old, tmp_path / "old.zip")
    old.dispose()
    db = Database(database_url)
    for check in (
        lambda: backup.check_archive(tmp_path / "old.zip"),
        lambda: backup.import_archive(db, tmp_path / "old.zip"),
    ):
        with pytest.raises(ArchiveInvalid) as raised:
            check()
        assert "tables/map.jsonl line 1 (id 1): display_name holds a NUL character" in str(
            raised.value
        )
        assert "export again" in str(raised.value)
    assert set(row_counts(db).values()) == {0}
    db.dispose()


def update_display_name(map_id: int, name: str) -> Any:
    return sqlalchemy_update(MapRow).where(MapRow.id == map_id).values(display_name=name)


def test_a_schema_mismatch_names_the_side_to_migrate() -> None:
    backup.check_schema_revision(head_revision() or "", head_revision())
    with pytest.raises(ArchiveIncompatible, match="migrate this database first"):
        backup.check_schema_revision(head_revision() or "", "255ed7c85f58")


def test_a_failed_export_leaves_no_file(source_db: Database, tmp_path: Path) -> None:
    def interrupt(done: int, _total: int) -> None:
        if done == 3:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        backup.export_archive(source_db, tmp_path / "out.zip", on_progress=interrupt)
    assert list(tmp_path.iterdir()) == []


def test_an_archive_from_before_maps_of_several_sessions_still_imports(
    source: Source, database_url: str, tmp_path: Path
) -> None:
    """No ``map_session`` table, no ``session_ids`` / ``shift_metric_version`` columns: each map
    holds its one session, versions and sweeps record none, and the sweeps were scored with the
    first shift metric (version 1)."""

    def drop_new_columns(name: str, data: bytes) -> bytes | None:
        if name == "tables/map_session.jsonl":
            return None
        new_columns = {
            "tables/map_version.jsonl": ("session_ids",),
            "tables/sweep.jsonl": ("session_ids", "shift_metric_version"),
        }.get(name)
        if new_columns is None:
            return data
        rows = [json.loads(line) for line in data.splitlines()]
        for row in rows:
            for column in new_columns:
                row.pop(column)
        return b"".join(json.dumps(row).encode() + b"\n" for row in rows)

    def drop_count(document: dict[str, Any]) -> None:
        document["counts"].pop("map_session")

    old = rewrite(
        source.archive, tmp_path / "old.zip", member=drop_new_columns, manifest=drop_count
    )
    db = Database(database_url)
    backup.import_archive(db, old)
    with db.read() as tx:
        for info in maps.list_maps(tx)[0]:
            assert info.session_ids == [info.session_id]
        assert maps.get_version(tx, 1, 1).session_ids == []
        sweep = sweeps.get_sweep(tx, 1)
        assert (sweep.shift_metric_version, sweep.session_ids) == (1, [])
    db.dispose()


def test_an_archive_from_before_corridor_edits_still_imports(
    source: Source, database_url: str, tmp_path: Path
) -> None:
    """No ``corridor_edit`` table, no ``corridor_edits_revision`` column: the maps have no
    edits, at revision 0."""

    def drop_edits(name: str, data: bytes) -> bytes | None:
        if name == "tables/corridor_edit.jsonl":
            return None
        if name != "tables/map.jsonl":
            return data
        rows = [json.loads(line) for line in data.splitlines()]
        for row in rows:
            row.pop("corridor_edits_revision")
        return b"".join(json.dumps(row).encode() + b"\n" for row in rows)

    def drop_count(document: dict[str, Any]) -> None:
        document["counts"].pop("corridor_edit")
        document["id_high_water"].pop("corridor_edit")

    old = rewrite(source.archive, tmp_path / "old.zip", member=drop_edits, manifest=drop_count)
    db = Database(database_url)
    backup.import_archive(db, old)
    with db.read() as tx:
        assert corridor_edits.list_edits(tx, 3) == (0, [])
        assert all(info.corridor_edits_revision == 0 for info in maps.list_maps(tx)[0])
    db.dispose()
