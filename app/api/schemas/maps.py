"""Schemas of the maps router: maps, versions, tags, rebuilds, the app's map format."""

from __future__ import annotations

from datetime import datetime
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, model_validator

from app.api.schemas.common import AT_EXAMPLE, LATER_EXAMPLE, SHA_EXAMPLE, BodyId, examples
from app.api.schemas.jobs import JobBrief
from app.services.maps import BuildQueued, image_url, map_session_uses
from app.storage.maps import MapInfo, TagPose, VersionInfo
from app.storage.queue import JobInfo
from app.web.deps import ID_RULE

TAG_EXAMPLE = {
    "tag_id": 3,
    "position_m": [1.52, 0.31, -4.07],
    "quat_xyzw": [0.0, 0.7071, 0.0, 0.7071],
    "detection_count": 24,
    "covariance": None,
}
_VERSION_EXAMPLE: dict[str, Any] = {
    "number": 1,
    "created_at": LATER_EXAMPLE,
    "job_id": 31,
    "params": {"tag_position_var_m2": 0.0001, "huber_k": 1.345},
    "statistics": {"poses": 621, "tags": 8, "path_length_m": 41.7, "iterations": 3},
    "metrics": {"shift_pre": 0.0139, "shift_opt": 0.0115},
    "shift_metric": 0.0115,
    "tag_count": 8,
    "detections_used": 191,
    "detections_rejected": 9,
    "warnings": [],
    "content_sha256": SHA_EXAMPLE,
    "session_ids": [17],
    "generation": 1,
}


class TagPosePublic(BaseModel):
    """A tag in a map version, map frame (y up)."""

    model_config = examples(TAG_EXAMPLE)

    tag_id: int
    position_m: list[float] = Field(description="[x, y, z], m")
    quat_xyzw: list[float] = Field(description="orientation, unit quaternion [x, y, z, w]")
    detection_count: int = Field(description="detections of it used in the optimization")
    covariance: list[float] | None = Field(
        description="6×6 marginal covariance, row-major, [rotation rad, translation m] in the "
        "tag frame; null if not computed"
    )


class VersionSummary(BaseModel):
    """One version of a map: how it was made and how good it is (without its tags)."""

    model_config = examples(_VERSION_EXAMPLE)

    number: int = Field(description="1, 2, … per map; the newest is the map's current version")
    created_at: datetime
    job_id: int | None = Field(description="the job that built it")
    params: dict[str, Any] = Field(description="every SLAM parameter it used")
    statistics: dict[str, Any] = Field(description="poses, tags, path length, solver figures")
    metrics: dict[str, Any] = Field(
        description="shift metric of the pre-optimized (shift_pre) and optimized (shift_opt) "
        "map; for a build given ground truth also gt_metric_pre, gt_metric_opt, tag_rmse_pre_m, "
        "tag_rmse_opt_m and tags_with_ground_truth"
    )
    shift_metric: float | None = Field(description="the optimized map's shift metric")
    tag_count: int
    detections_used: int
    detections_rejected: int
    warnings: list[str]
    content_sha256: str = Field(description="SHA-256 of the stored map document")
    session_ids: list[int] = Field(
        description="the sessions it was optimized from, in order (the first is the map frame); "
        "empty for versions made before maps held several sessions (the map's session_id)"
    )
    generation: int | None = Field(
        default=None,
        description="the map's generation it was built for (null: built before generations)",
    )

    @model_validator(mode="before")
    @classmethod
    def _from_version_info(cls, data: Any) -> Any:
        """From a :class:`VersionInfo`: its fields, and ``shift_metric`` from its metrics."""
        return _version_fields(data) if isinstance(data, VersionInfo) else data


class VersionPublic(VersionSummary):
    """A map version with its tag poses."""

    model_config = examples({**_VERSION_EXAMPLE, "tags": [TAG_EXAMPLE]})

    tags: list[TagPosePublic]

    @classmethod
    def with_tags(cls, version: VersionInfo, tags: list[TagPose]) -> VersionPublic:
        return cls(
            **_version_fields(version), tags=[TagPosePublic.model_validate(tag) for tag in tags]
        )


REJECTION_EXAMPLE = {
    "detection_index": 57,
    "tag_id": 5,
    "pose_index": 233,
    "reason": "reprojection",
    "value": 11.2,
    "limit": 8.0,
    "detail": "reprojection 11.2 px > 8 px",
}


