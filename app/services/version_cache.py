"""What the API derives from a map version, kept per process: map versions never change, so a
path graph or a version's tag poses read once can be reused until evicted (thread-safe LRU)."""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable, Hashable
from typing import Any, TypeVar

T = TypeVar("T")

#: Entries kept per API process (path graphs and tag tables of the most used versions).
VERSION_CACHE_ENTRIES = 64


class VersionCache:
    """An LRU of values derived from immutable map versions, keyed by ``(what, version_id)``."""

    def __init__(self, max_entries: int = VERSION_CACHE_ENTRIES) -> None:
        self.max_entries = max_entries
        self._values: OrderedDict[Hashable, Any] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, key: Hashable, load: Callable[[], T]) -> T:
        """The cached value for ``key``, or ``load()``'s (cached unless it raises)."""
        with self._lock:
            if key in self._values:
                self._values.move_to_end(key)
                value: T = self._values[key]
                return value
        value = load()
        with self._lock:
            self._values[key] = value
            self._values.move_to_end(key)
            while len(self._values) > self.max_entries:
                self._values.popitem(last=False)
        return value
