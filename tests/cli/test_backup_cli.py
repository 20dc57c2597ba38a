"""``invisible-map export`` and ``invisible-map import`` (``app/cli/backup.py``), run as a user runs
them: ``main([...])`` in this process with a monkeypatched environment, and once as real
processes. Every failure is one line on stderr, ``invisible-map: error: …``, exit status 1.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import sys
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from cli_support import assert_one_line_error

from app import cli
from app.domain.upload.session import decode_json_bytes, parse_session
from app.storage import backup, keys, maps, sessions
from app.storage.db import Database
from app.storage.migrate import head_revision
from app.storage.orm import Role
from tests.service.api_support import run_next_job
from tests.service.helpers import session_bytes

REPO_ROOT = Path(__file__).resolve().parents[2]

RunMain = Callable[..., tuple[int, str, str]]


# --------------------------------------------------------------------------- helpers


@pytest.fixture
def run_main(capsys: pytest.CaptureFixture[str], env: pytest.MonkeyPatch) -> RunMain:
    """``cli.main(ARGS)`` in this process against ``database``: (status, stdout, stderr)."""

    def run(database: str, *args: Any) -> tuple[int, str, str]:
        env.setenv("DATABASE_URL", database)
        capsys.readouterr()
        status = cli.main([str(a) for a in args])
        out, err = capsys.readouterr()
        return status, out, err

    return run


@pytest.fixture
def sqlite_url(sqlite_template: Path, tmp_path: Path) -> Callable[[str], str]:
    """A fresh migrated SQLite database per call: its URL."""

    def make(name: str) -> str:
        path = tmp_path / f"{name}.sqlite3"
        shutil.copyfile(sqlite_template, path)
        return f"sqlite:///{path}"

    return make


@pytest.fixture
def source_url(sqlite_url: Callable[[str], str]) -> str:
    """A deployment with two built maps: a device key's upload and the admin's."""
    url = sqlite_url("source")
    db = Database(url)
    with db.transaction() as tx:
        device, _ = keys.create_key(tx, name="phone", role=Role.DEVICE)
    for name, uploader in (("onetag", f"key:{device.id}"), ("pgt_tester3", keys.ENVIRONMENT_ADMIN)):
        raw = session_bytes(name)
        with db.transaction() as tx:
            sessions.create_session(
                tx,
                parsed=parse_session(decode_json_bytes(raw)),
                upload=sessions.StoredUpload.of(raw),
                uploaded_by=uploader,
            )
        run_next_job(db, path_graph=True)
    db.dispose()
    return url


@pytest.fixture
def empty_archive(sqlite_url: Callable[[str], str], tmp_path: Path) -> Path:
    """The archive of an empty deployment."""
    db = Database(sqlite_url("empty-source"))
    backup.export_archive(db, tmp_path / "empty.zip")
    db.dispose()
    return tmp_path / "empty.zip"


def uploads_of(url: str) -> dict[int, bytes]:
    db = Database(url)
    with db.read() as tx:
        ids = [info.id for info in sessions.list_sessions(tx)[0]]
        uploads = {i: sessions.raw_upload_gzip(tx, i) for i in ids}
    db.dispose()
    return uploads


# --------------------------------------------------------------------------- export and import


def test_export_then_import_into_postgresql_then_merge(
    source_url: str, postgres_url: str, run_main: RunMain, tmp_path: Path
) -> None:
    archive = tmp_path / "backup.zip"
    status, out, err = run_main(source_url, "export", archive)
    assert status == 0, err
    assert out.splitlines() == [
        f"exported 2 sessions, 2 maps, 2 map versions, 0 sweeps, 1 API keys (names only) from "
        f"{source_url} to {archive} ({archive.stat().st_size / 1e6:.1f} MB, schema revision "
        f"{head_revision()})"
    ]
    assert zipfile.is_zipfile(archive)

    status, out, err = run_main(postgres_url, "import", archive)
    assert status == 0, err
    shown = Database(postgres_url).url.render_as_string(hide_password=True)
    assert out.splitlines() == [
        f"imported 2 sessions, 2 maps, 2 map versions, 0 sweeps, 0 API keys from {archive} "
        f"into {shown} (ids kept)"
    ]
    assert "API keys were not imported" in err
    assert uploads_of(postgres_url) == uploads_of(source_url)

    status, _, err = run_main(postgres_url, "import", archive)
    assert_one_line_error(status, err, "nothing imported: the database is not empty", "--merge")
    status, out, err = run_main(postgres_url, "import", archive, "--check")
    assert status == 0, err
    assert out.startswith(
        f"{archive}: a valid backup of 2 sessions, 2 maps, 2 map versions, 0 sweeps, 1 API keys "
        "(without key hashes), exported "
    )
    assert out.rstrip().endswith("members, every checksum matches, every row fits")

    status, out, err = run_main(postgres_url, "import", archive, "--merge")
    assert status == 0, err
    assert out.splitlines()[1:] == ["map 1 -> 3", "map 2 -> 4"]
    db = Database(postgres_url)
    with db.read() as tx:
        assert [info.id for info in maps.list_maps(tx)[0]] == [4, 3, 2, 1]
    db.dispose()


def test_export_replaces_a_file_only_with_force(
    source_url: str, run_main: RunMain, tmp_path: Path
) -> None:
    archive = tmp_path / "backup.zip"
    archive.write_bytes(b"keep me")
    status, _, err = run_main(source_url, "export", archive)
    assert_one_line_error(status, err, f"{archive} exists; pass --force to replace it")
    assert archive.read_bytes() == b"keep me"

    status, _, err = run_main(source_url, "export", archive, "--force", "--include-keys")
    assert status == 0, err
    assert "keep it as safe as the keys" in err
    assert backup.read_manifest(archive).key_hashes


# --------------------------------------------------------------------------- errors


def newer_format(archive: Path, folder: Path) -> Path:
    """``archive`` with a manifest that claims format version 2."""
    out = folder / "newer.zip"
    with zipfile.ZipFile(archive) as source, zipfile.ZipFile(out, "w") as target:
        for name in source.namelist():
            data = source.read(name)
            if name == backup.MANIFEST:
                data = data.replace(b'"format_version": 1', b'"format_version": 2')
            target.writestr(name, data)
    return out


def altered_member(archive: Path, folder: Path) -> Path:
    """``archive`` with one member's bytes changed (and its zip CRC with them)."""
    out = folder / "altered.zip"
    with zipfile.ZipFile(archive) as source, zipfile.ZipFile(out, "w") as target:
        for name in source.namelist():
            data = source.read(name)
            target.writestr(name, data + b"\n" if name == "tables/session.jsonl" else data)
    return out


