"""Answers as the docs show them, compared with answers as the server gives them.

The README and ``docs/api.md`` show shortened answers: JSON with ``…`` where something is left
out, and command-line output lines. This module reads them as patterns and says, line by line,
where a real answer differs:

- ``…`` as a member of an object or an item of a list leaves out any number of members or items
  (``{"id":9,…}``, ``[{"a":1},…,{"z":2}]``); ``[…]`` and ``{…}`` leave out a whole value; an
  object shown without ``…`` must have exactly the keys shown; a list without ``…`` exactly the
  items shown.
- ``…`` inside a string leaves out part of it: the parts shown must appear, in order.
- A number is compared to the precision shown: ``95.36`` matches 95.355 ≤ x ≤ 95.365, ``8`` only
  8 (an integer answer) and ``0.0857`` matches 0.08565 ≤ x ≤ 0.08575.
- A text line (command-line output) is compared the same way: its words exactly, its numbers to
  the precision shown, ``…`` leaves out any text; a Markdown table row is matched by its first
  cell, with the header row shown above it naming the columns.
- What differs on every run for every reader (a made-up key, a time stamp, a duration) is named in
  :data:`VARYING`, with the reason, and not compared.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass
from decimal import Decimal
from typing import Any

ELLIPSIS = "…"

#: Keys (JSON) and table columns (text) whose values differ on every run, whatever the docs say.
VARYING: dict[str, str] = {
    "created_at": "the time of the reader's run",
    "updated_at": "the time of the reader's run",
    "started_at": "the time of the reader's run",
    "finished_at": "the time of the reader's run",
    "heartbeat_at": "the time of the reader's run",
    "duration_s": "a duration: the machine's speed and load",
    "opt ms": "a duration: the machine's speed and load",
    "worker": "names the worker process (host, pid)",
    "location@localization": "names the navigation session's id (see id@localization)",
    "id@localization": (
        "a navigation session's id counts the navigation sessions started before it (the README's"
        " quick start starts one per run)"
    ),
}

#: A number written in the docs: not part of a word (``pgt_tester3``, ``floor_2``, ``h1``).
_NUMBER = re.compile(r"(?<![\w.])-?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?(?![\w.])")
#: A duration in text output (``10.8 ms``), not compared.
_DURATION = re.compile(r"(?<![\w.])\d+(?:\.\d+)? ?ms\b")


# --------------------------------------------------------------------------- patterns


@dataclass(frozen=True)
class Number:
    """A number as written: its value and its precision (half a unit of its last digit)."""

    text: str

    @property
    def value(self) -> float:
        return float(self.text)

    @property
    def tolerance(self) -> float:
        exponent = Decimal(self.text).as_tuple().exponent
        assert isinstance(exponent, int)
        return 0.5 * 10.0**exponent

    def matches(self, actual: Any) -> bool:
        if isinstance(actual, bool) or not isinstance(actual, int | float):
            return False
        if "." not in self.text and "e" not in self.text.lower():
            return bool(actual == int(self.text))
        # 1e-9 of slack for the binary representation of the shown decimal
        return math.isfinite(actual) and abs(actual - self.value) <= self.tolerance * (1 + 1e-9)


@dataclass(frozen=True)
class Elided:
    """``…``: a member of an object or an item of a list left out, or a whole value."""


@dataclass(frozen=True)
class ObjectPattern:
    members: tuple[tuple[str, Any], ...]
    open: bool


@dataclass(frozen=True)
class ArrayPattern:
    head: tuple[Any, ...]
    tail: tuple[Any, ...]
    open: bool


class ElidedJsonError(ValueError):
    """The docs' JSON (with ``…``) does not parse."""


