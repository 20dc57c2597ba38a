"""Pydantic models of the navigation endpoints: points of interest, routes, localization.

Floors in responses are numbered as people say them: 1 is the lowest floor of the map (the path
graph's floor index + 1), as in the spoken steps ("take the stairs up to floor 2").
"""

from __future__ import annotations

import math
from datetime import datetime
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from app.domain.navigation.instructions import GuidanceStyle
from app.domain.navigation.path_graph import Anchor
from app.domain.navigation.routing import (
    Endpoint,
    NodeEnd,
    PoiEnd,
    PositionEnd,
    Route,
    Step,
    TagEnd,
)

FiniteFloat = Annotated[float, Field(allow_inf_nan=False)]
Position = Annotated[
    list[FiniteFloat],
    Field(min_length=3, max_length=3, description="[x, y, z], m, map frame (y up)"),
]


def _examples(*examples: dict[str, Any]) -> ConfigDict:
    return ConfigDict(json_schema_extra={"examples": list(examples)}, extra="forbid")


# --------------------------------------------------------------------------- points of interest


class PoiPublic(BaseModel):
    """A point of interest named while mapping, and the path-graph node it is reached from."""

    model_config = _examples(
        {"name": "Room 209", "position": [3.2, -0.1, -14.8], "floor": 1, "node": 57}
    )

    name: str
    position: list[float] = Field(description="[x, y, z], m, map frame (y up)")
    floor: int = Field(description="floor number, 1 = lowest")
    node: int = Field(description="the path-graph node it is reached from")

    @classmethod
    def from_domain(cls, anchor: Anchor) -> PoiPublic:
        return cls(
            name=anchor.name,
            position=list(anchor.position_m),
            floor=anchor.floor + 1,
            node=anchor.node,
        )


class PoisPublic(BaseModel):
    model_config = _examples(
        {
            "data": [{"name": "Room 209", "position": [3.2, -0.1, -14.8], "floor": 1, "node": 57}],
            "count": 1,
            "map_version": 2,
        }
    )

    data: list[PoiPublic]
    count: int
    map_version: int


# --------------------------------------------------------------------------- routes


class RouteEnd(BaseModel):
    """One end of a route: exactly one of ``tag``, ``poi``, ``node`` or ``position``."""

    model_config = ConfigDict(
        extra="forbid",
        json_schema_extra={
            "examples": [{"tag": 300}, {"poi": "Room 209"}, {"node": 12}, {"position": [1, 0, -3]}]
        },
    )

    tag: int | None = Field(default=None, ge=0, le=2**53, description="a tag id in the map")
    poi: str | None = Field(
        default=None, min_length=1, max_length=200, description="a point of interest's name"
    )
    node: int | None = Field(default=None, ge=0, le=2**53, description="a path-graph node id")
    position: Position | None = None

    @model_validator(mode="after")
    def _exactly_one(self) -> RouteEnd:
        given = [
            name for name in ("tag", "poi", "node", "position") if getattr(self, name) is not None
        ]
        if len(given) != 1:
            raise ValueError(
                "give exactly one of tag, poi, node or position"
                + (f" (got {', '.join(given)})" if given else "")
            )
        return self

    def to_domain(self) -> Endpoint:
        if self.tag is not None:
            return TagEnd(self.tag)
        if self.poi is not None:
            return PoiEnd(self.poi)
        if self.node is not None:
            return NodeEnd(self.node)
        assert self.position is not None
        x, y, z = self.position
        return PositionEnd((x, y, z))


class RouteStyle(BaseModel):
    """How the steps are worded: distance units, and clock-face directions instead of left/right
    ("turn to 9 o'clock")."""

    model_config = _examples({"units": "ft", "clock": True})

    units: Literal["m", "ft", "steps"] = "m"
    clock: bool = False

    def to_domain(self) -> GuidanceStyle:
        return GuidanceStyle(units=self.units, clock=self.clock)


