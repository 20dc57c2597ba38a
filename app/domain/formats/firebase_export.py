"""What a lab can export from the Firebase project the app used, read into one list of maps.

    export = read_firebase_export(Path("my-lab-export"))
    for entry in export.maps:        # sorted by (owner uid, map id)
        entry.uid, entry.map_id, entry.name, entry.raw_path, entry.image_path, entry.problem

The app (``InvisibleMapCreator2/.../MapRecorder.swift``, ``sendToFirebase``) writes, per recording:

- to Cloud Storage ``rawMapData/<uid>/<mapId>.json`` (the session, architecture §2) and
  ``rawMapData/<uid>/<mapId>.jpg`` (its picture), and a log ``<mapId> serialization error.json``
  next to them (not a session: skipped);
- to the Realtime Database ``maps/<uid>/<mapId> = {"name", "image", "raw_file"}`` (the storage
  paths) and ``unprocessed_maps/<uid>/<mapId> = "<raw_file path>"``, once the file is stored.

The export folder holds the Realtime Database's JSON export (any ``*.json`` file at the top of the
folder with a ``maps`` or ``unprocessed_maps`` key, as the console's "Export JSON" writes it) and
the Storage tree as downloaded (``gsutil -m cp -r gs://<bucket>/rawMapData <folder>/``). A map is
found through either: an entry of the database whose file is missing is kept with its
``problem``; a file in Storage that the database does not list (the app stores the file first,
then writes the database) is read too. Nothing here touches a server: the import command uploads
what this returns.

Every file is read through :func:`read_export_file`, which takes only what is the export's own: a
regular file whose real location is inside the folder (no symbolic link, or linked folder, leading
out; no FIFO, device or folder), no larger than asked (its size checked before it is read, and
read bounded). A recording whose file is not is kept with its ``problem``; a database export that
is not is skipped with a note.

    data = read_export_file(export_folder, entry.raw_path, max_bytes=2**28)  # or ExportFileRefused
    for chunk in export_file_chunks(export_folder, entry.raw_path, max_bytes=2**28): ...
"""

from __future__ import annotations

import json
import os
import stat
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import Any

from app.domain.json_values import value_error_reason

#: The folder of the app's raw uploads in Cloud Storage.
RAW_FOLDER = "rawMapData"
#: The app's log written next to each upload (not a session).
LOG_SUFFIX = " serialization error.json"
#: Largest Realtime Database export read, bytes.
MAX_DATABASE_EXPORT_BYTES = 512 * 2**20
#: Bytes read at a time from a file of the export (:func:`export_file_chunks`).
CHUNK_BYTES = 2**20


class FirebaseExportError(Exception):
    """Raised when the folder holds no export that can be read (no database export, a database
    export that is not JSON)."""


class ExportFileRefused(Exception):
    """Raised when a file of the export is not read: ``str(err)`` says why (it leaves the export
    folder, it is not a regular file, it is too large)."""


def export_file_problem(folder: Path, path: Path) -> str | None:
    """Why ``path`` is not a file of the export folder ``folder`` that can be read, or None: it
    does not exist, its real location (links followed) is outside the folder, or it is not a
    regular file (a FIFO, a device, a folder). Reads no file."""
    try:
        real = path.resolve(strict=True)
    except (OSError, RuntimeError):  # missing, a dangling link, a loop of links
        return "is not in the export"
    if not real.is_relative_to(folder.resolve()):
        return "is a link leading out of the export folder"
    try:
        mode = real.stat().st_mode
    except OSError as err:
        return f"cannot be read: {err.strerror or err}"
    if not stat.S_ISREG(mode):
        return "is not a regular file (a FIFO, a device or a folder)"
    return None


def read_export_file(folder: Path, path: Path, *, max_bytes: int) -> bytes:
    """The bytes of ``path``, a file of the export folder ``folder``, if
    :func:`export_file_problem` finds none and it holds at most ``max_bytes``; else
    ExportFileRefused with the reason (see :func:`export_file_chunks`)."""
    return b"".join(
        export_file_chunks(folder, path, max_bytes=max_bytes, chunk_bytes=max_bytes + 1)
    )