class _Parser:
    def __init__(self, text: str) -> None:
        self.text = text
        self.at = 0

    def error(self, what: str) -> ElidedJsonError:
        return ElidedJsonError(
            f"{what} at character {self.at}: …{self.text[self.at : self.at + 30]}"
        )

    def skip(self) -> None:
        while self.at < len(self.text) and self.text[self.at] in " \t\r\n":
            self.at += 1

    def peek(self) -> str:
        self.skip()
        return self.text[self.at] if self.at < len(self.text) else ""

    def expect(self, char: str) -> None:
        if self.peek() != char:
            raise self.error(f"expected {char!r}")
        self.at += 1

    def value(self) -> Any:
        char = self.peek()
        if char == "{":
            return self.object()
        if char == "[":
            return self.array()
        if char == '"':
            return self.string()
        if char == ELLIPSIS:
            self.at += 1
            return Elided()
        match = re.compile(r"-?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?").match(self.text, self.at)
        if match:
            self.at = match.end()
            return Number(match.group())
        for word, meaning in (("true", True), ("false", False), ("null", None)):
            if self.text.startswith(word, self.at):
                self.at += len(word)
                return meaning
        raise self.error("expected a value")

    def string(self) -> str:
        decoder = json.JSONDecoder()
        try:
            text, end = decoder.raw_decode(self.text, self.at)
        except json.JSONDecodeError as err:
            raise self.error(f"bad string ({err.msg})") from err
        self.at = end
        assert isinstance(text, str)
        return text

    def object(self) -> ObjectPattern:
        self.expect("{")
        members: list[tuple[str, Any]] = []
        is_open = False
        while self.peek() != "}":
            if self.peek() == ELLIPSIS:
                self.at += 1
                is_open = True
            else:
                key = self.string()
                self.expect(":")
                members.append((key, self.value()))
            if self.peek() != ",":
                break
            self.at += 1
        self.expect("}")
        return ObjectPattern(members=tuple(members), open=is_open)

    def array(self) -> ArrayPattern:
        self.expect("[")
        head: list[Any] = []
        tail: list[Any] = []
        is_open = False
        while self.peek() != "]":
            item = self.value()
            if isinstance(item, Elided):
                if is_open:
                    raise self.error("two … in one list")
                is_open = True
            else:
                (tail if is_open else head).append(item)
            if self.peek() != ",":
                break
            self.at += 1
        self.expect("]")
        return ArrayPattern(head=tuple(head), tail=tuple(tail), open=is_open)


def parse_elided_json(text: str) -> Any:
    """The pattern of a JSON text in which ``…`` leaves things out (see the module's doc)."""
    parser = _Parser(text)
    pattern = parser.value()
    if parser.peek():
        raise parser.error("text after the value")
    return pattern


def compare_json(pattern: Any, actual: Any, *, path: str = "$", context: str = "") -> list[str]:
    """Where ``actual`` differs from ``pattern``: one line per difference, naming its path.
    ``context`` qualifies VARYING keys (``id@localization``)."""
    if isinstance(pattern, Elided):
        return []
    if isinstance(pattern, ObjectPattern):
        if not isinstance(actual, dict):
            return [f"{path}: the docs show an object, the server answered {_short(actual)}"]
        problems = []
        for key, value in pattern.members:
            where = f"{path}.{key}"
            if key in VARYING or f"{key}@{context}" in VARYING:
                if key not in actual:
                    problems.append(f"{where}: missing from the answer")
                continue
            if key not in actual:
                problems.append(f"{where}: missing from the answer")
                continue
            problems += compare_json(value, actual[key], path=where, context=context)
        if not pattern.open:
            extra = sorted(set(actual) - {key for key, _ in pattern.members})
            if extra:
                problems.append(f"{path}: the answer has keys the docs do not show: {extra}")
        return problems
    if isinstance(pattern, ArrayPattern):
        if not isinstance(actual, list):
            return [f"{path}: the docs show a list, the server answered {_short(actual)}"]
        shown = len(pattern.head) + len(pattern.tail)
        if (pattern.open and len(actual) < shown) or (not pattern.open and len(actual) != shown):
            return [f"{path}: the docs show {shown} items, the server answered {len(actual)}"]
        problems = []
        for index, item in enumerate(pattern.head):
            problems += compare_json(item, actual[index], path=f"{path}[{index}]", context=context)
        for back, item in enumerate(reversed(pattern.tail), start=1):
            index = len(actual) - back
            problems += compare_json(item, actual[index], path=f"{path}[{index}]", context=context)
        return problems
    if isinstance(pattern, Number):
        if pattern.matches(actual):
            return []
        return [f"{path}: the docs show {pattern.text}, the server answered {_short(actual)}"]
    if isinstance(pattern, str):
        if isinstance(actual, str) and _string_matches(pattern, actual):
            return []
        return [
            f"{path}: the docs show {json.dumps(pattern)}, the server answered {_short(actual)}"
        ]
    if pattern is actual or (pattern is None and actual is None):
        return []
    return [f"{path}: the docs show {json.dumps(pattern)}, the server answered {_short(actual)}"]


