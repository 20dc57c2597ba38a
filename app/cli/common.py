"""What the command groups share: the program's name and data, its error, settings and database.

    settings = load_settings()                    # from the environment; CommandError if invalid
    database = open_migrated(settings)            # CommandError unless reachable and migrated
    add_param_option(parser); params = slam_params(args.param)

Every failure a person can fix is a :class:`CommandError`, printed by ``main`` as one line.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from app.domain.errors import ParameterError

if TYPE_CHECKING:
    from app.config import Settings
    from app.domain.mapping.params import SlamParams
    from app.storage.db import Database

PROGRAM = "invisible-map"


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
            raise ParameterError(f"--param expects NAME=VALUE, got {pair!r}")
        overrides[name.strip()] = value.strip()
    return SlamParams().with_overrides(overrides)