def export_file_chunks(
    folder: Path, path: Path, *, max_bytes: int, chunk_bytes: int = CHUNK_BYTES
) -> Iterator[bytes]:
    """The bytes of ``path``, a file of the export folder ``folder``, in chunks of at most
    ``chunk_bytes``, if :func:`export_file_problem` finds none and it holds at most
    ``max_bytes``; else ExportFileRefused with the reason, raised before the first chunk (or, for
    a file that grows while it is read, once it has grown past ``max_bytes``). The file is opened
    without following a last link and without blocking (a FIFO answers at once), its size is
    checked before it is read, it is read no further than ``max_bytes`` + 1, and the file opened
    must be the one inside the folder (on Linux, by the descriptor's own path)."""
    problem = export_file_problem(folder, path)
    if problem is not None:
        raise ExportFileRefused(f"{path.name} {problem}")
    real = path.resolve()
    try:
        descriptor = os.open(real, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK)
    except OSError as err:
        raise ExportFileRefused(f"cannot open {path.name}: {err.strerror or err}") from None
    with os.fdopen(descriptor, "rb", buffering=0) as file:
        opened = Path(f"/proc/self/fd/{descriptor}")
        if opened.is_symlink() and not opened.resolve().is_relative_to(folder.resolve()):
            raise ExportFileRefused(f"{path.name} is a link leading out of the export folder")
        status = os.fstat(descriptor)
        if not stat.S_ISREG(status.st_mode):
            raise ExportFileRefused(f"{path.name} is not a regular file")
        if status.st_size > max_bytes:
            raise ExportFileRefused(
                f"{path.name} ({status.st_size} bytes) is larger than {max_bytes} bytes"
            )
        left = max_bytes + 1  # one byte more tells a file that grew since
        while left > 0:
            try:
                chunk = file.read(min(chunk_bytes, left))
            except OSError as err:
                raise ExportFileRefused(f"cannot read {path.name}: {err.strerror or err}") from None
            if not chunk:
                return
            left -= len(chunk)
            if left == 0:  # it grew since
                raise ExportFileRefused(f"{path.name} is larger than {max_bytes} bytes")
            yield chunk


@dataclass(frozen=True, slots=True, kw_only=True)
class FirebaseMap:
    """One recording of the export.

    uid: its owner's Firebase user id; map_id: the app's map id (Storage file name);
    name: the name the person typed (``maps/…/name``; else the map id);
    raw_path, image_path: the files in the export (None where absent; read them with
    :func:`read_export_file` and ``export_folder``);
    export_folder: the export's folder;
    sources: where it was found ("maps", "unprocessed_maps", "storage");
    problem: why it cannot be imported, or None.
    """

    uid: str
    map_id: str
    name: str
    raw_path: Path | None
    image_path: Path | None
    export_folder: Path
    sources: tuple[str, ...]
    problem: str | None = None

    @property
    def key(self) -> str:
        """A stable key of the recording, the same on every run: ``<uid>/<map id>``."""
        return f"{self.uid}/{self.map_id}"


@dataclass(frozen=True, slots=True, kw_only=True)
class FirebaseExport:
    """The maps of an export and notes on what was skipped (with the reason)."""

    maps: list[FirebaseMap] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    database_files: list[Path] = field(default_factory=list)


def read_firebase_export(directory: Path) -> FirebaseExport:
    """The maps of the export in ``directory`` (see the module docstring)."""
    directory = Path(directory)
    if not directory.is_dir():
        raise FirebaseExportError(f"{directory} is not a folder")
    notes: list[str] = []
    database_files, database = _database_exports(directory, notes)
    storage = directory / RAW_FOLDER
    if not database_files and not storage.is_dir():
        raise FirebaseExportError(
            f"{directory} holds neither a Realtime Database export (a top-level *.json with "
            f"'maps' or 'unprocessed_maps') nor a Storage folder {RAW_FOLDER}/"
        )

    found: dict[tuple[str, str], dict[str, Any]] = {}

    def entry(uid: str, map_id: str) -> dict[str, Any]:
        return found.setdefault((uid, map_id), {"sources": [], "name": None, "raw": None})

    for uid, map_id, value in _children(database.get("maps"), "maps", notes):
        item = entry(uid, map_id)
        item["sources"].append("maps")
        if isinstance(value, Mapping):
            name, raw, image = value.get("name"), value.get("raw_file"), value.get("image")
            item["name"] = name if isinstance(name, str) else None
            item["raw"] = raw if isinstance(raw, str) else item["raw"]
            item["image"] = image if isinstance(image, str) else None
        else:
            notes.append(f"maps/{uid}/{map_id}: not an object, read as a bare entry")
    for uid, map_id, value in _children(
        database.get("unprocessed_maps"), "unprocessed_maps", notes
    ):
        item = entry(uid, map_id)
        item["sources"].append("unprocessed_maps")
        if isinstance(value, str) and item["raw"] is None:
            item["raw"] = value
    for path in sorted(storage.glob("*/*.json")) if storage.is_dir() else []:
        if path.name.endswith(LOG_SUFFIX):
            continue
        uid, map_id = path.parent.name, path.stem
        item = entry(uid, map_id)
        item["sources"].append("storage")
        item.setdefault("storage_raw", path)

    maps = [_resolve(directory, uid, map_id, item) for (uid, map_id), item in sorted(found.items())]
    return FirebaseExport(maps=maps, notes=notes, database_files=database_files)


