"""Reading a lab's Firebase export (app.domain.formats.firebase_export) on an export tree built here
from the sessions in data/, laid out as the app wrote it."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import pytest

from app.domain.formats import firebase_export
from app.domain.formats.firebase_export import (
    ExportFileRefused,
    FirebaseExportError,
    export_file_chunks,
    export_file_problem,
    read_export_file,
    read_firebase_export,
)
from tests.read_counting import ReadCounting

SESSIONS = Path(__file__).parents[2] / "data" / "sessions"
JPEG = b"\xff\xd8\xff\xe0" + b"\x00" * 16 + b"\xff\xd9"


def make_export(root: Path) -> Path:
    """alice: two maps in the database and Storage, one picture; bob: one map only under
    unprocessed_maps; carol: a file in Storage the database never got; dave: a database entry
    whose file is missing; plus the app's serialization log, which is no session."""
    storage = root / "rawMapData"
    files = {
        ("alice", "Lab 1700000000"): "occam_room",
        ("alice", "Hall 1700000500"): "onetag",
        ("bob", "Desk"): "pgt_tester3",
        ("carol", "Stairs"): "singletag3times",
    }
    for (uid, map_id), name in files.items():
        (storage / uid).mkdir(parents=True, exist_ok=True)
        shutil.copyfile(SESSIONS / f"{name}.json", storage / uid / f"{map_id}.json")
    (storage / "alice" / "Lab 1700000000.jpg").write_bytes(JPEG)
    (storage / "alice" / "Lab 1700000000 serialization error.json").write_text('{"log": ""}')
    database = {
        "maps": {
            "alice": {
                "Lab 1700000000": {
                    "name": "Lab",
                    "image": "rawMapData/alice/Lab 1700000000.jpg",
                    "raw_file": "rawMapData/alice/Lab 1700000000.json",
                },
                "Hall 1700000500": {
                    "name": "Hall",
                    "image": "rawMapData/alice/Hall 1700000500.jpg",
                    "raw_file": "rawMapData/alice/Hall 1700000500.json",
                },
            },
            "dave": {"Gone": {"name": "Gone", "raw_file": "rawMapData/dave/Gone.json"}},
        },
        "unprocessed_maps": {
            "alice": {"Lab 1700000000": "rawMapData/alice/Lab 1700000000.json"},
            "bob": {"Desk": "rawMapData/bob/Desk.json"},
        },
        "other": {"ignored": True},
    }
    (root / "invisible-map-sandbox-export.json").write_text(json.dumps(database))
    (root / "notes.json").write_text('{"something": "else"}')
    return root


def test_every_recording_is_found_once_with_its_owner_name_and_files(tmp_path):
    export = read_firebase_export(make_export(tmp_path))

    by_key = {m.key: m for m in export.maps}
    assert sorted(by_key) == [
        "alice/Hall 1700000500",
        "alice/Lab 1700000000",
        "bob/Desk",
        "carol/Stairs",
        "dave/Gone",
    ]
    lab = by_key["alice/Lab 1700000000"]
    assert (lab.uid, lab.name) == ("alice", "Lab")
    assert lab.raw_path == tmp_path / "rawMapData" / "alice" / "Lab 1700000000.json"
    assert lab.image_path is not None
    assert lab.image_path.read_bytes() == JPEG
    assert set(lab.sources) == {"maps", "unprocessed_maps", "storage"}
    assert lab.problem is None
    hall = by_key["alice/Hall 1700000500"]
    assert hall.image_path is None  # named in the database, not in the export
    assert by_key["bob/Desk"].name == "Desk"  # no maps entry: the map id
    assert by_key["carol/Stairs"].sources == ("storage",)
    gone = by_key["dave/Gone"]
    assert gone.raw_path is None
    assert gone.problem is not None
    assert "rawMapData/dave/Gone.json is not in the Storage export" in gone.problem
    assert export.database_files == [tmp_path / "invisible-map-sandbox-export.json"]
    assert any("notes.json" in note for note in export.notes)


