"""One JSON document read a value at a time from byte chunks, holding only a bounded window of
its text: the upload parser walks a 45 MiB session without building its object graph.

    stream = JsonStream(chunks, source="upload")     # chunks: UTF-8 bytes, any sizes
    for key in stream.object_keys():                  # after each key, read or skip its value
        if key == "pose_data":
            for entry in stream.array_items():        # one element decoded at a time
                ...
        else:
            stream.skip_value()
    stream.end()                                      # nothing but whitespace may follow

Each element is decoded by the standard library's ``json`` decoder, so values, numbers and error
messages are those of ``json.loads``; a syntax error raises :class:`SessionFormatError` with the
reason and the line and column in the whole document, as ``json.loads`` would give them. The
window holds :data:`WINDOW_CHARS` characters, more only while one value is larger than that.
"""

from __future__ import annotations

import codecs
import json
import re
import zlib
from collections.abc import Iterable, Iterator
from typing import Any

from app.domain.errors import SessionFormatError
from app.domain.json_values import value_error_reason

#: Characters of text held ahead of the reading position (about 1 MiB of ASCII JSON).
WINDOW_CHARS = 1 << 20
#: A decoding error this close to the end of the window may be a value cut by the window.
_CUT_MARGIN_CHARS = 16
_WHITESPACE = re.compile(r"[ \t\n\r]*")
_GZIP_WBITS = 16 + zlib.MAX_WBITS
_DECODER = json.JSONDecoder()


