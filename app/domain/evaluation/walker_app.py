"""The app's side of a simulated walk (issue 39): it sees tags and routes the walker again.

The real app localizes the phone on every tag its camera sees and plans from the vertex nearest
the phone (DESIGN §7). A walker who hears the steps once (``app.domain.evaluation.walker``) gets
no help; one who uses the app as it is meant to be used is corrected when a tag shows it off its
way. This module is that app, for the bench and the tests:

    app = TagCorrections(pg, space, tags, goal=TagEnd(b), route=route)
    walk_steps(route.steps, space, start, …, app=app)

- **What the phone sees.** A tag is seen when it is within ``see_within_m`` (horizontally, on
  the walker's floor), the walker is in front of it (the line from the tag to the phone within
  ``view_angle_max_deg`` of the tag's normal), nothing stands between them, and — while the walker
  walks, phone held ahead — the tag is within ``camera_half_fov_deg`` of its heading. A walker
  who is lost (a wall where it should walk on; the steps done short of the goal) turns on the
  spot, so the phone looks all round. The defaults are the simulator's camera and detector
  (``SimulationConfig``: 3 m, 60°, a 1850 px wide image at fx 1460 px: ±32°).
- **Where the app thinks the phone is.** The phone's offset from the nearest seen tag is measured
  well (centimetres at 3 m); the map's error is the tag's: the app puts the phone at its true
  offset from the map's tag position, heading as it truly is (the map's tag orientation error is
  not modelled).
- **When it routes again.** When the phone, so placed, is more than ``off_route_m`` from the
  route being walked (its polyline on that floor, and the point the app last routed from), or
  whenever the walker is lost and a tag is seen, the app plans from the phone's position
  (``PositionEnd``) to the goal with the phone's heading, and the walker follows the new steps.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from app.domain.evaluation.walker_space import FreeSpace, clear_line
from app.domain.frames import FloatArray
from app.domain.navigation.instructions import plan_guided_route
from app.domain.navigation.path_graph import PathGraph
from app.domain.navigation.routing import Endpoint, PositionEnd, Route, RouteError, Step

IntArray = npt.NDArray[np.int64]
BoolArray = npt.NDArray[np.bool_]


@dataclass(frozen=True, slots=True, kw_only=True)
class SeenTag:
    """A tag as it truly is — ``xz`` (2,) m and ``normal_xz`` (2,) its wall's outward direction,
    on ``floor`` — and ``map_xyz`` (3,) where the map has it, m."""

    tag_id: int
    xz: FloatArray
    normal_xz: FloatArray
    floor: int
    map_xyz: FloatArray


@dataclass(frozen=True, slots=True, kw_only=True)
class AppParams:
    """What the phone sees and when the app routes again (module docstring); SI units."""

    see_within_m: float = 3.0
    view_angle_max_deg: float = 60.0
    camera_half_fov_deg: float = 32.0
    off_route_m: float = 3.0


DEFAULT_APP = AppParams()


class TagCorrections:
    """The app: :meth:`correct` gives new steps when a tag it sees shows the walker off its way
    (or lost), else None. One per walk (it remembers the route being walked)."""

    def __init__(
        self,
        pg: PathGraph,
        space: FreeSpace,
        tags: Sequence[SeenTag],
        *,
        goal: Endpoint,
        route: Route,
        params: AppParams = DEFAULT_APP,
    ) -> None:
        self.pg = pg
        self.space = space
        self.tags = list(tags)
        self.goal = goal
        self.params = params
        self._way = _polyline_xz(route.polyline_m)
        self._way_floors = self._floors_of(route.polyline_m)
        self.replans = 0

    def correct(
        self, xz: tuple[float, float], heading_rad: float, floor: int, *, scanning: bool
    ) -> list[Step] | None:
        """New steps from where the app puts the walker, or None (see the module docstring)."""
        seen = self.seen(np.asarray(xz, dtype=np.float64), heading_rad, floor, scanning=scanning)
        if seen is None:
            return None
        believed = np.asarray(xz) + (seen.map_xyz[[0, 2]] - seen.xz)
        if not scanning and self._on_way(believed, floor):
            return None
        try:
            route = plan_guided_route(
                self.pg,
                PositionEnd((float(believed[0]), float(seen.map_xyz[1]), float(believed[1]))),
                self.goal,
                heading_rad=heading_rad,
            )
        except RouteError:
            return None
        self.replans += 1
        start = np.array([[believed[0], seen.map_xyz[1], believed[1]]])
        polyline = np.vstack([start, np.asarray(route.polyline_m, dtype=np.float64)])
        self._way = polyline[:, [0, 2]]
        self._way_floors = self._floors_of(polyline)
        return route.steps

    def seen(
        self, xz: FloatArray, heading_rad: float, floor: int, *, scanning: bool
    ) -> SeenTag | None:
        """The nearest tag the phone sees from ``xz`` facing ``heading_rad``, or None."""
        p = self.params
        forward = np.array([-math.sin(heading_rad), -math.cos(heading_rad)])
        best: tuple[float, SeenTag] | None = None
        for tag in self.tags:
            if tag.floor != floor:
                continue
            to_phone = xz - tag.xz
            d = float(np.linalg.norm(to_phone))
            if d > p.see_within_m or d < 1e-6 or (best is not None and d >= best[0]):
                continue
            if float(to_phone @ tag.normal_xz) < d * math.cos(math.radians(p.view_angle_max_deg)):
                continue
            if not scanning and float(-to_phone @ forward) < d * math.cos(
                math.radians(p.camera_half_fov_deg)
            ):
                continue
            # the line of sight ends just in front of the wall the tag is on
            if not clear_line(self.space, xz, tag.xz + 0.1 * tag.normal_xz, floor):
                continue
            best = (d, tag)
        return None if best is None else best[1]

    def _on_way(self, believed: FloatArray, floor: int) -> bool:
        on_floor = self._way_floors == floor
        if not on_floor.any():
            return False
        return _to_polyline_m(believed, self._way, on_floor) <= self.params.off_route_m

    def _floors_of(self, polyline_m: Sequence[Sequence[float]] | FloatArray) -> IntArray:
        heights = np.asarray(polyline_m, dtype=np.float64).reshape(-1, 3)[:, 1]
        levels = np.asarray(self.pg.floor_levels_m or (0.0,), dtype=np.float64)
        nearest = np.argmin(np.abs(heights[:, None] - levels[None, :]), axis=1)
        return np.asarray(nearest, dtype=np.int64)


def _polyline_xz(polyline_m: Sequence[Sequence[float]]) -> FloatArray:
    return np.asarray(polyline_m, dtype=np.float64).reshape(-1, 3)[:, [0, 2]]


def _to_polyline_m(p: FloatArray, polyline: FloatArray, keep: BoolArray) -> float:
    """Distance from the point (2,) to the segments of the polyline (K, 2) whose both ends
    ``keep`` (K,) flags, or to its single kept point, m."""
    both = keep[:-1] & keep[1:]
    if not both.any():
        return float(np.linalg.norm(polyline[keep] - p, axis=1).min())
    a, b = polyline[:-1][both], polyline[1:][both]
    ab = b - a
    t = np.clip(((p - a) * ab).sum(axis=1) / np.maximum((ab * ab).sum(axis=1), 1e-12), 0.0, 1.0)
    return float(np.linalg.norm(a + t[:, None] * ab - p, axis=1).min())
