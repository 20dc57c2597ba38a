"""``invisible-map import-firebase DIR`` (``app/cli/firebase.py``) on an export tree built from the
sessions in data/, against SQLite and PostgreSQL: every recording once, with its owner, name and
picture; a second run takes nothing twice; what cannot be taken is refused with the reason."""

from __future__ import annotations

import gzip
import hashlib
import json
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from cli_support import assert_one_line_error

from app import cli
from app.storage import images, maps, queue, sessions
from app.storage.db import Database
from tests.service.helpers import session_bytes
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


def add_recording(
    export: Path, uid: str, map_id: str, data: bytes, name: str | None = None
) -> None:
    """A recording in Storage, and with ``name`` an entry of the database export too."""
    (export / "rawMapData" / uid).mkdir(parents=True, exist_ok=True)
    (export / "rawMapData" / uid / f"{map_id}.json").write_bytes(data)
    if name is not None:
        database_file = export / "invisible-map-sandbox-export.json"
        database = json.loads(database_file.read_text())
        database["maps"].setdefault(uid, {})[map_id] = {"name": name}
        database_file.write_text(json.dumps(database))


def session_with(**changes: Any) -> bytes:
    document = json.loads(session_bytes("onetag"))
    document.update(changes)
    return json.dumps(document).encode()


#: recording → (how to make it, in the export folder and a folder outside it; the reason said)
BAD_RECORDINGS: dict[str, tuple[Callable[[Path, Path], None], str]] = {
    "mallory/linked-out": (
        lambda export, outside: (
            (export / "rawMapData/mallory").mkdir()
            or (export / "rawMapData/mallory/linked-out.json").symlink_to(outside / "secret.json")
        ),
        "linked-out.json is a link leading out of the export folder",
    ),
    "trudy/in-a-linked-folder": (
        lambda export, outside: _linked_folder(export, outside, "trudy", "in-a-linked-folder"),
        "in-a-linked-folder.json is a link leading out of the export folder",
    ),
    "erin/absolute": (
        lambda export, outside: (
            add_recording(export, "erin", "placeholder", b"{}")
            or _database_entry(export, "erin", "absolute", str(outside / "secret.json"))
        ),
        "is not in the Storage export",
    ),
    "erin/dotdot": (
        lambda export, _outside: _database_entry(export, "erin", "dotdot", "../secret.json"),
        "is not in the Storage export",
    ),
    "frank/fifo": (
        lambda export, _outside: (
            (export / "rawMapData/frank").mkdir()
            or os.mkfifo(export / "rawMapData/frank/fifo.json")
        ),
        "is not a regular file",
    ),
    "grace/huge": (
        lambda export, _outside: (
            (export / "rawMapData/grace").mkdir()
            or os.truncate(_touch(export / "rawMapData/grace/huge.json"), 64 * 2**20)
        ),
        "huge.json (67108864 bytes) is larger than 1048576 bytes",
    ),
    "heidi/gzip-bomb": (
        lambda export, _outside: add_recording(
            export, "heidi", "gzip-bomb", gzip.compress(b" " * (8 * 2**20))
        ),
        "gzip-bomb.json inflates to more than 1048576 bytes",
    ),
    "ivan/nul-in-the-name": (
        lambda export, _outside: add_recording(
            export, "ivan", "nul-in-the-name", session_with(map_id="ivan 1"), name="Lab\x003"
        ),
        "its name (maps/<uid>/<mapId>/name) holds a NUL character",
    ),
    "judy/nul-in-the-map-id": (
        lambda export, _outside: add_recording(
            export, "judy", "nul-in-the-map-id", session_with(map_id="judy\x00")
        ),
        "map_id: holds a NUL character",
    ),
    "ken/surrogate-in-a-poi": (
        lambda export, _outside: add_recording(
            export,
            "ken",
            "surrogate-in-a-poi",
            session_with(
                location_data=[
                    {
                        "name": "\ud800",
                        "pose_id": 1,
                        "timestamp": 0.0,
                        "transform": [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1],
                    }
                ]
            ),
        ),
        "location_data[0].name: holds a lone surrogate",
    ),
    "leo/deep": (
        lambda export, _outside: add_recording(
            export,
            "leo",
            "deep",
            b'{"map_id": "x", "extra": ' + b"[" * 200_000 + b"]" * 200_000 + b"}",
        ),
        "deep.json is nested too deeply to be a session",
    ),
    "aaron/huge-number": (  # first in the order: the recordings after it are imported
        lambda export, _outside: add_recording(
            export,
            "aaron",
            "huge-number",
            session_bytes("onetag")[:-1] + b', "extra": ' + b"7" * 5000 + b"}",
        ),
        "huge-number.json is not valid JSON: Exceeds the limit (4300 digits) for integer string "
        "conversion",
    ),
    "mia/not-json": (
        lambda export, _outside: add_recording(export, "mia", "not-json", b"\xff\xfe{"),
        "not-json.json is not UTF-8 text",
    ),
}


