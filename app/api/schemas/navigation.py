"""Pydantic models of the navigation endpoints: points of interest, routes, localization.

Floors in responses are numbered as people say them: 1 is the lowest floor of the map (the path
graph's floor index + 1), as in the spoken steps ("take the stairs up to floor 2").
"""

from __future__ import annotations

import math
from datetime import datetime
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from app.domain.navigation.instructions import (
    STEP_LENGTH_M,
    STRIDE_MAX_M,
    STRIDE_MIN_M,
    GuidanceStyle,
    route_text,
)
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
            "examples": [
                {"from": {"tag": 300}, "to": {"poi": "Room 209"}, "avoid": ["stairs"]},
                {"from": {"tag": 300}, "to": {"tag": 311}, "heading_deg": 180, "stride_m": 0.65},
            ]
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
    stride_m: FiniteFloat = Field(
        default=STEP_LENGTH_M,
        ge=STRIDE_MIN_M,
        le=STRIDE_MAX_M,
        description=(
            "the walker's step, m: distances are also given in steps of this length "
            '(`steps_count`, the text form, and `style.units` "steps")'
        ),
    )

    def heading_rad(self) -> float | None:
        return None if self.heading_deg is None else math.radians(self.heading_deg)

    def guidance_style(self) -> GuidanceStyle:
        style = RouteStyle() if self.style is None else self.style
        return GuidanceStyle(units=style.units, clock=style.clock, stride_m=self.stride_m)


_GO_EXAMPLE: dict[str, Any] = {
    "instruction": "go straight 12 m",
    "kind": "go",
    "position": [0.0, 0.0, 0.0],
    "distance_m": 12.0,
    "turn_deg": None,
    "floor": 1,
    "turn": None,
    "clock": None,
    "steps_count": 17,
    "landmark": None,
    "side": None,
    "text": "Go straight 12 metres (17 steps).",
}
_TURN_EXAMPLE: dict[str, Any] = {
    "instruction": "turn left",
    "kind": "turn",
    "position": [0.0, 0.0, -12.0],
    "distance_m": 0.0,
    "turn_deg": 90.0,
    "floor": 1,
    "turn": "turn",
    "clock": 9,
    "steps_count": None,
    "landmark": "tag 305",
    "side": None,
    "text": "At tag 305, turn left, to 9 o'clock.",
}
_KEEP_EXAMPLE: dict[str, Any] = {
    "instruction": "keep left at the fork",
    "kind": "keep",
    "position": [0.0, 0.0, -20.0],
    "distance_m": 0.0,
    "turn_deg": 15.0,
    "floor": 1,
    "turn": None,
    "clock": None,
    "steps_count": None,
    "landmark": "tag 307",
    "side": "left",
    "text": "At tag 307, keep left at the fork.",
}
_LAST_GO_EXAMPLE: dict[str, Any] = {
    **_GO_EXAMPLE,
    "instruction": "go straight 9 m to Room 209, on your right",
    "position": [0.0, 0.0, -12.0],
    "distance_m": 9.0,
    "steps_count": 13,
    "landmark": "Room 209",
    "side": "right",
    "text": "Go straight 9 metres (13 steps) to Room 209, on your right.",
}
_ARRIVE_EXAMPLE: dict[str, Any] = {
    **_GO_EXAMPLE,
    "instruction": "arrive at Room 209, on your right",
    "kind": "arrive",
    "position": [-9.0, 0.0, -12.0],
    "distance_m": 0.0,
    "steps_count": None,
    "landmark": "Room 209",
    "side": "right",
    "text": "Arrive at Room 209, on your right.",
}