ERRORS: dict[str, tuple[Callable[[Path, Path, str], list[Any]], list[str]]] = {
    "import: no such file": (
        lambda _a, folder, _u: ["import", folder / "nothing.zip"],
        ["nothing.zip", "No such file or directory"],
    ),
    "import: not an archive": (
        lambda _a, folder, _u: ["import", _write(folder / "x.zip", b"{}")],
        ["not a backup archive (not a zip file, or truncated)"],
    ),
    "import: a newer format": (
        lambda a, folder, _u: ["import", newer_format(a, folder)],
        ["archive format version 2 is newer than this invisible-map reads (1)"],
    ),
    "import: keys that are not in the archive": (
        lambda a, _f, _u: ["import", a, "--include-keys"],
        ["no API key hashes", "export it with --include-keys"],
    ),
    "import --check: a truncated archive": (
        lambda a, folder, _u: ["import", "--check", _write(folder / "x.zip", a.read_bytes()[:-9])],
        ["not a backup archive (not a zip file, or truncated)"],
    ),
    "import --check: a checksum mismatch": (
        lambda a, folder, _u: ["import", "--check", altered_member(a, folder)],
        ["tables/session.jsonl does not match the manifest (checksum mismatch"],
    ),
    "import: an unmigrated database": (
        lambda a, _f, _u: ["import", a],
        ["is not migrated; run `invisible-map migrate`"],
    ),
    "export: an unmigrated database": (
        lambda _a, folder, _u: ["export", folder / "out.zip"],
        ["is not migrated; run `invisible-map migrate`"],
    ),
    "export: to a directory": (
        lambda _a, folder, _u: ["export", folder],
        ["is a directory"],
    ),
    "export: into a missing directory": (
        lambda _a, folder, _u: ["export", folder / "no" / "out.zip"],
        ["No such file or directory"],
    ),
}
#: The cases run against an empty, unmigrated SQLite file (all others: a migrated one).
UNMIGRATED = {"import: an unmigrated database", "export: an unmigrated database"}


def _write(path: Path, data: bytes) -> Path:
    path.write_bytes(data)
    return path


