"""Import: an archive restored into an empty database (ids kept) or merged into one (new ids);
and the same checks of every row without a database (``import --check``).

Every value of a row is checked before it is written, so that an archive a database cannot hold
is refused naming its row (``tables/map.jsonl line 3 (id 3): display_name holds a NUL …``), not
with a driver's traceback: the column's type, an integer within the column's range (ids are
32-bit), text by the rule of every stored text (:func:`app.domain.upload.fields.text_fault`,
in JSON columns too) and within the column's length, a datetime that UTC can hold, references
to rows in the archive, no key or unique set of columns given twice (a primary key, a
``UNIQUE`` constraint), what the tables' ``CHECK`` constraints allow, numbers JSON has (no NaN or
Infinity: ``ArchiveReader.rows``), and each upload, which must inflate to its session's size and
SHA-256, a size no larger than the server takes (``INVISIBLE_MAP_MAX_SESSION_BYTES``), checked
before it is inflated.

These checks are the one validator of an archive: ``import`` and ``import --check`` both run them
(:class:`_ImportRun`, with and without a database), so that the check refuses what the import
refuses, on SQLite and PostgreSQL alike; what is left to the database is only what depends on its
data (a restore into a database that is not empty, a merge's clashes).
"""

from __future__ import annotations

import gzip
import hashlib
import io
import zlib
from collections.abc import Callable, Mapping
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from alembic.runtime.migration import MigrationContext
from sqlalchemy import (
    JSON,
    BigInteger,
    Boolean,
    Column,
    Float,
    Integer,
    LargeBinary,
    PrimaryKeyConstraint,
    SmallInteger,
    String,
    UniqueConstraint,
    insert,
    select,
    text,
)
from sqlalchemy.exc import DataError, IntegrityError
from sqlalchemy.orm import Session

from app.domain.upload.fields import json_text_fault, text_fault
from app.storage import blobs
from app.storage.backup.archive import (
    CHUNK_BYTES,
    ID_SEQUENCE_TABLES,
    INSERT_BATCH_ROWS,
    KEY_SUBJECT,
    MAX_MEMBER_BYTES,
    PROGRESS_TABLES,
    RESTORE_NEEDS_EMPTY,
    TABLES,
    ArchiveInvalid,
    ArchiveReader,
    ImportRefused,
    ImportReport,
    Manifest,
    Progress,
    TableSpec,
    check_schema_revision,
    is_int,
)
from app.storage.backup.export import sequence_value
from app.storage.db import Database
from app.storage.derived import add_derived_documents
from app.storage.orm import (
    ApiKey,
    JobState,
    Role,
    SessionRow,
    UTCDateTime,
)

#: What the tables' ``CHECK`` constraints (``app.storage.orm``) allow, by (table, column): the
#: values a column may hold, or the range (inclusive) of a number. A test checks that every
#: ``CHECK`` constraint of an exported table is here.
ALLOWED_VALUES: dict[tuple[str, str], frozenset[str]] = {
    ("api_key", "role"): frozenset(role.value for role in Role),
    ("job", "state"): frozenset(state.value for state in JobState),
}
ALLOWED_RANGES: dict[tuple[str, str], tuple[float, float]] = {("job", "progress"): (0.0, 1.0)}

# --------------------------------------------------------------------------- import


def import_archive(
    database: Database,
    path: Path,
    *,
    include_keys: bool = False,
    merge: bool = False,
    on_progress: Progress | None = None,
    max_member_bytes: int = MAX_MEMBER_BYTES,
) -> ImportReport:
    """Import the archive ``path`` into ``database`` in one transaction: all of it, or nothing.

    The archive is verified first (:func:`verify_archive`), and every row as it is read (the
    module's docstring). Without ``merge`` the database must
    have no sessions, maps, jobs or sweeps (and no API keys with ``include_keys``), and every id
    is kept; with ``merge`` rows get new ids. ``include_keys`` imports the API keys' hashes (the
    archive must have them); without it no key is imported and ``uploaded_by`` names the
    uploader's key prefix instead. ``max_member_bytes``: the largest upload (inflated) or other
    member read whole. Raises BackupError (see the module's docstring)."""
    with ArchiveReader(Path(path), max_member_bytes=max_member_bytes) as archive:
        archive.verify()
        manifest = archive.manifest
        if include_keys and not manifest.key_hashes:
            raise ImportRefused(
                f"{path} has no API key hashes (export it with --include-keys to carry keys)"
            )
        try:
            with database.transaction() as db_session:
                check_schema_revision(
                    manifest.schema_revision,
                    MigrationContext.configure(db_session.connection()).get_current_revision(),
                )
                if not merge:
                    _lock_for_restore(db_session)
                    _require_empty(db_session, include_keys)
                run = _ImportRun(
                    db_session=db_session,
                    archive=archive,
                    include_keys=include_keys,
                    merge=merge,
                    on_progress=on_progress,
                )
                run.run()
                if not merge:
                    _raise_id_sequences(db_session, manifest.id_high_water)
                return run.report()
        except (IntegrityError, DataError) as err:
            raise ArchiveInvalid(
                f"{path}: the archive's rows do not fit the database: {_first_line(err)}"
            ) from err