class VersionDetail(VersionPublic):
    """A map version with its tag poses and the detections it left out, and why."""

    model_config = examples(
        {**_VERSION_EXAMPLE, "tags": [TAG_EXAMPLE], "rejections": [REJECTION_EXAMPLE]}
    )

    rejections: list[dict[str, Any]] = Field(
        description="detections left out: reason (reprojection, view_angle, distance), value, limit"
    )

    @classmethod
    def with_details(cls, version: VersionInfo, tags: list[TagPose]) -> VersionDetail:
        return cls(
            **_version_fields(version),
            tags=[TagPosePublic.model_validate(tag) for tag in tags],
            rejections=version.rejections,
        )


def _version_fields(version: VersionInfo) -> dict[str, Any]:
    return {
        "number": version.number,
        "created_at": version.created_at,
        "job_id": version.job_id,
        "params": version.params,
        "statistics": version.statistics,
        "metrics": version.metrics,
        "shift_metric": version.metrics.get("shift_opt"),
        "tag_count": version.tag_count,
        "detections_used": version.detections_used,
        "detections_rejected": version.detections_rejected,
        "warnings": version.warnings,
        "content_sha256": version.content_sha256,
        "session_ids": version.session_ids,
        "generation": version.generation,
    }


class VersionsPublic(BaseModel):
    """All versions of a map, oldest first."""

    model_config = examples({"data": [_VERSION_EXAMPLE], "count": 1})

    data: list[VersionSummary]
    count: int


_MAP_EXAMPLE: dict[str, Any] = {
    "id": 12,
    "name": "occam_room 1700000000",
    "display_name": "occam_room",
    "image_url": "/v1/maps/12/image?v=3f1c2a9e0b7d4c21",
    "session_id": 17,
    "session_ids": [17],
    "created_at": AT_EXAMPLE,
    "version_count": 1,
    "generation": 1,
    "up_to_date": True,
    "pending_job_id": None,
    "latest_job": {"id": 31, "kind": "build_map", "state": "succeeded"},
}

#: A map in a list: no pending build (read for one map only) and no newest job.
_SUMMARY_EXAMPLE = {
    k: v for k, v in _MAP_EXAMPLE.items() if k not in ("pending_job_id", "latest_job")
}

GENERATION_DESCRIPTION = (
    "bumped by every change of what the map is built from (a session added, taken out or merged "
    "in; a rebuild); only a build of the map's generation stores a version"
)
UP_TO_DATE_DESCRIPTION = (
    "whether the current version was built from the map's current sessions and parameters "
    "(its generation); false while a change is being built, or after its build failed"
)
PENDING_JOB_DESCRIPTION = (
    "the queued or running build of the current sessions and parameters; null when none is "
    "under way"
)


DISPLAY_NAME_DESCRIPTION = (
    "the name people see: the name typed in the app (map_id without its timestamp digits), or "
    "as an admin set it (PATCH)"
)
IMAGE_URL_DESCRIPTION = (
    "the map's picture (JPEG), versioned by content, so it may be cached for good; null without one"
)


class MapUpdate(BaseModel):
    """What an admin may change of a map."""

    model_config = ConfigDict(
        extra="forbid", json_schema_extra={"examples": [{"display_name": "Occam lab, 3rd floor"}]}
    )

    display_name: str = Field(min_length=1, max_length=200, description=DISPLAY_NAME_DESCRIPTION)


class MapSummary(BaseModel):
    """A map in a list: its current version without tags (null until the first build)."""

    model_config = examples(
        {
            **_SUMMARY_EXAMPLE,
            "current_version": _VERSION_EXAMPLE,
        }
    )

    id: int
    name: str = Field(description="the session's map_id")
    display_name: str = Field(description=DISPLAY_NAME_DESCRIPTION)
    image_url: str | None = Field(description=IMAGE_URL_DESCRIPTION)
    session_id: int = Field(description="its first session (the map frame)")
    session_ids: list[int] = Field(
        description="every session it is made of, in order; the next build uses them"
    )
    created_at: datetime
    version_count: int
    generation: int = Field(description=GENERATION_DESCRIPTION)
    up_to_date: bool = Field(description=UP_TO_DATE_DESCRIPTION)
    current_version: VersionSummary | None

    @classmethod
    def from_domain(cls, info: MapInfo) -> MapSummary:
        return cls(
            id=info.id,
            name=info.name,
            display_name=info.display_name,
            image_url=image_url(info),
            session_id=info.session_id,
            session_ids=info.session_ids,
            created_at=info.created_at,
            version_count=info.version_count,
            generation=info.generation,
            up_to_date=info.up_to_date,
            current_version=VersionSummary.model_validate(info.current) if info.current else None,
        )