class RouteRequest(BaseModel):
    """Where from, where to, what to avoid, and how to word the steps."""

    model_config = ConfigDict(
        extra="forbid",
        populate_by_name=True,
        json_schema_extra={
            "examples": [{"from": {"tag": 300}, "to": {"poi": "Room 209"}, "avoid": ["stairs"]}]
        },
    )

    from_: RouteEnd = Field(alias="from")
    to: RouteEnd
    avoid: list[Literal["stairs", "elevator"]] = Field(default_factory=list, max_length=2)
    heading_deg: FiniteFloat | None = Field(
        default=None,
        ge=-360,
        le=360,
        description=(
            "the phone's walking direction (e.g. from a localization), degrees about the map's "
            "up axis: 0 faces −z, +90 faces −x (counter-clockwise seen from above); when given, "
            "the first step says which way to turn to face the route"
        ),
    )
    style: RouteStyle | None = None

    def heading_rad(self) -> float | None:
        return None if self.heading_deg is None else math.radians(self.heading_deg)

    def guidance_style(self) -> GuidanceStyle:
        return GuidanceStyle() if self.style is None else self.style.to_domain()


class StepPublic(BaseModel):
    """One spoken instruction and where to carry it out."""

    model_config = _examples(
        {
            "instruction": "turn left",
            "kind": "turn",
            "position": [4.0, 0.0, -12.0],
            "distance_m": 0.0,
            "turn_deg": 88.5,
            "floor": 1,
        }
    )

    instruction: str
    kind: Literal["face", "go", "announce", "turn", "stairs", "elevator", "arrive"]
    position: list[float] = Field(description="[x, y, z], m, map frame")
    distance_m: float
    turn_deg: float | None = Field(description="signed horizontal turn, + is left")
    floor: int = Field(description="floor number where the step starts, 1 = lowest")

    @classmethod
    def from_domain(cls, step: Step) -> StepPublic:
        return cls(
            instruction=step.instruction,
            kind=step.kind,
            position=list(step.position_m),
            distance_m=step.distance_m,
            turn_deg=step.turn_deg,
            floor=step.floor + 1,
        )


class RoutePublic(BaseModel):
    """A route on the map's current version (``map_version`` says which)."""

    model_config = _examples(
        {
            "map_id": 12,
            "map_version": 2,
            "length_m": 23.4,
            "polyline": [[0.0, 0.0, 0.0], [0.0, 0.0, -12.0], [-9.0, 0.0, -12.0]],
            "floors": [1],
            "steps": [
                {
                    "instruction": "go straight 12 m",
                    "kind": "go",
                    "position": [0.0, 0.0, 0.0],
                    "distance_m": 12.0,
                    "turn_deg": None,
                    "floor": 1,
                },
                {
                    "instruction": "turn left",
                    "kind": "turn",
                    "position": [0.0, 0.0, -12.0],
                    "distance_m": 0.0,
                    "turn_deg": 90.0,
                    "floor": 1,
                },
                {
                    "instruction": "arrive at Room 209",
                    "kind": "arrive",
                    "position": [-9.0, 0.0, -12.0],
                    "distance_m": 0.0,
                    "turn_deg": None,
                    "floor": 1,
                },
            ],
        }
    )

    map_id: int
    map_version: int
    length_m: float
    polyline: list[list[float]] = Field(description="[[x, y, z], …], m, map frame (y up)")
    floors: list[int] = Field(description="floor numbers crossed, in order, 1 = lowest")
    steps: list[StepPublic]

    @classmethod
    def from_domain(cls, route: Route, *, map_id: int, map_version: int) -> RoutePublic:
        return cls(
            map_id=map_id,
            map_version=map_version,
            length_m=route.length_m,
            polyline=[list(point) for point in route.polyline_m],
            floors=[floor + 1 for floor in route.floors],
            steps=[StepPublic.from_domain(step) for step in route.steps],
        )


# --------------------------------------------------------------------------- localization

