"""API keys: creating one with its checks.

What the API routers and the dashboard pages both do; errors are :mod:`app.services.errors`.
"""

from __future__ import annotations

import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from datetime import UTC, datetime

from sqlalchemy.orm import Session

from app.services.errors import InvalidInput, require_text
from app.storage import keys
from app.storage.changes import KEY_CHANGES
from app.storage.orm import Role, utc_now

#: Keys one API process remembers (the least recently used beyond are forgotten).
PRINCIPAL_CACHE_ENTRIES = 10_000


@dataclass(frozen=True, slots=True, kw_only=True)
class _KeptKey:
    active: keys.ActiveKey
    checked_at_s: float
    change_total: int


class PrincipalCache:
    """Per process: the keys that worked, by digest, for ``ttl_s`` (0: none kept), so that a
    request needs no database read to know who calls. Bounds: a key revoked by another process
    (another API process, the CLI) is refused at most ``ttl_s`` after the revocation committed;
    one revoked in this process at once (``app.storage.changes.KEY_CHANGES`` drops every kept
    key); an ``expires_at`` is checked on every request, exactly. Unknown, revoked and expired
    keys are never kept (so random keys cannot grow it), and at most ``max_entries`` keys are."""

    def __init__(
        self,
        ttl_s: float,
        *,
        max_entries: int = PRINCIPAL_CACHE_ENTRIES,
        clock: Callable[[], float] = time.monotonic,
        now: Callable[[], datetime] = utc_now,
    ) -> None:
        self.ttl_s = ttl_s
        self.max_entries = max_entries
        self.clock = clock
        self.now = now
        self._kept: OrderedDict[str, _KeptKey] = OrderedDict()
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return len(self._kept)

    def cached(self, key: str) -> keys.Principal | None:
        """The principal of ``key`` if it is kept and still good, else None (then
        :meth:`authenticate` it)."""
        if not self._kept:
            return None
        digest = keys.key_digest(key)
        kept = self._kept.get(digest)
        if kept is None:
            return None
        expires_at = kept.active.expires_at
        if (
            self.clock() - kept.checked_at_s >= self.ttl_s
            or KEY_CHANGES.total != kept.change_total
            or (expires_at is not None and expires_at <= self.now())
        ):
            with self._lock:
                self._kept.pop(digest, None)
            return None
        return kept.active.principal

    def authenticate(
        self, db_session: Session, key: str, *, admin_key: str | None
    ) -> keys.Principal | None:
        """Check ``key`` in the database (:func:`app.storage.keys.active_key`) and keep it if it
        works."""
        change_total = KEY_CHANGES.total  # before the read: a revocation meanwhile wins
        checked_at_s = self.clock()
        active = keys.active_key(db_session, key, admin_key=admin_key, now=self.now())
        if active is None:
            return None
        if self.ttl_s > 0:
            digest = keys.key_digest(key)
            with self._lock:
                if self._kept and KEY_CHANGES.total != next(iter(self._kept.values())).change_total:
                    self._kept.clear()  # kept before a revocation: all stale
                self._kept[digest] = _KeptKey(
                    active=active, checked_at_s=checked_at_s, change_total=change_total
                )
                self._kept.move_to_end(digest)
                while len(self._kept) > self.max_entries:
                    self._kept.popitem(last=False)
        return active.principal


#: The longest name a key may have (the API's schema says the same).
MAX_KEY_NAME_CHARS = 100


def create_checked_key(
    db_session: Session, *, name: str, role: Role, expires_at: datetime | None
) -> tuple[keys.KeyInfo, str]:
    """Store a new key (422 naming the field if its name is empty, longer than
    ``MAX_KEY_NAME_CHARS`` or no storable text, if it would already have expired or if its expiry
    is beyond the year 9999 in UTC); returns it and its secret."""
    if not name or len(name) > MAX_KEY_NAME_CHARS:
        bound = f"at most {MAX_KEY_NAME_CHARS} characters" if name else "at least 1 character"
        raise InvalidInput("validation_error", f"name: String should have {bound}", field="name")
    require_text("name", name)
    if expires_at is not None:
        try:
            expires_at = expires_at.astimezone(UTC)
        except OverflowError:
            raise InvalidInput(
                "validation_error", "expires_at is beyond the year 9999 in UTC", field="expires_at"
            ) from None
        if expires_at <= datetime.now(UTC):
            raise InvalidInput("validation_error", "expires_at is in the past", field="expires_at")
    return keys.create_key(db_session, name=name, role=role, expires_at=expires_at)
