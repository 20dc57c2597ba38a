"""The number readers of ``app.domain.upload.fields``: a list of JSON numbers becomes a float64
array; anything else is named, down to the item. And the one rule of stored text: a NUL or a lone
surrogate, in a string or anywhere in a JSON document (keys too, at any depth), is named."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from app.domain.errors import SessionFormatError
from app.domain.upload.fields import json_text_fault, number_field, number_list, text_fault


def item_by_item(value: Any, where: str, length: int) -> np.ndarray:
    """What ``number_list`` must answer, written out."""
    if not isinstance(value, list):
        raise SessionFormatError(where, "not a list")
    if len(value) != length:
        raise SessionFormatError(where, "length")
    for j, item in enumerate(value):
        if isinstance(item, bool) or not isinstance(item, (int, float)):
            raise SessionFormatError(f"{where}[{j}]", "type")
        if not math.isfinite(float(item)):
            raise SessionFormatError(f"{where}[{j}]", "non-finite")
    return np.asarray(value, dtype=np.float64)


CASES = [
    [1.5, -2, 0, 3e300],
    [1, 2, 3, 4],
    [0.1, True, 2.0, 3.0],
    [0.1, None, 2.0, 3.0],
    [0.1, 2.0, "3", 3.0],
    [0.1, 2.0, 3.0, float("nan")],
    [float("-inf"), 2.0, 3.0, 4.0],
    [0.1, 2.0, 3.0],
    [0.1, 2.0, 3.0, 4.0, 5.0],
    [0.1, 2.0, [3.0], 4.0],
    [np.float64(0.5), 1.0, 2.0, 3.0],  # a float subclass: read item by item, accepted
    [2**63 + 5, 1.0, 2.0, 3.0],  # beyond int64, within float64
    (0.1, 2.0, 3.0, 4.0),
    {"a": 1},
]


@pytest.mark.parametrize("value", CASES, ids=range(len(CASES)))
def test_a_list_is_read_or_its_first_bad_item_named(value):
    try:
        expected: np.ndarray | str = item_by_item(value, "pose", 4)
    except SessionFormatError as err:
        expected = err.field
    if isinstance(expected, str):
        with pytest.raises(SessionFormatError) as raised:
            number_list(value, "pose", 4)
        assert raised.value.field == expected
        return
    got = number_list(value, "pose", 4)
    assert got.dtype == np.float64
    assert np.array_equal(got, expected)


def test_an_integer_beyond_float_range_is_named_not_an_overflow():
    # Python's JSON parser (FastAPI's) reads 400 digits as an int; float() of it overflows.
    huge = 10**400
    with pytest.raises(SessionFormatError) as err:
        number_list([0.0, 1.0, huge, 2.0], "poses[0].pose", 4)
    assert err.value.field == "poses[0].pose[2]"
    assert "out of range" in str(err.value)
    with pytest.raises(SessionFormatError) as err:
        number_field({"timestamp": -huge}, "timestamp", "poses[3]")
    assert err.value.field == "poses[3].timestamp"
    assert number_field({"timestamp": 2**70}, "timestamp", "poses[3]") == float(2**70)


@pytest.mark.parametrize(
    ("text", "fault"),
    [
        ("Room 210", None),
        ("Salle à manger 🚻", None),
        ("", None),
        ("a\x00b", "holds a NUL character (U+0000)"),
        ("a\ud800b", "holds a lone surrogate (U+D800), which is no text"),
        ("é\udfff", "holds a lone surrogate (U+DFFF), which is no text"),
        ("\udc80", "holds a lone surrogate (U+DC80), which is no text"),  # undecodable argv byte
    ],
)
def test_text_fault_names_what_no_database_holds(text, fault):
    assert text_fault(text) == fault


def test_json_text_fault_names_the_first_bad_string_by_its_path():
    assert json_text_fault({"a": [1, "ok", {"b": None}], "c": 2.5}) is None
    assert json_text_fault({"a": [1, "ok", {"b": "x\x00"}]}) == (
        "a[2].b",
        "holds a NUL character (U+0000)",
    )
    assert json_text_fault({"a": {"ok": 1, "k\ud800": 2}}) == (
        "a",
        "a key holds a lone surrogate (U+D800), which is no text",
    )
    assert json_text_fault({"\x00": 1}) == ("(top level)", "a key holds a NUL character (U+0000)")
    assert json_text_fault(["a", "b\x00"], "poses") == (
        "poses[1]",
        "holds a NUL character (U+0000)",
    )


def test_json_text_fault_reads_any_depth_without_recursing():
    deep: object = "\x00"
    for _ in range(20_000):  # 20 times Python's recursion limit
        deep = [deep]
    fault = json_text_fault(deep)
    assert fault is not None
    assert fault[0] == "[0]" * 20_000
