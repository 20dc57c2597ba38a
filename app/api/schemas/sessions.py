"""Schemas of the sessions router (uploads)."""

from __future__ import annotations

from datetime import datetime
from typing import Any

from pydantic import BaseModel, Field

from app.api.schemas.common import AT_EXAMPLE, SHA_EXAMPLE, examples
from app.storage.sessions import UploadResult

STATS_EXAMPLE: dict[str, Any] = {
    "pose_count": 621,
    "detection_count": 200,
    "tag_count": 8,
    "poi_count": 0,
    "duration_s": 62.1,
    "path_length_m": 41.7,
    "tag_ids": [0, 1, 2, 3, 4, 5, 6, 7],
    "warnings": [],
}


class SessionStatisticsPublic(BaseModel):
    """What a session holds, computed when it was uploaded."""

    model_config = examples(STATS_EXAMPLE)

    pose_count: int
    detection_count: int
    tag_count: int
    poi_count: int = Field(description="points of interest (location_data)")
    duration_s: float = Field(description="last pose timestamp minus the first, s")
    path_length_m: float = Field(description="distance walked along the raw odometry, m")
    tag_ids: list[int]
    warnings: list[str]


class SessionCreated(BaseModel):
    """The answer to an upload (202): where to follow the build of its map."""

    model_config = examples(
        {
            "session_id": 17,
            "map_id": 12,
            "job_id": 31,
            "map_name": "occam_room",
            "job_url": "/v1/jobs/31",
            "map_url": "/v1/maps/12",
            "statistics": STATS_EXAMPLE,
        }
    )

    session_id: int
    map_id: int
    job_id: int = Field(description="the build_map job; poll it at job_url")
    map_name: str = Field(description="the upload's map_id")
    job_url: str
    map_url: str
    statistics: SessionStatisticsPublic

    @classmethod
    def from_domain(cls, result: UploadResult) -> SessionCreated:
        return cls(
            session_id=result.session_id,
            map_id=result.map_id,
            job_id=result.job_id,
            map_name=result.map_name,
            job_url=f"/v1/jobs/{result.job_id}",
            map_url=f"/v1/maps/{result.map_id}",
            statistics=SessionStatisticsPublic.model_validate(result.statistics),
        )


_SESSION_EXAMPLE: dict[str, Any] = {
    "id": 17,
    "map_name": "occam_room",
    "created_at": AT_EXAMPLE,
    "uploaded_by": "key:3",
    "idempotency_key": "3f1c2a9e-occam-1",
    "raw_sha256": SHA_EXAMPLE,
    "raw_size_bytes": 912204,
    "stored_size_bytes": 251377,
    "statistics": STATS_EXAMPLE,
    "map_id": 12,
    "job_ids": [31],
}


class SessionPublic(BaseModel):
    """A stored session: metadata, statistics, and the map and jobs made from it."""

    model_config = examples(_SESSION_EXAMPLE)

    id: int
    map_name: str = Field(description="the upload's map_id")
    created_at: datetime
    uploaded_by: str = Field(description="key:<id> of the key that uploaded it, or env-admin")
    idempotency_key: str | None
    raw_sha256: str = Field(description="SHA-256 of the JSON bytes as uploaded (hex)")
    raw_size_bytes: int = Field(description="size of the JSON as uploaded, after any gunzip")
    stored_size_bytes: int = Field(description="size as stored (gzip)")
    statistics: SessionStatisticsPublic
    map_id: int | None = Field(description="the map built from it (null once deleted)")
    job_ids: list[int] = Field(description="its jobs, oldest first (the upload's build first)")


class SessionsPublic(BaseModel):
    """A page of sessions, newest first; ``count`` is how many there are in all."""

    model_config = examples(
        {
            "data": [_SESSION_EXAMPLE],
            "count": 1,
            "limit": 50,
            "offset": 0,
        }
    )

    data: list[SessionPublic]
    count: int
    limit: int
    offset: int


# --------------------------------------------------------------------------- jobs


class ImageStored(BaseModel):
    """The answer to a picture upload: where it is served and whether it changed anything."""

    model_config = examples(
        {
            "session_id": 17,
            "map_id": 12,
            "sha256": SHA_EXAMPLE,
            "size_bytes": 48213,
            "changed": True,
            "image_url": "/v1/maps/12/image?v=3f1c2a9e0b7d4c21",
        }
    )

    session_id: int
    map_id: int | None = Field(description="the session's map (null if it was deleted)")
    sha256: str = Field(description="SHA-256 of the JPEG's bytes")
    size_bytes: int
    changed: bool = Field(description="false when these very bytes were already stored")
    image_url: str | None = Field(description="where the map serves it")
