"""Backups: a deployment's sessions, maps and sweeps in one archive file, and back into a database.

    manifest = export_archive(db, Path("im-backup.zip"))                 # one consistent snapshot
    manifest = read_manifest(Path("im-backup.zip"))                      # no database needed
    report = import_archive(other_db, Path("im-backup.zip"))             # restore: ids kept
    report = import_archive(other_db, path, merge=True)                  # add: new ids
    report.map_ids                                                        # {archive id: new id}

**The archive** (``FORMAT_VERSION`` 1) is a zip file:

==================================  ========================================================
``manifest.json``                   format, format version, schema revision (Alembic),
                                    created_at, source backend, whether key hashes are in,
                                    row counts, id high-water marks, size and SHA-256 of
                                    every other member (written last, read first)
``tables/<table>.jsonl``            one JSON object per row, columns by name: ``api_key``,
                                    ``session``, ``session_upload``, ``map``,
                                    ``session_image``, ``job``, ``map_version``, ``map_tag``,
                                    ``sweep``, ``sweep_trial``
``uploads/<session id>.json.gz``    the stored upload, the database's bytes unchanged (one
                                    gzip member of the JSON exactly as the phone sent it)
``images/<session id>.jpg``         the picture the app sent with the session
``versions/<id>/map.json.gz``       a version's map document, ``plot.png`` its plot,
                                    ``path_graph.json.gz`` its path graph (as stored)
==================================  ========================================================

In the JSON rows datetimes are ISO 8601 strings with their UTC offset, and a binary column holds
the name of the member with its bytes (or null). Of the queue only ``build_map`` jobs are in it:
finished and queued ones as they are (so a version still names its job, and a phone's job URL
and idempotent replay keep working), a running one as queued again without the source's lease.
``sweep_trials`` jobs are not: their trials' ``job_id`` is null, and a sweep still running is
marked canceled. API keys are in it by name and prefix (to name the uploaders), with their
SHA-256 hashes only when asked (``include_key_hashes``; the file is created readable by its owner
only). Live localization sessions and worker rows are not in it.

**Import** runs in one transaction, and checks the whole archive (every member's size and
SHA-256, the set of members) before it writes anything. Into a database with no sessions, maps,
jobs or sweeps it *restores*: every id is kept (phones refer to maps by id), and the id
sequences are raised to the source's high-water marks so that an id deleted there is never given
out again (on PostgreSQL that is the last statement: sequences ignore rollbacks). Into a
database with data it refuses, unless ``merge=True``: then every row gets a new id (the report
maps old to new). Without keys imported, ``uploaded_by`` ``key:N`` becomes
``imported:im_<prefix>``, so that no key of the new deployment owns another's sessions.

Exceptions::

    BackupError
    ├── ArchiveInvalid       not a backup archive, truncated or corrupt, a member or row that
    │                        does not match the manifest or the schema
    ├── ArchiveIncompatible  a newer format version, or another schema revision than the database
    └── ImportRefused        restore into a database with data, merge clashes, keys asked for
                             but not in the archive
"""

from __future__ import annotations

import gzip
import hashlib
import io
import json
import os
import re
import tempfile
import zipfile
import zlib
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import IO, Any, TypeGuard

from alembic.runtime.migration import MigrationContext
from alembic.script import ScriptDirectory
from sqlalchemy import (
    JSON,
    Boolean,
    Column,
    ColumnElement,
    Float,
    Integer,
    LargeBinary,
    String,
    Table,
    func,
    insert,
    select,
    text,
)
from sqlalchemy.exc import DataError, IntegrityError
from sqlalchemy.orm import Session

from app.storage import queue, sweeps
from app.storage.db import Database
from app.storage.migrate import alembic_config
from app.storage.orm import (
    ApiKey,
    Base,
    Job,
    JobState,
    MapRow,
    MapTag,
    MapVersion,
    SessionImage,
    SessionRow,
    SessionUpload,
    Sweep,
    SweepTrial,
    UTCDateTime,
    utc_now,
)
from app.storage.sessions import BUILD_MAP

#: What ``manifest.json`` says it is.
FORMAT = "invisible-map-backup"
#: The archive layout this module writes; it reads this one and older ones.
FORMAT_VERSION = 1
MANIFEST = "manifest.json"
#: Rows read per query while exporting (keyset pages, so no cursor stays open).
PAGE_ROWS = 500
#: Rows inserted per statement for tables nobody refers to (map_tag, sweep_trial).
INSERT_BATCH_ROWS = 500
#: A table's rows stay in memory up to this size while its blobs are written, then go to a file.
SPOOL_MAX_BYTES = 8 * 2**20
#: Bytes read or written at a time when copying a member.
CHUNK_BYTES = 2**20
#: Tables whose ids are never given out twice (``NEVER_REUSE_IDS`` in orm.py).
ID_SEQUENCE_TABLES = ("api_key", "session", "map", "job", "map_version", "localization", "sweep")
#: Tables that must be empty for a restore (one that keeps the archive's ids).
RESTORE_NEEDS_EMPTY = ("session", "map", "job", "sweep")
_KEY_SUBJECT = re.compile(r"key:(\d+)")

