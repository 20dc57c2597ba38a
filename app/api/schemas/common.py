"""What every router's schemas share: the error body and example values."""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict, Field

AT_EXAMPLE = "2026-11-22T10:15:30Z"
LATER_EXAMPLE = "2026-11-22T10:15:31.250000Z"
SHA_EXAMPLE = "9f86d081884c7d659a2feaa0c55ad015a3bf4f1b2b0b822cd15d6c15b0f00a08"


def examples(*examples: dict[str, Any]) -> ConfigDict:
    """A model's configuration: its OpenAPI examples, and validation from the storage layer's
    dataclasses by attribute name (``KeyPublic.model_validate(key_info)``)."""
    return ConfigDict(json_schema_extra={"examples": list(examples)}, from_attributes=True)


# --------------------------------------------------------------------------- errors


class ErrorBody(BaseModel):
    """Every error response: what went wrong, a stable code, and the field at fault if any."""

    model_config = examples(
        {
            "detail": "pose_data[3].pose: rotation not orthonormal",
            "code": "invalid_session",
            "field": "pose_data[3].pose",
        },
        {"detail": "map 42 not found", "code": "not_found", "field": None},
    )

    detail: str = Field(description="a sentence for a person")
    code: str = Field(description="stable, for programs: not_found, invalid_session, …")
    field: str | None = Field(
        default=None, description="where in the request: a JSON path, a parameter or a header"
    )


# --------------------------------------------------------------------------- sessions
