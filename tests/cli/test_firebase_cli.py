"""``invisible-map import-firebase DIR`` (``app/cli/firebase.py``) on an export tree built from the
sessions in data/, against SQLite and PostgreSQL: every recording once, with its owner, name and
picture; a second run takes nothing twice; what cannot be taken is refused with the reason."""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from cli_support import assert_one_line_error

from app import cli
from app.storage import images, maps, queue, sessions
from app.storage.db import Database
from tests.unit.test_firebase_export import JPEG, make_export

pytestmark = pytest.mark.db

RunMain = Callable[..., tuple[int, str, str]]


@pytest.fixture
def run_main(capsys: pytest.CaptureFixture[str], env: pytest.MonkeyPatch) -> RunMain:
    def run(database: str, *args: Any) -> tuple[int, str, str]:
        env.setenv("DATABASE_URL", database)
        capsys.readouterr()
        status = cli.main([str(a) for a in args])
        out, err = capsys.readouterr()
        return status, out, err

    return run


def stored(url: str) -> dict[str, dict[str, Any]]:
    """map id (the upload's) → what the database holds of it."""
    db = Database(url)
    found = {}
    with db.read() as tx:
        for info in sessions.list_sessions(tx, limit=100)[0]:
            assert info.map_id is not None
            map_info = maps.get_map(tx, info.map_id)
            found[info.map_name] = {
                "owner": info.uploaded_by,
                "display_name": map_info.display_name,
                "raw": sessions.raw_upload(tx, info.id),
                "picture": images.map_image(tx, info.map_id),
                "jobs": [job.kind for job in queue.list_jobs(tx, map_id=info.map_id)[0]],
            }
    db.dispose()
    return found


def test_every_recording_is_imported_once_with_its_owner_name_and_picture(
    database_url: str, tmp_path: Path, run_main: RunMain
) -> None:
    export = make_export(tmp_path / "export")

    status, out, _ = run_main(database_url, "import-firebase", export)

    assert status == 1  # dave's file is missing: refused, the rest imported
    assert "4 taken, 0 already there, 1 refused" in out
    assert "refused: dave/Gone: its session file rawMapData/dave/Gone.json is not in" in out
    assert "taken: alice/Lab 1700000000 → session" in out
    assert "(picture kept)" in out
    db = stored(database_url)
    occam_map_id = json.loads((export / "rawMapData/alice/Lab 1700000000.json").read_bytes())[
        "map_id"
    ]
    assert len(db) == 4
    lab = db[occam_map_id]
    assert lab["owner"] == "firebase:alice"
    assert lab["display_name"] == "Lab"  # the name typed in the app, from maps/<uid>/<id>/name
    assert lab["raw"] == (export / "rawMapData/alice/Lab 1700000000.json").read_bytes()
    assert lab["picture"].jpeg == JPEG
    assert lab["jobs"] == ["build_map"]
    owners = sorted(entry["owner"] for entry in db.values())
    assert owners == ["firebase:alice", "firebase:alice", "firebase:bob", "firebase:carol"]

    again, out, _ = run_main(database_url, "import-firebase", export)

    assert again == 1
    assert "0 taken, 4 already there, 1 refused" in out
    assert stored(database_url).keys() == db.keys()


def test_a_changed_file_a_broken_session_and_a_bad_picture_are_reported(
    database_url: str, tmp_path: Path, run_main: RunMain
) -> None:
    export = make_export(tmp_path / "export")
    (export / "rawMapData/dave").mkdir()
    (export / "rawMapData/dave/Gone.json").write_text('{"map_id": "x", "pose_data": [')
    (export / "rawMapData/alice/Lab 1700000000.jpg").write_bytes(b"GIF89a not a jpeg")
    assert run_main(database_url, "import-firebase", export)[0] == 1
    hall = export / "rawMapData/alice/Hall 1700000500.json"
    changed = json.loads(hall.read_bytes())
    changed["pose_data"] = changed["pose_data"][:-1]
    hall.write_text(json.dumps(changed))

    status, out, _ = run_main(database_url, "import-firebase", export)

    assert status == 1
    assert "refused: dave/Gone: not a session the server takes: " in out
    assert "not valid JSON" in out
    assert "refused: alice/Hall 1700000500: imported before from a different file" in out
    assert "0 taken, 3 already there, 2 refused" in out
    first_out = stored(database_url)
    assert all(entry["picture"] is None for entry in first_out.values())


def test_the_picture_skipped_is_said_in_the_summary(
    database_url: str, tmp_path: Path, run_main: RunMain
) -> None:
    export = make_export(tmp_path / "export")
    (export / "rawMapData/alice/Lab 1700000000.jpg").write_bytes(b"\xff\xd8\xff" + b"\0" * 9)
    _, out, _ = run_main(database_url, "import-firebase", export)
    assert "picture skipped: the JPEG is cut short" in out


def test_a_folder_that_is_no_export_is_one_line_error(
    database_url: str, tmp_path: Path, run_main: RunMain
) -> None:
    status, _, err = run_main(database_url, "import-firebase", tmp_path / "missing")
    assert_one_line_error(status, err, "is not a folder")
    status, _, err = run_main(database_url, "import-firebase", tmp_path)
    assert_one_line_error(status, err, "neither a Realtime Database export")


def test_long_or_odd_uids_are_hashed_into_the_owner_column() -> None:
    from app.services.firebase_import import owner_of

    assert owner_of("abc") == "firebase:abc"
    long_uid = "u" * 100
    digest = hashlib.sha256(long_uid.encode()).hexdigest()[:40]
    assert owner_of(long_uid) == f"firebase:sha256:{digest}"
    assert len(owner_of("ü" * 10)) <= 64