#: ``on_progress(done, total)``: sessions and map versions copied so far, and in all.
Progress = Callable[[int, int], None]


class BackupError(Exception):
    """Base of the errors of exporting and importing archives."""


class ArchiveInvalid(BackupError):
    """Raised when a file is not a readable backup archive, or its contents do not match its
    manifest or the schema (truncated, corrupt, altered)."""


class ArchiveIncompatible(BackupError):
    """Raised when an archive is of a newer format version, or was exported at another schema
    revision than the database it would go into."""


class ImportRefused(BackupError):
    """Raised when an import would not do what its caller meant: a restore into a database that
    already has data, a merge that clashes with it, keys asked for that are not in the archive."""


# --------------------------------------------------------------------------- what is exported


@dataclass(frozen=True, slots=True, kw_only=True)
class _TableSpec:
    """How one table goes into the archive and comes back."""

    model: type[Base]
    #: the primary key; rows are read and written in its order
    key: str = "id"
    #: False: the id is not exported (nothing refers to it) and the target gives a new one
    export_key: bool = True
    #: binary column → its member's name (``str.format`` of the row)
    blobs: Mapping[str, str] = field(default_factory=dict)
    #: column → table whose ids it holds (the row must be in the archive)
    refs: Mapping[str, str] = field(default_factory=dict)
    #: column → table whose ids it holds, or null when that row is not in the archive
    soft_refs: Mapping[str, str] = field(default_factory=dict)
    #: only these rows are exported
    only: Callable[[], ColumnElement[bool]] | None = None

    @property
    def table(self) -> Table:
        table: Table = self.model.__table__  # type: ignore[assignment]
        return table

    @property
    def name(self) -> str:
        return self.table.name

    @property
    def member(self) -> str:
        return f"tables/{self.name}.jsonl"

    @property
    def allocates_ids(self) -> bool:
        """True when other rows refer to this table's ids (so a merge maps old ids to new)."""
        return self.key == "id" and self.export_key

    def columns(self) -> list[Column[Any]]:
        """The exported columns, in table order."""
        return [c for c in self.table.columns if self.export_key or c.name != self.key]


#: In dependency order: a row's references come before it.
TABLES = (
    _TableSpec(model=ApiKey),
    _TableSpec(model=SessionRow),
    _TableSpec(
        model=SessionUpload,
        key="session_id",
        blobs={"raw_gzip": "uploads/{session_id}.json.gz"},
        refs={"session_id": "session"},
    ),
    _TableSpec(model=MapRow, refs={"session_id": "session"}),
    _TableSpec(
        model=SessionImage,
        key="session_id",
        blobs={"jpeg": "images/{session_id}.jpg"},
        refs={"session_id": "session"},
    ),
    _TableSpec(
        model=Job,
        refs={"map_id": "map", "session_id": "session"},
        only=lambda: Job.kind == BUILD_MAP,
    ),
    _TableSpec(
        model=MapVersion,
        refs={"map_id": "map"},
        soft_refs={"job_id": "job"},
        blobs={
            "map_json_gzip": "versions/{id}/map.json.gz",
            "plot_png": "versions/{id}/plot.png",
            "path_graph_gzip": "versions/{id}/path_graph.json.gz",
        },
    ),
    _TableSpec(model=MapTag, export_key=False, refs={"map_version_id": "map_version"}),
    _TableSpec(
        model=Sweep,
        refs={"map_id": "map", "session_id": "session"},
        soft_refs={"applied_job_id": "job"},
    ),
    _TableSpec(model=SweepTrial, export_key=False, refs={"sweep_id": "sweep"}),
)
_BY_NAME = {spec.name: spec for spec in TABLES}
#: The tables whose rows the progress counts (the large ones: an upload, a version's blobs).
_PROGRESS_TABLES = ("session_upload", "map_version")


@dataclass(frozen=True, slots=True, kw_only=True)
class Member:
    """A member of the archive: its size and SHA-256 (of its bytes in the archive)."""

    size_bytes: int
    sha256: str


