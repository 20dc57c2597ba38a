"""Errors raised by the domain core.

InvisibleMapError            anything the core refuses, with a message fit for a person
├── SessionFormatError       an upload that does not follow the app's format (architecture §2)
├── NoTagsRecorded           a well-formed session with no tag detection: it can make no map
├── GroundTruthFormatError   a ground-truth file in neither supported form
├── MapFormatError           a saved map file that cannot be read back
└── ParameterError           an unknown or out-of-range SLAM parameter
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any


class InvisibleMapError(Exception):
    """Base of every error the core raises on bad input; ``str(err)`` is one readable line."""


class SessionFormatError(InvisibleMapError):
    """Raised when an upload is malformed; ``field`` names where (``tag_data[3][0].tag_pose``)."""

    def __init__(self, field: str, reason: str) -> None:
        self.field = field
        self.reason = reason
        super().__init__(f"{field}: {reason}" if field else reason)


class NoTagsRecorded(InvisibleMapError):
    """Raised when a map is asked of a session with no tag detections: the upload is valid (and
    kept), but the tags are a map's landmarks, and without one there is no map to build."""


class GroundTruthFormatError(InvisibleMapError):
    """Raised when a ground-truth file is neither an RTAB-Map export nor the GT JSON form."""


class MapFormatError(InvisibleMapError):
    """Raised when a saved map JSON cannot be read back."""


class ParameterError(InvisibleMapError):
    """Raised for an unknown SLAM parameter name or a value out of its documented range."""


def require_finite_non_negative(params: Any) -> None:
    """Every field of the dataclass instance ``params`` a finite number ≥ 0: a
    :class:`ParameterError` naming the first that is not (the common rule of the domain's
    parameter sets; each adds its own stricter ones after it)."""
    for f in dataclasses.fields(params):
        value = getattr(params, f.name)
        if not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
            raise ParameterError(f"{f.name} must be a finite number ≥ 0, got {value!r}")