class MapPublic(BaseModel):
    """A map: its current version with tag poses (null until the first build succeeds) and its
    newest job (to tell "not built yet" from "build failed")."""

    model_config = examples(
        {**_MAP_EXAMPLE, "current_version": {**_VERSION_EXAMPLE, "tags": [TAG_EXAMPLE]}},
        {
            **_MAP_EXAMPLE,
            "version_count": 0,
            "up_to_date": False,
            "pending_job_id": 31,
            "current_version": None,
            "latest_job": {"id": 31, "kind": "build_map", "state": "queued"},
        },
    )

    id: int
    name: str = Field(description="the session's map_id")
    display_name: str = Field(description=DISPLAY_NAME_DESCRIPTION)
    image_url: str | None = Field(description=IMAGE_URL_DESCRIPTION)
    session_id: int = Field(description="its first session (the map frame)")
    session_ids: list[int] = Field(
        description="every session it is made of, in order; the next build uses them"
    )
    created_at: datetime
    version_count: int
    generation: int = Field(description=GENERATION_DESCRIPTION)
    up_to_date: bool = Field(description=UP_TO_DATE_DESCRIPTION)
    pending_job_id: int | None = Field(description=PENDING_JOB_DESCRIPTION)
    current_version: VersionPublic | None
    latest_job: JobBrief | None

    @classmethod
    def from_domain(
        cls, info: MapInfo, *, tags: list[TagPose], latest_job: JobInfo | None
    ) -> MapPublic:
        return cls(
            id=info.id,
            name=info.name,
            display_name=info.display_name,
            image_url=image_url(info),
            session_id=info.session_id,
            session_ids=info.session_ids,
            created_at=info.created_at,
            version_count=info.version_count,
            generation=info.generation,
            up_to_date=info.up_to_date,
            pending_job_id=info.pending_job_id,
            current_version=VersionPublic.with_tags(info.current, tags) if info.current else None,
            latest_job=JobBrief.from_domain(latest_job) if latest_job else None,
        )


class MapsPublic(BaseModel):
    """A page of maps, newest first."""

    model_config = examples(
        {
            "data": [{**_SUMMARY_EXAMPLE, "current_version": _VERSION_EXAMPLE}],
            "count": 1,
            "limit": 50,
            "offset": 0,
        }
    )

    data: list[MapSummary]
    count: int
    limit: int
    offset: int


class RebuildRequest(BaseModel):
    """Optional body of a rebuild: SLAM parameters to change from the defaults."""

    model_config = ConfigDict(
        extra="forbid",
        json_schema_extra={
            "examples": [
                {"params": {"tag_position_var_m2": 1e-3, "huber_k": 0}},
                {"params": {"tag_sizes_m": {"301": 0.15}, "max_reprojection_px": "12"}},
                {"auto_tune_trials": 40},
                {
                    "ground_truth": {
                        "poses": [
                            {"tag_id": 0, "pose": [0.42, 0.14, -1.38, 0.0, 0.13, 0.0, 0.99]},
                            {"tag_id": 1, "pose": [2.1, 0.15, -1.4, 0.0, 0.7, 0.0, 0.71]},
                        ]
                    }
                },
            ]
        },
    )

    params: dict[str, Any] = Field(
        default_factory=dict,
        description="name → value of any SlamParams field (see the README's parameter table)",
    )
    auto_tune_trials: int = Field(
        default=0,
        ge=0,
        le=1000,
        description="first choose the noise variances by the shift metric with this many "
        "sampler trials (0: use the parameters as given); a map of one session only: for a map "
        "of several it is a 422 naming this field (tune those with a sweep)",
    )
    session_ids: list[BodyId] | None = Field(
        default=None,
        min_length=1,
        max_length=1000,
        description="build from these sessions, in this order (e.g. an older version's "
        f"session_ids, to make it again); default: the map's sessions now. Each {ID_RULE} "
        "(422 invalid_sessions naming it)",
    )
    ground_truth: dict[str, Any] | None = Field(
        default=None,
        description="ground truth of the map's tags, "
        '{"poses": [{"tag_id": N, "pose": [x, y, z, qx, qy, qz, qw]}, …]} (as for a sweep): the '
        "version this build makes carries the ground-truth metric and tag RMSE in its metrics "
        "(a later rebuild without it does not)",
    )


