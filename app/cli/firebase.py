"""The ``import-firebase`` subcommand of ``invisible-map``: a lab's recorded maps moved over.

    invisible-map import-firebase DIR

``DIR`` holds what a lab exports from the Firebase project the app used: the Realtime Database's
JSON export (``maps/<uid>/<mapId>``, ``unprocessed_maps/…``) and the Storage folder
``rawMapData/<uid>/<mapId>.json`` with the pictures (how it is read:
``app/domain/formats/firebase_export.py``; how each recording is uploaded:
``app/services/firebase_import.py``). Every recording is uploaded
once into the database in ``DATABASE_URL`` (with its owner, typed name and picture), and its map
is queued for building by the workers. Running it again takes nothing twice. It ends with a
summary: what was taken, what was there already, and what was refused and why (one line each,
``refused: <uid>/<mapId>: <reason>``; a recording that fails in a way no rule names is refused
too, and the import goes on); the exit status is 1 when anything was refused (the rest is
imported all the same).
"""

from __future__ import annotations

import argparse
import sys
from collections import Counter
from pathlib import Path
from typing import Any

from app.cli.common import CommandError, first_line, load_settings, open_migrated, safe_url


def add_firebase_commands(commands: Any) -> None:
    """Register import-firebase on the ``invisible-map`` subparsers."""
    parser = commands.add_parser(
        "import-firebase",
        help="upload a lab's recordings from a Firebase export (Realtime Database JSON and the "
        "Storage folder rawMapData/)",
        description="Upload every recording of a Firebase export into the database in "
        "DATABASE_URL, once: the Realtime Database export (a top-level *.json with 'maps' or "
        "'unprocessed_maps') and the Storage folder rawMapData/<uid>/<mapId>.json with the "
        "pictures. Each keeps its owner (uploaded_by firebase:<uid>), its typed name and its "
        "picture; its map is queued for the workers. Running it again takes nothing twice.",
    )
    parser.add_argument("directory", type=Path, metavar="DIR", help="the export folder")
    parser.set_defaults(handler=_import_firebase)


def _import_firebase(args: argparse.Namespace) -> int:
    from sqlalchemy.exc import SQLAlchemyError
    from tqdm import tqdm

    from app.domain.formats.firebase_export import FirebaseExportError, read_firebase_export
    from app.services.firebase_import import ImportOutcome, ImportStatus, import_recording

    try:
        export = read_firebase_export(args.directory)
    except FirebaseExportError as err:
        raise CommandError(str(err)) from err
    settings = load_settings()
    database = open_migrated(settings)
    outcomes = []
    try:
        with tqdm(
            export.maps, desc="import", unit=" maps", leave=False, disable=None, file=sys.stderr
        ) as bar:
            for entry in bar:
                bar.set_postfix_str(shown(entry.key)[:40], refresh=False)
                try:
                    outcome = import_recording(
                        database,
                        entry,
                        max_attempts=settings.max_attempts,
                        max_session_bytes=settings.max_session_bytes,
                        max_poses=settings.max_poses,
                    )
                except SQLAlchemyError:
                    raise
                except Exception as err:  # a fault no rule names: this recording only
                    outcome = ImportOutcome(
                        key=entry.key,
                        status=ImportStatus.REFUSED,
                        reason=f"cannot be read ({type(err).__name__}: {first_line(err)})",
                    )
                outcomes.append(outcome)
    except SQLAlchemyError as err:  # the database itself (a bad recording is refused, not this)
        raise CommandError(
            f"stopped after {len(outcomes)} of {len(export.maps)} recording(s) (those are "
            f"imported; run it again to go on): {first_line(err)}"
        ) from err
    finally:
        database.dispose()

    counts = Counter(outcome.status for outcome in outcomes)
    for note in export.notes:
        print(f"note: {shown(note)}")
    for outcome in outcomes:
        if outcome.status == ImportStatus.TAKEN:
            print(
                f"taken: {shown(outcome.key)} → session {outcome.session_id}, map "
                f"{outcome.map_id} ({outcome.picture})"
            )
        elif outcome.status == ImportStatus.REFUSED:
            print(f"refused: {shown(outcome.key)}: {shown(outcome.reason or '')}")
    print(
        f"{len(outcomes)} recording(s) in {args.directory} → {safe_url(settings)}: "
        f"{counts[ImportStatus.TAKEN]} taken, {counts[ImportStatus.ALREADY_THERE]} already "
        f"there, {counts[ImportStatus.REFUSED]} refused"
    )
    return 1 if counts[ImportStatus.REFUSED] else 0


def shown(text: str) -> str:
    """``text`` as printed: what the export names (user ids, map ids, names) may hold control
    characters (a NUL, a terminal's escape sequences, a newline), written as escapes."""
    if text.isprintable():
        return text
    return "".join(c if c.isprintable() else c.encode("unicode_escape").decode() for c in text)
