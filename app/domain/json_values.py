"""Small helpers for reading JSON documents that people and phones send us.

json_type_name([1, 2])          # "a list", for messages like "expected an object, got a list"
gunzip_if_compressed(raw)       # the bytes, decompressed when they start with gzip's magic
finite_or_none(math.nan)        # None: JSON has no NaN or infinity, a measure not made is null
value_error_reason(err)         # a ValueError of json.loads as one line, the same however read
"""

from __future__ import annotations

import gzip
import math
import zlib
from collections.abc import Mapping, Sequence
from typing import Any

GZIP_MAGIC = b"\x1f\x8b"


def value_error_reason(err: Exception) -> str:
    """A ``ValueError`` of decoding JSON (bad UTF-8, an integer of more digits than Python
    converts) as one line for a message. Python's advice to the programmer (after the ';') is
    left out, and so is its count of an integer's digits: "Exceeds the limit (4300 digits) for
    integer string conversion", the same whether the document was read whole or streamed (a
    stream holds part of a long integer and would count that part)."""
    return str(err).partition(";")[0].partition(": value has")[0]


def json_type_name(value: Any) -> str:
    """How a decoded JSON value reads in an error message: "null", "a number", "an object", …"""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "a boolean"
    if isinstance(value, (int, float)):
        return "a number"
    if isinstance(value, str):
        return "a string"
    if isinstance(value, Mapping):
        return "an object"
    if isinstance(value, Sequence):
        return "a list"
    return type(value).__name__


def gunzip_if_compressed(raw: bytes) -> bytes:
    """``raw`` gunzipped if it is gzip, else unchanged; ValueError (with the reason) if corrupt."""
    if raw[:2] != GZIP_MAGIC:
        return raw
    try:
        return gzip.decompress(raw)
    except (OSError, EOFError, zlib.error) as err:
        raise ValueError(str(err)) from err


def finite_or_none(value: float) -> float | None:
    """``value`` as a float for a JSON document, None where it is NaN or infinite."""
    return float(value) if math.isfinite(value) else None