class RebuildAccepted(BaseModel):
    """The answer to a rebuild (202): the new job, which adds a version when it succeeds."""

    model_config = examples(
        {
            "job_id": 40,
            "map_id": 12,
            "session_id": 17,
            "session_ids": [17],
            "params": {"tag_position_var_m2": 0.001},
            "job_url": "/v1/jobs/40",
            "generation": 3,
            "coalesced": False,
            "superseded_job_ids": [],
        },
        {
            "job_id": 40,
            "map_id": 12,
            "session_id": 17,
            "session_ids": [17, 18, 19],
            "params": {},
            "job_url": "/v1/jobs/40",
            "generation": 4,
            "coalesced": True,
            "superseded_job_ids": [39],
        },
    )

    job_id: int
    map_id: int
    session_id: int
    session_ids: list[int] = Field(description="the sessions the build uses, in order")
    params: dict[str, Any] = Field(description="the overrides, as the job will use them")
    job_url: str
    generation: int = Field(
        description="the map's generation the job builds (" + GENERATION_DESCRIPTION + ")"
    )
    coalesced: bool = Field(
        description="the change was folded into job_id, a build of this map queued before and "
        "not started yet (it now builds this generation), instead of another build"
    )
    superseded_job_ids: list[int] = Field(
        description="builds of the map's previous generations that were running (asked to "
        "stop: their result would not be current) or queued (canceled)"
    )

    @classmethod
    def queued(cls, info: MapInfo, job_id: int, params: dict[str, Any]) -> RebuildAccepted:
        """The answer for the build job ``job_id`` of map ``info`` (as it is after the change)
        with ``params``, where what it replaced is not known (a sweep's apply)."""
        return cls.from_build(
            BuildQueued(
                info=info,
                job_id=job_id,
                generation=info.generation,
                coalesced=False,
                superseded=(),
                params=params,
            ),
            params,
        )

    @classmethod
    def from_build(cls, build: BuildQueued, params: dict[str, Any]) -> RebuildAccepted:
        """The answer for ``build``, queued with ``params``."""
        info = build.info
        return cls(
            job_id=build.job_id,
            map_id=info.id,
            session_id=info.session_id,
            session_ids=info.session_ids,
            params=params,
            job_url=f"/v1/jobs/{build.job_id}",
            generation=build.generation,
            coalesced=build.coalesced,
            superseded_job_ids=list(build.superseded),
        )


class Vector3(BaseModel):
    x: float
    y: float
    z: float


class Quaternion(BaseModel):
    x: float
    y: float
    z: float
    w: float


TRANSLATION_EXAMPLE = {"x": 1.52, "y": 0.31, "z": -4.07}
ROTATION_EXAMPLE = {"x": 0.0, "y": 0.7071, "z": 0.0, "w": 0.7071}


class AppTagVertex(BaseModel):
    id: int
    translation: Vector3
    rotation: Quaternion


class AppOdometryVertex(BaseModel):
    poseId: int  # noqa: N815 (the app's name)
    translation: Vector3
    rotation: Quaternion
    adjChi2: float  # noqa: N815
    vizTags: float  # noqa: N815
    neighbors: list[int]


class AppWaypointVertex(BaseModel):
    id: str = Field(description="the point of interest's name")
    translation: Vector3
    rotation: Quaternion


class AppMap(BaseModel):
    """The iPhone app's map download format (docs/architecture.md §7), map frame y up."""

    model_config = examples(
        {
            "tag_vertices": [
                {"id": 3, "translation": TRANSLATION_EXAMPLE, "rotation": ROTATION_EXAMPLE}
            ],
            "odometry_vertices": [
                {
                    "poseId": 0,
                    "translation": {"x": 0.0, "y": 0.0, "z": 0.0},
                    "rotation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0},
                    "adjChi2": 0.0003,
                    "vizTags": 0.0,
                    "neighbors": [1],
                }
            ],
            "waypoints_vertices": [
                {"id": "Room 101", "translation": TRANSLATION_EXAMPLE, "rotation": ROTATION_EXAMPLE}
            ],
            "notes": [],
        }
    )

    tag_vertices: list[AppTagVertex]
    odometry_vertices: list[AppOdometryVertex]
    waypoints_vertices: list[AppWaypointVertex]
    notes: list[str] = Field(
        description="what was adjusted so the app can route on the map (the app ignores this "
        "key): a walk that falls apart (only its largest part is kept), renamed waypoints"
    )


# --------------------------------------------------------------------------- keys


class AddSessionRequest(BaseModel):
    """Add an uploaded session to a map."""

    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [{"session_id": 18}]})

    session_id: BodyId = Field(description=f"a session uploaded before: {ID_RULE} (404 not_found)")


class MergeRequest(BaseModel):
    """Merge another map (its sessions) into this one."""

    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [{"map_id": 13}]})

    map_id: BodyId = Field(
        description=f"the map to merge in; it is deleted: {ID_RULE} (404 not_found)"
    )