def _linked_folder(export: Path, outside: Path, uid: str, map_id: str) -> None:
    """A session in a folder outside, linked into Storage as ``uid``'s folder, and named in the
    database export too."""
    (outside / uid).mkdir()
    (outside / uid / f"{map_id}.json").write_bytes(session_bytes("onetag"))
    (export / "rawMapData" / uid).symlink_to(outside / uid)
    _database_entry(export, uid, map_id, f"rawMapData/{uid}/{map_id}.json")


def _touch(path: Path) -> Path:
    path.touch()
    return path


def _database_entry(export: Path, uid: str, map_id: str, raw_file: str) -> None:
    database_file = export / "invisible-map-sandbox-export.json"
    database = json.loads(database_file.read_text())
    database["maps"].setdefault(uid, {})[map_id] = {"name": map_id, "raw_file": raw_file}
    database_file.write_text(json.dumps(database))


def test_every_kind_of_bad_recording_is_refused_with_its_reason_and_the_rest_imported(
    database_url: str, tmp_path: Path, run_main: RunMain, env: pytest.MonkeyPatch
) -> None:
    """Issue 28, finding 3: links leading out were imported, a 1.2 GB file was read whole, a NUL
    in a name ended the whole import with a traceback on PostgreSQL."""
    env.setenv("INVISIBLE_MAP_MAX_SESSION_BYTES", str(2**20))
    export, outside = make_export(tmp_path / "export"), tmp_path / "outside"
    outside.mkdir()
    (outside / "secret.json").write_bytes(session_with(map_id="a secret"))
    for make, _ in BAD_RECORDINGS.values():
        make(export, outside)
    (export / "rawMapData/alice/Lab 1700000000.jpg").unlink()
    (export / "rawMapData/alice/Lab 1700000000.jpg").symlink_to(outside / "secret.json")

    status, out, err = run_main(database_url, "import-firebase", export)

    assert status == 1, err
    assert "Traceback" not in out + err
    refused = dict(
        line.removeprefix("refused: ").split(": ", 1)
        for line in out.splitlines()
        if line.startswith("refused: ")
    )
    for key, (_, reason) in BAD_RECORDINGS.items():
        assert reason in refused.get(key, ""), (key, refused.get(key))
    assert "erin/placeholder" in refused  # "{}" is no session
    assert "taken: alice/Lab 1700000000 → session" in out
    assert "picture skipped: Lab 1700000000.jpg is a link leading out of the export folder" in out
    db = stored(database_url)
    assert sorted(entry["owner"] for entry in db.values()) == [
        "firebase:alice", "firebase:alice", "firebase:bob", "firebase:carol"
    ]  # fmt: skip
    assert "a secret" not in db


def test_a_database_export_that_is_no_file_of_the_export_is_skipped_and_a_deep_one_refused(
    database_url: str, tmp_path: Path, run_main: RunMain
) -> None:
    export, outside = make_export(tmp_path / "export"), tmp_path / "outside"
    outside.mkdir()
    (outside / "other.json").write_text(json.dumps({"maps": {"zoe": {"x": {"name": "x"}}}}))
    (export / "linked.json").symlink_to(outside / "other.json")
    os.mkfifo(export / "fifo.json")
    status, out, err = run_main(database_url, "import-firebase", export)
    assert status == 1, err  # dave's file is missing, as ever
    assert "note: linked.json: skipped: linked.json is a link leading out of the export" in out
    assert "note: fifo.json: skipped: fifo.json is not a regular file" in out
    assert "zoe/x" not in out
    assert "4 taken" in out

    (export / "deep.json").write_bytes(b"[" * 200_000 + b"]" * 200_000)
    status, _, err = run_main(database_url, "import-firebase", export)
    assert_one_line_error(status, err, "deep.json is nested too deeply to be a database export")


