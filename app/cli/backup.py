"""The ``export`` and ``import`` subcommands of ``invisible-map``: backups of a deployment.

    invisible-map export OUT.zip [--include-keys] [--force]
    invisible-map import ARCHIVE.zip [--include-keys] [--merge]
    invisible-map import ARCHIVE.zip --check        # verify it; no database is touched

``export`` writes every session (its upload byte for byte), map, map version, build job and sweep
of the database in ``DATABASE_URL`` to one zip archive; ``import`` puts such an archive into
another migrated database, SQLite or PostgreSQL, in one transaction. The archive format and what
it holds are in ``app/storage/backup.py``. Settings come from the environment, as for the server
commands (``app/cli/server.py``); heavy imports happen inside the handlers.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any

from app.cli.common import CommandError, first_line, load_settings, open_migrated, safe_url

if TYPE_CHECKING:
    from app.storage.backup import ImportReport, Manifest

#: The tables a summary line names, with their names for people.
SUMMARY_TABLES = (
    ("session", "sessions"),
    ("map", "maps"),
    ("map_version", "map versions"),
    ("sweep", "sweeps"),
    ("api_key", "API keys"),
)


def add_backup_commands(commands: Any) -> None:
    """Register export and import on the ``invisible-map`` subparsers."""
    export = commands.add_parser(
        "export",
        help="write the sessions, maps and sweeps to one archive file (a backup)",
        description="Write every session (its raw upload byte for byte), map, map version, "
        "build job and sweep of the database in DATABASE_URL to OUT, a zip archive that "
        "`invisible-map import` reads into SQLite or PostgreSQL. The database is read in one "
        "snapshot, so the server may keep running.",
    )
    export.add_argument("out", type=Path, metavar="OUT", help="the archive to write (.zip)")
    export.add_argument(
        "--include-keys",
        action="store_true",
        help="also the API keys' SHA-256 hashes, so the same keys work where it is imported "
        "(keep such an archive as safe as the keys)",
    )
    export.add_argument("--force", action="store_true", help="replace OUT if it exists")
    export.set_defaults(handler=_export)

    restore = commands.add_parser(
        "import",
        help="read an archive written by `export` into the database",
        description="Import ARCHIVE into the database in DATABASE_URL in one transaction: all "
        "of it or, on any error, nothing. Into a freshly migrated database the archive's ids "
        "are kept (phones refer to maps by id); a database that has data is refused unless "
        "--merge.",
    )
    restore.add_argument("archive", type=Path, metavar="ARCHIVE", help="an `export` archive")
    restore.add_argument(
        "--include-keys",
        action="store_true",
        help="import the API keys too (the archive must have been exported with --include-keys)",
    )
    restore.add_argument(
        "--merge",
        action="store_true",
        help="add the archive to a database that has data: every row gets a new id, and the "
        "new map ids are printed",
    )
    restore.add_argument(
        "--check",
        action="store_true",
        help="only verify the archive (its format and schema revision, every member's size and "
        "checksum, every row as an import would check it) and say what it holds; no database is "
        "touched",
    )
    restore.set_defaults(handler=_import)


# --------------------------------------------------------------------------- commands


def _export(args: argparse.Namespace) -> int:
    from sqlalchemy.exc import SQLAlchemyError

    from app.storage import backup

    out: Path = args.out
    if out.is_dir():
        raise CommandError(f"{out} is a directory; give the archive's file name")
    if out.exists() and not args.force:
        raise CommandError(f"{out} exists; pass --force to replace it")
    settings = load_settings()
    database = open_migrated(settings)
    try:
        with _progress_bar("export") as on_progress:
            manifest = backup.export_archive(
                database, out, include_key_hashes=args.include_keys, on_progress=on_progress
            )
    except backup.BackupError as err:
        raise CommandError(str(err)) from err
    except SQLAlchemyError as err:
        raise CommandError(f"cannot export {safe_url(settings)}: {first_line(err)}") from err
    finally:
        database.dispose()
    size_mb = out.stat().st_size / 1e6
    keys = " (names only)" if manifest.counts["api_key"] and not args.include_keys else ""
    _say(
        f"exported {_summary(manifest.counts)}{keys} from {safe_url(settings)} to {out} "
        f"({size_mb:.1f} MB, schema revision {manifest.schema_revision})"
    )
    if args.include_keys:
        _say("the archive holds the API keys' hashes: keep it as safe as the keys", err=True)
    return 0


def _import(args: argparse.Namespace) -> int:
    from sqlalchemy.exc import SQLAlchemyError

    from app.storage import backup
    from app.storage.migrate import head_revision

    settings = load_settings()
    limit = settings.max_session_bytes  # the largest upload (or other member) read whole
    try:  # the archive first: its problems do not depend on the database
        manifest = backup.read_manifest(args.archive)
        backup.check_schema_revision(manifest.schema_revision, head_revision())
        if args.check:
            with _progress_bar("check") as on_progress:
                manifest = backup.check_archive(
                    args.archive, max_member_bytes=limit, on_progress=on_progress
                )
    except backup.BackupError as err:
        raise CommandError(str(err)) from err
    if args.check:
        keys = "with" if manifest.key_hashes else "without"
        _say(
            f"{args.archive}: a valid backup of {_summary(manifest.counts)} ({keys} key "
            f"hashes), exported {manifest.created_at:%Y-%m-%d %H:%M:%S} UTC from "
            f"{manifest.source_backend} at schema revision {manifest.schema_revision}; "
            f"{len(manifest.members)} members, every checksum matches, every row fits"
        )
        return 0
    database = open_migrated(settings)
    try:
        with _progress_bar("import") as on_progress:
            report = backup.import_archive(
                database,
                args.archive,
                include_keys=args.include_keys,
                merge=args.merge,
                on_progress=on_progress,
                max_member_bytes=limit,
            )
    except backup.BackupError as err:
        raise CommandError(f"nothing imported: {err}") from err
    except SQLAlchemyError as err:
        raise CommandError(
            f"nothing imported into {safe_url(settings)}: {first_line(err)}"
        ) from err
    finally:
        database.dispose()
    _report_import(
        report, manifest, into=safe_url(settings), archive=args.archive, keys=args.include_keys
    )
    return 0


def _report_import(
    report: ImportReport, manifest: Manifest, *, into: str, archive: Path, keys: bool
) -> None:
    """What was imported (stdout; a merge's new map ids one per line) and notes (stderr)."""
    how = "new ids" if report.merged else "ids kept"
    _say(f"imported {_summary(report.counts)} from {archive} into {into} ({how})")
    if report.merged:
        for old, new in sorted(report.map_ids.items()):
            _say(f"map {old} -> {new}")
    if queued := len(report.queued_job_ids):
        _say(
            f"build jobs queued (unfinished at export; workers will run them): {queued}",
            err=True,
        )
    if manifest.counts["api_key"] and not keys:
        _say(
            "API keys were not imported; their sessions' uploaded_by names the key's prefix "
            "(imported:im_…)",
            err=True,
        )


@contextmanager
def _progress_bar(what: str) -> Iterator[Callable[[int, int], None]]:
    """A tqdm bar on stderr (none when stderr is not a terminal) and the callback moving it."""
    from tqdm import tqdm

    with tqdm(desc=what, unit=" rows", leave=False, disable=None, file=sys.stderr) as bar:

        def on_progress(done: int, total: int) -> None:
            bar.total = total
            bar.update(done - bar.n)

        yield on_progress


def _summary(counts: dict[str, int]) -> str:
    return ", ".join(f"{counts.get(table, 0)} {name}" for table, name in SUMMARY_TABLES)


def _say(line: str, *, err: bool = False) -> None:
    print(line, file=sys.stderr if err else sys.stdout)
