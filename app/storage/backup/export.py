"""Export: one consistent snapshot of a database written as a backup archive."""

from __future__ import annotations

import hashlib
import io
import json
import os
import tempfile
import zipfile
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from datetime import datetime
from pathlib import Path
from typing import IO, Any

from alembic.runtime.migration import MigrationContext
from sqlalchemy import (
    Column,
    ColumnElement,
    func,
    or_,
    select,
    text,
)
from sqlalchemy.orm import Session

from app.storage import maps, queue, sweeps
from app.storage.backup.archive import (
    CHUNK_BYTES,
    FORMAT_VERSION,
    ID_SEQUENCE_TABLES,
    MANIFEST,
    PAGE_ROWS,
    PROGRESS_TABLES,
    SPOOL_MAX_BYTES,
    TABLES,
    TABLES_BY_NAME,
    BackupError,
    Manifest,
    Member,
    Progress,
    TableSpec,
)
from app.storage.db import Database
from app.storage.orm import (
    JobState,
    utc_now,
)

# --------------------------------------------------------------------------- export


def export_archive(
    database: Database,
    path: Path,
    *,
    include_key_hashes: bool = False,
    on_progress: Progress | None = None,
) -> Manifest:
    """Write every session (with its upload's bytes), map, version, build job and sweep of
    ``database`` to the archive ``path``, from one snapshot of the database.

    The file appears only when it is complete (written beside it, then renamed); an existing file
    is replaced. Rows are read a page at a time and blobs one row at a time."""
    path = Path(path)
    handle, partial_name = tempfile.mkstemp(
        prefix=f".{path.name}.", suffix=".partial", dir=path.parent
    )
    os.close(handle)
    partial = Path(partial_name)
    try:
        with _snapshot(database) as session, _ArchiveWriter(partial) as writer:
            manifest = _export(session, writer, include_key_hashes, on_progress)
        os.replace(partial, path)
    finally:
        partial.unlink(missing_ok=True)
    return manifest


@contextmanager
def _snapshot(database: Database) -> Iterator[Session]:
    """A read-only transaction that sees one state of the database throughout (SQLite's WAL
    read transactions do; PostgreSQL needs REPEATABLE READ)."""
    with database.read() as db_session:
        if database.backend == "postgresql":
            db_session.connection(execution_options={"isolation_level": "REPEATABLE READ"})
        yield db_session


def _export(
    db_session: Session,
    writer: _ArchiveWriter,
    include_key_hashes: bool,
    on_progress: Progress | None,
) -> Manifest:
    now = utc_now()
    revision = MigrationContext.configure(db_session.connection()).get_current_revision()
    if revision is None:
        raise BackupError("the database has no schema (run `invisible-map migrate`)")
    total = sum(_row_count(db_session, TABLES_BY_NAME[name]) for name in PROGRESS_TABLES)
    done = 0
    counts: dict[str, int] = {}
    for spec in TABLES:
        with writer.table(spec.member) as write_line:
            for row in _exported_rows(db_session, spec, include_key_hashes, now):
                write_line(_encode_row(spec, row))
                for column, pattern in spec.blobs.items():
                    if row[column]:
                        _copy_blob(db_session, spec, row, column, writer, pattern.format(**row))
                counts[spec.name] = counts.get(spec.name, 0) + 1
                if spec.name in PROGRESS_TABLES:
                    done += 1
                    if on_progress is not None:
                        on_progress(done, total)
        counts.setdefault(spec.name, 0)
    manifest = Manifest(
        format_version=FORMAT_VERSION,
        schema_revision=revision,
        created_at=now,
        source_backend=db_session.get_bind().dialect.name,
        key_hashes=include_key_hashes,
        counts=counts,
        id_high_water=_id_high_water(db_session),
        members=dict(writer.members),
    )
    writer.write_manifest(manifest)
    return manifest