_MATRIX_EXAMPLE = [
    [0.0, 0.0, 1.0, 2.5],
    [0.0, 1.0, 0.0, 0.0],
    [-1.0, 0.0, 0.0, -4.0],
    [0.0, 0.0, 0.0, 1.0],
]
_ESTIMATE_EXAMPLE: dict[str, Any] = {
    "status": "localized",
    "pose_id": 140,
    "timestamp_s": 21.4,
    "map_T_phone": _MATRIX_EXAMPLE,
    "position": [2.5, 0.0, -4.0],
    "map_T_session": _MATRIX_EXAMPLE,
    "covariance": [[0.0] * 6 for _ in range(6)],
    "position_sigma_m": 0.12,
    "tags_used": [300],
    "rejections": [],
}


class LocalizationEstimate(BaseModel):
    """Where the phone is in the map, as of one update.

    ``map_T_phone`` and ``map_T_session`` are 4×4 rigid transforms (row-major nested lists, map
    frame, y up, m). ``covariance`` is the 6×6 covariance of ``map_T_session``, ordered
    [rotation rad, translation m] (gtsam's tangent, perturbation on the right, session frame).
    """

    model_config = _examples(_ESTIMATE_EXAMPLE)

    status: Literal["not_localized", "localized"]
    pose_id: int | None
    timestamp_s: float | None
    map_T_phone: list[list[float]] | None
    position: list[float] | None = Field(description="the phone's [x, y, z] in the map, m")
    map_T_session: list[list[float]] | None
    covariance: list[list[float]] | None
    position_sigma_m: float | None = Field(description="RMS 3-D position uncertainty, m")
    tags_used: list[int] = Field(description="tags whose detections this update used")
    rejections: list[dict[str, Any]] = Field(
        description="this update's detections left out, with the reason"
    )

    @classmethod
    def from_result_json(cls, result: dict[str, Any]) -> LocalizationEstimate:
        map_T_phone = result.get("map_T_phone")
        return cls(
            status=result["status"],
            pose_id=result.get("pose_id"),
            timestamp_s=result.get("timestamp_s"),
            map_T_phone=map_T_phone,
            position=[row[3] for row in map_T_phone[:3]] if map_T_phone else None,
            map_T_session=result.get("map_T_session"),
            covariance=result.get("covariance"),
            position_sigma_m=result.get("position_sigma_m"),
            tags_used=list(result.get("tags_used", [])),
            rejections=list(result.get("rejections", [])),
        )


class LocalizationPublic(BaseModel):
    """A navigation session: which map version it localizes in, and its latest estimate."""

    model_config = _examples(
        {
            "id": 7,
            "map_id": 12,
            "map_version": 2,
            "created_at": "2026-11-22T10:15:30Z",
            "updated_at": "2026-11-22T10:16:02Z",
            "updates": 14,
            "estimate": _ESTIMATE_EXAMPLE,
        }
    )

    id: int
    map_id: int
    map_version: int
    created_at: datetime
    updated_at: datetime
    updates: int = Field(description="updates applied so far")
    estimate: LocalizationEstimate | None = Field(description="null before the first update")


class LocalizationUpdate(BaseModel):
    """New odometry poses and tag detections since the last update, in the upload's formats:
    ``poses`` like ``pose_data`` (``pose`` is ``session_T_phone``, 16 numbers column-major, the
    phone's own ARKit frame), ``tag_data`` like the upload's (a list of frames, each a list of
    detections whose ``pose_id`` is a pose of this update or a recent one). Pose ids and timestamps
    must keep increasing from one update to the next."""

    model_config = ConfigDict(
        extra="allow",
        json_schema_extra={
            "examples": [
                {
                    "poses": [
                        {
                            "id": 140,
                            "timestamp": 21.4,
                            "pose": [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0.1, 0.0, -2.0, 1],
                        }
                    ],
                    "tag_data": [
                        [
                            {
                                "tag_id": 300,
                                "pose_id": 140,
                                "timestamp": 21.4,
                                "tag_pose": [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 1.5, 0, 0, 0, 1],
                                "camera_intrinsics": [1400, 1400, 960, 720],
                                "tag_corners_pixel_coordinates": [0] * 8,
                            }
                        ]
                    ],
                }
            ]
        },
    )

    poses: list[Any] = Field(default_factory=list)
    tag_data: list[Any] = Field(default_factory=list)
