"""What the API derives from a map version, kept per process: map versions never change, so a
path graph, a version's tag poses or a ready document (app-map, GeoJSON, as bytes) read once can be
reused until evicted (thread-safe LRU, bounded by entries and by the bytes of its documents)."""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable, Hashable
from typing import Any, TypeVar

T = TypeVar("T")

#: Entries kept per API process (path graphs, tag tables and documents of the most used versions).
VERSION_CACHE_ENTRIES = 256
#: Bytes of documents kept per API process (``INVISIBLE_MAP_VERSION_CACHE_BYTES``).
VERSION_CACHE_BYTES = 256 * 2**20


def size_in_bytes(value: object) -> int:
    """What a cached value counts against the byte bound: the length of bytes, the sum over a
    tuple of bytes, a document's ``size_bytes``; 0 for anything else (path graphs and tag tables
    are bounded by entries)."""
    if isinstance(value, bytes | bytearray | memoryview):
        return len(value)
    if isinstance(value, tuple):
        return sum(size_in_bytes(item) for item in value)
    size = getattr(value, "size_bytes", None)
    return size if isinstance(size, int) else 0


class VersionCache:
    """An LRU of values derived from immutable map versions, keyed by ``(what, version_id)``:
    at most ``max_entries`` values and ``max_bytes`` bytes of documents (a document larger than
    ``max_bytes`` is made and served, not kept)."""

    def __init__(
        self, max_entries: int = VERSION_CACHE_ENTRIES, max_bytes: int = VERSION_CACHE_BYTES
    ) -> None:
        self.max_entries = max_entries
        self.max_bytes = max_bytes
        self._values: OrderedDict[Hashable, tuple[Any, int]] = OrderedDict()
        self._bytes = 0
        self._lock = threading.Lock()

    @property
    def size_bytes(self) -> int:
        """Bytes of documents kept now."""
        return self._bytes

    def __len__(self) -> int:
        return len(self._values)

    def peek(self, key: Hashable) -> Any | None:
        """The cached value for ``key`` or None, without loading anything (the event loop's
        look-up: a miss goes to a thread)."""
        with self._lock:
            entry = self._values.get(key)
            if entry is None:
                return None
            self._values.move_to_end(key)
            return entry[0]

    def get(self, key: Hashable, load: Callable[[], T]) -> T:
        """The cached value for ``key``, or ``load()``'s (cached unless it raises)."""
        with self._lock:
            entry = self._values.get(key)
            if entry is not None:
                self._values.move_to_end(key)
                value: T = entry[0]
                return value
        value = load()
        self.put(key, value)
        return value

    def put(self, key: Hashable, value: object) -> None:
        """Keep ``value`` for ``key`` (evicting the least recently used beyond the bounds)."""
        size = size_in_bytes(value)
        if size > self.max_bytes:
            return
        with self._lock:
            previous = self._values.pop(key, None)
            if previous is not None:
                self._bytes -= previous[1]
            self._values[key] = (value, size)
            self._bytes += size
            while len(self._values) > self.max_entries or self._bytes > self.max_bytes:
                _, (_, evicted_size) = self._values.popitem(last=False)
                self._bytes -= evicted_size