def test_a_recording_failing_in_a_way_no_rule_names_is_refused_and_the_import_goes_on(
    database_url: str, tmp_path: Path, run_main: RunMain, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Issue 40, finding 1: a ValueError inside one recording's parsing ended the import with a
    traceback, and the recordings after it were never imported."""
    from app.services import firebase_import

    real_parse = firebase_import.parse_upload

    def failing_for_alice_lab(chunks: Any, **kwargs: Any) -> Any:
        if kwargs["source"] == "Lab 1700000000.json":
            raise ValueError("a fault of no rule")
        return real_parse(chunks, **kwargs)

    monkeypatch.setattr(firebase_import, "parse_upload", failing_for_alice_lab)
    status, out, err = run_main(database_url, "import-firebase", make_export(tmp_path / "export"))
    assert status == 1
    assert "Traceback" not in out + err
    assert (
        "refused: alice/Lab 1700000000: cannot be read (ValueError: a fault of no rule)"
        in out.splitlines()
    )
    assert "3 taken, 0 already there, 2 refused" in out  # and dave's missing file
    assert sorted(entry["owner"] for entry in stored(database_url).values()) == [
        "firebase:alice", "firebase:bob", "firebase:carol"
    ]  # fmt: skip


def test_a_database_export_with_a_number_python_does_not_read_is_one_line_error(
    database_url: str, tmp_path: Path, run_main: RunMain
) -> None:
    export = make_export(tmp_path / "export")
    (export / "big.json").write_bytes(b'{"maps": {"zoe": {"x": {"n": ' + b"9" * 5000 + b"}}}}")
    status, out, err = run_main(database_url, "import-firebase", export)
    assert_one_line_error(
        status, err, "big.json is not valid JSON: Exceeds the limit (4300 digits)"
    )
    assert out == ""
    assert stored(database_url) == {}


def test_a_value_the_database_refuses_refuses_its_recording_not_the_import(
    database_url: str, tmp_path: Path, run_main: RunMain, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Whatever the door rules miss: the database's own refusal of one recording."""
    from sqlalchemy.exc import DataError

    from app.services import firebase_import

    real_create = firebase_import.sessions.create_session

    def refusing_bob(db_session: Any, **kwargs: Any) -> Any:
        if kwargs["uploaded_by"] == "firebase:bob":
            raise DataError("INSERT …", {}, Exception("value too long for type character"))
        return real_create(db_session, **kwargs)

    monkeypatch.setattr(firebase_import.sessions, "create_session", refusing_bob)
    status, out, _ = run_main(database_url, "import-firebase", make_export(tmp_path / "export"))
    assert status == 1
    assert "refused: bob/Desk: the database refused it: value too long" in out
    assert "3 taken, 0 already there, 2 refused" in out


class NoDatabase:
    """A database that must not be used: a recording refused before it writes anything."""

    def __getattr__(self, name: str) -> Any:
        raise AssertionError(f"the database was used ({name})")


def test_a_gzip_bomb_is_inflated_no_further_than_the_limit_and_nothing_is_written(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Issue 40, finding 5: the inflating of a gzip recording had no bound a test held it to.
    64 MiB of zeros (64 KiB of gzip, read in one chunk) against a limit of 1 MiB: inflated a
    MiB at most at a time, 1 MiB + 1 byte in all, refused, and no database touched."""
    from app.domain.formats.firebase_export import read_firebase_export
    from app.services import firebase_import

    export = make_export(tmp_path / "export")
    add_recording(export, "heidi", "gzip-bomb", gzip.compress(b" " * (64 * 2**20)))
    entry = next(m for m in read_firebase_export(export).maps if m.key == "heidi/gzip-bomb")
    pieces: list[int] = []
    real_member = firebase_import._gzip_member

    class CountedMember:
        def __init__(self) -> None:
            self._inflater = real_member()

        def __getattr__(self, name: str) -> Any:
            return getattr(self._inflater, name)

        def decompress(self, data: bytes, max_length: int = 0) -> bytes:
            piece: bytes = self._inflater.decompress(data, max_length)
            pieces.append(len(piece))
            return piece

    monkeypatch.setattr(firebase_import, "_gzip_member", CountedMember)
    outcome = firebase_import.import_recording(
        NoDatabase(),  # type: ignore[arg-type]
        entry,
        max_attempts=3,
        max_session_bytes=2**20,
        max_poses=1000,
    )
    assert outcome.status == firebase_import.ImportStatus.REFUSED
    assert outcome.reason == "gzip-bomb.json inflates to more than 1048576 bytes"
    assert sum(pieces) == 2**20 + 1
    assert max(pieces) <= firebase_import.INFLATE_CHUNK_BYTES


def test_a_recording_is_read_inflated_and_parsed_a_chunk_at_a_time(
    database_url: str, tmp_path: Path, run_main: RunMain, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Issue 40, finding 4: a recording of 250 MiB was held whole, and again as text (666 MB of
    memory). Now no piece of it larger than a chunk reaches the parser, plain or gzip, and what
    is stored is the recording's JSON byte for byte."""
    from app.services import firebase_import

    def padded(filler: bytes) -> bytes:  # 3 MiB
        strings = b",".join([b'"' + filler * 1000 + b'"'] * 3000)
        session = session_with(map_id=f"ivy {filler.decode()}")
        return session[:-1] + b', "padding": [' + strings + b"]}"

    export = make_export(tmp_path / "export")
    add_recording(export, "ivy", "plain", padded(b"x"))
    add_recording(export, "ivy", "zipped", gzip.compress(padded(b"y")))
    largest: list[int] = []
    real_parse = firebase_import.parse_upload

    def parse_watched(chunks: Any, **kwargs: Any) -> Any:
        def watched() -> Any:
            for chunk in chunks:
                largest.append(len(chunk))
                yield chunk

        return real_parse(watched(), **kwargs)

    monkeypatch.setattr(firebase_import, "parse_upload", parse_watched)
    _, out, _ = run_main(database_url, "import-firebase", export)
    assert "taken: ivy/plain → session" in out
    assert "taken: ivy/zipped → session" in out
    assert max(largest) == 2**20
    db = stored(database_url)
    assert db["ivy x"]["raw"] == padded(b"x")
    assert db["ivy y"]["raw"] == padded(b"y")  # inflated, as the app's JSON


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