def _string_matches(pattern: str, actual: str) -> bool:
    if ELLIPSIS not in pattern:
        return pattern == actual
    parts = pattern.split(ELLIPSIS)
    regex = ".*?".join(re.escape(part) for part in parts)
    return re.fullmatch(regex, actual, re.DOTALL) is not None


def _short(value: Any) -> str:
    text = json.dumps(value, ensure_ascii=False)
    return text if len(text) <= 200 else text[:200] + "…"


# --------------------------------------------------------------------------- text output


def compare_text(shown: list[str], output: str) -> list[str]:
    """Where ``output`` (a command's printed lines) differs from the lines ``shown``.

    Each line shown must match one line of the output, in order: the same words, numbers to the
    precision shown, ``…`` for any text, durations (``10.8 ms``) not compared. A table row
    (``| name | 1 | …``) is found by its first cell; the row shown just above it, if it is the
    table's header, names the columns, and the VARYING ones are not compared."""
    lines = output.splitlines()
    problems: list[str] = []
    header: list[str] | None = None
    start = 0
    for line in shown:
        if line.startswith("|"):
            cells = _cells(line)
            if set(line) <= set("|-: "):
                continue  # the table's rule
            if header is None and not any(_NUMBER.search(cell) for cell in cells):
                header = cells
                found = _find(lines, start, lambda text, cells=cells: _cells(text) == cells)
                if found is None:
                    problems.append(f"the table's header {line!r} is not in the output")
                else:
                    start = found + 1
                continue
            found = _find(lines, start, lambda text, cells=cells: _cells(text)[:1] == cells[:1])
            if found is None:
                problems.append(f"no row {cells[0]!r} in the output:\n{output}")
                continue
            start = found + 1
            problems += _compare_row(cells, _cells(lines[found]), header)
            continue
        regex, numbers = _line_pattern(line)
        found = _find(lines, start, lambda text, regex=regex: regex.fullmatch(text) is not None)
        if found is None:
            problems.append(f"no line like {line!r} in the output:\n{output}")
            continue
        start = found + 1
        match = regex.fullmatch(lines[found])
        assert match is not None
        for number, printed in zip(numbers, match.groups(), strict=True):
            if number is not None and not number.matches(float(printed)):
                problems.append(
                    f"{line!r}: the docs show {number.text}, the output has {printed}: "
                    f"{lines[found]!r}"
                )
    return problems


def _find(lines: list[str], start: int, test: Any) -> int | None:
    return next((index for index in range(start, len(lines)) if test(lines[index])), None)


def _cells(line: str) -> list[str]:
    return [cell.strip() for cell in line.strip().strip("|").split("|")]


def _compare_row(shown: list[str], printed: list[str], header: list[str] | None) -> list[str]:
    if len(shown) != len(printed):
        return [f"row {shown[0]!r}: the docs show {len(shown)} cells, the output has {printed}"]
    problems = []
    for column, (cell, value) in enumerate(zip(shown, printed, strict=True)):
        name = header[column] if header is not None and column < len(header) else str(column)
        if name in VARYING or cell == ELLIPSIS:
            continue
        if _NUMBER.fullmatch(cell.rstrip("%")) and _NUMBER.fullmatch(value.rstrip("%")):
            if cell.endswith("%") == value.endswith("%") and Number(cell.rstrip("%")).matches(
                float(value.rstrip("%"))
            ):
                continue
        elif cell == value:
            continue
        problems.append(f"row {shown[0]!r}, column {name!r}: the docs show {cell}, output {value}")
    return problems


def _line_pattern(line: str) -> tuple[re.Pattern[str], list[Number | None]]:
    """A regex for a shown line, with a group per number shown (None: a duration, not
    compared)."""
    pieces: list[str] = []
    numbers: list[Number | None] = []
    at = 0
    tokens = re.compile(f"{_DURATION.pattern}|{_NUMBER.pattern}| *{ELLIPSIS} *| +")
    for match in tokens.finditer(line):
        pieces.append(re.escape(line[at : match.start()]))
        token = match.group()
        if ELLIPSIS in token:
            pieces.append(".*?")
        elif token.isspace():
            pieces.append(" +")
        elif _DURATION.fullmatch(token):
            pieces.append(r"(\d+(?:\.\d+)?) ?ms")
            numbers.append(None)
        else:
            pieces.append(r"(-?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?)")
            numbers.append(Number(token))
        at = match.end()
    pieces.append(re.escape(line[at:]))
    return re.compile("".join(pieces)), numbers
