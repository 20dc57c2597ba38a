"""Dashboard logins kept on the server (table ``admin_login``).

    token = start_login(db_session, subject="key:3", key_id=3, ttl_s=8 * 3600)  # in the cookie
    login = find_login(db_session, token)      # None once ended or expired
    end_login(db_session, token)               # logout
    end_logins_of_key(db_session, 3)           # the key was revoked
    end_all_logins(db_session)                 # "end all dashboard sessions"

The token is 256 random bits; only its SHA-256 is stored, so a copy of the database opens no
dashboard. A login ends when its row goes; a copied cookie is then worth nothing.
"""

from __future__ import annotations

import hashlib
import secrets
from dataclasses import dataclass
from datetime import datetime, timedelta

from sqlalchemy import delete, func, select
from sqlalchemy.orm import Session

from app.storage.orm import AdminLogin, utc_now


@dataclass(frozen=True, slots=True, kw_only=True)
class LoginInfo:
    """A dashboard login that has not ended."""

    id: int
    subject: str
    key_id: int | None
    created_at: datetime
    expires_at: datetime


def start_login(
    db_session: Session,
    *,
    subject: str,
    key_id: int | None,
    ttl_s: float,
    now: datetime | None = None,
) -> str:
    """Store a new login of ``subject``; returns its token (for the cookie, never stored).
    Forgets logins that expired."""
    now = now or utc_now()
    db_session.execute(delete(AdminLogin).where(AdminLogin.expires_at <= now))
    token = secrets.token_urlsafe(32)
    db_session.add(
        AdminLogin(
            token_sha256=_digest(token),
            key_id=key_id,
            subject=subject,
            created_at=now,
            expires_at=now + timedelta(seconds=ttl_s),
        )
    )
    db_session.flush()
    return token


def find_login(db_session: Session, token: str, *, now: datetime | None = None) -> LoginInfo | None:
    """The login ``token`` opened, if it has not ended or expired."""
    row = db_session.scalar(select(AdminLogin).where(AdminLogin.token_sha256 == _digest(token)))
    if row is None or row.expires_at <= (now or utc_now()):
        return None
    return LoginInfo(
        id=row.id,
        subject=row.subject,
        key_id=row.key_id,
        created_at=row.created_at,
        expires_at=row.expires_at,
    )


def count_logins(db_session: Session, *, now: datetime | None = None) -> int:
    """How many dashboard logins are open now."""
    return int(
        db_session.scalar(select(func.count()).where(AdminLogin.expires_at > (now or utc_now())))
        or 0
    )


def end_login(db_session: Session, token: str) -> bool:
    """End one login (logout); whether there was one."""
    result = db_session.execute(delete(AdminLogin).where(AdminLogin.token_sha256 == _digest(token)))
    return bool(result.rowcount)  # type: ignore[attr-defined]


def end_logins_of_key(db_session: Session, key_id: int) -> int:
    """End every login opened with API key ``key_id``; how many."""
    result = db_session.execute(delete(AdminLogin).where(AdminLogin.key_id == key_id))
    return int(result.rowcount)  # type: ignore[attr-defined]


def end_all_logins(db_session: Session) -> int:
    """End every dashboard login, of every key; how many."""
    result = db_session.execute(delete(AdminLogin))
    return int(result.rowcount)  # type: ignore[attr-defined]


def _digest(token: str) -> str:
    return hashlib.sha256(token.encode("utf-8", "surrogatepass")).hexdigest()
