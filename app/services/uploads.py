"""What an upload must be, beyond what the parser checks, for it to be stored and built: checked
at the door (``POST /v1/sessions``), so that a session accepted with 202 can always be stored
and rendered, and a bad one is a 422 naming the field instead of a 500 or a build that fails.

    parsed = parse_upload(json_chunks, max_poses=…)   # INVISIBLE_MAP_MAX_POSES while parsing
    check_storable(parsed)                            # (called by parse_upload)
    # each: SessionFormatError (422 invalid_session, naming the field)

- text (``map_id``, the points of interest's names) must be encodable as UTF-8 (no lone surrogate
  such as ``"\\ud800"``, which JSON allows) and hold no NUL (PostgreSQL's text cannot);
- tag ids must fit the database's 32-bit integer column (``map_tag.tag_id``);
- the session's duration and path length must be finite numbers (timestamps of ±1e308 make
  their difference infinite, which JSON cannot carry back).
"""

from __future__ import annotations

import math
from collections.abc import Iterable

from sqlalchemy.orm import Session

from app.domain.errors import SessionFormatError
from app.domain.upload.fields import text_fault
from app.domain.upload.session import Session as ParsedSession
from app.domain.upload.session import parse_session_stream
from app.storage import sessions
from app.storage.sessions import MAX_MAP_NAME_LENGTH

#: The largest tag id the database stores (``map_tag.tag_id`` is a 32-bit integer).
MAX_TAG_ID = 2**31 - 1


def parse_upload(
    json_chunks: Iterable[bytes], *, max_poses: int, source: str = "upload"
) -> ParsedSession:
    """The session in the upload's JSON bytes (in chunks), parsed as they come: a session with
    more than ``max_poses`` poses (``INVISIBLE_MAP_MAX_POSES``) is refused when pose
    ``max_poses`` + 1 is reached, so that a small gzip body that inflates to millions of poses
    costs no decoding of the rest, no build, no stored map; then :func:`check_storable`.
    SessionFormatError (naming the field) for any fault; ``source`` names the document in a
    fault of the whole (``upload is not valid JSON: …``)."""
    parsed = parse_session_stream(
        json_chunks, max_poses=max_poses, max_poses_name="INVISIBLE_MAP_MAX_POSES", source=source
    )
    if len(parsed.map_id) > MAX_MAP_NAME_LENGTH:
        raise SessionFormatError(
            "map_id", f"longer than {MAX_MAP_NAME_LENGTH} characters ({len(parsed.map_id)})"
        )
    check_storable(parsed)
    return parsed


def stored_session(db_session: Session, session_id: int) -> ParsedSession:
    """A stored session parsed again (the dashboard's raw trajectory, detections per tag), read
    from the database a piece at a time and parsed as it is inflated, never held whole.
    Raises SessionNotFound."""
    return sessions.parsed_upload(db_session, session_id)


def check_text(field: str, value: str) -> None:
    """SessionFormatError naming ``field`` if ``value`` cannot be stored as text everywhere
    (:func:`app.domain.upload.fields.text_fault`, the rule of every text that is stored)."""
    reason = text_fault(value)
    if reason is not None:
        raise SessionFormatError(field, reason)


def check_storable(parsed: ParsedSession) -> None:
    """Refuse (SessionFormatError) what the parser accepts but storage or rendering cannot hold;
    see the module docstring."""
    check_text("map_id", parsed.map_id)
    for k, poi in enumerate(parsed.pois):
        check_text(f"location_data[{k}].name", poi.name)
    too_large = [tag for tag in parsed.tag_ids if tag > MAX_TAG_ID]
    if too_large:
        raise SessionFormatError(
            "tag_data", f"tag id {too_large[0]} is larger than {MAX_TAG_ID}, the largest stored"
        )
    if parsed.num_poses:
        duration_s = float(parsed.timestamp_s[-1]) - float(parsed.timestamp_s[0])  # no warning
        if not math.isfinite(duration_s):
            raise SessionFormatError(
                "pose_data", "the timestamps span more time than a number can hold"
            )
        if not math.isfinite(parsed.path_length_m()):
            raise SessionFormatError(
                "pose_data", "the poses span more distance than a number can hold"
            )