def test_storage_paths_cannot_leave_the_export_folder(tmp_path):
    root = make_export(tmp_path / "export")
    (tmp_path / "secret.json").write_text("{}")
    database = json.loads((root / "invisible-map-sandbox-export.json").read_text())
    database["maps"]["eve"] = {
        "x": {"raw_file": "../secret.json", "image": "/../../secret.json"},
        "y": {"raw_file": "gs://bucket/../secret.json"},
    }
    (root / "invisible-map-sandbox-export.json").write_text(json.dumps(database))

    export = read_firebase_export(root)

    for entry in (m for m in export.maps if m.uid == "eve"):
        assert entry.raw_path is None
        assert entry.image_path is None
        assert entry.problem is not None


def test_gs_urls_and_leading_slashes_name_files_in_the_export(tmp_path):
    root = make_export(tmp_path)
    database = json.loads((root / "invisible-map-sandbox-export.json").read_text())
    database["maps"]["bob"] = {
        "Desk": {"name": "Desk", "raw_file": "gs://lab/rawMapData/bob/Desk.json"}
    }
    (root / "invisible-map-sandbox-export.json").write_text(json.dumps(database))
    shutil.rmtree(root / "rawMapData" / "carol")

    desk = next(m for m in read_firebase_export(root).maps if m.key == "bob/Desk")

    assert desk.raw_path == root / "rawMapData" / "bob" / "Desk.json"


def test_storage_alone_is_an_export(tmp_path):
    root = make_export(tmp_path)
    (root / "invisible-map-sandbox-export.json").unlink()
    keys = [m.key for m in read_firebase_export(root).maps]
    assert keys == ["alice/Hall 1700000500", "alice/Lab 1700000000", "bob/Desk", "carol/Stairs"]


def test_a_folder_without_an_export_or_with_a_broken_one_is_refused(tmp_path):
    with pytest.raises(FirebaseExportError, match="not a folder"):
        read_firebase_export(tmp_path / "missing")
    with pytest.raises(FirebaseExportError, match="neither a Realtime Database export"):
        read_firebase_export(tmp_path)
    (tmp_path / "db.json").write_text('{"maps": ')
    with pytest.raises(FirebaseExportError, match=r"db\.json is not valid JSON"):
        read_firebase_export(tmp_path)


def test_malformed_database_entries_are_noted_not_fatal(tmp_path):
    (tmp_path / "db.json").write_text(
        json.dumps({"maps": {"u": {"a": None, "b": "text"}, "v": 3}, "unprocessed_maps": []})
    )
    export = read_firebase_export(tmp_path)
    assert [m.key for m in export.maps] == ["u/b"]
    assert export.maps[0].problem is not None
    assert any("maps/u/a: null" in n for n in export.notes)
    assert any("maps/v" in n for n in export.notes)
    assert any("unprocessed_maps is not an object" in n for n in export.notes)


def test_only_the_exports_own_regular_files_are_read_and_no_further_than_asked(tmp_path):
    """Issue 28, finding 3: links leading out of the folder were followed, a FIFO would block,
    a 1.2 GB file was read whole before it was refused."""
    folder, outside = tmp_path / "export", tmp_path / "outside"
    (folder / "rawMapData" / "u").mkdir(parents=True)
    outside.mkdir()
    (outside / "secret.json").write_text("{}")
    own = folder / "rawMapData" / "u" / "own.json"
    own.write_text('{"a": 1}')
    cases = {
        "own": own,
        "link inside": folder / "rawMapData" / "u" / "alias.json",
        "link out": folder / "rawMapData" / "u" / "out.json",
        "linked folder": folder / "rawMapData" / "v" / "secret.json",
        "fifo": folder / "rawMapData" / "u" / "fifo.json",
        "folder": folder / "rawMapData" / "u",
        "missing": folder / "rawMapData" / "u" / "missing.json",
        "large": folder / "rawMapData" / "u" / "large.json",
    }
    cases["link inside"].symlink_to(own)
    cases["link out"].symlink_to(outside / "secret.json")
    (folder / "rawMapData" / "v").symlink_to(outside)
    os.mkfifo(cases["fifo"])
    with cases["large"].open("wb") as sparse:
        sparse.truncate(2**30)  # 1 GiB, no disk used
    assert read_export_file(folder, own, max_bytes=8) == b'{"a": 1}'
    assert read_export_file(folder, cases["link inside"], max_bytes=8) == b'{"a": 1}'
    expected = {
        "link out": "out.json is a link leading out of the export folder",
        "linked folder": "secret.json is a link leading out of the export folder",
        "fifo": "fifo.json is not a regular file",
        "folder": "u is not a regular file",
        "missing": "missing.json is not in the export",
        "large": "large.json (1073741824 bytes) is larger than 1048576 bytes",
    }
    for case, reason in expected.items():
        with pytest.raises(ExportFileRefused) as refused:
            read_export_file(folder, cases[case], max_bytes=2**20)
        assert reason in str(refused.value), case
        assert export_file_problem(folder, cases[case]) is not None or case == "large", case
    with pytest.raises(ExportFileRefused, match="larger than 7 bytes"):
        read_export_file(folder, own, max_bytes=7)


