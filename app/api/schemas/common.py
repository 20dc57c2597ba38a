"""What every router's schemas share: example values and how a model shows them."""

from __future__ import annotations

from typing import Any

from pydantic import ConfigDict

AT_EXAMPLE = "2026-11-22T10:15:30Z"
LATER_EXAMPLE = "2026-11-22T10:15:31.250000Z"
SHA_EXAMPLE = "9f86d081884c7d659a2feaa0c55ad015a3bf4f1b2b0b822cd15d6c15b0f00a08"


def examples(*examples: dict[str, Any]) -> ConfigDict:
    """A model's configuration: its OpenAPI examples, and validation from the storage layer's
    dataclasses by attribute name (``KeyPublic.model_validate(key_info)``)."""
    return ConfigDict(json_schema_extra={"examples": list(examples)}, from_attributes=True)


# --------------------------------------------------------------------------- sessions
