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
    """Store a new key (422 naming the field if it would already have expired, if its expiry
    is beyond the year 9999 in UTC, or if its name is no storable text); returns it and its
    secret."""
    if "\x00" in name or _has_surrogate(name):
        raise InvalidInput(
            "validation_error",
            "name: holds a NUL or a lone surrogate, which is no text",
            field="name",
        )
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


def _has_surrogate(text: str) -> bool:
    return any("\ud800" <= char <= "\udfff" for char in text)
