"""Schemas of the keys router."""

from __future__ import annotations

from datetime import datetime
from typing import Any

from pydantic import AwareDatetime, BaseModel, ConfigDict, Field

from app.api.schemas.common import AT_EXAMPLE, LATER_EXAMPLE, examples
from app.services.keys import MAX_KEY_NAME_CHARS
from app.storage.orm import Role

KEY_EXAMPLE: dict[str, Any] = {
    "id": 3,
    "name": "lab iPhone 12",
    "role": "device",
    "prefix": "a1b2c3d4",
    "created_at": AT_EXAMPLE,
    "expires_at": None,
    "revoked_at": None,
    "last_used_at": LATER_EXAMPLE,
}


class KeyCreate(BaseModel):
    """A new API key: a name for people, a role, and optionally when it stops working."""

    model_config = ConfigDict(
        extra="forbid",
        json_schema_extra={
            "examples": [
                {"name": "lab iPhone 12", "role": "device"},
                {"name": "ops laptop", "role": "admin", "expires_at": "2027-01-01T00:00:00Z"},
            ]
        },
    )

    name: str = Field(min_length=1, max_length=MAX_KEY_NAME_CHARS)
    role: Role
    expires_at: AwareDatetime | None = Field(
        default=None, description="with a time zone, in the future"
    )


class KeyPublic(BaseModel):
    """An API key as listed: never its secret."""

    model_config = examples(KEY_EXAMPLE)

    id: int
    name: str
    role: Role
    prefix: str = Field(description="the public part of the key, im_<prefix>_…")
    created_at: datetime
    expires_at: datetime | None
    revoked_at: datetime | None
    last_used_at: datetime | None = Field(description="to within a minute")


class KeyCreated(KeyPublic):
    """A new key with its secret: shown this once, never stored or shown again."""

    model_config = examples(
        {**KEY_EXAMPLE, "last_used_at": None, "key": "im_a1b2c3d4_Zq9…(32 characters)"}
    )

    key: str = Field(description="send as 'Authorization: Bearer <key>'")


class KeysPublic(BaseModel):
    """All API keys, oldest first."""

    model_config = examples({"data": [KEY_EXAMPLE], "count": 1})

    data: list[KeyPublic]
    count: int


# --------------------------------------------------------------------------- system
