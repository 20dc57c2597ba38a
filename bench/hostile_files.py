"""What hostile and large files cost the offline commands (issue 28, findings 3 and 4; issue 40,
finding 4): the peak memory and CPU time of ``invisible-map import --check``, ``import`` and
``import-firebase`` until each refuses its file, and of ``import-firebase`` taking a large
recording, and what each says.

    .venv/bin/python -m bench.hostile_files                       # 1.5 GB member, 1.2 GB file
    .venv/bin/python -m bench.hostile_files --inflated-mib 256 --file-mib 256 --recording-mib 250

- *backup member*: a real archive (the onetag session, exported) whose upload member is replaced
  by ``--inflated-mib`` MiB of zeros, deflated in the zip (a few MiB on disk), the manifest's size
  and SHA-256 updated to match, so only what the member is refuses it;
- *Firebase file*: an export folder whose one recording is a sparse file of ``--file-mib`` MiB
  (no disk used; reading it costs what reading a real one would);
- *Firebase recording*: an export folder whose one recording is a real session (onetag) with
  ``--recording-mib`` MiB of its own poses again under a key the parser passes over, taken
  (``INVISIBLE_MAP_MAX_SESSION_BYTES`` raised to fit it). Issue 40: 666 MB peak for 250 MiB when
  the recording was held whole (and again as text); read, inflated and parsed a MiB at a time,
  the gzip of it kept to be stored, it is about 150 MB (most of it the program's own imports).

Each command runs in a process of its own (``os.wait4`` gives its peak resident set and CPU
time), on SQLite in a temporary folder. Prints a Markdown table.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import subprocess
import sys
import tempfile
import time
import zipfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != REPO / "bench"]
sys.path.insert(0, str(REPO))

from app.storage import backup  # noqa: E402
from app.storage.db import Database  # noqa: E402
from app.storage.migrate import upgrade_to_head  # noqa: E402
from tests.service.helpers import insert_session, session_bytes  # noqa: E402

MIB = 2**20
CLI = [sys.executable, "-m", "app.cli"]


def run(args: list[str], env: dict[str, str]) -> tuple[int, float, float, str]:
    """(exit status, peak RSS MiB, CPU s, what it said last: stderr's last line, else stdout's)
    of one command."""
    with tempfile.TemporaryFile() as out, tempfile.TemporaryFile() as err:
        process = subprocess.Popen(CLI + args, env=env, stdout=out, stderr=err, cwd=REPO)
        _, status, usage = os.wait4(process.pid, 0)
        process.returncode = os.waitstatus_to_exitcode(status)
        said = []
        for stream in (err, out):
            stream.seek(0)
            said += stream.read().decode(errors="replace").strip().splitlines()[-1:]
    return (
        process.returncode,
        usage.ru_maxrss / 1024,
        usage.ru_utime + usage.ru_stime,
        said[0] if said else "",
    )


def zeros_member_archive(source: Path, out: Path, inflated_bytes: int) -> Path:
    """``source`` with its first upload member replaced by ``inflated_bytes`` zeros (deflated in
    the zip), the manifest's size and SHA-256 of it updated."""
    with zipfile.ZipFile(source) as archive:
        manifest = json.loads(archive.read(backup.MANIFEST))
        members = {n: archive.read(n) for n in archive.namelist() if n != backup.MANIFEST}
    target = next(name for name in members if name.startswith("uploads/"))
    digest = hashlib.sha256()
    block = bytes(MIB)
    with zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as archive:
        for name, data in members.items():
            if name != target:
                archive.writestr(name, data)
        with archive.open(target, "w", force_zip64=True) as member:
            for _ in range(inflated_bytes // MIB):
                member.write(block)
                digest.update(block)
        manifest["members"][target] = {
            "size_bytes": inflated_bytes,
            "sha256": digest.hexdigest(),
        }
        archive.writestr(backup.MANIFEST, json.dumps(manifest))
    return out


def padded_recording(path: Path, mib: int) -> int:
    """A real session (onetag) with about ``mib`` MiB of its poses again under ``padding`` (a key
    the parser passes over), written to ``path``; its size in bytes."""
    document = json.loads(session_bytes("onetag"))
    poses = json.dumps(document["pose_data"]).encode()[1:-1]  # "{…}, {…}"
    with path.open("wb") as out:
        out.write(json.dumps(document).encode()[:-1] + b', "padding": [' + poses)
        for _ in range(mib * MIB // (len(poses) + 2)):
            out.write(b", " + poses)
        out.write(b"]}")
    return path.stat().st_size


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--inflated-mib", type=int, default=1536, help="the upload member, MiB")
    parser.add_argument("--file-mib", type=int, default=1229, help="the Firebase file, MiB")
    parser.add_argument(
        "--recording-mib", type=int, default=250, help="the Firebase recording taken, MiB"
    )
    args = parser.parse_args()

    rows = []
    with tempfile.TemporaryDirectory() as folder_name:
        folder = Path(folder_name)
        source_url = f"sqlite:///{folder / 'source.sqlite3'}"
        source = Database(source_url)
        upgrade_to_head(source)
        insert_session(source, session_bytes("onetag"))
        archive = folder / "source.zip"
        backup.export_archive(source, archive)
        source.dispose()
        hostile = zeros_member_archive(archive, folder / "hostile.zip", args.inflated_mib * MIB)

        target = folder / "target.sqlite3"
        env = {**os.environ, "DATABASE_URL": f"sqlite:///{target}"}
        subprocess.run([*CLI, "migrate"], env=env, check=True, capture_output=True, cwd=REPO)
        started = time.perf_counter()
        for what, command in (
            ("import --check, member inflating to", ["import", str(hostile), "--check"]),
            ("import, member inflating to", ["import", str(hostile)]),
        ):
            status, rss_mib, cpu_s, said = run(command, env)
            rows.append((f"{what} {args.inflated_mib} MiB", status, rss_mib, cpu_s, said))

        export = folder / "firebase"
        (export / "rawMapData" / "alice").mkdir(parents=True)
        (export / "rawMapData" / "bob").mkdir(parents=True)
        (export / "rawMapData" / "bob" / "Desk.json").write_bytes(session_bytes("onetag"))
        huge = export / "rawMapData" / "alice" / "Hall.json"
        with huge.open("wb") as sparse:
            sparse.truncate(args.file_mib * MIB)
        status, rss_mib, cpu_s, said = run(["import-firebase", str(export)], env)
        rows.append((f"import-firebase, a {args.file_mib} MiB file", status, rss_mib, cpu_s, said))

        large = folder / "firebase-large"
        (large / "rawMapData" / "carol").mkdir(parents=True)
        size = padded_recording(large / "rawMapData" / "carol" / "Big.json", args.recording_mib)
        limit = {"INVISIBLE_MAP_MAX_SESSION_BYTES": str(size)}
        status, rss_mib, cpu_s, said = run(["import-firebase", str(large)], {**env, **limit})
        rows.append(
            (f"import-firebase, a {args.recording_mib} MiB recording", status, rss_mib, cpu_s, said)
        )
        wall_s = time.perf_counter() - started

    print("| command | exit | peak RSS MiB | CPU s | last line |")
    print("|---|---|---|---|---|")
    for what, status, rss_mib, cpu_s, said in rows:
        print(f"| {what} | {status} | {rss_mib:.0f} | {cpu_s:.2f} | {said[:140]} |")
    print(f"\n(wall {wall_s:.1f} s on {os.cpu_count()} cores)")


if __name__ == "__main__":
    main()
