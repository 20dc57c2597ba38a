"""Rows to the storage layer's frozen dataclasses, by field name.

    JobInfo.from_row(row)  ==  info_from_row(JobInfo, row)

Each field of the dataclass is the row's attribute of the same name, turned into the field's
type where the column stores less: an enum kept as its text becomes the enum (``Role``,
``JobState``), and a JSON column's dict or list is copied (the dataclass does not share the ORM's
mutable value). Fields the row does not have are given as keyword arguments.
"""

from __future__ import annotations

import enum
import types
import typing
from collections.abc import Callable
from dataclasses import fields
from typing import Any, TypeVar

T = TypeVar("T")


def info_from_row(info_type: type[T], row: object, **values: Any) -> T:
    """An ``info_type`` from ``row``'s attributes of the same names; ``values`` for the rest."""
    converters = _CONVERTERS.get(info_type)
    if converters is None:
        converters = _CONVERTERS[info_type] = _converters(info_type)
    for name, convert in converters:
        if name not in values:
            value = getattr(row, name)
            values[name] = value if value is None or convert is None else convert(value)
    return info_type(**values)


Converters = tuple[tuple[str, Callable[[Any], Any] | None], ...]
#: Per dataclass, each field's name and converter (built once: reading type hints is slow).
_CONVERTERS: dict[type, Converters] = {}


def _converters(info_type: type) -> Converters:
    hints = typing.get_type_hints(info_type)
    return tuple((f.name, _converter(hints[f.name])) for f in fields(info_type))


def _converter(annotation: Any) -> Callable[[Any], Any] | None:
    """How a column's value becomes a field of type ``annotation`` (None: as it is)."""
    if isinstance(annotation, types.UnionType) or typing.get_origin(annotation) is typing.Union:
        choices = [a for a in typing.get_args(annotation) if a is not type(None)]
        return _converter(choices[0]) if len(choices) == 1 else None
    origin = typing.get_origin(annotation) or annotation
    if isinstance(origin, type) and issubclass(origin, enum.Enum):
        return origin
    if origin in (dict, list):
        return origin  # type: ignore[no-any-return]
    return None
