"""Readers of the fields of an upload's JSON (docs/architecture.md §2), each raising
:class:`SessionFormatError` with the field's path and the reason.

    integer_field(entry, "pose_id", "tag_data[3][0]")     # int, or "…pose_id: expected an integer"
    rigid_pose(matrix16_field(entry, "pose", where), where)  # a checked rigid 4×4

Shared by the session parser (``app.domain.upload.session``) and the localizer's update parser
(``app.domain.localize.batch``).

And the one rule for every text that may reach the database (issue 28, finding 1)::

    text_fault("a\\x00b")                  # "holds a NUL character (U+0000)"; None for good text
    json_text_fault({"k": ["\\ud800"]})    # ("k[0]", "holds a lone surrogate (U+D800), …")

Uploads (``app.services.uploads``), JSON bodies and query strings of the API, the dashboard's
forms, key names, map names, the Firebase import and backup imports all ask it, each raising
its own error with the field named.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np
import numpy.typing as npt

from app.domain.errors import SessionFormatError
from app.domain.frames import ORTHONORMAL_TOLERANCE, FloatArray, orthonormalized, rigidity_defect
from app.domain.json_values import json_type_name

#: Largest id accepted: integers a JSON number can hold exactly (2^53).
MAX_ID = 2**53
#: Farthest a pose (of the phone, or of a tag from the camera) may be from its frame's origin, m:
#: a walk through a building stays within kilometres; beyond this the arithmetic of a map would
#: lose its precision (or overflow), so the upload is refused instead.
MAX_TRANSLATION_M = 1e5
#: Largest focal length, principal point or corner coordinate accepted, px.
MAX_PIXELS = 1e5


def text_fault(text: str) -> str | None:
    """Why ``text`` cannot be stored as text in every database we run on, or None if it can: a
    NUL character (PostgreSQL's text and JSONB cannot hold one), or a lone surrogate such as
    ``"\\ud800"``, which JSON and Python strings allow but UTF-8 cannot encode (so neither
    database, nor a JSON answer, can carry it)."""
    if "\x00" in text:
        return "holds a NUL character (U+0000)"
    if text.isascii():
        return None
    try:
        text.encode("utf-8")
    except UnicodeEncodeError as err:
        return f"holds a lone surrogate (U+{ord(text[err.start]):04X}), which is no text"
    return None


#: A path inside a JSON document, as a chain of (parent chain, key or index); None: the top.
_PathChain = tuple[Any, str | int] | None


def json_text_fault(value: Any, where: str = "") -> tuple[str, str] | None:
    """The first string (an object's key or a value) of a decoded JSON ``value`` that
    :func:`text_fault` refuses, as (its path, the reason), or None. The path reads as fields do
    (``params.tag_sizes_m``, ``poses[3].name``; a key at fault is named by its object's path).
    Walked without recursion, and a path is spelled out only for the fault, so a document of any
    depth is read in time proportional to its size."""
    pending: list[tuple[Any, _PathChain]] = [(value, None)]
    while pending:
        item, chain = pending.pop()
        if isinstance(item, str):
            reason = text_fault(item)
            if reason is not None:
                return _spelled(chain, where), reason
        elif isinstance(item, Mapping):
            children = []
            for key, child in item.items():
                key_text = str(key)
                reason = text_fault(key_text)
                if reason is not None:
                    return _spelled(chain, where) or "(top level)", f"a key {reason}"
                children.append((child, (chain, key_text)))
            pending.extend(reversed(children))
        elif isinstance(item, (list, tuple)):
            pending.extend(reversed([(child, (chain, k)) for k, child in enumerate(item)]))
    return None


def _spelled(chain: _PathChain, where: str) -> str:
    """A path chain of :func:`json_text_fault` as a field path below ``where``."""
    parts: list[str | int] = []
    while chain is not None:
        chain, part = chain
        parts.append(part)
    path = where
    for part in reversed(parts):
        path += f"[{part}]" if isinstance(part, int) else (f".{part}" if path else part)
    return path


def require_list(value: Any, where: str) -> None:
    if not isinstance(value, list):
        raise SessionFormatError(where, f"expected a list, got {json_type_name(value)}")


def require_object(value: Any, where: str) -> None:
    if not isinstance(value, Mapping):
        raise SessionFormatError(where, f"expected an object, got {json_type_name(value)}")


def required_field(entry: Mapping[str, Any], key: str, where: str) -> Any:
    if key not in entry:
        raise SessionFormatError(f"{where}.{key}", "missing")
    return entry[key]


def integer_field(entry: Mapping[str, Any], key: str, where: str) -> int:
    value = required_field(entry, key, where)
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise SessionFormatError(
            f"{where}.{key}", f"expected an integer, got {json_type_name(value)}"
        )
    if isinstance(value, float) and not value.is_integer():
        raise SessionFormatError(f"{where}.{key}", f"expected an integer, got {value}")
    if not -MAX_ID <= value <= MAX_ID:
        raise SessionFormatError(
            f"{where}.{key}", f"integer out of range (|value| > 2^53): {value}"
        )
    return int(value)


def number_field(entry: Mapping[str, Any], key: str, where: str) -> float:
    value = required_field(entry, key, where)
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise SessionFormatError(
            f"{where}.{key}", f"expected a number, got {json_type_name(value)}"
        )
    return _finite(value, f"{where}.{key}")


def vector_field(entry: Mapping[str, Any], key: str, where: str, length: int) -> FloatArray:
    value = required_field(entry, key, where)
    return number_list(value, f"{where}.{key}", length)


def optional_vector_field(
    entry: Mapping[str, Any], key: str, where: str, length: int
) -> FloatArray:
    if key not in entry or entry[key] is None:
        return np.full(length, np.nan)
    return number_list(entry[key], f"{where}.{key}", length)


def matrix16_field(entry: Mapping[str, Any], key: str, where: str) -> FloatArray:
    value = required_field(entry, key, where)
    if isinstance(value, list) and len(value) == 4 and all(isinstance(r, list) for r in value):
        raise SessionFormatError(f"{where}.{key}", "expected 16 numbers in a flat list, got 4 rows")
    return number_list(value, f"{where}.{key}", 16)


def number_list(value: Any, where: str, length: int) -> FloatArray:
    if not isinstance(value, list):
        raise SessionFormatError(
            where, f"expected a list of {length} numbers, got {json_type_name(value)}"
        )
    if len(value) != length:
        raise SessionFormatError(where, f"expected {length} numbers, got {len(value)}")
    for j, item in enumerate(value):
        if isinstance(item, bool) or not isinstance(item, (int, float)):
            raise SessionFormatError(
                f"{where}[{j}]", f"expected a number, got {json_type_name(item)}"
            )
        _finite(item, f"{where}[{j}]")
    return np.asarray(value, dtype=np.float64)


def _finite(value: float, where: str) -> float:
    """``value`` as a finite float (an integer too large for one, such as Python's JSON parser
    reads from 400 digits, is refused, not an ``OverflowError``)."""
    try:
        number = float(value)
    except OverflowError:
        raise SessionFormatError(where, "number out of range (beyond ±1.8e308)") from None
    if not math.isfinite(number):
        raise SessionFormatError(where, f"non-finite number {value}")
    return number


def rigid_pose(matrix: FloatArray, where: str) -> FloatArray:
    defect = rigidity_defect(matrix)
    if defect is not None:
        raise SessionFormatError(where, defect)
    distance_m = float(np.max(np.abs(matrix[:3, 3])))
    if distance_m > MAX_TRANSLATION_M:
        raise SessionFormatError(
            where, f"translation {distance_m:.3g} m is beyond {MAX_TRANSLATION_M:.0f} m"
        )
    return orthonormalized(matrix)


def maybe_not_rigid(poses: FloatArray) -> npt.NDArray[np.bool_]:
    """(N,) for (N, 4, 4) ``poses``: True where :func:`rigid_pose` may refuse the matrix, all at
    once. Every matrix it refuses is flagged (the same tests with half their tolerances), so one
    left out surely passes; the flagged ones are checked one by one."""
    with np.errstate(all="ignore"):  # non-finite or huge entries are named, not computed
        rotations = poses[:, :3, :3]
        margin = 0.5 * ORTHONORMAL_TOLERANCE
        suspect = ~np.all(np.isfinite(poses), axis=(1, 2))
        suspect |= np.any(np.abs(poses[:, 3] - [0.0, 0.0, 0.0, 1.0]) > 0.5e-3, axis=1)
        suspect |= np.max(np.abs(rotations), axis=(1, 2)) > 1.0 + margin
        gram = np.swapaxes(rotations, 1, 2) @ rotations
        suspect |= np.max(np.abs(gram - np.eye(3)), axis=(1, 2)) > margin
        suspect |= ~(np.linalg.det(np.where(suspect[:, None, None], 1.0, rotations)) > 0)
        suspect |= np.max(np.abs(poses[:, :3, 3]), axis=1) > 0.5 * MAX_TRANSLATION_M
    return np.asarray(suspect, dtype=np.bool_)


def within_pixels(values: FloatArray, where: str) -> None:
    worst = int(np.argmax(np.abs(values)))
    if abs(values[worst]) > MAX_PIXELS:
        raise SessionFormatError(
            f"{where}[{worst}]", f"{values[worst]:.3g} px is beyond {MAX_PIXELS:.0f} px"
        )