@dataclass(frozen=True, slots=True, kw_only=True)
class Manifest:
    """What ``manifest.json`` says about the archive."""

    format_version: int
    schema_revision: str
    created_at: datetime
    source_backend: str
    #: True when the API keys' hashes are in the archive (``include_key_hashes``)
    key_hashes: bool
    #: rows per table
    counts: dict[str, int]
    #: per table, the largest id the source ever gave out (deleted rows included)
    id_high_water: dict[str, int]
    members: dict[str, Member]

    def to_json(self) -> dict[str, Any]:
        return {
            "format": FORMAT,
            "format_version": self.format_version,
            "schema_revision": self.schema_revision,
            "created_at": self.created_at.isoformat(),
            "source_backend": self.source_backend,
            "key_hashes": self.key_hashes,
            "counts": self.counts,
            "id_high_water": self.id_high_water,
            "members": {
                name: {"size_bytes": m.size_bytes, "sha256": m.sha256}
                for name, m in self.members.items()
            },
        }

    @classmethod
    def from_json(cls, document: Any, where: str) -> Manifest:
        """Check and read a parsed ``manifest.json``. Raises ArchiveInvalid or, for a newer
        format version, ArchiveIncompatible."""
        if not isinstance(document, dict) or document.get("format") != FORMAT:
            raise ArchiveInvalid(f"{where}: not an invisible-map backup (manifest format)")
        version = document.get("format_version")
        if not _is_int(version) or version < 1:
            raise ArchiveInvalid(f"{where}: format_version {version!r} is not a version")
        if version > FORMAT_VERSION:
            raise ArchiveIncompatible(
                f"{where}: archive format version {version} is newer than this invisible-map "
                f"reads ({FORMAT_VERSION}); import it with a newer invisible-map"
            )
        try:
            members = {
                str(name): Member(size_bytes=int(m["size_bytes"]), sha256=str(m["sha256"]))
                for name, m in document["members"].items()
            }
            manifest = cls(
                format_version=version,
                schema_revision=str(document["schema_revision"]),
                created_at=datetime.fromisoformat(document["created_at"]),
                source_backend=str(document["source_backend"]),
                key_hashes=bool(document["key_hashes"]),
                counts={str(k): int(v) for k, v in document["counts"].items()},
                id_high_water={str(k): int(v) for k, v in document["id_high_water"].items()},
                members=members,
            )
        except (KeyError, TypeError, ValueError, AttributeError) as err:
            raise ArchiveInvalid(
                f"{where}: malformed manifest ({type(err).__name__}: {err})"
            ) from err
        for spec in TABLES:
            if spec.name not in manifest.counts or spec.member not in manifest.members:
                raise ArchiveInvalid(f"{where}: the manifest lists no table {spec.name}")
        return manifest


@dataclass(frozen=True, slots=True, kw_only=True)
class ImportReport:
    """What an import wrote."""

    #: False: a restore, every id kept; True: a merge, new ids
    merged: bool
    #: rows written per table
    counts: dict[str, int]
    #: the archive's map id → this database's (identical in a restore)
    map_ids: dict[int, int]
    #: the archive's session id → this database's
    session_ids: dict[int, int]
    #: jobs that were unfinished at export and are queued now
    queued_job_ids: list[int]


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
    with database.read() as session:
        if database.backend == "postgresql":
            session.connection(execution_options={"isolation_level": "REPEATABLE READ"})
        yield session


def _export(
    session: Session,
    writer: _ArchiveWriter,
    include_key_hashes: bool,
    on_progress: Progress | None,
) -> Manifest:
    now = utc_now()
    revision = MigrationContext.configure(session.connection()).get_current_revision()
    if revision is None:
        raise BackupError("the database has no schema (run `invisible-map migrate`)")
    total = sum(_row_count(session, _BY_NAME[name]) for name in _PROGRESS_TABLES)
    done = 0
    counts: dict[str, int] = {}
    for spec in TABLES:
        with writer.table(spec.member) as write_line:
            for row in _exported_rows(session, spec, include_key_hashes, now):
                write_line(_encode_row(spec, row))
                for column, pattern in spec.blobs.items():
                    if row[column]:
                        _copy_blob(session, spec, row, column, writer, pattern.format(**row))
                counts[spec.name] = counts.get(spec.name, 0) + 1
                if spec.name in _PROGRESS_TABLES:
                    done += 1
                    if on_progress is not None:
                        on_progress(done, total)
        counts.setdefault(spec.name, 0)
    manifest = Manifest(
        format_version=FORMAT_VERSION,
        schema_revision=revision,
        created_at=now,
        source_backend=session.get_bind().dialect.name,
        key_hashes=include_key_hashes,
        counts=counts,
        id_high_water=_id_high_water(session),
        members=dict(writer.members),
    )
    writer.write_manifest(manifest)
    return manifest


