"""API keys: creating one with its checks.

What the API routers and the dashboard pages both do; errors are :mod:`app.services.errors`.
"""

from __future__ import annotations

from datetime import UTC, datetime

from sqlalchemy.orm import Session

from app.services.errors import InvalidInput
from app.storage import keys
from app.storage.orm import Role


def create_checked_key(
    db_session: Session, *, name: str, role: Role, expires_at: datetime | None
) -> tuple[keys.KeyInfo, str]:
    """Store a new key (422 if it would already have expired); returns it and its secret."""
    if expires_at is not None and expires_at <= datetime.now(UTC):
        raise InvalidInput("validation_error", "expires_at is in the past", field="expires_at")
    return keys.create_key(db_session, name=name, role=role, expires_at=expires_at)
