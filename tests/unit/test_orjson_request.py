"""``OrjsonRequest.json()`` (the API's bodies, ``app.web.route_class``) reads every body as the
standard library's parser, which FastAPI uses, does: the same values, down to each float's bits,
and the same refusals; integers beyond 64 bits, the one documented difference, as floats. And it
is the door of text: a string no database can hold (a NUL, a lone surrogate), in any encoding
the standard library reads, is refused with its path (issue 28, finding 1)."""

from __future__ import annotations

import asyncio
import json
import math
import random
import struct
from typing import Any

import pytest

from app.web.route_class import OrjsonRequest, UnstorableText


def read(body: bytes) -> Any:
    async def receive() -> dict[str, Any]:
        return {"type": "http.request", "body": body, "more_body": False}

    request = OrjsonRequest({"type": "http", "method": "POST", "headers": []}, receive)
    return asyncio.run(request.json())


def same(a: Any, b: Any) -> bool:
    """Equal, with floats compared bit for bit (and NaN equal to NaN)."""
    if isinstance(a, float) and isinstance(b, float):
        return struct.pack("<d", a) == struct.pack("<d", b) or (math.isnan(a) and math.isnan(b))
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(same(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(same(a[k], b[k]) for k in a)
    return type(a) is type(b) and a == b


def random_doubles(count: int) -> list[float]:
    generator = random.Random(7)
    values = []
    while len(values) < count:
        (value,) = struct.unpack("<d", generator.getrandbits(64).to_bytes(8, "little"))
        if math.isfinite(value):
            values.append(value)
    return values


BODIES = [
    json.dumps({"poses": [{"id": 3, "timestamp": 0.1, "pose": random_doubles(16)}]}).encode(),
    json.dumps(random_doubles(2000)).encode(),
    b"[0.1000000000000000055511151231257827, 1e-400, 4.9e-324, 2.2250738585072011e-308]",
    b"[123456789012345678901234567890.5, -0.0, 1E5, 1e+5, 0.5e-3]",
    b'{"a": 1, "a": 2, "b": [true, false, null]}',
    b"[9223372036854775807, 9223372036854775808, 18446744073709551615, -9223372036854775808]",
    b'{"s": "caf\\u00e9 \\ud83d\\ude00 \\u00ff", "t": "\\u00e9"}',
    # orjson refuses these; the standard library reads them
    b"[NaN, Infinity, -Infinity]",
    b"[1e400]",
    b"[" + b"1" + b"0" * 400 + b"]",
    '{"s": "é"}'.encode("utf-16"),
]


@pytest.mark.parametrize("body", BODIES, ids=range(len(BODIES)))
def test_a_body_reads_as_the_standard_library_reads_it(body):
    assert same(read(body), json.loads(body))


@pytest.mark.parametrize("body", [b"{", b'{"a": }', b"[1, 2", b""])
def test_a_malformed_body_raises_what_the_standard_library_raises(body):
    try:
        json.loads(body)
    except ValueError as err:  # JSONDecodeError
        expected = err
    with pytest.raises(type(expected)) as raised:
        read(body)
    assert str(raised.value) == str(expected)


def test_bytes_that_are_no_text_raise_a_json_error_naming_the_encoding():
    """The standard library raises UnicodeDecodeError here; the request raises JSONDecodeError,
    so that every malformed body is answered alike (400 invalid_json)."""
    with pytest.raises(UnicodeDecodeError):
        json.loads(b"\xff\xfe\x00")
    with pytest.raises(json.JSONDecodeError, match="not UTF-8 text"):
        read(b"\xff\xfe\x00")


def test_an_integer_beyond_64_bits_reads_as_the_nearest_float():
    assert same(read(b"[-9223372036854775809, 1, 2.5]"), [-9223372036854775809.0, 1, 2.5])
    assert same(read(b"[18446744073709551616]"), [18446744073709551616.0])


@pytest.mark.parametrize(
    ("body", "field", "reason"),
    [
        (b'{"s": "caf\\u00e9 \\u0000"}', "s", "NUL"),
        (b'{"a": [1, {"b": "\\ud800"}]}', "a[1].b", "lone surrogate (U+D800)"),
        (b'{"a": {"k\\u0000": 1}}', "a", "a key holds a NUL"),
        ('{"s": "\\u0000"}'.encode("utf-16"), "s", "NUL"),
    ],
    ids=["nul", "surrogate", "key", "utf-16"],
)
def test_a_body_holding_text_no_database_holds_is_refused_naming_it(body, field, reason):
    json.loads(body)  # valid JSON all the same
    with pytest.raises(UnstorableText) as raised:
        read(body)
    assert (raised.value.status_code, raised.value.field) == (422, field)
    assert reason in str(raised.value.detail)