def _row_count(session: Session, spec: _TableSpec) -> int:
    query = select(func.count()).select_from(spec.table)
    if spec.only is not None:
        query = query.where(spec.only())
    return int(session.scalar(query) or 0)


def _exported_rows(
    session: Session, spec: _TableSpec, include_key_hashes: bool, now: datetime
) -> Iterator[dict[str, Any]]:
    """The table's rows as exported, in key order, a page at a time. A binary column's value is
    whether the row has one (its bytes are read by :func:`_copy_blob`)."""
    key = spec.table.c[spec.key]
    selected: list[ColumnElement[Any]] = [
        column.is_not(None).label(column.name) if column.name in spec.blobs else column
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
        page = [dict(row) for row in session.execute(query).mappings()]
        if not page:
            return
        last = page[-1][spec.key]
        for row in page:
            if not spec.export_key:
                del row[spec.key]
            yield _as_exported(session, spec.name, row, include_key_hashes, now)


def _as_exported(
    session: Session, table: str, row: dict[str, Any], include_key_hashes: bool, now: datetime
) -> dict[str, Any]:
    """A row as the archive holds it: no key hashes unless asked for, no state of the queue."""
    if table == "api_key" and not include_key_hashes:
        row["secret_sha256"] = None
    elif table == "job":
        _requeued(row, now)
    elif table == "sweep":
        info = sweeps.get_sweep(session, row["id"])  # its state as the API shows it
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
    session: Session,
    spec: _TableSpec,
    row: Mapping[str, Any],
    column: str,
    writer: _ArchiveWriter,
    member: str,
) -> None:
    key = spec.table.c[spec.key]
    data = session.scalar(select(spec.table.c[column]).where(key == row[spec.key]))
    if data is not None:
        writer.write_blob(member, bytes(data))


def _encode_row(spec: _TableSpec, row: Mapping[str, Any]) -> dict[str, Any]:
    encoded: dict[str, Any] = {}
    for column in spec.columns():
        value = row[column.name]
        if column.name in spec.blobs:
            value = spec.blobs[column.name].format(**row) if value else None
        elif isinstance(value, datetime):
            value = value.isoformat()
        encoded[column.name] = value
    return encoded


def _id_high_water(session: Session) -> dict[str, int]:
    """Per table, the largest id ever given out: the id sequence, or the largest id left."""
    marks: dict[str, int] = {}
    for table in ID_SEQUENCE_TABLES:
        largest = session.scalar(text(f'SELECT COALESCE(MAX(id), 0) FROM "{table}"'))
        marks[table] = max(int(largest or 0), _sequence_value(session, table))
    return marks