@pytest.mark.parametrize("case", ERRORS)
def test_errors_are_one_line_and_write_nothing(
    case: str,
    empty_archive: Path,
    sqlite_url: Callable[[str], str],
    run_main: RunMain,
    tmp_path: Path,
) -> None:
    if case in UNMIGRATED:
        (tmp_path / "bare.sqlite3").touch()
        url = f"sqlite:///{tmp_path / 'bare.sqlite3'}"
    else:
        url = sqlite_url("target")
    folder = tmp_path / "files"
    folder.mkdir()
    make_args, parts = ERRORS[case]
    args = make_args(empty_archive, folder, url)
    files = sorted(folder.rglob("*"))
    status, out, err = run_main(url, *args)
    assert_one_line_error(status, err, *parts)
    assert out == ""
    assert sorted(folder.rglob("*")) == files  # no archive, not even a partial one
    if case not in UNMIGRATED:
        assert uploads_of(url) == {}


def with_map_row(archive: Path, out: Path, **values: Any) -> Path:
    """``archive`` with its first map row's ``values`` changed (the manifest's checksum too)."""
    with zipfile.ZipFile(archive) as source:
        manifest = json.loads(source.read(backup.MANIFEST))
        members = {n: source.read(n) for n in source.namelist() if n != backup.MANIFEST}
    rows = [json.loads(line) for line in members["tables/map.jsonl"].splitlines()]
    rows[0].update(values)
    members["tables/map.jsonl"] = b"".join(json.dumps(r).encode() + b"\n" for r in rows)
    with zipfile.ZipFile(out, "w") as target:
        for name, data in members.items():
            target.writestr(name, data)
            manifest["members"][name] = {
                "size_bytes": len(data),
                "sha256": hashlib.sha256(data).hexdigest(),
            }
        target.writestr(backup.MANIFEST, json.dumps(manifest))
    return out


@pytest.mark.parametrize(
    ("values", "words"),
    [
        ({"id": 2**63}, "id: 9223372036854775808 is beyond the column's 32-bit integers"),
        ({"display_name": "\ud800"}, "display_name holds a lone surrogate (U+D800)"),
        ({"id": 2}, "line 2 (id 2): id 2: an earlier row of tables/map.jsonl has it too"),
    ],
    ids=["id-2^63", "surrogate", "id-twice"],
)
def test_an_archive_no_database_holds_is_refused_by_the_check_and_the_import(
    values: dict[str, Any],
    words: str,
    source_url: str,
    sqlite_url: Callable[[str], str],
    run_main: RunMain,
    tmp_path: Path,
) -> None:
    """Issue 28, finding 4: a 46-line traceback on SQLite, and `import --check` said valid
    (issue 40, finding 3: a map id twice, which the database's key refused)."""
    archive = tmp_path / "backup.zip"
    assert run_main(source_url, "export", archive)[0] == 0
    hostile = with_map_row(archive, tmp_path / "hostile.zip", **values)
    target = sqlite_url("target")
    for args in (["import", hostile, "--check"], ["import", hostile]):
        status, out, err = run_main(target, *args)
        assert_one_line_error(status, err, "tables/map.jsonl line ", words)
        assert out == ""
    assert uploads_of(target) == {}


# --------------------------------------------------------------------------- as processes


def process_env(database_url: str, data_dir: Path) -> dict[str, str]:
    environment = {
        name: value
        for name, value in os.environ.items()
        if name != "DATABASE_URL" and not name.startswith("INVISIBLE_MAP_")
    }
    environment.update(DATABASE_URL=database_url, INVISIBLE_MAP_DATA_DIR=str(data_dir))
    return environment


def run_cli(database_url: str, data_dir: Path, *args: Any) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "app.cli", *(str(a) for a in args)],
        cwd=REPO_ROOT,
        env=process_env(database_url, data_dir),
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )


def test_the_commands_as_processes(
    source_url: str, sqlite_url: Callable[[str], str], tmp_path: Path
) -> None:
    archive, target = tmp_path / "backup.zip", sqlite_url("target")
    exported = run_cli(source_url, tmp_path, "export", archive)
    assert exported.returncode == 0, exported.stderr
    assert exported.stderr == ""  # no progress bar when stderr is not a terminal
    assert exported.stdout.startswith("exported 2 sessions")

    imported = run_cli(target, tmp_path, "import", archive)
    assert imported.returncode == 0, imported.stderr
    assert imported.stdout.startswith("imported 2 sessions")
    assert uploads_of(target) == uploads_of(source_url)

    truncated = _write(tmp_path / "truncated.zip", archive.read_bytes()[:1000])
    failed = run_cli(sqlite_url("other"), tmp_path, "import", truncated)
    assert_one_line_error(failed.returncode, failed.stderr, "truncated")