def test_a_recording_whose_file_leads_out_is_listed_with_its_problem(tmp_path):
    root = make_export(tmp_path / "export")
    (tmp_path / "secret.json").write_bytes((SESSIONS / "onetag.json").read_bytes())
    (root / "rawMapData" / "eve").mkdir()
    (root / "rawMapData" / "eve" / "x.json").symlink_to(tmp_path / "secret.json")
    entry = next(m for m in read_firebase_export(root).maps if m.key == "eve/x")
    assert entry.raw_path is None
    assert entry.problem == (
        "its session file rawMapData/eve/x.json is a link leading out of the export folder"
    )


def test_a_database_export_nested_too_deeply_is_refused_in_one_line(tmp_path):
    (tmp_path / "db.json").write_bytes(b"[" * 200_000 + b"]" * 200_000)
    with pytest.raises(FirebaseExportError, match=r"db\.json is nested too deeply"):
        read_firebase_export(tmp_path)


def _sparse(path: Path, size: int) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("wb") as sparse:
        sparse.truncate(size)  # no disk used
    return path


def test_a_file_larger_than_asked_is_refused_before_a_byte_of_it_is_read(tmp_path, monkeypatch):
    """Issue 40, finding 5: the size check was caught only by its message's wording (without it
    the read's bound refused the file too, after reading ``max_bytes`` + 1 of it)."""
    large = _sparse(tmp_path / "rawMapData" / "u" / "large.json", 8 * 2**20)
    reads = ReadCounting()
    monkeypatch.setattr(firebase_export, "os", reads)
    for read in (
        lambda: read_export_file(tmp_path, large, max_bytes=2**20),
        lambda: list(export_file_chunks(tmp_path, large, max_bytes=2**20)),
    ):
        with pytest.raises(ExportFileRefused) as refused:
            read()
        assert str(refused.value) == "large.json (8388608 bytes) is larger than 1048576 bytes"
    assert reads.opened == 2
    assert reads.bytes_read == 0


def test_a_file_growing_past_its_checked_size_is_read_no_further_than_asked(tmp_path, monkeypatch):
    """Issue 40, finding 5: the read of an export's file had no bound of its own (only the size
    checked before covered it): a file that grows after the check, as its size says it is 0
    bytes here, is read to ``max_bytes`` + 1 and no further, in one piece or in chunks."""
    grown = tmp_path / "rawMapData" / "u" / "grown.json"
    grown.parent.mkdir(parents=True)
    grown.write_bytes(b" " * (3 * 2**20))
    reads = ReadCounting(fstat_size=0)
    monkeypatch.setattr(firebase_export, "os", reads)
    for read in (
        lambda: read_export_file(tmp_path, grown, max_bytes=2**20),
        lambda: list(export_file_chunks(tmp_path, grown, max_bytes=2**20, chunk_bytes=2**16)),
    ):
        reads.bytes_read = 0
        with pytest.raises(ExportFileRefused) as refused:
            read()
        assert str(refused.value) == "grown.json is larger than 1048576 bytes"
        assert reads.bytes_read == 2**20 + 1
    chunks = list(export_file_chunks(tmp_path, grown, max_bytes=4 * 2**20, chunk_bytes=2**16))
    assert {len(chunk) for chunk in chunks} == {2**16}
    assert b"".join(chunks) == grown.read_bytes()