class JsonStream:
    """A cursor over one JSON document arriving as UTF-8 byte chunks (a leading BOM is dropped)."""

    def __init__(
        self, chunks: Iterable[bytes], *, source: str = "upload", window_chars: int = WINDOW_CHARS
    ) -> None:
        self.source = source
        self._chunks = iter(chunks)
        self._utf8 = codecs.getincrementaldecoder("utf-8-sig")()
        self._window_chars = window_chars
        self._text = ""
        self._pos = 0
        self._ended = False
        self._lines_before = 0  # newlines in the text already dropped
        self._column_before = 0  # characters of the current line already dropped

    # ----------------------------------------------------------------- reading structure

    def peek(self) -> str:
        """The next character that is not whitespace, not consumed ('' at the end)."""
        while True:
            match = _WHITESPACE.match(self._text, self._pos)
            self._pos = match.end() if match else self._pos
            if self._pos < len(self._text):
                return self._text[self._pos]
            if not self._read():
                return ""

    def object_keys(self) -> Iterator[str]:
        """The keys of the object that comes next; the caller reads or skips each key's value
        before asking for the next key."""
        self._take("{", "Expecting value")
        if self.peek() == "}":
            self._pos += 1
            return
        while True:
            if self.peek() != '"':
                raise self.syntax_error("Expecting property name enclosed in double quotes")
            key = self.value()
            self._take(":", "Expecting ':' delimiter")
            yield key
            after = self.peek()
            self._pos += 1
            if after == "}":
                return
            if after != ",":
                self._pos -= 1
                raise self.syntax_error("Expecting ',' delimiter")

    def array_items(self) -> Iterator[Any]:
        """The elements of the array that comes next, each decoded as it is reached."""
        self._take("[", "Expecting value")
        if self.peek() == "]":
            self._pos += 1
            return
        while True:
            yield self.value()
            after = self.peek()
            self._pos += 1
            if after == "]":
                return
            if after != ",":
                self._pos -= 1
                raise self.syntax_error("Expecting ',' delimiter")

    def value(self) -> Any:
        """The next value, decoded whole."""
        self.peek()
        if len(self._text) - self._pos < self._window_chars // 2:
            self._fill(self._window_chars)
        while True:
            try:
                value, end = _DECODER.raw_decode(self._text, self._pos)
            except json.JSONDecodeError as err:
                cut = err.pos >= len(self._text) - _CUT_MARGIN_CHARS or err.msg.startswith(
                    "Unterminated string"
                )
                if cut and self._fill(2 * (len(self._text) - self._pos) + 1):
                    continue
                raise self.syntax_error(err.msg, err.pos) from None
            except ValueError as err:  # an integer of more digits than Python converts
                raise SessionFormatError(
                    "", f"{self.source} is not valid JSON: {value_error_reason(err)}"
                ) from None
            except RecursionError:
                raise SessionFormatError(
                    "", f"{self.source} is nested too deeply to be a session"
                ) from None
            # a number at the very end of the window may go on in the next chunk
            if end == len(self._text) and self._fill(len(self._text) - self._pos + 1):
                continue
            self._pos = end
            return value

    def skip_value(self) -> None:
        """Pass over the next value; an array is passed an element at a time."""
        if self.peek() == "[":
            for _ in self.array_items():
                pass
        else:
            self.value()

    def end(self) -> None:
        """Check that only whitespace follows the document."""
        if self.peek():
            raise self.syntax_error("Extra data")

    def syntax_error(self, reason: str, pos: int | None = None) -> SessionFormatError:
        """The format error for invalid JSON at ``pos`` of the window (default: here)."""
        pos = self._pos if pos is None else pos
        newlines = self._text.count("\n", 0, pos)
        if newlines:
            line = self._lines_before + newlines + 1
            column = pos - self._text.rfind("\n", 0, pos)
        else:
            line = self._lines_before + 1
            column = self._column_before + pos + 1
        return SessionFormatError(
            "", f"{self.source} is not valid JSON: {reason} at line {line} column {column}"
        )

    # ----------------------------------------------------------------- the window

    def _take(self, char: str, reason: str) -> None:
        if self.peek() != char:
            raise self.syntax_error(reason)
        self._pos += 1

    def _fill(self, chars: int) -> bool:
        """Read until ``chars`` characters lie ahead of the position; False if the input ended
        with nothing more read."""
        grew = False
        while len(self._text) - self._pos < chars and self._read():
            grew = True
        return grew

    def _read(self) -> bool:
        """Append the next chunk's text, dropping what was read; False at the end."""
        while not self._ended:
            chunk = next(self._chunks, None)
            try:
                if chunk is None:
                    self._ended = True
                    text = self._utf8.decode(b"", final=True)
                else:
                    text = self._utf8.decode(chunk)
            except UnicodeDecodeError as err:
                raise SessionFormatError(
                    "", f"{self.source} is not UTF-8 text: {err.reason}"
                ) from None
            if text:
                self._append(text)
                return True
        return False

    def _append(self, text: str) -> None:
        if self._pos:
            newlines = self._text.count("\n", 0, self._pos)
            if newlines:
                self._lines_before += newlines
                self._column_before = self._pos - self._text.rfind("\n", 0, self._pos) - 1
            else:
                self._column_before += self._pos
            self._text = self._text[self._pos :] + text
            self._pos = 0
        else:
            self._text += text


def gunzipped(
    chunks: Iterable[bytes], max_chunk_bytes: int, *, complete: bool = False
) -> Iterator[bytes]:
    """The inflated bytes of gzip ``chunks`` (one or more members), at most ``max_chunk_bytes``
    at a time (a stored upload read a piece at a time, for a download or a parse). With
    ``complete``: EOFError if the last member is cut short (a parse of what came would blame
    the JSON instead)."""
    inflater = zlib.decompressobj(_GZIP_WBITS)
    started = False
    for chunk in chunks:
        pending = chunk
        while pending:
            started = True
            out = inflater.decompress(pending, max_chunk_bytes)
            if out:
                yield out
            if inflater.eof:  # another member may follow
                pending, started = inflater.unused_data, False
                inflater = zlib.decompressobj(_GZIP_WBITS)
            else:
                pending = inflater.unconsumed_tail
    if complete and started and not inflater.eof:
        raise EOFError("the stream is cut short")