class StepPublic(BaseModel):
    """One instruction and where to carry it out: ``instruction`` as the app speaks it (worded by
    the request's ``style``), its structure (``kind``, ``distance_m``, ``turn_deg``, ``turn``,
    ``clock``, ``steps_count``, ``landmark``, ``side``: what a program or a simulated walker
    reads), and ``text``, the same step as a plain sentence for a screen reader (metres and
    steps, left/right and the clock, landmarks by name). A turn's word is a function of its angle
    alone: |turn_deg| < 20 straight, 20–45 bear, 45–135 turn, 135–150 sharp, ≥ 150 around. A
    ``keep`` step ("keep left at the fork") is said at a junction the route goes through without a
    turn while another way leaves within 45° of straight on; its ``side`` is the side to keep."""

    model_config = _examples(_TURN_EXAMPLE, _KEEP_EXAMPLE, _LAST_GO_EXAMPLE)

    instruction: str = Field(description="as spoken, in the request's style")
    kind: Literal["face", "go", "announce", "turn", "keep", "stairs", "elevator", "arrive"]
    position: list[float] = Field(description="[x, y, z], m, map frame")
    distance_m: float = Field(description="length to walk (go) or of the stairs, m; else 0")
    turn_deg: float | None = Field(
        description="signed horizontal turn, + is left (face, announce and turn steps; on a keep "
        "step the route's own bend at the fork)"
    )
    floor: int = Field(description="floor number where the step starts, 1 = lowest")
    turn: Literal["straight", "bear", "turn", "sharp", "around"] | None = Field(
        default=None,
        description="the class of `turn_deg` by its size alone: < 20° straight, 20–45° bear, "
        "45–135° turn, 135–150° sharp, ≥ 150° around (face, announce and turn steps)",
    )
    clock: int | None = Field(
        default=None,
        ge=1,
        le=12,
        description="`turn_deg` as a clock-face hour: 12 ahead, 3 right, 6 behind, 9 left "
        "(face, announce and turn steps)",
    )
    steps_count: int | None = Field(
        default=None, description="`distance_m` in steps of the request's `stride_m` (go steps)"
    )
    landmark: str | None = Field(
        default=None,
        description='the tag or point of interest at the step ("Room 210", "tag 305"; '
        "within 3 m, on its floor), or the goal on the last go step and the arrival",
    )
    side: Literal["ahead", "left", "right", "behind"] | None = Field(
        default=None,
        description="where the goal is: on the last go step and the arrival; on a keep step, "
        'the side to keep at the fork ("ahead": straight on)',
    )
    text: str = Field(default="", description="the step as a sentence for a screen reader")

    @classmethod
    def from_domain(cls, step: Step) -> StepPublic:
        return cls(
            instruction=step.instruction,
            kind=step.kind,
            position=list(step.position_m),
            distance_m=step.distance_m,
            turn_deg=step.turn_deg,
            floor=step.floor + 1,
            turn=step.turn,
            clock=step.clock,
            steps_count=step.steps_count,
            landmark=step.landmark,
            side=step.side,
            text=step.text,
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
            "steps": [_GO_EXAMPLE, _TURN_EXAMPLE, _LAST_GO_EXAMPLE, _ARRIVE_EXAMPLE],
            "stride_m": 0.7,
            "text": "1. Go straight 12 metres (17 steps).\n"
            "2. At tag 305, turn left, to 9 o'clock.\n"
            "3. Go straight 9 metres (13 steps) to Room 209, on your right.\n"
            "4. Arrive at Room 209, on your right.",
        }
    )

    map_id: int
    map_version: int
    length_m: float
    polyline: list[list[float]] = Field(description="[[x, y, z], …], m, map frame (y up)")
    floors: list[int] = Field(description="floor numbers crossed, in order, 1 = lowest")
    steps: list[StepPublic]
    stride_m: float = Field(description="the step length `steps_count` and `text` count in, m")
    text: str = Field(
        description="the route for a screen reader: numbered plain sentences, one a line, the "
        "steps' `text` without the announcements (also the whole answer with "
        "`Accept: text/plain`)"
    )

    @classmethod
    def from_domain(
        cls, route: Route, *, map_id: int, map_version: int, stride_m: float = STEP_LENGTH_M
    ) -> RoutePublic:
        return cls(
            map_id=map_id,
            map_version=map_version,
            length_m=route.length_m,
            polyline=[list(point) for point in route.polyline_m],
            floors=[floor + 1 for floor in route.floors],
            steps=[StepPublic.from_domain(step) for step in route.steps],
            stride_m=stride_m,
            text=route_text(route),
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
