"""What the command groups share: the program's name and data, its error, settings and database.

    settings = load_settings()                    # from the environment; CommandError if invalid
    database = open_migrated(settings)            # CommandError unless reachable and migrated
    add_param_option(parser); params = slam_params(args.param)
    session = load_session_file(path)              # bounded, regular files only (also
    truth = load_ground_truth_file(path)           # read_input_file: the bytes, inflated)

Every failure a person can fix is a :class:`CommandError`, printed by ``main`` as one line.
Every file a command reads is read through :func:`read_input_file` (or, for archives and
exports, ``app.storage.backup`` and ``app.domain.formats.firebase_export``, which check the same
way): a FIFO, a device or a folder is refused at once, and no file is read, or inflated, beyond
a bound.
"""

from __future__ import annotations

import argparse
import os
import stat
import zlib
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from app.domain.errors import ParameterError
from app.domain.json_values import value_error_reason

if TYPE_CHECKING:
    from app.config import Settings
    from app.domain.frames import FloatArray
    from app.domain.mapping.params import SlamParams
    from app.domain.upload.session import Session
    from app.storage.db import Database

PROGRAM = "invisible-map"

#: The largest file a command reads (a session, a ground truth, ``--space``), bytes, and the
#: most a gzip one may inflate to: the server's own default limit on an upload
#: (``INVISIBLE_MAP_MAX_SESSION_BYTES``).
MAX_INPUT_BYTES = 256 * 2**20


#: The demo sessions and their ground truth, shipped in the repository (see data/README.md).
DATA_DIR = Path(__file__).resolve().parents[2] / "data"


DEMO_SESSIONS = (
    ("occam_room", "occam_room_tape.json"),
    ("floor_2_straight", "rtabmap_mac_1_2.txt"),
    ("straight_209_occam", "rtabmap_mac_1_2.txt"),
    ("desnat_straight_once", "rtabmap_mac_1_2.txt"),
    ("pgt_tester3", None),
    ("singletag3times", None),
    ("onetag", None),
)
#: The demo session with points of interest (the README's quick start): floor_2_straight with
#: three added to its ``location_data``, so floor_2_straight's ground truth.
DEMO_POI_SESSION = ("floor_2_pois", "rtabmap_mac_1_2.txt")


class CommandError(Exception):
    """A readable reason the command cannot go on."""


def load_settings(**overrides: Any) -> Settings:
    from pydantic import ValidationError

    from app.config import Settings

    try:
        settings = Settings()
    except ValidationError as err:
        first = err.errors()[0]
        where = ".".join(str(part) for part in first["loc"]) or "settings"
        raise CommandError(f"{where}: {first['msg']}") from err
    return settings.model_copy(update=overrides) if overrides else settings


def open_database(settings: Settings) -> Database:
    from sqlalchemy.exc import SQLAlchemyError

    from app.storage.db import Database

    try:
        database = Database(settings.resolved_database_url)
        database.ping()
    except (SQLAlchemyError, ValueError) as err:
        raise CommandError(
            f"cannot use the database {safe_url(settings)}: {first_line(err)}"
        ) from err
    return database


def migrate_database(database: Database, settings: Settings) -> str:
    from sqlalchemy.exc import SQLAlchemyError

    from app.storage.migrate import current_revision, upgrade_to_head

    try:
        upgrade_to_head(database)
        return current_revision(database) or "empty"
    except SQLAlchemyError as err:
        raise CommandError(
            f"cannot migrate the database {safe_url(settings)}: {first_line(err)}"
        ) from err


def safe_url(settings: Settings) -> str:
    from sqlalchemy import make_url

    try:
        return make_url(settings.resolved_database_url).render_as_string(hide_password=True)
    except Exception:  # an unparsable URL: show nothing of it
        return "(DATABASE_URL)"


def first_line(err: BaseException) -> str:
    from app.storage.db import first_line as database_first_line  # (imports SQLAlchemy lazily)

    return database_first_line(err)


def open_migrated(settings: Settings) -> Database:
    from app.storage.migrate import is_current

    database = open_database(settings)
    if not is_current(database):
        database.dispose()
        raise CommandError(
            f"the database {safe_url(settings)} is not migrated; run `invisible-map migrate`"
        )
    return database


def add_param_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--param",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="override a SLAM parameter (see SlamParams), e.g. tag_position_var_m2=1e-4",
    )