def check_archive(
    path: Path, *, max_member_bytes: int = MAX_MEMBER_BYTES, on_progress: Progress | None = None
) -> Manifest:
    """Check the archive as :func:`import_archive` would, without a database: every member
    (:func:`verify_archive`) and every row (values, references, uploads; the module's
    docstring), in bounded memory. Returns the manifest; raises BackupError."""
    with ArchiveReader(Path(path), max_member_bytes=max_member_bytes) as archive:
        archive.verify()
        _ImportRun(
            db_session=None,
            archive=archive,
            include_keys=archive.manifest.key_hashes,
            merge=False,
            on_progress=on_progress,
        ).run()
        return archive.manifest


def _first_line(err: BaseException) -> str:
    message = str(getattr(err, "orig", None) or err).strip()
    return message.splitlines()[0] if message else type(err).__name__


def _lock_for_restore(db_session: Session) -> None:
    """On PostgreSQL, keep other writers out of the restored tables until the commit (SQLite's
    BEGIN IMMEDIATE already does)."""
    if db_session.get_bind().dialect.name == "postgresql":
        tables = ", ".join(f'"{name}"' for name in ("api_key", *RESTORE_NEEDS_EMPTY))
        db_session.execute(text(f"LOCK TABLE {tables} IN SHARE ROW EXCLUSIVE MODE"))


def _require_empty(db_session: Session, include_keys: bool) -> None:
    names = RESTORE_NEEDS_EMPTY + (("api_key",) if include_keys else ())
    found = {
        name: int(db_session.scalar(text(f'SELECT COUNT(*) FROM "{name}"')) or 0) for name in names
    }
    held = ", ".join(f"{count} {name} rows" for name, count in found.items() if count)
    if held:
        raise ImportRefused(
            f"the database is not empty ({held}); a restore keeps the archive's ids and needs a "
            "freshly migrated database: import into one, or pass --merge to add the archive "
            "with new ids"
        )


def _raise_id_sequences(db_session: Session, high_water: Mapping[str, int]) -> None:
    """Make every id sequence give out ids above both the source's and this database's."""
    postgres = db_session.get_bind().dialect.name == "postgresql"
    for table in ID_SEQUENCE_TABLES:
        largest = int(db_session.scalar(text(f'SELECT COALESCE(MAX(id), 0) FROM "{table}"')) or 0)
        wanted = max(high_water.get(table, 0), largest)
        if wanted <= sequence_value(db_session, table):
            continue
        if postgres:
            db_session.execute(
                text("SELECT setval(pg_get_serial_sequence(:t, 'id'), :v, true)"),
                {"t": table, "v": wanted},
            )
        else:
            db_session.execute(text("DELETE FROM sqlite_sequence WHERE name = :t"), {"t": table})
            db_session.execute(
                text("INSERT INTO sqlite_sequence (name, seq) VALUES (:t, :v)"),
                {"t": table, "v": wanted},
            )


