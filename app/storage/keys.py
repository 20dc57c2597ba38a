"""API keys: ``im_<prefix>_<secret>``. Only the SHA-256 of the whole key is stored; the prefix
(public, unique) finds the row and the digests are compared in constant time. Keys are 190 bits of
randomness, so a fast hash is enough (there is nothing to brute-force as with passwords).
"""

from __future__ import annotations

import hashlib
import hmac
import secrets
from dataclasses import dataclass
from datetime import datetime

from sqlalchemy import delete, select
from sqlalchemy.orm import Session

from app.storage.changes import KEY_CHANGES
from app.storage.orm import AdminLogin, ApiKey, Role, utc_now
from app.storage.rows import info_from_row

KEY_SCHEME = "im"
#: ``uploaded_by`` of uploads made with ``INVISIBLE_MAP_ADMIN_KEY``.
ENVIRONMENT_ADMIN = "env-admin"


class KeyNotFound(LookupError):
    """Raised when no API key has the given id."""

    def __init__(self, key_id: int) -> None:
        super().__init__(f"API key {key_id} not found")
        self.key_id = key_id


@dataclass(frozen=True, slots=True, kw_only=True)
class KeyInfo:
    """An API key as listed (never with its secret)."""

    id: int
    name: str
    role: Role
    prefix: str
    created_at: datetime
    expires_at: datetime | None
    revoked_at: datetime | None
    last_used_at: datetime | None

    @classmethod
    def from_row(cls, row: ApiKey) -> KeyInfo:
        return info_from_row(cls, row)


@dataclass(frozen=True, slots=True, kw_only=True)
class Principal:
    """Who made a request: ``subject`` is ``key:<id>`` or :data:`ENVIRONMENT_ADMIN`."""

    subject: str
    role: Role
    key_id: int | None = None

    @property
    def is_admin(self) -> bool:
        return self.role is Role.ADMIN


def create_key(
    db_session: Session, *, name: str, role: Role, expires_at: datetime | None = None
) -> tuple[KeyInfo, str]:
    """Store a new key; returns it and its secret (shown once, never stored)."""
    prefix = secrets.token_hex(4)
    key = f"{KEY_SCHEME}_{prefix}_{secrets.token_urlsafe(24)}"
    row = ApiKey(
        name=name,
        role=role.value,
        prefix=prefix,
        secret_sha256=_digest(key),
        created_at=utc_now(),
        expires_at=expires_at,
    )
    db_session.add(row)
    db_session.flush()
    return KeyInfo.from_row(row), key


@dataclass(frozen=True, slots=True, kw_only=True)
class ActiveKey:
    """A key that works now, with what a cache of it must check again: when it expires."""

    principal: Principal
    expires_at: datetime | None


def authenticate(
    db_session: Session, key: str, *, admin_key: str | None = None, now: datetime | None = None
) -> Principal | None:
    """The principal a presented key stands for, or None if it is unknown, revoked or expired."""
    active = active_key(db_session, key, admin_key=admin_key, now=now)
    return None if active is None else active.principal


def active_key(
    db_session: Session, key: str, *, admin_key: str | None = None, now: datetime | None = None
) -> ActiveKey | None:
    """:func:`authenticate`, with the key's expiry (None for keys that never expire)."""
    now = now or utc_now()
    if admin_key is not None and hmac.compare_digest(_digest(key), _digest(admin_key)):
        return ActiveKey(
            principal=Principal(subject=ENVIRONMENT_ADMIN, role=Role.ADMIN), expires_at=None
        )
    scheme, _, rest = key.partition("_")
    prefix, _, secret = rest.partition("_")
    if scheme != KEY_SCHEME or not prefix or not secret:
        return None
    row = db_session.scalar(select(ApiKey).where(ApiKey.prefix == prefix))
    if row is None or not hmac.compare_digest(row.secret_sha256, _digest(key)):
        return None
    principal = _principal_if_active(row, now)
    return None if principal is None else ActiveKey(principal=principal, expires_at=row.expires_at)


def key_digest(key: str) -> str:
    """The SHA-256 of a presented key, as stored (hex)."""
    return _digest(key)


def active_principal(
    db_session: Session, key_id: int, *, now: datetime | None = None
) -> Principal | None:
    """The principal of key ``key_id`` if it still works (exists, not revoked, not expired), else
    None: how a login made with the key earlier (the admin dashboard's) is checked again."""
    row = db_session.get(ApiKey, key_id)
    return None if row is None else _principal_if_active(row, now or utc_now())


def _principal_if_active(row: ApiKey, now: datetime) -> Principal | None:
    if row.revoked_at is not None or (row.expires_at is not None and row.expires_at <= now):
        return None
    return Principal(subject=f"key:{row.id}", role=Role(row.role), key_id=row.id)


def touch(db_session: Session, key_id: int, *, now: datetime | None = None) -> None:
    """Record that a key was used."""
    row = db_session.get(ApiKey, key_id)
    if row is not None:
        row.last_used_at = now or utc_now()


def get_key(db_session: Session, key_id: int) -> KeyInfo:
    """One key (without its secret). Raises :class:`KeyNotFound`."""
    row = db_session.get(ApiKey, key_id)
    if row is None:
        raise KeyNotFound(key_id)
    return KeyInfo.from_row(row)


def list_keys(db_session: Session) -> list[KeyInfo]:
    return [KeyInfo.from_row(row) for row in db_session.scalars(select(ApiKey).order_by(ApiKey.id))]


def revoke_key(db_session: Session, key_id: int, *, now: datetime | None = None) -> KeyInfo:
    """Revoke a key (idempotent: revoking a revoked key keeps its first revocation time) and end
    the dashboard logins it opened. This process's caches of keys forget it at the commit
    (``app.storage.changes``)."""
    row = db_session.get(ApiKey, key_id)
    if row is None:
        raise KeyNotFound(key_id)
    KEY_CHANGES.note(db_session, key_id)
    if row.revoked_at is None:
        row.revoked_at = now or utc_now()
    db_session.execute(delete(AdminLogin).where(AdminLogin.key_id == key_id))
    db_session.flush()
    return KeyInfo.from_row(row)


def _digest(key: str) -> str:
    return hashlib.sha256(key.encode("utf-8", "surrogatepass")).hexdigest()