def _row_count(db_session: Session, spec: TableSpec) -> int:
    query = select(func.count()).select_from(spec.table)
    if spec.only is not None:
        query = query.where(spec.only())
    return int(db_session.scalar(query) or 0)


def _exported_rows(
    db_session: Session, spec: TableSpec, include_key_hashes: bool, now: datetime
) -> Iterator[dict[str, Any]]:
    """The table's rows as exported, in key order, a page at a time. A binary column's value is
    whether the row has one (its bytes are read by :func:`_copy_blob`)."""
    key = spec.table.c[spec.key]
    selected: list[ColumnElement[Any]] = [
        _has_bytes(spec, column).label(column.name) if column.name in spec.blobs else column
        for column in spec.columns()
    ]
    if not spec.export_key:
        selected.append(key)
    last: Any = None
    while True:
        query = select(*selected).order_by(key).limit(PAGE_ROWS)
        if spec.only is not None:
            query = query.where(spec.only())
        if last is not None:
            query = query.where(key > last)
        page = [dict(row) for row in db_session.execute(query).mappings()]
        if not page:
            return
        last = page[-1][spec.key]
        for row in page:
            if not spec.export_key:
                del row[spec.key]
            yield _as_exported(db_session, spec.name, row, include_key_hashes, now)


def _has_bytes(spec: TableSpec, column: Column[Any]) -> ColumnElement[bool]:
    """Whether a row has bytes for a binary column: in the column, or in the blob it names."""
    has: ColumnElement[bool] = column.is_not(None)
    if column.name in spec.blob_refs:
        has = or_(has, spec.table.c[spec.blob_refs[column.name]].is_not(None))
    return has


def _as_exported(
    db_session: Session, table: str, row: dict[str, Any], include_key_hashes: bool, now: datetime
) -> dict[str, Any]:
    """A row as the archive holds it: no key hashes unless asked for, no state of the queue."""
    if table == "api_key" and not include_key_hashes:
        row["secret_sha256"] = None
    elif table == "job":
        _requeued(row, now)
    elif table == "sweep":
        info = sweeps.get_sweep(db_session, row["id"])  # its state as the API shows it
        row["state"], row["error"] = info.state, info.error
        if row["state"] == "running":
            row["state"], row["finished_at"] = "canceled", row["finished_at"] or now
            row["error"] = "not finished when the deployment was exported (its jobs are not)"
    elif table == "sweep_trial":
        row["job_id"] = None  # sweep_trials jobs are not exported
    return row


def _requeued(job: dict[str, Any], now: datetime) -> None:
    """A build job running at export as a fresh queued one, as a retry makes it (or canceled,
    if a cancel was asked of it). A queued job stays as it is."""
    job["sweep_id"] = None
    if job["state"] != JobState.RUNNING.value:
        return
    if job["cancel_requested"]:
        job.update(state=JobState.CANCELED.value, finished_at=now)
        message = "running at export with a cancel requested: canceled"
    else:
        job.update(
            state=JobState.QUEUED.value,
            attempts=0,
            progress=0.0,
            stage=None,
            started_at=None,
            run_after=now,
        )
        message = "running at export: queued again"
    job["log_tail"] = queue.append_log(job["log_tail"], message, now=now)
    job.update(lease_owner=None, lease_expires_at=None, updated_at=now)


def _copy_blob(
    db_session: Session,
    spec: TableSpec,
    row: Mapping[str, Any],
    column: str,
    writer: _ArchiveWriter,
    member: str,
) -> None:
    key = spec.table.c[spec.key]
    if column in spec.blob_refs:
        inline, sha256 = db_session.execute(
            select(spec.table.c[column], spec.table.c[spec.blob_refs[column]]).where(
                key == row[spec.key]
            )
        ).one()
        data = maps.version_bytes(db_session, inline, sha256)
    else:
        data = db_session.scalar(select(spec.table.c[column]).where(key == row[spec.key]))
    if data is not None:
        writer.write_blob(member, bytes(data))


