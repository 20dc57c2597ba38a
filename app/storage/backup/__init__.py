"""Backups: a deployment's sessions, maps and sweeps in one archive file, and back into a database.

    manifest = export_archive(db, Path("im-backup.zip"))                 # one consistent snapshot
    manifest = read_manifest(Path("im-backup.zip"))                      # no database needed
    manifest = check_archive(Path("im-backup.zip"))       # every member and row, no database
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

What a worker derived from a version (its app-map and dashboard overview,
``app.domain.formats.derived_documents``) is not in the archive: an import makes it again from the
version's map document, path graph and session (``app.storage.derived``), in its transaction,
so a restored version is served as stored, like one a worker built (about 3 s and 100 MiB of
the importing process per 100,000 poses).

In the JSON rows datetimes are ISO 8601 strings with their UTC offset, and a binary column holds
the name of the member with its bytes (or null). Of the queue only ``build_map`` jobs are in it:
finished and queued ones as they are (so a version still names its job, and a phone's job URL
and idempotent replay keep working), a running one as queued again without the source's lease.
``sweep_trials`` jobs are not: their trials' ``job_id`` is null, and a sweep still running is
marked canceled. API keys are in it by name and prefix (to name the uploaders), with their
SHA-256 hashes only when asked (``include_key_hashes``; the file is created readable by its owner
only). Live localization sessions and worker rows are not in it, nor how long jobs' stages took
(``job_stage``), nor the building maps' incremental state (``isam_state``, ``isam_walk_state``:
derivable, ``app.storage.isam_states``): a restored map's next change is built the batch way,
and writes the state again.

**Import** runs in one transaction, and checks the whole archive (every member's size and SHA-256,
the set of members; each size before anything is inflated, a member read whole at most
``max_member_bytes``) before it writes anything, and every row before it is written (its values'
types, integer ranges, text, references, and each upload against its session's size and SHA-256:
``restore``'s docstring), so that any archive it cannot take is refused naming the member or row, in
bounded memory. ``check_archive`` makes the same checks without a database. Into a database with no
sessions, maps, jobs or sweeps it *restores*: every id is kept (phones refer to maps by id), and the
id sequences are raised to the source's high-water marks so that an id deleted there is never given
out again (on PostgreSQL that is the last statement: sequences ignore rollbacks). Into a database
with data it refuses, unless ``merge=True``: then every row gets a new id (the report maps old to
new). Without keys imported, ``uploaded_by`` ``key:N`` becomes ``imported:im_<prefix>``, so that no
key of the new deployment owns another's sessions.

Exceptions::

    BackupError
    ├── ArchiveInvalid       not a backup archive, truncated or corrupt, a member or row that
    │                        does not match the manifest or the schema
    ├── ArchiveIncompatible  a newer format version, or another schema revision than the database
    └── ImportRefused        restore into a database with data, merge clashes, keys asked for
                             but not in the archive

The package: ``archive`` (the format: manifest, tables, members, errors, reading), ``export``,
``restore`` (import).
"""

from __future__ import annotations

from app.storage.backup.archive import (
    FORMAT,
    FORMAT_VERSION,
    MANIFEST,
    TABLES,
    ArchiveIncompatible,
    ArchiveInvalid,
    BackupError,
    ImportRefused,
    ImportReport,
    Manifest,
    Member,
    Progress,
    check_schema_revision,
    read_manifest,
    verify_archive,
)
from app.storage.backup.export import export_archive
from app.storage.backup.restore import check_archive, import_archive

__all__ = [
    "FORMAT",
    "FORMAT_VERSION",
    "MANIFEST",
    "TABLES",
    "ArchiveIncompatible",
    "ArchiveInvalid",
    "BackupError",
    "ImportRefused",
    "ImportReport",
    "Manifest",
    "Member",
    "Progress",
    "check_archive",
    "check_schema_revision",
    "export_archive",
    "import_archive",
    "read_manifest",
    "verify_archive",
]