def slam_params(pairs: Sequence[str]) -> SlamParams:
    from app.domain.mapping.params import SlamParams

    overrides = {}
    for pair in pairs:
        name, sep, value = pair.partition("=")
        if not sep or not name.strip():
            shown = pair if len(pair) <= 60 else pair[:59] + "…"  # one readable line
            raise ParameterError(f"--param expects NAME=VALUE, got {shown!r}")
        overrides[name.strip()] = value.strip()
    return SlamParams().with_checked_overrides(overrides)  # each within its range, as the API's


def read_input_file(path: Path, *, max_bytes: int | None = None) -> bytes:
    """The bytes of the file ``path``, inflated if they are gzip. CommandError (one line) for
    what is not a regular file (a FIFO would hang, ``/dev/zero`` would be read without end:
    refused at once, by its status before it is opened and again on the descriptor, opened
    without blocking), for a file of more than ``max_bytes`` (checked before it is read, read no
    further than ``max_bytes`` + 1) and for gzip that inflates further (inflated no further);
    OSError (missing, unreadable) as the system says it. ``max_bytes``: :data:`MAX_INPUT_BYTES`
    unless given."""
    max_bytes = MAX_INPUT_BYTES if max_bytes is None else max_bytes
    if not stat.S_ISREG(os.stat(path).st_mode):
        raise CommandError(f"{path} is not a regular file (a FIFO, a device or a folder)")
    descriptor = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
    with os.fdopen(descriptor, "rb", buffering=0) as file:
        status = os.fstat(descriptor)
        if not stat.S_ISREG(status.st_mode):
            raise CommandError(f"{path} is not a regular file (a FIFO, a device or a folder)")
        if status.st_size > max_bytes:
            raise CommandError(f"{path} ({status.st_size} bytes) is larger than {max_bytes} bytes")
        data = bytearray()
        while len(data) <= max_bytes and (chunk := file.read(max_bytes + 1 - len(data))):
            data += chunk
    if len(data) > max_bytes:  # it grew since
        raise CommandError(f"{path} is larger than {max_bytes} bytes")
    if data[:2] != b"\x1f\x8b":
        return bytes(data)
    return _inflated(bytes(data), path, max_bytes=max_bytes)


def _inflated(raw: bytes, path: Path, *, max_bytes: int) -> bytes:
    """Gzip ``raw`` (every member) inflated no further than ``max_bytes``."""
    pieces: list[bytes] = []
    size, rest = 0, raw
    try:
        while rest:
            inflater = zlib.decompressobj(wbits=16 + zlib.MAX_WBITS)
            piece = inflater.decompress(rest, max_bytes + 1 - size)
            pieces.append(piece)
            size += len(piece)
            if size > max_bytes or inflater.unconsumed_tail:
                raise CommandError(f"{path} inflates to more than {max_bytes} bytes")
            if not inflater.eof:
                raise CommandError(f"{path} is not valid gzip: cut short")
            rest = inflater.unused_data
    except zlib.error as err:
        raise CommandError(f"{path} is not valid gzip: {err}") from None
    return b"".join(pieces)


def load_session_file(path: Path, *, correct_poi_pose_id: bool = True) -> Session:
    """The session in the file ``path`` (JSON, may be gzip), read by :func:`read_input_file`;
    SessionFormatError naming the file and the fault."""
    from app.domain.upload.session import decode_json_bytes, parse_session

    document = decode_json_bytes(read_input_file(path), source=str(path))
    return parse_session(document, correct_poi_pose_id=correct_poi_pose_id)


def load_ground_truth_file(path: Path) -> dict[int, FloatArray]:
    """The tag poses of the ground-truth file ``path`` (either form, may be gzip), read by
    :func:`read_input_file`; GroundTruthFormatError naming the file and the fault."""
    from app.domain.errors import GroundTruthFormatError
    from app.domain.evaluation.ground_truth import parse_ground_truth_text

    try:
        text = read_input_file(path).decode("utf-8")
    except UnicodeDecodeError as err:
        raise GroundTruthFormatError(f"{path}: not UTF-8 text: {err.reason}") from None
    try:
        return parse_ground_truth_text(text)
    except GroundTruthFormatError as err:
        raise GroundTruthFormatError(f"{path}: {err}") from err
    except RecursionError:
        raise GroundTruthFormatError(f"{path}: nested too deeply to be a ground truth") from None
    except ValueError as err:  # an integer of more digits than Python converts
        reason = value_error_reason(err)
        raise GroundTruthFormatError(f"{path}: not valid JSON: {reason}") from None