def _sequence_value(session: Session, table: str) -> int:
    """The last id the table's sequence gave out (0 if none)."""
    if session.get_bind().dialect.name == "sqlite":
        value = session.scalar(
            text("SELECT seq FROM sqlite_sequence WHERE name = :table"), {"table": table}
        )
        return int(value or 0)
    sequence = session.scalar(text("SELECT pg_get_serial_sequence(:t, 'id')"), {"t": table})
    if sequence is None:
        return 0
    last_value, is_called = session.execute(
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


# --------------------------------------------------------------------------- reading archives


def read_manifest(path: Path) -> Manifest:
    """The archive's manifest, checked for format and version (not its members: see
    :func:`verify_archive`). Raises OSError (no such file), ArchiveInvalid, ArchiveIncompatible."""
    with _ArchiveReader(Path(path)) as archive:
        return archive.manifest


def verify_archive(path: Path) -> Manifest:
    """Check every member of the archive against its manifest (names, sizes, SHA-256, zip CRC);
    returns the manifest. Raises as :func:`read_manifest` does."""
    with _ArchiveReader(Path(path)) as archive:
        archive.verify()
        return archive.manifest


class _ArchiveReader:
    """An open archive whose manifest has been read and checked."""

    def __init__(self, path: Path) -> None:
        self.path = path
        try:
            self._zip = zipfile.ZipFile(path)
        except zipfile.BadZipFile as err:
            raise ArchiveInvalid(
                f"{path}: not a backup archive (not a zip file, or truncated): {err}"
            ) from err
        try:
            self.manifest = self._read_manifest()
        except BaseException:
            self._zip.close()
            raise

    def __enter__(self) -> _ArchiveReader:
        return self

    def __exit__(self, *exc: Any) -> None:
        self._zip.close()

    def _read_manifest(self) -> Manifest:
        try:
            encoded = self._zip.read(MANIFEST)
        except KeyError as err:
            raise ArchiveInvalid(
                f"{self.path}: not an invisible-map backup (no {MANIFEST})"
            ) from err
        except (zipfile.BadZipFile, zlib.error, EOFError) as err:
            raise ArchiveInvalid(f"{self.path}: {MANIFEST} is corrupt: {err}") from err
        try:
            document = json.loads(encoded)
        except ValueError as err:
            raise ArchiveInvalid(f"{self.path}: {MANIFEST} is not JSON: {err}") from err
        return Manifest.from_json(document, str(self.path))

    def verify(self) -> None:
        names = self._zip.namelist()
        if len(names) != len(set(names)):
            raise ArchiveInvalid(f"{self.path}: a member name occurs twice")
        present, listed = set(names) - {MANIFEST}, set(self.manifest.members)
        if missing := sorted(listed - present):
            raise ArchiveInvalid(
                f"{self.path}: {missing[0]} is in the manifest but not in the archive"
            )
        if extra := sorted(present - listed):
            raise ArchiveInvalid(f"{self.path}: {extra[0]} is not in the manifest")
        for name, expected in self.manifest.members.items():
            digest, size = hashlib.sha256(), 0
            with self._open(name) as member:
                while chunk := self._read(member, name):
                    digest.update(chunk)
                    size += len(chunk)
            if size != expected.size_bytes or digest.hexdigest() != expected.sha256:
                raise ArchiveInvalid(
                    f"{self.path}: {name} does not match the manifest (checksum mismatch: "
                    f"{size} bytes, sha256 {digest.hexdigest()[:12]}…; expected "
                    f"{expected.size_bytes} bytes, sha256 {expected.sha256[:12]}…)"
                )

    def rows(self, spec: _TableSpec) -> Iterator[tuple[str, dict[str, Any]]]:
        """The table's rows with where each is (``tables/x.jsonl line 3``)."""
        with self._open(spec.member) as member:
            for number, line in enumerate(member, start=1):
                where = f"{spec.member} line {number}"
                try:
                    row = json.loads(line)  # UTF-8 bytes (a bad byte is a ValueError too)
                except ValueError as err:
                    raise ArchiveInvalid(f"{self.path}: {where}: not JSON: {err}") from err
                if not isinstance(row, dict):
                    raise ArchiveInvalid(f"{self.path}: {where}: not a JSON object")
                yield where, row

    def blob(self, name: str, where: str) -> bytes:
        """A member's bytes; ``where`` names the row that refers to it."""
        if name not in self.manifest.members:
            raise ArchiveInvalid(f"{where}: member {name!r} is not in the archive")
        with self._open(name) as member:
            return b"".join(iter(lambda: self._read(member, name), b""))

    def _open(self, name: str) -> IO[bytes]:
        try:
            return self._zip.open(name)
        except (KeyError, zipfile.BadZipFile, zlib.error) as err:
            raise ArchiveInvalid(f"{self.path}: cannot read {name}: {err}") from err

    def _read(self, member: IO[bytes], name: str) -> bytes:
        try:
            return member.read(CHUNK_BYTES)
        except (zipfile.BadZipFile, zlib.error, EOFError) as err:
            raise ArchiveInvalid(f"{self.path}: {name} is corrupt: {err}") from err


def check_schema_revision(archive_revision: str, database_revision: str | None) -> None:
    """Raise ArchiveIncompatible unless the archive was exported at the database's revision,
    saying which side to migrate."""
    if archive_revision == database_revision:
        return
    known = _known_revisions()
    problem = (
        f"the archive was exported at schema revision {archive_revision}, "
        f"the database is at {database_revision or 'no revision (empty)'}"
    )
    if archive_revision not in known:
        advice = "it comes from a newer invisible-map: import it with that version"
    elif database_revision not in known or known.index(archive_revision) > known.index(
        database_revision
    ):
        advice = "migrate this database first (`invisible-map migrate`)"
    else:
        advice = (
            "migrate the source deployment (`invisible-map migrate` with this version) "
            "and export it again"
        )
    raise ArchiveIncompatible(f"{problem}: {advice}")


def _known_revisions() -> list[str]:
    """The migrations' revisions, oldest first."""
    script = ScriptDirectory.from_config(alembic_config("sqlite://"))
    return [revision.revision for revision in script.walk_revisions()][::-1]


# --------------------------------------------------------------------------- import


def import_archive(
    database: Database,
    path: Path,
    *,
    include_keys: bool = False,
    merge: bool = False,
    on_progress: Progress | None = None,
) -> ImportReport:
    """Import the archive ``path`` into ``database`` in one transaction: all of it, or nothing.

    The archive is verified first (:func:`verify_archive`). Without ``merge`` the database must
    have no sessions, maps, jobs or sweeps (and no API keys with ``include_keys``), and every id
    is kept; with ``merge`` rows get new ids. ``include_keys`` imports the API keys' hashes (the
    archive must have them); without it no key is imported and ``uploaded_by`` names the
    uploader's key prefix instead. Raises BackupError (see the module's docstring)."""
    with _ArchiveReader(Path(path)) as archive:
        archive.verify()
        manifest = archive.manifest
        if include_keys and not manifest.key_hashes:
            raise ImportRefused(
                f"{path} has no API key hashes (export it with --include-keys to carry keys)"
            )
        try:
            with database.transaction() as session:
                check_schema_revision(
                    manifest.schema_revision,
                    MigrationContext.configure(session.connection()).get_current_revision(),
                )
                if not merge:
                    _lock_for_restore(session)
                    _require_empty(session, include_keys)
                run = _ImportRun(
                    session=session,
                    archive=archive,
                    include_keys=include_keys,
                    merge=merge,
                    on_progress=on_progress,
                )
                run.run()
                if not merge:
                    _raise_id_sequences(session, manifest.id_high_water)
                return run.report()
        except (IntegrityError, DataError) as err:
            raise ArchiveInvalid(
                f"{path}: the archive's rows do not fit the database: {_first_line(err)}"
            ) from err


def _first_line(err: BaseException) -> str:
    message = str(getattr(err, "orig", None) or err).strip()
    return message.splitlines()[0] if message else type(err).__name__


def _lock_for_restore(session: Session) -> None:
    """On PostgreSQL, keep other writers out of the restored tables until the commit (SQLite's
    BEGIN IMMEDIATE already does)."""
    if session.get_bind().dialect.name == "postgresql":
        tables = ", ".join(f'"{name}"' for name in ("api_key", *RESTORE_NEEDS_EMPTY))
        session.execute(text(f"LOCK TABLE {tables} IN SHARE ROW EXCLUSIVE MODE"))


def _require_empty(session: Session, include_keys: bool) -> None:
    names = RESTORE_NEEDS_EMPTY + (("api_key",) if include_keys else ())
    found = {
        name: int(session.scalar(text(f'SELECT COUNT(*) FROM "{name}"')) or 0) for name in names
    }
    held = ", ".join(f"{count} {name} rows" for name, count in found.items() if count)
    if held:
        raise ImportRefused(
            f"the database is not empty ({held}); a restore keeps the archive's ids and needs a "
            "freshly migrated database: import into one, or pass --merge to add the archive "
            "with new ids"
        )


def _raise_id_sequences(session: Session, high_water: Mapping[str, int]) -> None:
    """Make every id sequence give out ids above both the source's and this database's."""
    postgres = session.get_bind().dialect.name == "postgresql"
    for table in ID_SEQUENCE_TABLES:
        largest = int(session.scalar(text(f'SELECT COALESCE(MAX(id), 0) FROM "{table}"')) or 0)
        wanted = max(high_water.get(table, 0), largest)
        if wanted <= _sequence_value(session, table):
            continue
        if postgres:
            session.execute(
                text("SELECT setval(pg_get_serial_sequence(:t, 'id'), :v, true)"),
                {"t": table, "v": wanted},
            )
        else:
            session.execute(text("DELETE FROM sqlite_sequence WHERE name = :t"), {"t": table})
            session.execute(
                text("INSERT INTO sqlite_sequence (name, seq) VALUES (:t, :v)"),
                {"t": table, "v": wanted},
            )


class _ImportRun:
    """One import: the tables in order, the archive's ids mapped to the database's."""

    def __init__(
        self,
        *,
        session: Session,
        archive: _ArchiveReader,
        include_keys: bool,
        merge: bool,
        on_progress: Progress | None,
    ) -> None:
        self.session = session
        self.archive = archive
        self.include_keys = include_keys
        self.merge = merge
        self.on_progress = on_progress
        counts = archive.manifest.counts
        self.total = sum(counts[name] for name in _PROGRESS_TABLES)
        self.done = 0
        #: table → archive id → database id
        self.ids: dict[str, dict[int, int]] = {spec.name: {} for spec in TABLES}
        self.written: dict[str, int] = {spec.name: 0 for spec in TABLES}
        #: archive key id → its prefix (to name uploaders whose keys are not imported)
        self.key_prefixes: dict[int, str] = {}
        #: archive session id → (SHA-256, size) of its upload's JSON
        self.uploads: dict[int, tuple[str, int]] = {}
        self.queued_job_ids: list[int] = []

    def run(self) -> None:
        for spec in TABLES:
            batch: list[dict[str, Any]] = []
            read = 0
            for where, raw in self.archive.rows(spec):
                read += 1
                values = self._values(spec, raw, where)
                if values is not None:
                    self._write(spec, values, batch)
                if spec.name in _PROGRESS_TABLES:
                    self.done += 1
                    if self.on_progress is not None:
                        self.on_progress(self.done, self.total)
            self._flush(spec, batch)
            if read != self.archive.manifest.counts[spec.name]:
                raise ArchiveInvalid(
                    f"{self.archive.path}: {spec.member} has {read} rows, the manifest says "
                    f"{self.archive.manifest.counts[spec.name]}"
                )

    def report(self) -> ImportReport:
        return ImportReport(
            merged=self.merge,
            counts=dict(self.written),
            map_ids=dict(self.ids["map"]),
            session_ids=dict(self.ids["session"]),
            queued_job_ids=list(self.queued_job_ids),
        )

    # ----------------------------------------------------------------- one row

    def _values(self, spec: _TableSpec, raw: dict[str, Any], where: str) -> dict[str, Any] | None:
        """The row to insert (references mapped), or None when it is not imported."""
        where = f"{self.archive.path}: {where}"
        columns = spec.columns()
        expected = {column.name for column in columns}
        if set(raw) != expected:
            missing, extra = sorted(expected - set(raw)), sorted(set(raw) - expected)
            raise ArchiveInvalid(f"{where}: columns differ (missing {missing}, unexpected {extra})")
        if spec.name == "api_key" and not self.include_keys:
            self._note_key_prefix(raw, where)
            return None
        values = {
            column.name: _decoded(column, raw[column.name], f"{where}: {column.name}")
            for column in columns
            if column.name not in spec.blobs
        }
        for name, table in spec.refs.items():
            if values[name] is not None:
                values[name] = self._mapped(table, values[name], f"{where}: {name}")
        for name, table in spec.soft_refs.items():
            if values[name] is not None:
                values[name] = self.ids[table].get(values[name])
        for name in spec.blobs:
            values[name] = self._blob(spec.table.c[name], raw[name], where)
        return self._adjusted(spec.name, values, raw, where)

    def _mapped(self, table: str, archive_id: int, where: str) -> int:
        try:
            return self.ids[table][archive_id]
        except KeyError:
            raise ArchiveInvalid(f"{where}: {table} {archive_id} is not in the archive") from None

    def _blob(self, column: Column[Any], name: Any, where: str) -> bytes | None:
        if name is None:
            if not column.nullable:
                raise ArchiveInvalid(f"{where}: {column.name} is null")
            return None
        if not isinstance(name, str):
            raise ArchiveInvalid(f"{where}: {column.name} is not a member name")
        return self.archive.blob(name, where)

    def _adjusted(
        self, table: str, values: dict[str, Any], raw: Mapping[str, Any], where: str
    ) -> dict[str, Any] | None:
        """The row after what its table needs: keys, uploaders, a check of each upload."""
        if table == "api_key":
            return self._key(values)
        if table == "session":
            self.uploads[values["id"]] = (values["raw_sha256"], values["raw_size_bytes"])
            values["uploaded_by"] = self._uploader(values["uploaded_by"])
            if self.merge:
                self._check_idempotency_key_free(values)
        elif table == "session_upload":
            _check_upload(values["raw_gzip"], *self.uploads[raw["session_id"]], where)
        return values

    def _note_key_prefix(self, raw: Mapping[str, Any], where: str) -> None:
        """Remember a key that is not imported by its prefix (to name its uploads)."""
        key_id, prefix = raw["id"], raw["prefix"]
        if not _is_int(key_id) or not isinstance(prefix, str):
            raise ArchiveInvalid(f"{where}: expected an integer id and a string prefix")
        self.key_prefixes[key_id] = prefix

    def _key(self, values: dict[str, Any]) -> dict[str, Any] | None:
        """The key to insert, or None when this database has it already (a merge)."""
        if self.merge:
            existing = self.session.execute(
                select(ApiKey.id, ApiKey.secret_sha256).where(ApiKey.prefix == values["prefix"])
            ).first()
            if existing is not None:
                if existing.secret_sha256 != values["secret_sha256"]:
                    raise ImportRefused(
                        f"API key {values['id']}'s prefix {values['prefix']} belongs to another "
                        "key in this database; import without --include-keys"
                    )
                self.ids["api_key"][values["id"]] = existing.id  # the same key: keep one
                return None
        return values

    def _uploader(self, uploaded_by: str) -> str:
        """``key:N`` as this database knows that key: its new id, or (keys not imported) its
        prefix, so that no key here owns the session."""
        match = _KEY_SUBJECT.fullmatch(uploaded_by)
        if match is None:
            return uploaded_by
        archive_id = int(match.group(1))
        if self.include_keys and archive_id in self.ids["api_key"]:
            return f"key:{self.ids['api_key'][archive_id]}"
        prefix = self.key_prefixes.get(archive_id)
        return f"imported:im_{prefix}" if prefix else f"imported:{uploaded_by}"

    def _check_idempotency_key_free(self, values: dict[str, Any]) -> None:
        key = values["idempotency_key"]
        if key is None:
            return
        existing = self.session.scalar(
            select(SessionRow.id).where(
                SessionRow.uploaded_by == values["uploaded_by"], SessionRow.idempotency_key == key
            )
        )
        if existing is not None:
            raise ImportRefused(
                f"session {values['id']} of the archive has the idempotency key {key!r} of "
                f"{values['uploaded_by']}, which session {existing} here already has; was this "
                "archive imported before?"
            )

    # ----------------------------------------------------------------- writing

    def _write(self, spec: _TableSpec, values: dict[str, Any], batch: list[dict[str, Any]]) -> None:
        """Insert the row (batched for tables nobody refers to and without blobs)."""
        if not spec.allocates_ids and not spec.blobs:
            batch.append(values)
            if len(batch) >= INSERT_BATCH_ROWS:
                self._flush(spec, batch)
            return
        if not spec.allocates_ids:
            self.session.execute(insert(spec.table).values(values))
            self.written[spec.name] += 1
            return
        archive_id = values["id"]
        if self.merge:
            del values["id"]
            new_id = self.session.execute(
                insert(spec.table).values(values).returning(spec.table.c.id)
            ).scalar_one()
        else:
            self.session.execute(insert(spec.table).values(values))
            new_id = archive_id
        self.ids[spec.name][archive_id] = new_id
        self.written[spec.name] += 1
        if spec.name == "job" and values["state"] == JobState.QUEUED.value:
            self.queued_job_ids.append(new_id)

    def _flush(self, spec: _TableSpec, batch: list[dict[str, Any]]) -> None:
        if batch:
            self.session.execute(insert(spec.table), batch)
            self.written[spec.name] += len(batch)
            batch.clear()


def _decoded(column: Column[Any], value: Any, where: str) -> Any:
    """A JSON value as the column's Python value; raises ArchiveInvalid if it cannot be one."""
    if value is None:
        if not column.nullable:
            raise ArchiveInvalid(f"{where} is null")
        return None
    kind = column.type
    if isinstance(kind, UTCDateTime):
        try:
            parsed = datetime.fromisoformat(value) if isinstance(value, str) else None
        except ValueError:
            parsed = None
        if parsed is None or parsed.tzinfo is None:
            raise ArchiveInvalid(f"{where}: {value!r} is not a datetime with a UTC offset")
        return parsed
    if isinstance(kind, JSON):
        return value
    checks: tuple[tuple[type[Any], Callable[[Any], bool]], ...] = (
        (Boolean, lambda v: isinstance(v, bool)),
        (Integer, _is_int),
        (Float, lambda v: _is_int(v) or isinstance(v, float)),
        (String, lambda v: isinstance(v, str)),
        (LargeBinary, lambda _v: False),
    )
    for type_, accepts in checks:
        if isinstance(kind, type_):
            if not accepts(value):
                raise ArchiveInvalid(f"{where}: expected {type_.__name__.lower()}, got {value!r}")
            return float(value) if type_ is Float else value
    raise ArchiveInvalid(f"{where}: a column of type {kind} cannot be imported")


def _is_int(value: Any) -> TypeGuard[int]:
    return isinstance(value, int) and not isinstance(value, bool)


def _check_upload(raw_gzip: bytes | None, sha256: str, size_bytes: int, where: str) -> None:
    """Raise ArchiveInvalid unless ``raw_gzip`` inflates to the session's upload (its SHA-256
    and size), inflating at most one byte more than the upload's size."""
    if raw_gzip is None:
        raise ArchiveInvalid(f"{where}: no upload")
    digest, inflated = hashlib.sha256(), 0
    try:
        with gzip.GzipFile(fileobj=io.BytesIO(raw_gzip)) as upload:
            while chunk := upload.read(min(CHUNK_BYTES, size_bytes + 1 - inflated)):
                digest.update(chunk)
                inflated += len(chunk)
                if inflated > size_bytes:
                    break
    except (OSError, EOFError, zlib.error) as err:
        raise ArchiveInvalid(f"{where}: the upload is not gzip: {err}") from err
    if inflated != size_bytes or digest.hexdigest() != sha256:
        raise ArchiveInvalid(
            f"{where}: the upload does not match its session (sha256 or size differs)"
        )
