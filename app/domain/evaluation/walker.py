"""A simulated blind walker who follows a route's spoken steps through the *true* building
(DESIGN §10, issue 39): instructions are judged by whether a walker arrives.

    space = BoxFreeSpace.of_building(walk.building)               # a simulated building's truth
    space = CapsuleFreeSpace.of_lines(lines_xz, radius_m=1.6)     # corridors drawn as centrelines
    route = plan_guided_route(pg, TagEnd(a), TagEnd(b), heading_rad=start.heading_rad)
    outcome = walk_steps(route.steps, space, start, goal_xz=…, goal_floor=0, rng=rng)
    outcome.arrived, outcome.reason, outcome.where_xz

The walker knows only the steps as a user hears them (``Step.kind``, ``turn_deg``,
``distance_m``; never the route's polyline nor the map). It errs as people do:

- **Heading.** Every turn it makes (the facing turn included) is off by a uniform error of up to
  ``heading_error_deg`` (±15°).
- **Distance.** Each leg it walks is misjudged by a factor uniform in 1 ± ``stride_error`` (±10%):
  it counts its steps, and its steps are not the 0.7 m it assumes.
- **Walls stop it.** It moves in ``step_m`` steps inside the free space; a wall met at up to
  ``slide_max_deg`` from its heading turns it along the wall (a cane or a hand on the wall: it
  *shorelines*); a wall met more head-on stops it (the corridor ends there).
- **A trailing hand where the instruction says so.** Before a turn ("in 5 m, turn left"; the
  last ``search`` window of the leg: ``search_share`` of the leg, at least ``search_min_m``) it
  steps over to the wall on the turn's side and trails it; it turns (a turn of at least
  ``SEARCH_MIN_TURN_DEG``; a "bear" is taken where the told distance ends) at the first
  opening its hand finds there (the wall gone ``probe_m`` out), after stepping
  ``into_opening_m`` into it.
  No opening within the window past the told distance: it turns where it is.
- **Arrival.** On the last leg ("… to tag 311, on your right") the walker trails the wall of
  the side it is told for the leg's last window, and the app says "arrive" when it is within
  ``arrive_within_m`` of the goal (it tracks the phone against the tags); with
  ``app_says_arrive=False`` the walker stops when it has walked the told distance.
- **Stairs.** "take the stairs" takes the nearest stairs' foot or head within ``stairs_find_m``
  to their other end (a handrail leads); none there is a failure.

Success is ending within ``arrive_within_m`` of the goal (horizontally, on its floor) without a
turn of more than ``TURN_AROUND_DEG`` (a "turn around" is a failure of the instructions).
Every failure says where (x–z, m) and why: the step it happened at, in its own words.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
import numpy.typing as npt

from app.domain.errors import ParameterError
from app.domain.frames import FloatArray
from app.domain.navigation.routing import Step

BoolArray = npt.NDArray[np.bool_]

#: A told turn beyond this is a turn-around: the route sends the walker back, degrees.
TURN_AROUND_DEG = 150.0
#: Before a turn of at least this the walker trails the wall for the opening; a "bear" (a fork
#: or a bend of the corridor) it takes where it has walked the told distance, degrees.
SEARCH_MIN_TURN_DEG = 45.0


@dataclass(frozen=True, slots=True, kw_only=True)
class WalkerErrors:
    """How the walker errs and searches (see the module docstring); SI units in the names.

    WalkerErrors()                              # ±15° per turn, ±10% per leg, the app says arrive
    WalkerErrors(heading_error_deg=0.0, stride_error=0.0)     # a perfect walker
    WalkerErrors(app_says_arrive=False)          # stops after the told distance of the last leg
    """

    heading_error_deg: float = 15.0
    stride_error: float = 0.10
    step_m: float = 0.1
    slide_max_deg: float = 45.0
    search_share: float = 0.25
    search_min_m: float = 3.0
    probe_m: float = 1.0
    wall_find_m: float = 4.0
    into_opening_m: float = 0.8
    arrive_within_m: float = 2.0
    app_says_arrive: bool = True
    stairs_find_m: float = 3.0

    def __post_init__(self) -> None:
        for name in self.__dataclass_fields__:
            value = getattr(self, name)
            if not math.isfinite(float(value)) or float(value) < 0:
                raise ParameterError(f"{name} must be finite and ≥ 0, got {value!r}")
        if self.step_m <= 0 or self.stride_error >= 1:
            raise ParameterError("step_m must be > 0 and stride_error < 1")


DEFAULT_WALKER = WalkerErrors()


class FreeSpace(Protocol):
    """Where a walker can be: ``contains(xz, floor)`` → (N,) bool for points (N, 2), m."""

    def contains(self, xz: FloatArray, floor: int) -> BoolArray: ...


@dataclass(frozen=True, slots=True, eq=False)
class BoxFreeSpace:
    """The free space of a simulated building: axis-aligned boxes (B, 2, 3) of min and max
    corners (y up), each on the floor whose level its bottom is nearest; ``stairs`` the stairs'
    centrelines (P, 3), each from its lower end."""

    boxes_m: FloatArray
    floor_levels_m: tuple[float, ...]
    stairs: tuple[FloatArray, ...] = ()
    _on_floor: BoolArray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        levels = np.asarray(self.floor_levels_m, dtype=np.float64)
        bottoms, tops = self.boxes_m[:, 0, 1], self.boxes_m[:, 1, 1]
        # (B, F): a box is on every floor whose level lies within it (a stairwell spans two)
        on_floor = (bottoms[:, None] - 0.5 <= levels[None, :]) & (levels[None, :] < tops[:, None])
        object.__setattr__(self, "_on_floor", on_floor)

    @classmethod
    def of_building(cls, building: object) -> BoxFreeSpace:
        """The truth of an ``app.domain.evaluation.simulate.Building``."""
        boxes = np.asarray(building.free_space_boxes_m, dtype=np.float64)  # type: ignore[attr-defined]
        ends = np.asarray(building.edge_nodes)  # type: ignore[attr-defined]
        xyz = np.asarray(building.node_xyz_m)  # type: ignore[attr-defined]
        polylines = building.edge_polylines_m  # type: ignore[attr-defined]
        stairs = tuple(
            np.asarray(polylines[e], dtype=np.float64)
            for e in range(len(ends))
            if abs(float(xyz[ends[e, 0], 1] - xyz[ends[e, 1], 1])) > 1e-9
        )
        levels = tuple(float(v) for v in building.floor_heights_m)  # type: ignore[attr-defined]
        return cls(boxes, levels, stairs)

    def contains(self, xz: FloatArray, floor: int) -> BoolArray:
        on = self._on_floor[:, floor]
        low, high = self.boxes_m[on, 0][:, [0, 2]], self.boxes_m[on, 1][:, [0, 2]]
        p = xz[:, None, :]
        return np.asarray(((p >= low[None]) & (p <= high[None])).all(axis=2).any(axis=1))


@dataclass(frozen=True, slots=True, eq=False)
class CapsuleFreeSpace:
    """Corridors drawn as centrelines: segments (S, 2, 2) (x–z, m) widened by ``radius_m``, one
    floor (floor 0)."""

    segments_m: FloatArray
    radius_m: float

    @classmethod
    def of_lines(
        cls, lines_xz: Sequence[Sequence[tuple[float, float]]], *, radius_m: float
    ) -> CapsuleFreeSpace:
        segments = [(a, b) for line in lines_xz for a, b in itertools.pairwise(line)]
        return cls(np.asarray(segments, dtype=np.float64).reshape(-1, 2, 2), radius_m)

    def contains(self, xz: FloatArray, floor: int) -> BoolArray:
        if floor != 0:
            return np.zeros(len(xz), dtype=np.bool_)
        a, b = self.segments_m[:, 0], self.segments_m[:, 1]
        ab = b - a
        ap = xz[:, None, :] - a[None]
        t = np.clip((ap * ab).sum(axis=2) / np.maximum((ab * ab).sum(axis=1), 1e-12), 0.0, 1.0)
        distance = np.linalg.norm(ap - t[..., None] * ab, axis=2).min(axis=1)
        return np.asarray(distance <= self.radius_m)


@dataclass(frozen=True, slots=True, kw_only=True)
class Start:
    """Where the walker stands and which way it faces: ``heading_rad`` as the instructions take
    it (the walking direction's angle in x–z, atan2(−x, −z); + turns left)."""

    xz: tuple[float, float]
    heading_rad: float
    floor: int = 0


@dataclass(frozen=True, slots=True, kw_only=True)
class WalkOutcome:
    """What happened: ``arrived``; ``reason`` (why it failed, or "arrived"); ``where_xz`` where
    it ended or failed, m; ``distance_to_goal_m`` at the end; ``path_xz`` (K, 2) its walk; the
    index of the step it failed at (None if it arrived)."""

    arrived: bool
    reason: str
    where_xz: tuple[float, float]
    distance_to_goal_m: float
    path_xz: FloatArray
    failed_step: int | None = None


class _Blocked(Exception):
    pass


@dataclass(slots=True)
class _Walker:
    space: FreeSpace
    xz: FloatArray
    heading_rad: float
    floor: int
    errors: WalkerErrors
    path: list[tuple[float, float]]
    notes: list[str] = field(default_factory=list)

    def note(self, words: str) -> None:
        """Remember what went unexpectedly (the first such note explains a failure)."""
        x, z = self.xz
        self.notes.append(f"{words} at ({x:.1f}, {z:.1f})")

    def forward(self) -> FloatArray:
        return np.array([-math.sin(self.heading_rad), -math.cos(self.heading_rad)])

    def side(self, sign: float) -> FloatArray:
        """The unit x–z vector to the left (``sign`` +1) or right (−1)."""
        h = self.heading_rad
        return sign * np.array([-math.cos(h), math.sin(h)])

    def free(self, xz: FloatArray) -> bool:
        return bool(self.space.contains(xz[None, :], self.floor)[0])

    def step(self) -> bool:
        """One ``step_m`` forward, along a wall met at a glancing angle; False when blocked."""
        e = self.errors
        for delta_deg in _slide_angles(e.slide_max_deg):
            h = self.heading_rad + math.radians(delta_deg)
            to = self.xz + e.step_m * np.array([-math.sin(h), -math.cos(h)])
            if self.free(to):
                self.xz = to
                self.heading_rad = h  # the wall turned it: it now walks along the wall
                self.path.append((float(to[0]), float(to[1])))
                return True
        return False

    def sidestep(self, direction: FloatArray, up_to_m: float) -> bool:
        """Step sideways until a wall is within ``probe_m / 2``; False if none within
        ``up_to_m`` (open space on that side)."""
        e = self.errors
        moved = 0.0
        while moved < up_to_m:
            if not self.free(self.xz + 0.5 * e.probe_m * direction):
                return True
            to = self.xz + e.step_m * direction
            if not self.free(to):
                return True
            self.xz = to
            self.path.append((float(to[0]), float(to[1])))
            moved += e.step_m
        return False


def _slide_angles(max_deg: float) -> list[float]:
    angles = [0.0]
    for d in range(5, int(max_deg) + 1, 5):
        angles += [float(d), float(-d)]
    return angles


def walk_steps(
    steps: Sequence[Step],
    space: FreeSpace,
    start: Start,
    *,
    goal_xz: tuple[float, float],
    goal_floor: int,
    rng: np.random.Generator,
    errors: WalkerErrors = DEFAULT_WALKER,
) -> WalkOutcome:
    """Walk ``steps`` from ``start`` through ``space`` (see the module docstring)."""
    w = _Walker(
        space=space,
        xz=np.array(start.xz, dtype=np.float64),
        heading_rad=start.heading_rad,
        floor=start.floor,
        errors=errors,
        path=[(float(start.xz[0]), float(start.xz[1]))],
    )
    goal = np.asarray(goal_xz, dtype=np.float64)

    def outcome(arrived: bool, reason: str, k: int | None) -> WalkOutcome:
        d = float(np.linalg.norm(w.xz - goal)) if w.floor == goal_floor else math.inf
        return WalkOutcome(
            arrived=arrived,
            reason=reason,
            where_xz=(float(w.xz[0]), float(w.xz[1])),
            distance_to_goal_m=d,
            path_xz=np.array(w.path, dtype=np.float64).reshape(-1, 2),
            failed_step=k,
        )

    last_walk = max((k for k, s in enumerate(steps) if s.kind == "go"), default=-1)
    for k, s in enumerate(steps):
        if s.kind in ("face", "turn"):
            turn = float(s.turn_deg or 0.0)
            if abs(turn) > TURN_AROUND_DEG and s.kind == "turn":
                return outcome(False, f"turn-around told at step {k} ({s.instruction!r})", k)
            error = rng.uniform(-errors.heading_error_deg, errors.heading_error_deg)
            w.heading_rad += math.radians(turn + error)
        elif s.kind == "go":
            following = next((t for t in steps[k + 1 :] if t.kind != "announce"), None)
            turn_side = (
                math.copysign(1.0, float(following.turn_deg or 0.0))
                if following is not None
                and following.kind == "turn"
                and abs(float(following.turn_deg or 0.0)) >= SEARCH_MIN_TURN_DEG
                else _told_side(s.instruction)
                if k == last_walk
                else None
            )
            told_m = s.distance_m
            judged_m = told_m * (1 + rng.uniform(-errors.stride_error, errors.stride_error))
            failure = _walk_leg(w, judged_m, told_m, turn_side, k == last_walk, goal, errors, k)
            if failure:
                return outcome(False, f"{failure} (step {k}: {s.instruction!r})", k)
            if k == last_walk and errors.app_says_arrive and _near(w, goal, goal_floor, errors):
                return outcome(True, "arrived", None)
        elif s.kind in ("stairs", "elevator"):
            failure = _change_floor(w, space, errors)
            if failure:
                return outcome(False, f"{failure} (step {k}: {s.instruction!r})", k)
    if _near(w, goal, goal_floor, errors):
        return outcome(True, "arrived", None)
    d = float(np.linalg.norm(w.xz - goal))
    where = "on another floor" if w.floor != goal_floor else f"{d:.1f} m from the goal"
    first = f"; first, {w.notes[0]}" if w.notes else ""
    return outcome(False, f"ended {where}{first}", len(steps) - 1)


def _told_side(instruction: str) -> float | None:
    """+1 for a goal "on your left", −1 "on your right", else None: on the last leg the walker
    trails that wall."""
    if "on your left" in instruction:
        return 1.0
    if "on your right" in instruction:
        return -1.0
    return None


def _near(w: _Walker, goal: FloatArray, goal_floor: int, errors: WalkerErrors) -> bool:
    return w.floor == goal_floor and float(np.linalg.norm(w.xz - goal)) <= errors.arrive_within_m


def _walk_leg(
    w: _Walker,
    judged_m: float,
    told_m: float,
    hand_side: float | None,
    last: bool,
    goal: FloatArray,
    errors: WalkerErrors,
    k: int,
) -> str | None:
    """Walk one leg (step ``k``) of ``told_m`` (the walker judges ``judged_m``); ``hand_side``
    (+1 left, −1 right): the side whose wall it trails near the leg's end (the next turn's, or
    the goal's on the last leg). A failure's words, or None."""
    window_m = max(errors.search_min_m, errors.search_share * told_m)
    walked_m = 0.0
    # before a turn, and on the last leg told the goal's side, the hand goes on that wall for the
    # leg's last window (not at its start: the walker may still be in the corridor it turned from)
    search_from_m = math.inf if hand_side is None else judged_m - window_m
    arriving = last and errors.app_says_arrive
    limit_m = judged_m + window_m if (hand_side is not None and not last) or arriving else judged_m
    trailing = False
    while walked_m < limit_m:
        if arriving and float(np.linalg.norm(w.xz - goal)) <= errors.arrive_within_m:
            return None
        if hand_side is not None and walked_m >= search_from_m:
            hand = w.side(hand_side)
            if not trailing:
                trailing = True
                if not w.sidestep(hand, errors.wall_find_m) and not last:
                    w.note(f"no wall on the turn's side to trail (step {k})")
                    return None  # open space on that side: it turns here
            elif not w.free(w.xz + errors.probe_m * hand):
                w.sidestep(hand, 0.3)  # the wall is there: keep the hand on it
            elif not last:
                # the wall is gone: an opening; step into it, then turn
                for _ in range(round(errors.into_opening_m / errors.step_m)):
                    if not w.step():
                        break
                return None
            # on the last leg the hand crosses an opening and finds the wall again beyond it
        if not w.step():
            if walked_m < 1.0 and told_m >= 2.0:
                x, z = w.xz
                return (
                    f"walked into a wall at ({x:.1f}, {z:.1f}) after {walked_m:.1f} m "
                    f"of {told_m:.0f} m"
                )
            if walked_m < judged_m - 2.0:
                w.note(
                    f"the corridor ended {judged_m - walked_m:.0f} m short of the told "
                    f"{told_m:.0f} m (step {k})"
                )
            return None  # the corridor ends here: the next step begins at its end
        walked_m += errors.step_m
    if hand_side is not None and not last:
        w.note(
            f"no opening on the turn's side up to {window_m:.0f} m past the told distance "
            f"(step {k})"
        )
    return None


def _change_floor(w: _Walker, space: FreeSpace, errors: WalkerErrors) -> str | None:
    """Take the nearest stairs within ``stairs_find_m`` to their other end; a failure's words
    or None."""
    stairs = getattr(space, "stairs", ())
    levels = getattr(space, "floor_levels_m", (0.0,))
    best: tuple[float, FloatArray, bool] | None = None
    for line in stairs:
        for from_start in (True, False):
            ordered = line if from_start else line[::-1]
            end_floor = int(np.argmin(np.abs(np.asarray(levels) - ordered[0][1])))
            if end_floor != w.floor:
                continue
            # the stairs' level approach on this floor (to the first step), then the flights
            level = ordered[np.abs(ordered[:, 1] - ordered[0][1]) < 0.05][:, [0, 2]]
            d = _to_polyline_m(w.xz, level)
            if d <= errors.stairs_find_m and (best is None or d < best[0]):
                best = (d, line, from_start)
    if best is None:
        x, z = w.xz
        return f"no stairs within {errors.stairs_find_m:.0f} m of ({x:.1f}, {z:.1f})"
    _, line, from_start = best
    line = line if from_start else line[::-1]
    w.xz = line[-1][[0, 2]].astype(np.float64)
    w.floor = int(np.argmin(np.abs(np.asarray(levels) - line[-1][1])))
    out = line[-1][[0, 2]] - line[-2][[0, 2]]
    w.heading_rad = math.atan2(-out[0], -out[1])
    w.path.append((float(w.xz[0]), float(w.xz[1])))
    return None


def _to_polyline_m(p: FloatArray, polyline: FloatArray) -> float:
    """Distance from the point (2,) to the polyline (K, 2), m."""
    if len(polyline) == 1:
        return float(np.linalg.norm(polyline[0] - p))
    a, b = polyline[:-1], polyline[1:]
    ab = b - a
    t = np.clip(((p - a) * ab).sum(axis=1) / np.maximum((ab * ab).sum(axis=1), 1e-12), 0.0, 1.0)
    return float(np.linalg.norm(a + t[:, None] * ab - p, axis=1).min())
