"""How the simulated walker's body moves through the true building (``walker``, issue 39): its
errors (``WalkerErrors``), steps that slide along walls, a hand that feels a wall's direction,
and stairs. ``walker`` makes it follow the spoken steps.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from app.domain.errors import ParameterError, require_finite_non_negative
from app.domain.evaluation.walker_space import FreeSpace
from app.domain.frames import FloatArray
from app.domain.navigation.routing import Step

#: The hand feels for the wall in steps of this, m.
_FEEL_STEP_M = 0.02


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
    hand_m: float = 0.5
    feel_ahead_m: float = 0.3
    corner_deg: float = 30.0
    wall_find_m: float = 4.0
    into_opening_m: float = 0.8
    arrive_within_m: float = 2.0
    app_says_arrive: bool = True
    stairs_find_m: float = 3.0
    cane_m: float = 1.0
    short_m: float = 2.0
    around_max_deg: float = 85.0
    check_every_m: float = 0.5
    step_back_m: float = 1.0
    max_corrections: int = 3

    def __post_init__(self) -> None:
        require_finite_non_negative(self)
        if self.step_m <= 0 or self.stride_error >= 1 or self.feel_ahead_m <= 0:
            raise ParameterError("step_m and feel_ahead_m must be > 0 and stride_error < 1")
        if not self.hand_m < self.probe_m:
            raise ParameterError("hand_m must be less than probe_m")


DEFAULT_WALKER = WalkerErrors()


class Corrector(Protocol):
    """The app's side (:mod:`app.domain.evaluation.walker_app`): given where the walker truly is
    (x–z, m), its heading (rad, as ``Start``), its floor and whether it is looking round on the
    spot (``scanning``), new steps for the rest of the way, or None (nothing seen, or on the
    way)."""

    def correct(
        self, xz: tuple[float, float], heading_rad: float, floor: int, *, scanning: bool
    ) -> Sequence[Step] | None: ...


class Corrected(Exception):
    """The app gave new steps (raised from inside a leg)."""

    def __init__(self, steps: Sequence[Step]) -> None:
        super().__init__("corrected")
        self.steps = list(steps)


@dataclass(slots=True)
class Body:
    space: FreeSpace
    xz: FloatArray
    heading_rad: float
    floor: int
    errors: WalkerErrors
    path: list[tuple[float, float]]
    app: Corrector | None = None
    corrections: int = 0
    blocked: bool = False
    notes: list[str] = field(default_factory=list)

    def note(self, words: str) -> None:
        """Remember what went unexpectedly (the first such note explains a failure)."""
        x, z = self.xz
        self.notes.append(f"{words} at ({x:.1f}, {z:.1f})")

    def check(self, *, scanning: bool) -> None:
        """Ask the app; raise ``Corrected`` with its new steps. Scanning, the walker first steps
        back from the wall before it (up to ``step_back_m``) and then turns on the spot."""
        if self.app is None or self.corrections >= self.errors.max_corrections:
            return
        stood = self.xz
        if scanning:
            back = -self.errors.step_m * self.forward()
            for _ in range(round(self.errors.step_back_m / self.errors.step_m)):
                if not self.free(self.xz + back):
                    break
                self.move(self.xz + back)
        xz = (float(self.xz[0]), float(self.xz[1]))
        steps = self.app.correct(xz, self.heading_rad, self.floor, scanning=scanning)
        if not steps and scanning:
            self.move(stood)  # nothing seen: back to where it stood
        if steps:
            self.corrections += 1
            self.note(f"the app routed again ({self.corrections})")
            raise Corrected(steps)

    def forward(self) -> FloatArray:
        return np.array([-math.sin(self.heading_rad), -math.cos(self.heading_rad)])

    def side(self, sign: float) -> FloatArray:
        """The unit x–z vector to the left (``sign`` +1) or right (−1)."""
        h = self.heading_rad
        return sign * np.array([-math.cos(h), math.sin(h)])

    def free(self, xz: FloatArray) -> bool:
        return bool(self.space.contains(xz[None, :], self.floor)[0])

    def move(self, to: FloatArray) -> None:
        self.xz = to
        self.path.append((float(to[0]), float(to[1])))

    def step(self, *, slide_max_deg: float | None = None) -> bool:
        """One ``step_m`` forward, along a wall met within ``slide_max_deg`` (default
        ``errors.slide_max_deg``) of its heading; False when blocked."""
        e = self.errors
        for delta_deg in _slide_angles(e.slide_max_deg if slide_max_deg is None else slide_max_deg):
            h = self.heading_rad + math.radians(delta_deg)
            to = self.xz + e.step_m * np.array([-math.sin(h), -math.cos(h)])
            if self.free(to):
                self.heading_rad = h  # the wall turned it: it now walks along the wall
                self.move(to)
                return True
        return False

    def sidestep(self, direction: FloatArray, up_to_m: float) -> bool:
        """Step sideways until a wall is within ``hand_m``; False if none within ``up_to_m``
        (open space on that side)."""
        e = self.errors
        moved = 0.0
        while moved < up_to_m:
            if not self.free(self.xz + e.hand_m * direction):
                return True
            to = self.xz + e.step_m * direction
            if not self.free(to):
                return True
            self.move(to)
            moved += e.step_m
        return False

    def wall_m(self, origin: FloatArray, direction: FloatArray) -> float | None:
        """How far the wall is from ``origin`` along ``direction`` (to ``_FEEL_STEP_M``), None
        if beyond ``probe_m``; 0 if ``origin`` itself is in the wall."""
        reach = np.arange(0.0, self.errors.probe_m + 1e-9, _FEEL_STEP_M)
        points = origin[None, :] + reach[:, None] * direction[None, :]
        blocked = np.flatnonzero(~self.space.contains(points, self.floor))
        return float(reach[blocked[0]]) if blocked.size else None

    def feel(self, sign: float) -> tuple[float | None, float | None]:
        """The wall on the ``sign`` side at the body and ``feel_ahead_m`` ahead of it, m."""
        hand = self.side(sign)
        ahead = self.xz + self.errors.feel_ahead_m * self.forward()
        return self.wall_m(self.xz, hand), self.wall_m(ahead, hand)

    def trail(self, sign: float, *, turn_max_deg: float) -> float | None:
        """Keep the hand on the wall of the ``sign`` side for one step: turn with the wall when
        it turns by less than ``turn_max_deg`` and keep ``hand_m`` from it. Returns how much the
        wall turns away from the walker ahead, degrees (None: the wall is gone, an opening)."""
        e = self.errors
        at_m, ahead_m = self.feel(sign)
        if at_m is None or ahead_m is None:
            return None
        away_deg = math.degrees(math.atan2(ahead_m - at_m, e.feel_ahead_m))
        if -e.corner_deg < away_deg < turn_max_deg:  # a wall across its way is no guide
            self.heading_rad += sign * math.radians(away_deg)  # turn with the wall
            gap_m = at_m - e.hand_m
            if abs(gap_m) > 0.05:
                to = self.xz + max(-0.3, min(gap_m, 0.3)) * self.side(sign)
                if self.free(to):
                    self.move(to)
        return away_deg


def wrapped(angle_rad: float) -> float:
    """``angle_rad`` in (−π, π]."""
    return math.atan2(math.sin(angle_rad), math.cos(angle_rad))


def _slide_angles(max_deg: float) -> list[float]:
    angles = [0.0]
    for d in range(5, int(max_deg) + 1, 5):
        angles += [float(d), float(-d)]
    return angles


def stairs_tops(w: Body) -> FloatArray:
    """(S, 2, 2) where each flight of stairs leaving the walker's floor starts: the last segment
    of its level approach (x–z, m)."""
    levels = np.asarray(getattr(w.space, "floor_levels_m", (0.0,)))
    found = []
    for line in getattr(w.space, "stairs", ()):
        for ordered in (line, line[::-1]):
            if int(np.argmin(np.abs(levels - ordered[0][1]))) != w.floor:
                continue
            level = ordered[np.abs(ordered[:, 1] - ordered[0][1]) < 0.05][:, [0, 2]]
            found.append(level[-2:] if len(level) > 1 else level[[0, 0]])
    return np.array(found, dtype=np.float64).reshape(-1, 2, 2)


def take_stairs(w: Body, errors: WalkerErrors) -> str | None:
    """Take the nearest stairs within ``stairs_find_m`` to their other end; a failure's words
    or None."""
    stairs = getattr(w.space, "stairs", ())
    levels = getattr(w.space, "floor_levels_m", (0.0,))
    best: tuple[float, FloatArray, bool] | None = None
    for line in stairs:
        for from_start in (True, False):
            ordered = line if from_start else line[::-1]
            end_floor = int(np.argmin(np.abs(np.asarray(levels) - ordered[0][1])))
            if end_floor != w.floor:
                continue
            # the stairs' level approach on this floor (to the first step), then the flights
            level = ordered[np.abs(ordered[:, 1] - ordered[0][1]) < 0.05][:, [0, 2]]
            d = to_polyline_m(w.xz, level)
            if d <= errors.stairs_find_m and (best is None or d < best[0]):
                best = (d, line, from_start)
    if best is None:
        x, z = w.xz
        return f"no stairs within {errors.stairs_find_m:.0f} m of ({x:.1f}, {z:.1f})"
    _, line, from_start = best
    line = line if from_start else line[::-1]
    w.floor = int(np.argmin(np.abs(np.asarray(levels) - line[-1][1])))
    # it leaves the stairs at the top (or foot) of their last flight, facing along it
    top = int(np.flatnonzero(np.abs(line[:, 1] - line[-1][1]) >= 0.05)[-1]) + 1
    out = line[top][[0, 2]] - line[top - 1][[0, 2]]
    w.heading_rad = math.atan2(-out[0], -out[1])
    w.move(line[top][[0, 2]].astype(np.float64))
    return None


def to_polyline_m(p: FloatArray, polyline: FloatArray) -> float:
    """Distance from the point (2,) to the polyline (K, 2), m."""
    if len(polyline) == 1:
        return float(np.linalg.norm(polyline[0] - p))
    a, b = polyline[:-1], polyline[1:]
    ab = b - a
    t = np.clip(((p - a) * ab).sum(axis=1) / np.maximum((ab * ab).sum(axis=1), 1e-12), 0.0, 1.0)
    return float(np.linalg.norm(a + t[:, None] * ab - p, axis=1).min())