def _encode_row(spec: TableSpec, row: Mapping[str, Any]) -> dict[str, Any]:
    encoded: dict[str, Any] = {}
    for column in spec.columns():
        value = row[column.name]
        if column.name in spec.blobs:
            value = spec.blobs[column.name].format(**row) if value else None
        elif isinstance(value, datetime):
            value = value.isoformat()
        encoded[column.name] = value
    return encoded


def _id_high_water(db_session: Session) -> dict[str, int]:
    """Per table, the largest id ever given out: the id sequence, or the largest id left."""
    marks: dict[str, int] = {}
    for table in ID_SEQUENCE_TABLES:
        largest = db_session.scalar(text(f'SELECT COALESCE(MAX(id), 0) FROM "{table}"'))
        marks[table] = max(int(largest or 0), sequence_value(db_session, table))
    return marks


def sequence_value(db_session: Session, table: str) -> int:
    """The last id the table's sequence gave out (0 if none)."""
    if db_session.get_bind().dialect.name == "sqlite":
        value = db_session.scalar(
            text("SELECT seq FROM sqlite_sequence WHERE name = :table"), {"table": table}
        )
        return int(value or 0)
    sequence = db_session.scalar(text("SELECT pg_get_serial_sequence(:t, 'id')"), {"t": table})
    if sequence is None:
        return 0
    last_value, is_called = db_session.execute(
        text(f"SELECT last_value, is_called FROM {sequence}")
    ).one()
    return int(last_value) if is_called else 0


class _ArchiveWriter:
    """Writes the zip: blobs straight in (stored: they are compressed already), each table's
    lines spooled and added when the table is done (deflated), the manifest last."""

    def __init__(self, path: Path) -> None:
        self._zip = zipfile.ZipFile(path, "w", allowZip64=True)
        self._date_time = utc_now().timetuple()[:6]
        self.members: dict[str, Member] = {}

    def __enter__(self) -> _ArchiveWriter:
        return self

    def __exit__(self, *exc: Any) -> None:
        self._zip.close()

    def write_blob(self, name: str, data: bytes) -> None:
        self.add_stream(name, io.BytesIO(data), zipfile.ZIP_STORED)

    @contextmanager
    def table(self, name: str) -> Iterator[Callable[[dict[str, Any]], None]]:
        """``write(row)`` for one table's JSON lines, spooled until the block ends (so that the
        table's blobs can be written meanwhile), then added as the member ``name``."""
        with tempfile.SpooledTemporaryFile(max_size=SPOOL_MAX_BYTES) as spool:

            def write(row: dict[str, Any]) -> None:
                line = json.dumps(row, ensure_ascii=False, separators=(",", ":"), sort_keys=True)
                spool.write(line.encode() + b"\n")

            yield write
            spool.seek(0)
            self.add_stream(name, spool, zipfile.ZIP_DEFLATED)

    def write_manifest(self, manifest: Manifest) -> None:
        encoded = json.dumps(manifest.to_json(), indent=2, sort_keys=True).encode()
        info = zipfile.ZipInfo(MANIFEST, date_time=self._date_time)
        info.compress_type = zipfile.ZIP_DEFLATED
        self._zip.writestr(info, encoded)

    def add_stream(self, name: str, source: IO[bytes], compress_type: int) -> None:
        """Copy ``source`` into the member ``name``, noting its size and SHA-256."""
        info = zipfile.ZipInfo(name, date_time=self._date_time)
        info.compress_type = compress_type
        digest, size = hashlib.sha256(), 0
        with self._zip.open(info, "w", force_zip64=True) as out:
            while chunk := source.read(CHUNK_BYTES):
                digest.update(chunk)
                size += len(chunk)
                out.write(chunk)
        self.members[name] = Member(size_bytes=size, sha256=digest.hexdigest())
