"""Counting what a module reads from files: a stand-in for the module's ``os`` that counts the
bytes read from every file it opens (``os.fdopen``), and can make ``os.fstat`` report a smaller
size than a file has (a file that grows after its size is checked).

    reads = ReadCounting(fstat_size=0)
    monkeypatch.setattr(firebase_export, "os", reads)
    ...
    assert reads.bytes_read == 2**20 + 1
"""

from __future__ import annotations

import os
from typing import Any


class ReadCounting:
    """``os`` with ``fdopen`` counting the bytes read (``bytes_read``, ``opened``) and, with
    ``fstat_size``, ``fstat`` reporting that size."""

    def __init__(self, *, fstat_size: int | None = None) -> None:
        self.fstat_size = fstat_size
        self.bytes_read = 0
        self.opened = 0

    def __getattr__(self, name: str) -> Any:
        return getattr(os, name)

    def fdopen(self, descriptor: int, *args: Any, **kwargs: Any) -> _CountedFile:
        self.opened += 1
        return _CountedFile(os.fdopen(descriptor, *args, **kwargs), self)

    def fstat(self, descriptor: int) -> os.stat_result:
        real = os.fstat(descriptor)
        if self.fstat_size is None:
            return real
        fields = list(real[:10])
        fields[6] = self.fstat_size  # st_size
        return os.stat_result(fields)


class _CountedFile:
    def __init__(self, file: Any, counter: ReadCounting) -> None:
        self._file = file
        self._counter = counter

    def __enter__(self) -> _CountedFile:
        return self

    def __exit__(self, *exc: object) -> None:
        self._file.close()

    def __getattr__(self, name: str) -> Any:
        return getattr(self._file, name)

    def read(self, size: int = -1) -> bytes:
        data: bytes = self._file.read(size)
        self._counter.bytes_read += len(data)
        return data