class _ImportRun:
    """One import: the tables in order, the archive's ids mapped to the database's. Without a
    ``db_session`` it only checks (``import --check``): every row is read and checked, nothing
    is written, and the archive's ids stand for themselves."""

    def __init__(
        self,
        *,
        db_session: Session | None,
        archive: ArchiveReader,
        include_keys: bool,
        merge: bool,
        on_progress: Progress | None,
    ) -> None:
        self.db_session = db_session
        self.archive = archive
        self.include_keys = include_keys
        self.merge = merge
        self.on_progress = on_progress
        counts = archive.manifest.counts
        self.total = sum(counts[name] for name in PROGRESS_TABLES)
        self.done = 0
        #: table → archive id → database id
        self.ids: dict[str, dict[int, int]] = {spec.name: {} for spec in TABLES}
        self.written: dict[str, int] = {spec.name: 0 for spec in TABLES}
        #: archive key id → its prefix (to name uploaders whose keys are not imported)
        self.key_prefixes: dict[int, str] = {}
        #: archive session id → (SHA-256, size) of its upload's JSON
        self.uploads: dict[int, tuple[str, int]] = {}
        self.queued_job_ids: list[int] = []
        #: (table, unique columns) → the values taken (the archive's ids; references mapped)
        self.taken: dict[tuple[str, tuple[str, ...]], set[tuple[Any, ...]]] = {}
        self.unique_sets: dict[str, list[tuple[str, ...]]] = {}

    def run(self) -> None:
        for spec in TABLES:
            if spec.optional and spec.name not in self.archive.manifest.counts:
                continue  # an archive from before the table existed
            batch: list[dict[str, Any]] = []
            read = 0
            for where, raw in self.archive.rows(spec):
                read += 1
                values = self._values(spec, raw, where)
                if values is not None:
                    self._check_constraints(spec, values, raw, where)
                    self._write(spec, values, batch)
                if spec.name in PROGRESS_TABLES:
                    self.done += 1
                    if self.on_progress is not None:
                        self.on_progress(self.done, self.total)
            self._flush(spec, batch)
            if read != self.archive.manifest.counts[spec.name]:
                raise ArchiveInvalid(
                    f"{self.archive.path}: {spec.member} has {read} rows, the manifest says "
                    f"{self.archive.manifest.counts[spec.name]}"
                )
        # what a worker derived from each version is not in the archive: made again here, so
        # that the API serves it as stored (issue 19, finding 3)
        if self.db_session is not None:
            for version_id in self.ids["map_version"].values():
                add_derived_documents(self.db_session, version_id)

    def report(self) -> ImportReport:
        return ImportReport(
            merged=self.merge,
            counts=dict(self.written),
            map_ids=dict(self.ids["map"]),
            session_ids=dict(self.ids["session"]),
            queued_job_ids=list(self.queued_job_ids),
        )

    # ----------------------------------------------------------------- one row

    def _values(self, spec: TableSpec, raw: dict[str, Any], where: str) -> dict[str, Any] | None:
        """The row to insert (references mapped), or None when it is not imported."""
        key = raw.get(spec.key)
        where = f"{self.archive.path}: {where}" + (f" ({spec.key} {key})" if is_int(key) else "")
        columns = spec.columns()
        expected = {column.name for column in columns}
        if set(raw) != expected:
            missing, extra = sorted(expected - set(raw)), sorted(set(raw) - expected)
            if extra or any(not _added_later(spec, name) for name in missing):
                raise ArchiveInvalid(
                    f"{where}: columns differ (missing {missing}, unexpected {extra})"
                )
            columns = [column for column in columns if column.name in raw]
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
        for name, reference in spec.blob_refs.items():  # stored as the source stores them
            data, values[name] = values[name], None
            if data is not None and self.db_session is not None:
                values[reference] = blobs.put_blob_in(self.db_session, data)
            else:
                values[reference] = None
        return self._adjusted(spec.name, values, raw, where)

    def _check_constraints(
        self, spec: TableSpec, values: Mapping[str, Any], raw: Mapping[str, Any], where: str
    ) -> None:
        """ArchiveInvalid for a row that a table's ``CHECK`` constraint refuses, or whose key or
        unique columns an earlier row of the archive holds (the database's constraints, checked
        the same way with or without a database)."""
        key = raw.get(spec.key)
        where = f"{self.archive.path}: {where}" + (f" ({spec.key} {key})" if is_int(key) else "")
        for (table, column), allowed in ALLOWED_VALUES.items():
            if table == spec.name and column in values and values[column] not in allowed:
                raise ArchiveInvalid(
                    f"{where}: {column} {values[column]!r} is not one of {sorted(allowed)}"
                )
        for (table, column), (low, high) in ALLOWED_RANGES.items():
            number = values.get(column) if table == spec.name else None
            if number is not None and not low <= number <= high:
                raise ArchiveInvalid(f"{where}: {column} {number!r} is not from {low} to {high}")
        if spec.name not in self.unique_sets:
            self.unique_sets[spec.name] = _unique_column_sets(spec)
        for columns in self.unique_sets[spec.name]:
            if spec.allocates_ids and columns == ("id",):
                taken: tuple[Any, ...] = (raw["id"],)  # the archive's id (a merge gives a new one)
            else:
                taken = tuple(values.get(name) for name in columns)
            if any(value is None for value in taken):
                continue  # NULLs never clash
            seen = self.taken.setdefault((spec.name, columns), set())
            if taken in seen:
                shown = ", ".join(
                    f"{name} {value!r}" for name, value in zip(columns, taken, strict=True)
                )
                raise ArchiveInvalid(
                    f"{where}: {shown}: an earlier row of {spec.member} has "
                    f"{'it' if len(columns) == 1 else 'them'} too (the table holds "
                    f"{'it' if len(columns) == 1 else 'them'} once)"
                )
            seen.add(taken)

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
        if self.db_session is None and column.table.name != "session_upload":
            # only checking: verify() has matched its bytes with the manifest; only an upload's
            # are read again (to be inflated against its session)
            if name not in self.archive.manifest.members:
                raise ArchiveInvalid(f"{where}: member {name!r} is not in the archive")
            return b""
        return self.archive.blob(name, where)

    def _adjusted(
        self, table: str, values: dict[str, Any], raw: Mapping[str, Any], where: str
    ) -> dict[str, Any] | None:
        """The row after what its table needs: keys, uploaders, a check of each upload."""
        if table == "api_key":
            return self._key(values)
        if table == "session":
            if not 0 <= values["raw_size_bytes"] <= self.archive.max_member_bytes:
                raise ArchiveInvalid(
                    f"{where}: raw_size_bytes {values['raw_size_bytes']} is not from 0 to the "
                    f"{self.archive.max_member_bytes} bytes an upload may inflate to "
                    "(INVISIBLE_MAP_MAX_SESSION_BYTES)"
                )
            self.uploads[values["id"]] = (values["raw_sha256"], values["raw_size_bytes"])
            values["uploaded_by"] = self._uploader(values["uploaded_by"])
            _check_text(
                values["uploaded_by"], f"{where}: uploaded_by", _length(SessionRow, "uploaded_by")
            )
            if self.merge:
                self._check_idempotency_key_free(values)
        elif table == "session_upload":
            _check_upload(values["raw_gzip"], *self.uploads[raw["session_id"]], where)
        return values

    def _note_key_prefix(self, raw: Mapping[str, Any], where: str) -> None:
        """Remember a key that is not imported by its prefix (to name its uploads)."""
        key_id, prefix = raw["id"], raw["prefix"]
        if not is_int(key_id) or not isinstance(prefix, str):
            raise ArchiveInvalid(f"{where}: expected an integer id and a string prefix")
        _check_text(prefix, f"{where}: prefix", _length(ApiKey, "prefix"))
        self.key_prefixes[key_id] = prefix

    def _key(self, values: dict[str, Any]) -> dict[str, Any] | None:
        """The key to insert, or None when this database has it already (a merge)."""
        if self.merge and self.db_session is not None:
            existing = self.db_session.execute(
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
        match = KEY_SUBJECT.fullmatch(uploaded_by)
        if match is None:
            return uploaded_by
        archive_id = int(match.group(1))
        if self.include_keys and archive_id in self.ids["api_key"]:
            return f"key:{self.ids['api_key'][archive_id]}"
        prefix = self.key_prefixes.get(archive_id)
        return f"imported:im_{prefix}" if prefix else f"imported:{uploaded_by}"

    def _check_idempotency_key_free(self, values: dict[str, Any]) -> None:
        key = values["idempotency_key"]
        if key is None or self.db_session is None:
            return
        existing = self.db_session.scalar(
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

    def _write(self, spec: TableSpec, values: dict[str, Any], batch: list[dict[str, Any]]) -> None:
        """Insert the row (batched for tables nobody refers to and without blobs)."""
        if self.db_session is None:  # only checking: the archive's ids stand for themselves
            if spec.allocates_ids:
                self.ids[spec.name][values["id"]] = values["id"]
            self.written[spec.name] += 1
            return
        if not spec.allocates_ids and not spec.blobs:
            batch.append(values)
            if len(batch) >= INSERT_BATCH_ROWS:
                self._flush(spec, batch)
            return
        if not spec.allocates_ids:
            self.db_session.execute(insert(spec.table).values(values))
            self.written[spec.name] += 1
            return
        archive_id = values["id"]
        if self.merge:
            del values["id"]
            new_id = self.db_session.execute(
                insert(spec.table).values(values).returning(spec.table.c.id)
            ).scalar_one()
        else:
            self.db_session.execute(insert(spec.table).values(values))
            new_id = archive_id
        self.ids[spec.name][archive_id] = new_id
        self.written[spec.name] += 1
        if spec.name == "job" and values["state"] == JobState.QUEUED.value:
            self.queued_job_ids.append(new_id)

    def _flush(self, spec: TableSpec, batch: list[dict[str, Any]]) -> None:
        if batch and self.db_session is not None:
            self.db_session.execute(insert(spec.table), batch)
            self.written[spec.name] += len(batch)
            batch.clear()


def _unique_column_sets(spec: TableSpec) -> list[tuple[str, ...]]:
    """The sets of the table's exported columns that the database holds once (its primary key,
    its ``UNIQUE`` constraints), each as a tuple of column names."""
    exported = {column.name for column in spec.columns()}
    found = []
    for constraint in spec.table.constraints:
        if isinstance(constraint, (PrimaryKeyConstraint, UniqueConstraint)):
            names = tuple(column.name for column in constraint.columns)
            if names and set(names) <= exported:
                found.append(names)
    return found


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
            if parsed is not None and parsed.tzinfo is not None:
                parsed.astimezone(UTC)  # the column stores UTC
        except (ValueError, OverflowError):
            parsed = None
        if parsed is None or parsed.tzinfo is None:
            raise ArchiveInvalid(
                f"{where}: {value!r} is not a datetime with a UTC offset (within years 1–9999 "
                "in UTC)"
            )
        return parsed
    if isinstance(kind, JSON):
        fault = json_text_fault(value, where)
        if fault is not None:
            path, reason = fault  # "…: warnings[1]" "holds a NUL …"; "…: params" "a key holds …"
            raise ArchiveInvalid(f"{path}{':' if reason.startswith('a key') else ''} {reason}")
        return value
    checks: tuple[tuple[type[Any], Callable[[Any], bool]], ...] = (
        (Boolean, lambda v: isinstance(v, bool)),
        (Integer, is_int),
        (Float, lambda v: is_int(v) or isinstance(v, float)),
        (String, lambda v: isinstance(v, str)),
        (LargeBinary, lambda _v: False),
    )
    for type_, accepts in checks:
        if isinstance(kind, type_):
            if not accepts(value):
                raise ArchiveInvalid(f"{where}: expected {type_.__name__.lower()}, got {value!r}")
            if type_ is Integer:
                _check_integer(kind, value, where)
            elif type_ is Float:
                try:
                    return float(value)
                except OverflowError:
                    raise ArchiveInvalid(f"{where}: {value} is beyond a float's range") from None
            elif type_ is String:
                _check_text(value, where, getattr(kind, "length", None))
            return value
    raise ArchiveInvalid(f"{where}: a column of type {kind} cannot be imported")


#: The range of each integer column type, the same on SQLite and PostgreSQL (SQLite's integers
#: are 64-bit; PostgreSQL's INTEGER is 32-bit): an archive imports into either.
INTEGER_BITS = ((SmallInteger, 16), (BigInteger, 64), (Integer, 32))


def _check_integer(kind: Any, value: int, where: str) -> None:
    bits = next(bits for type_, bits in INTEGER_BITS if isinstance(kind, type_))
    if not -(2 ** (bits - 1)) <= value < 2 ** (bits - 1):
        raise ArchiveInvalid(
            f"{where}: {value} is beyond the column's {bits}-bit integers "
            f"({-(2 ** (bits - 1))} to {2 ** (bits - 1) - 1})"
        )


def _length(model: type[Any], column: str) -> int | None:
    """The length of a string column."""
    length: int | None = getattr(model.__table__.c[column].type, "length", None)
    return length


def _check_text(value: str, where: str, max_length: int | None) -> None:
    """Text by the rule of every stored text, within the column's length (which PostgreSQL
    enforces and SQLite does not)."""
    reason = text_fault(value)
    if reason is not None:
        raise ArchiveInvalid(
            f"{where} {reason}: correct it where the archive was exported (the API and the "
            "dashboard now refuse such text) and export again"
        )
    if max_length is not None and len(value) > max_length:
        raise ArchiveInvalid(
            f"{where}: {len(value)} characters, more than the column's {max_length}"
        )


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


def _added_later(spec: TableSpec, name: str) -> bool:
    """Whether an archive written before column ``name`` existed may lack it: the column is
    nullable or has a server default, which the row then gets."""
    column = spec.table.columns[name]
    return bool(column.nullable) or column.server_default is not None