class MapSessionPublic(BaseModel):
    """A session of a map and, if the current version used it, what it contributed."""

    model_config = examples(
        {
            "session_id": 18,
            "in_current_version": True,
            "contribution": {
                "session_id": 18,
                "poses": 1007,
                "first_pose_row": 1004,
                "tags": [1, 2, 302, 303],
                "detections_used": 120,
                "detections_rejected": 30,
                "tag_chi2_mean": 0.004,
                "shared_tags": [302, 303],
                "placed_by_tags": [302, 303],
                "own_landmark_tags": [],
                "odometry_variance_scale": 0.105,
                "tag_depth_scale": 1.0,
                "yaw_rad": 3.0,
                "odometry_scale": 1.0,
                "noise": {
                    "variances": {
                        "odom_linear_var_m2_per_s": 1.05e-4,
                        "odom_angular_var_rad2_per_s": 4.3e-5,
                        "tag_position_var_m2": 1.35e-5,
                        "tag_orientation_var_rad2": 4.8e-3,
                    },
                    "components": {
                        "odom_linear": {
                            "scale": 0.105,
                            "redundancy": 171.9,
                            "rows": 1008.0,
                            "chi2_per_redundancy": 1.0,
                        }
                    },
                    "rounds": 4,
                    "converged": True,
                    "note": "",
                },
                "noise_scales": {
                    "odom_linear": 0.105,
                    "odom_angular": 0.432,
                    "tag_position": 0.135,
                    "tag_orientation": 0.048,
                },
                "disagreement_factor": 1.0,
                "cost_alone": 412.5,
                "cost_joint": 418.4,
                "redundancy_gain": 6.1,
                "weighting": "weighed by its own noise: its cost grew by 5.9 on joining, for 6.1 "
                "degrees of freedom gained, which that noise explains",
                "alone_vs_joint": {
                    "all": {"tags": [1, 2, 302, 303], "tags_compared": 4, "moved_rms_m": 0.04},
                    "shared": {"tags": [302, 303], "tags_compared": 2, "moved_rms_m": None},
                    "own": {"tags": [1, 2], "tags_compared": 2, "moved_rms_m": None},
                    "shift_alone": 0.0190,
                    "shift_joint": 0.0196,
                },
            },
        }
    )

    session_id: int
    in_current_version: bool = Field(description="whether the current version was made with it")
    contribution: dict[str, Any] | None = Field(
        description="from the current version: its poses, tags, detections used and rejected, "
        "mean tag chi², shared tags and those that placed it, tags given a landmark of their own "
        "(they disagreed with the map beyond its noise); what it weighs and why: its noise "
        "estimated from its own residuals (`noise`), the factors on its variances in the map "
        "(`noise_scales`, with `disagreement_factor` ≥ 1 when its disagreement with the other "
        "walks was more than that noise explains), its odometry scale, and `weighting` in a "
        "sentence; and `alone_vs_joint`: its own map alone against the building map on all its "
        "tags, on those other walks saw too and on its own (RMS movement after a rigid fit, m, "
        "and the shift metric over its own sightings); null when the version did not use it or "
        "has one session"
    )


class MapSessionsPublic(BaseModel):
    """The sessions a map is made of, in order (the first is the map frame)."""

    model_config = examples(
        {
            "map_id": 12,
            "data": [
                {"session_id": 17, "in_current_version": True, "contribution": None},
                {"session_id": 18, "in_current_version": False, "contribution": None},
            ],
            "count": 2,
            "current_version": 1,
            "current_session_ids": [17],
            "generation": 2,
            "up_to_date": False,
            "pending_job_id": 32,
        }
    )

    map_id: int
    data: list[MapSessionPublic]
    count: int
    current_version: int | None = Field(description="the current version's number")
    current_session_ids: list[int] = Field(
        description="the sessions the current version was built from, in order (empty: none)"
    )
    generation: int = Field(description=GENERATION_DESCRIPTION)
    up_to_date: bool = Field(description=UP_TO_DATE_DESCRIPTION)
    pending_job_id: int | None = Field(description=PENDING_JOB_DESCRIPTION)

    @classmethod
    def from_domain(cls, info: MapInfo) -> MapSessionsPublic:
        data = [MapSessionPublic.model_validate(use) for use in map_session_uses(info)]
        current = info.current
        return cls(
            map_id=info.id,
            data=data,
            count=len(data),
            current_version=None if current is None else current.number,
            current_session_ids=[]
            if current is None
            else (current.session_ids or [info.session_id]),
            generation=info.generation,
            up_to_date=info.up_to_date,
            pending_job_id=info.pending_job_id,
        )
