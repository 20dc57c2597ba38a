"""What every router's schemas share: example values and how a model shows them."""

from __future__ import annotations

from typing import Annotated, Any

from pydantic import BeforeValidator, ConfigDict

AT_EXAMPLE = "2026-11-22T10:15:30Z"
LATER_EXAMPLE = "2026-11-22T10:15:31.250000Z"
SHA_EXAMPLE = "9f86d081884c7d659a2feaa0c55ad015a3bf4f1b2b0b822cd15d6c15b0f00a08"


def examples(*examples: dict[str, Any]) -> ConfigDict:
    """A model's configuration: its OpenAPI examples, and validation from the storage layer's
    dataclasses by attribute name (``KeyPublic.model_validate(key_info)``)."""
    return ConfigDict(json_schema_extra={"examples": list(examples)}, from_attributes=True)


def _whole_float_as_int(value: Any) -> Any:
    """A JSON body's integer beyond 64 bits arrives as the float nearest it
    (``app.web.route_class.OrjsonRequest``): as an id, the whole number it stands for, so that
    it names nothing like any other id out of range instead of being refused as no integer."""
    if isinstance(value, float) and value.is_integer():
        return int(value)
    return value


#: An id in a JSON body: any whole number; one that is no id (``app.web.deps.ID_RULE``) gets
#: the answer of an id that does not exist.
BodyId = Annotated[int, BeforeValidator(_whole_float_as_int)]


# --------------------------------------------------------------------------- sessions