def _resolve(directory: Path, uid: str, map_id: str, item: dict[str, Any]) -> FirebaseMap:
    default_raw = f"{RAW_FOLDER}/{uid}/{map_id}.json"
    raw_path = item.get("storage_raw") or _inside(directory, item["raw"] or default_raw)
    image = _inside(directory, item.get("image") or f"{RAW_FOLDER}/{uid}/{map_id}.jpg")
    problem = None
    found = None if raw_path is None else export_file_problem(directory, raw_path)
    if raw_path is None or found == "is not in the export":
        problem = (
            f"its session file {item['raw'] or default_raw} is not in the Storage export "
            f"(download {RAW_FOLDER}/ into the folder)"
        )
        raw_path = None
    elif found is not None:
        relative = _relative(directory, raw_path)
        problem = f"its session file {relative} {found}"
        raw_path = None
    return FirebaseMap(
        uid=uid,
        map_id=map_id,
        name=item["name"] or map_id,
        raw_path=raw_path,
        image_path=image if image is not None and image.is_file() else None,
        export_folder=directory,
        sources=tuple(item["sources"]),
        problem=problem,
    )


def _relative(directory: Path, path: Path) -> str:
    try:
        return path.relative_to(directory).as_posix()
    except ValueError:
        return path.name


def _inside(directory: Path, storage_path: str) -> Path | None:
    """The export's copy of a Storage path (``gs://bucket/`` and leading slashes dropped), or
    None for a path that would leave the folder."""
    path = storage_path.strip()
    if path.startswith("gs://"):
        path = path[5:].partition("/")[2]
    parts = PurePosixPath(path.lstrip("/")).parts
    if not parts or any(part in ("..", "") for part in parts):
        return None
    return directory.joinpath(*parts)


def _database_exports(directory: Path, notes: list[str]) -> tuple[list[Path], dict[str, Any]]:
    """The top-level JSON files with ``maps``/``unprocessed_maps``, merged (later files add)."""
    merged: dict[str, Any] = {"maps": {}, "unprocessed_maps": {}}
    files = []
    for path in sorted(directory.glob("*.json")):
        try:
            encoded = read_export_file(directory, path, max_bytes=MAX_DATABASE_EXPORT_BYTES)
        except ExportFileRefused as err:
            notes.append(f"{path.name}: skipped: {err}")
            continue
        try:
            document = json.loads(encoded)
        except ValueError as err:  # not UTF-8, not JSON, an integer of too many digits
            reason = value_error_reason(err)
            raise FirebaseExportError(f"{path.name} is not valid JSON: {reason}") from err
        except RecursionError:
            raise FirebaseExportError(
                f"{path.name} is nested too deeply to be a database export"
            ) from None
        if not isinstance(document, Mapping) or not (
            "maps" in document or "unprocessed_maps" in document
        ):
            notes.append(f"{path.name}: no 'maps' or 'unprocessed_maps' key, not a database export")
            continue
        files.append(path)
        for key in ("maps", "unprocessed_maps"):
            users = document.get(key)
            if isinstance(users, Mapping):
                for uid, children in users.items():
                    if isinstance(children, Mapping):
                        merged[key].setdefault(uid, {}).update(children)
                    else:
                        notes.append(f"{key}/{uid}: not an object of maps, skipped")
            elif users is not None:
                notes.append(f"{path.name}: {key} is not an object, skipped")
    return files, merged


def _children(users: Any, key: str, notes: list[str]) -> Iterator[tuple[str, str, Any]]:
    if not isinstance(users, Mapping):
        return
    for uid, children in users.items():
        for map_id, value in children.items():
            if value is None:
                notes.append(f"{key}/{uid}/{map_id}: null, skipped")
                continue
            yield str(uid), str(map_id), value
