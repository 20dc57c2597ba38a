"""The backup archive's format: its manifest, tables and members, its errors, and reading it."""

from __future__ import annotations

import hashlib
import json
import math
import os
import re
import stat
import zipfile
import zlib
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import IO, Any, BinaryIO, TypeGuard

from alembic.script import ScriptDirectory
from sqlalchemy import (
    Column,
    ColumnElement,
    Table,
)

from app.domain.json_values import value_error_reason
from app.domain.upload.fields import text_fault
from app.storage.migrate import alembic_config
from app.storage.orm import (
    ApiKey,
    Base,
    CorridorEditRow,
    Job,
    MapRow,
    MapSession,
    MapTag,
    MapVersion,
    SessionImage,
    SessionRow,
    SessionUpload,
    Sweep,
    SweepTrial,
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
#: The largest member read whole (an upload, a picture, a version's document, plot or path
#: graph), bytes, as the zip says it inflates: the server's own limit on an upload after gunzip
#: (``INVISIBLE_MAP_MAX_SESSION_BYTES``) by default. Checked before the member is read.
MAX_MEMBER_BYTES = 256 * 2**20
#: The longest row of a table (one line of ``tables/<table>.jsonl``), bytes.
MAX_ROW_BYTES = 64 * 2**20
#: The largest ``manifest.json``, bytes (it lists every member: ~100 bytes each).
MAX_MANIFEST_BYTES = 64 * 2**20
#: The largest id and count an archive may hold: ids are 32-bit integer columns.
MAX_ID = 2**31 - 1
#: Tables whose ids are never given out twice (``NEVER_REUSE_IDS`` in orm.py).
ID_SEQUENCE_TABLES = (
    "api_key",
    "session",
    "map",
    "job",
    "map_version",
    "localization",
    "sweep",
    "corridor_edit",
)
#: Tables that must be empty for a restore (one that keeps the archive's ids).
RESTORE_NEEDS_EMPTY = ("session", "map", "job", "sweep")
KEY_SUBJECT = re.compile(r"key:(\d+)")

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
class TableSpec:
    """How one table goes into the archive and comes back."""

    model: type[Base]
    #: the primary key; rows are read and written in its order
    key: str = "id"
    #: False: the id is not exported (nothing refers to it) and the target gives a new one
    export_key: bool = True
    #: binary column → its member's name (``str.format`` of the row)
    blobs: Mapping[str, str] = field(default_factory=dict)
    #: binary column → the column naming the content-addressed blob (``app.storage.blobs``)
    #: that holds its bytes when the column is null; the archive holds the bytes as the
    #: binary column's member (the blob columns are not exported), and an import stores them
    #: as a blob again
    blob_refs: Mapping[str, str] = field(default_factory=dict)
    #: columns not exported: what is derived from the row's data (a version's app-map and
    #: overview, ``app.domain.formats.derived_documents``); an import makes them again
    #: (``app.storage.derived``)
    derived: tuple[str, ...] = ()
    #: column → table whose ids it holds (the row must be in the archive)
    refs: Mapping[str, str] = field(default_factory=dict)
    #: column → table whose ids it holds, or null when that row is not in the archive
    soft_refs: Mapping[str, str] = field(default_factory=dict)
    #: only these rows are exported
    only: Callable[[], ColumnElement[bool]] | None = None
    #: archives written before the table existed lack it (it is then left empty)
    optional: bool = False

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
        skipped = (
            set(self.blob_refs.values())
            | set(self.derived)
            | (set() if self.export_key else {self.key})
        )
        return [c for c in self.table.columns if c.name not in skipped]


#: In dependency order: a row's references come before it.
TABLES = (
    TableSpec(model=ApiKey),
    TableSpec(model=SessionRow),
    TableSpec(
        model=SessionUpload,
        key="session_id",
        blobs={"raw_gzip": "uploads/{session_id}.json.gz"},
        refs={"session_id": "session"},
    ),
    TableSpec(model=MapRow, refs={"session_id": "session"}),
    TableSpec(
        model=CorridorEditRow,
        refs={"map_id": "map"},
        optional=True,  # added with corridor edits (issue 27)
    ),
    TableSpec(
        model=SessionImage,
        key="session_id",
        blobs={"jpeg": "images/{session_id}.jpg"},
        refs={"session_id": "session"},
        optional=True,  # added with the app's pictures
    ),
    TableSpec(
        model=MapSession,
        export_key=False,
        refs={"map_id": "map", "session_id": "session"},
        optional=True,  # added with maps of several sessions
    ),
    TableSpec(
        model=Job,
        refs={"map_id": "map", "session_id": "session"},
        only=lambda: Job.kind == BUILD_MAP,
    ),
    TableSpec(
        model=MapVersion,
        refs={"map_id": "map"},
        soft_refs={"job_id": "job"},
        blobs={
            "map_json_gzip": "versions/{id}/map.json.gz",
            "plot_png": "versions/{id}/plot.png",
            "path_graph_gzip": "versions/{id}/path_graph.json.gz",
        },
        blob_refs={
            "map_json_gzip": "map_json_sha256",
            "plot_png": "plot_png_sha256",
            "path_graph_gzip": "path_graph_sha256",
        },
        derived=("app_map_sha256", "app_map_export", "overview_sha256"),
    ),
    TableSpec(model=MapTag, export_key=False, refs={"map_version_id": "map_version"}),
    TableSpec(
        model=Sweep,
        refs={"map_id": "map", "session_id": "session"},
        soft_refs={"applied_job_id": "job"},
    ),
    TableSpec(model=SweepTrial, export_key=False, refs={"sweep_id": "sweep"}),
)
TABLES_BY_NAME = {spec.name: spec for spec in TABLES}
#: The tables whose rows the progress counts (the large ones: an upload, a version's blobs).
PROGRESS_TABLES = ("session_upload", "map_version")


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
        if not is_int(version) or version < 1:
            raise ArchiveInvalid(f"{where}: format_version {version!r} is not a version")
        if version > FORMAT_VERSION:
            raise ArchiveIncompatible(
                f"{where}: archive format version {version} is newer than this invisible-map "
                f"reads ({FORMAT_VERSION}); import it with a newer invisible-map"
            )
        try:
            members = {
                str(name): Member(
                    size_bytes=_counted(m["size_bytes"], f"members.{name}.size_bytes", 2**63 - 1),
                    sha256=str(m["sha256"]),
                )
                for name, m in document["members"].items()
            }
            manifest = cls(
                format_version=version,
                schema_revision=str(document["schema_revision"]),
                created_at=datetime.fromisoformat(document["created_at"]),
                source_backend=str(document["source_backend"]),
                key_hashes=bool(document["key_hashes"]),
                counts={
                    str(k): _counted(v, f"counts.{k}", MAX_ID)
                    for k, v in document["counts"].items()
                },
                id_high_water={
                    str(k): _counted(v, f"id_high_water.{k}", MAX_ID)
                    for k, v in document["id_high_water"].items()
                },
                members=members,
            )
        except (KeyError, TypeError, ValueError, AttributeError) as err:
            raise ArchiveInvalid(
                f"{where}: malformed manifest ({type(err).__name__}: {err})"
            ) from err
        for name in [*manifest.members, *manifest.counts, *manifest.id_high_water]:
            if (reason := text_fault(name)) is not None:
                raise ArchiveInvalid(f"{where}: malformed manifest (a name {reason})")
        for spec in TABLES:
            if spec.name not in manifest.counts or spec.member not in manifest.members:
                if spec.optional and spec.name not in manifest.counts:
                    continue
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


# --------------------------------------------------------------------------- reading archives


def read_manifest(path: Path) -> Manifest:
    """The archive's manifest, checked for format and version (not its members: see
    :func:`verify_archive`). Raises OSError (no such file), ArchiveInvalid, ArchiveIncompatible."""
    with ArchiveReader(Path(path)) as archive:
        return archive.manifest


def verify_archive(path: Path, *, max_member_bytes: int = MAX_MEMBER_BYTES) -> Manifest:
    """Check every member of the archive against its manifest (names, sizes, SHA-256, zip CRC;
    each size before anything is inflated); returns the manifest. Raises as
    :func:`read_manifest` does. (:func:`app.storage.backup.restore.check_archive` also checks
    every row.)"""
    with ArchiveReader(Path(path), max_member_bytes=max_member_bytes) as archive:
        archive.verify()
        return archive.manifest


class ArchiveReader:
    """An open archive whose manifest has been read and checked. A member other than a table is
    read whole only if the zip says it inflates to at most ``max_member_bytes``, and a table's
    rows one line of at most :data:`MAX_ROW_BYTES` at a time, so that memory stays bounded
    whatever the archive holds."""

    def __init__(self, path: Path, *, max_member_bytes: int = MAX_MEMBER_BYTES) -> None:
        self.path = path
        self.max_member_bytes = max_member_bytes
        self._file = open_regular_file(path)
        try:
            self._zip = zipfile.ZipFile(self._file)
        except zipfile.BadZipFile as err:
            self._file.close()
            raise ArchiveInvalid(
                f"{path}: not a backup archive (not a zip file, or truncated): {err}"
            ) from err
        except BaseException:
            self._file.close()
            raise
        try:
            self.manifest = self._read_manifest()
        except BaseException:
            self.close()
            raise

    def __enter__(self) -> ArchiveReader:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def close(self) -> None:
        self._zip.close()
        self._file.close()

    def _read_manifest(self) -> Manifest:
        try:
            size_bytes = self._zip.getinfo(MANIFEST).file_size
        except KeyError as err:
            raise ArchiveInvalid(
                f"{self.path}: not an invisible-map backup (no {MANIFEST})"
            ) from err
        if size_bytes > MAX_MANIFEST_BYTES:
            raise ArchiveInvalid(
                f"{self.path}: {MANIFEST} inflates to {size_bytes} bytes, more than a manifest "
                f"holds ({MAX_MANIFEST_BYTES})"
            )
        try:
            encoded = self._zip.read(MANIFEST)
        except (zipfile.BadZipFile, zlib.error, EOFError) as err:
            raise ArchiveInvalid(f"{self.path}: {MANIFEST} is corrupt: {err}") from err
        try:
            document = json.loads(encoded)
        except (ValueError, RecursionError) as err:
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
        for name in self.manifest.members:  # every size first, before anything is inflated
            self._check_size(name)
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

    def rows(self, spec: TableSpec) -> Iterator[tuple[str, dict[str, Any]]]:
        """The table's rows with where each is (``tables/x.jsonl line 3``), a line of at most
        :data:`MAX_ROW_BYTES` at a time."""
        with self._open(spec.member) as member:
            number = 0
            while line := self._read_line(member, spec.member):
                number += 1
                where = f"{spec.member} line {number}"
                if len(line) > MAX_ROW_BYTES:
                    raise ArchiveInvalid(
                        f"{self.path}: {where}: longer than a row may be ({MAX_ROW_BYTES} bytes)"
                    )
                try:  # UTF-8 bytes (a bad byte is a ValueError too)
                    row = json.loads(line, parse_constant=_no_constant, parse_float=_finite)
                except NotAJsonNumber as err:
                    raise ArchiveInvalid(f"{self.path}: {where}: {err}") from None
                except (ValueError, RecursionError) as err:
                    reason = value_error_reason(err)
                    raise ArchiveInvalid(f"{self.path}: {where}: not JSON: {reason}") from err
                if not isinstance(row, dict):
                    raise ArchiveInvalid(f"{self.path}: {where}: not a JSON object")
                yield where, row

    def blob(self, name: str, where: str) -> bytes:
        """A member's bytes (at most ``max_member_bytes``); ``where`` names the row that refers
        to it."""
        if name not in self.manifest.members:
            raise ArchiveInvalid(f"{where}: member {name!r} is not in the archive")
        self._check_size(name)
        data = bytearray()
        with self._open(name) as member:
            while chunk := self._read(member, name):
                data += chunk
        return bytes(data)

    def _check_size(self, name: str) -> None:
        """ArchiveInvalid unless the zip says a member read whole (not a table, which is read a
        row at a time) inflates to at most ``max_member_bytes``: checked before it is read (the
        zip's reader stops at the size the zip says, and a member that inflates further fails
        its CRC)."""
        try:
            size_bytes = self._zip.getinfo(name).file_size
        except KeyError as err:
            raise ArchiveInvalid(f"{self.path}: {name} is not in the archive") from err
        if size_bytes > self.max_member_bytes and not name.startswith("tables/"):
            raise ArchiveInvalid(
                f"{self.path}: {name} inflates to {size_bytes} bytes, more than the "
                f"{self.max_member_bytes} a member may (INVISIBLE_MAP_MAX_SESSION_BYTES)"
            )

    def _read_line(self, member: IO[bytes], name: str) -> bytes:
        try:
            return member.readline(MAX_ROW_BYTES + 1)
        except (zipfile.BadZipFile, zlib.error, EOFError) as err:
            raise ArchiveInvalid(f"{self.path}: {name} is corrupt: {err}") from err

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


def open_regular_file(path: Path) -> BinaryIO:
    """``path`` opened for reading if it is a regular file; ArchiveInvalid at once for a FIFO, a
    device or a folder (which would hang, or be read without end: ``/dev/zero``), OSError if it
    is missing or cannot be opened. Checked before it is opened, and again on the descriptor,
    opened without blocking, so that a FIFO put in its place meanwhile cannot hang it."""
    refused = ArchiveInvalid(
        f"{path}: not a regular file (a FIFO, a device or a folder), not a backup archive"
    )
    if not stat.S_ISREG(os.stat(path).st_mode):
        raise refused
    descriptor = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
    try:
        if not stat.S_ISREG(os.fstat(descriptor).st_mode):
            raise refused
        os.set_blocking(descriptor, True)
        return os.fdopen(descriptor, "rb")
    except BaseException:
        os.close(descriptor)
        raise


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


class NotAJsonNumber(ValueError):
    """Raised while a row is decoded for a number JSON does not have (``NaN``, ``Infinity``, a
    literal beyond a float's range) that Python's decoder would take: PostgreSQL refuses it in a
    JSON column, SQLite stores NaN as NULL."""


def _no_constant(name: str) -> float:
    raise NotAJsonNumber(f"holds {name}, which is no JSON number (no database holds it as one)")


def _finite(literal: str) -> float:
    value = float(literal)
    if not math.isfinite(value):
        raise NotAJsonNumber(
            f"holds {literal[:40]}, a number beyond a float's range (no database holds it)"
        )
    return value


def is_int(value: Any) -> TypeGuard[int]:
    return isinstance(value, int) and not isinstance(value, bool)


def _counted(value: Any, where: str, largest: int) -> int:
    """``value`` if it is an integer from 0 to ``largest``; ValueError naming ``where``."""
    if not is_int(value) or not 0 <= value <= largest:
        raise ValueError(f"{where} is {value!r}, not an integer from 0 to {largest}")
    return value
