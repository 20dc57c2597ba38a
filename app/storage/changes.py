"""Counters of the changes this process commits, for the API's per-process caches.

    MAP_CHANGES.note(db_session, map_id)     # in the transaction that changes map ``map_id``
    MAP_CHANGES.count(map_id)                # compare with the count an entry was loaded at

A cache entry remembers the count it was loaded at and is stale as soon as the count moved: so
what this process commits is seen at once, and only what other processes commit waits for the
cache's time bound. The count moves when the transaction commits (a rolled-back change moves
nothing), after the rows are visible to any new transaction. Process-wide on purpose: every app
and dashboard page in the process shares them (more invalidation is always safe).
"""

from __future__ import annotations

import threading

from sqlalchemy import event
from sqlalchemy.orm import Session


class ChangeCounter:
    """A count of committed changes in this process, overall and per item id."""

    def __init__(self) -> None:
        self._total = 0
        self._per_item: dict[int, int] = {}
        self._lock = threading.Lock()

    @property
    def total(self) -> int:
        """Changes of any item so far."""
        return self._total

    def count(self, item_id: int) -> int:
        """Changes of ``item_id`` so far."""
        return self._per_item.get(item_id, 0)

    def bump(self, item_id: int | None = None) -> None:
        """Count a change (of ``item_id``, or of every item when None) now."""
        with self._lock:
            self._total += 1
            if item_id is None:
                for known in self._per_item:
                    self._per_item[known] += 1
            else:
                self._per_item[item_id] = self._per_item.get(item_id, 0) + 1

    def note(self, db_session: Session, item_id: int | None = None) -> None:
        """Count a change of ``item_id`` when ``db_session``'s transaction commits."""
        event.listen(db_session, "after_commit", lambda _session: self.bump(item_id), once=True)


#: Maps: their rows, sessions, versions' jobs (rebuilds), deletions, new maps.
MAP_CHANGES = ChangeCounter()
#: API keys: revocations.
KEY_CHANGES = ChangeCounter()
