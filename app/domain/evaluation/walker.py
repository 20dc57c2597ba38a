"""A simulated blind walker who follows a route's spoken steps through the *true* building
(DESIGN §10, issue 39): instructions are judged by whether a walker arrives.

    space = BoxFreeSpace.of_building(walk.building)               # a simulated building's truth
    space = CapsuleFreeSpace.of_lines(lines_xz, radius_m=1.6)     # corridors drawn as centrelines
    route = plan_guided_route(pg, PositionEnd(p), TagEnd(b), heading_rad=start.heading_rad)
    outcome = walk_steps(route.steps, space, start, goal_xz=…, goal_floor=0, rng=rng)
    outcome = walk_steps(…, app=TagCorrections(…))    # … re-routed when a tag shows it off the way
    outcome.arrived, outcome.reason, outcome.where_xz, outcome.corrections

The walker knows only the steps as a user hears them (``Step.kind``, ``turn_deg``,
``distance_m``, ``side``; never the route's polyline nor the map). It errs as people do:

- **Heading.** Every turn it makes (the facing turn included) is off by a uniform error of up to
  ``heading_error_deg`` (±15°).
- **Distance.** Each leg it walks is misjudged by a factor uniform in 1 ± ``stride_error`` (±10%):
  it counts its steps, and its steps are not the 0.7 m it assumes.
- **Walls stop it.** It moves in ``step_m`` steps inside the free space; a wall met at up to
  ``slide_max_deg`` from its heading turns it along the wall (a cane or a hand on the wall: it
  *shorelines*); a wall met more head-on stops it (the corridor ends there) — unless that is
  more than ``short_m`` short of the distance it was told: then it feels along the wall for the
  way on, up to ``around_max_deg`` off the way it set out (never back).
- **A trailing hand where the instruction says so.** Before a turn ("in 5 m, turn left"; the
  last window of the leg: ``search_share`` of it, at least ``search_min_m``, but not in its
  first half) it steps over to the wall on the turn's side (none within ``wall_find_m``: open
  space, it turns there) and trails it ``hand_m`` off. The hand feels the wall's direction
  (``feel_ahead_m`` ahead of the body, out to ``probe_m``): along a wall that bends less than
  ``corner_deg`` the walker turns with it; where the wall turns away by ``corner_deg`` or more,
  or is gone (an opening), it is at the corner: it steps ``into_opening_m`` on and turns as
  told. No corner within the window past the told distance: it turns where it is.
- **Forks.** Told "keep left" (or "right"), or "bear left" (said only at a junction), it trails
  that wall from the window before the fork to the window after it, turning with the wall and
  crossing openings on that side: the branch it keeps to continues the wall, so the wall turns
  it (a bear is not turned by its angle as well).
- **Arrival.** On the last leg ("… to tag 311, on your right") the walker trails the wall of
  the side it is told for the leg's last window (crossing openings), and the app says "arrive"
  when it is within ``arrive_within_m`` of the goal (it tracks the phone against the tags); with
  ``app_says_arrive=False`` the walker stops when it has walked the told distance. Told "arrive
  at tag 311, on your right" while not there yet, it turns to that side and walks up to the wall
  (``wall_find_m`` at most).
- **Stairs.** Before "take the stairs" its cane finds their first step (within ``cane_m``) and
  it stops there; then it takes the nearest stairs' foot or head within ``stairs_find_m`` to
  the top (or foot) of their last flight (a handrail leads); none there is a failure.
- **The app's corrections** (``app``, none by default): the real app localizes the phone on
  every tag its camera sees and can route again from there (DESIGN §7). Every
  ``check_every_m`` walked, after every leg, and when it is lost (a wall where it should walk
  on, the steps done short of the goal; then it steps back ``step_back_m`` from the wall and
  turns on the spot to let the phone look round), the walker asks ``app.correct``; new steps
  replace the rest of the old ones, at most ``max_corrections`` times
  (:mod:`app.domain.evaluation.walker_app` says when they come).

Success is ending within ``arrive_within_m`` of the goal (horizontally, on its floor) without a
turn of more than ``TURN_AROUND_DEG`` told in a route's steps (a "turn around" is a failure of
the instructions). Every failure says where (x–z, m) and why: the step it happened at, in its own
words.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np

from app.domain.evaluation.walker_body import (
    DEFAULT_WALKER,
    Body,
    Corrected,
    Corrector,
    WalkerErrors,
    stairs_tops,
    take_stairs,
    to_polyline_m,
    wrapped,
)
from app.domain.evaluation.walker_space import (
    BoxFreeSpace,
    CapsuleFreeSpace,
    FreeSpace,
)
from app.domain.frames import FloatArray
from app.domain.navigation.routing import Step

__all__ = [
    "DEFAULT_WALKER",
    "TURN_AROUND_DEG",
    "BoxFreeSpace",
    "CapsuleFreeSpace",
    "Corrector",
    "FreeSpace",
    "Start",
    "WalkOutcome",
    "WalkerErrors",
    "walk_steps",
]

#: A told turn beyond this is a turn-around: the route sends the walker back, degrees.
TURN_AROUND_DEG = 150.0
#: A told turn below this is a "bear" (``instructions.TURN_MIN_DEG``), degrees.
BEAR_MAX_DEG = 45.0


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
    index of the step it failed at (None if it arrived); ``corrections``: how many times the app
    routed it again."""

    arrived: bool
    reason: str
    where_xz: tuple[float, float]
    distance_to_goal_m: float
    path_xz: FloatArray
    failed_step: int | None = None
    corrections: int = 0


HandMode = Literal["turn", "follow"]


@dataclass(frozen=True, slots=True)
class _Hand:
    """A hand on the wall of ``side`` (+1 left, −1 right) from ``from_m`` to ``to_m`` along a
    leg: ``turn`` looks for the corner of a turn, ``follow`` trails the wall across openings."""

    side: float
    mode: HandMode
    from_m: float
    to_m: float


def walk_steps(
    steps: Sequence[Step],
    space: FreeSpace,
    start: Start,
    *,
    goal_xz: tuple[float, float],
    goal_floor: int,
    rng: np.random.Generator,
    errors: WalkerErrors = DEFAULT_WALKER,
    app: Corrector | None = None,
) -> WalkOutcome:
    """Walk ``steps`` from ``start`` through ``space`` (see the module docstring)."""
    w = Body(
        space=space,
        xz=np.array(start.xz, dtype=np.float64),
        heading_rad=start.heading_rad,
        floor=start.floor,
        errors=errors,
        path=[(float(start.xz[0]), float(start.xz[1]))],
        app=app,
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
            corrections=w.corrections,
        )

    plan = list(steps)
    while True:
        try:
            failure, k = _follow(w, plan, goal, goal_floor, rng)
            if failure is None and _near(w, goal, goal_floor, errors):
                return outcome(True, "arrived", None)
            if failure is None:
                w.check(scanning=True)  # lost: it turns on the spot so that the phone looks round
        except Corrected as corrected:
            plan = corrected.steps
            continue
        if failure is not None:
            return outcome(False, failure, k)
        d = float(np.linalg.norm(w.xz - goal))
        where = "on another floor" if w.floor != goal_floor else f"{d:.1f} m from the goal"
        first = f"; first, {w.notes[0]}" if w.notes else ""
        return outcome(False, f"ended {where}{first}", len(plan) - 1)


def _follow(
    w: Body,
    steps: Sequence[Step],
    goal: FloatArray,
    goal_floor: int,
    rng: np.random.Generator,
) -> tuple[str | None, int | None]:
    """Follow ``steps``: (None, None) when they are done or the goal reached, else (the
    failure's words, the step's index). Raises ``Corrected`` when the app routes again."""
    errors = w.errors
    last_walk = max((k for k, s in enumerate(steps) if s.kind == "go"), default=-1)
    kept: float | None = None  # the side a "keep" holds into the next leg
    for k, s in enumerate(steps):
        if s.kind in ("face", "turn"):
            turn = float(s.turn_deg or 0.0)
            if abs(turn) > TURN_AROUND_DEG and s.kind == "turn":
                return f"turn-around told at step {k} ({s.instruction!r})", k
            if s.kind == "turn" and _is_bear(s):
                kept = math.copysign(1.0, turn)  # the hand on that wall took it round
                continue
            error = rng.uniform(-errors.heading_error_deg, errors.heading_error_deg)
            w.heading_rad += math.radians(turn + error)
        elif s.kind == "keep":
            kept = _SIDES.get(s.side or "")
        elif s.kind == "go":
            told_m = s.distance_m
            judged_m = told_m * (1 + rng.uniform(-errors.stride_error, errors.stride_error))
            hands = _hands(steps, k, k == last_walk, judged_m, told_m, kept, errors)
            kept = None
            w.blocked = False
            following = next((t for t in steps[k + 1 :] if t.kind != "announce"), None)
            stairs_from_m = (
                max(judged_m - _window_m(told_m, errors), judged_m / 2)
                if following is not None and following.kind == "stairs"
                else None
            )
            failure = _walk_leg(
                w, judged_m, told_m, hands, k == last_walk, goal, k, stairs_from_m=stairs_from_m
            )
            if failure:
                w.check(scanning=True)
                return f"{failure} (step {k}: {s.instruction!r})", k
            if k == last_walk and errors.app_says_arrive and _near(w, goal, goal_floor, errors):
                return None, None
            w.check(scanning=w.blocked)  # stopped by a wall, it looks round
        elif s.kind in ("stairs", "elevator"):
            failure = take_stairs(w, errors)
            if failure:
                w.check(scanning=True)
                return f"{failure} (step {k}: {s.instruction!r})", k
        elif (
            s.kind == "arrive" and s.side in _FACING_DEG and not _near(w, goal, goal_floor, errors)
        ):
            # not there yet: it turns to the side it is told and walks up to the wall there
            error = rng.uniform(-errors.heading_error_deg, errors.heading_error_deg)
            w.heading_rad += math.radians(_FACING_DEG[s.side] + error)
            walked_m = 0.0
            while walked_m < errors.wall_find_m and not _near(w, goal, goal_floor, errors):
                if not w.step(slide_max_deg=0.0):
                    break
                walked_m += errors.step_m
    return None, None


#: Where the walker turns to find a goal "on your left" and so on, degrees (+ left).
_FACING_DEG = {"ahead": 0.0, "left": 90.0, "right": -90.0, "behind": 180.0}


#: The hand's sign for a side said.
_SIDES = {"left": 1.0, "right": -1.0}


def _hands(
    steps: Sequence[Step],
    k: int,
    last: bool,
    judged_m: float,
    told_m: float,
    kept: float | None,
    errors: WalkerErrors,
) -> list[_Hand]:
    """Where the hand goes on the wall along go step ``k`` (the first that applies wins)."""
    window_m = _window_m(told_m, errors)
    from_m = max(judged_m - window_m, judged_m / 2)  # not in the first half: it just started
    hands = []
    following = next((t for t in steps[k + 1 :] if t.kind != "announce"), None)
    if following is not None and following.kind == "turn" and following.turn_deg:
        sign = math.copysign(1.0, following.turn_deg)
        if _is_bear(following):
            hands.append(_Hand(sign, "follow", from_m, math.inf))
        else:
            hands.append(_Hand(sign, "turn", from_m, judged_m + window_m))
    elif following is not None and following.kind == "keep" and following.side in _SIDES:
        hands.append(_Hand(_SIDES[following.side], "follow", from_m, math.inf))
    elif last:
        told = _told_side(steps[k].instruction)
        if told is not None:
            hands.append(_Hand(told, "follow", from_m, math.inf))
    if kept is not None:
        hands.append(_Hand(kept, "follow", 0.0, window_m))
    return hands


def _window_m(told_m: float, errors: WalkerErrors) -> float:
    """How long before (and after) a told distance the walker searches: the leg's
    ``search_share``, at least ``search_min_m``."""
    return max(errors.search_min_m, errors.search_share * told_m)


def _is_bear(step: Step) -> bool:
    """A "bear left/right": said only at a fork; the walker keeps to that side's wall through
    it (as for "keep left"), which turns it into the branch."""
    return abs(float(step.turn_deg or 0.0)) < BEAR_MAX_DEG


def _told_side(instruction: str) -> float | None:
    """+1 for a goal "on your left", −1 "on your right", else None: on the last leg the walker
    trails that wall."""
    if "on your left" in instruction:
        return 1.0
    if "on your right" in instruction:
        return -1.0
    return None


def _near(w: Body, goal: FloatArray, goal_floor: int, errors: WalkerErrors) -> bool:
    return w.floor == goal_floor and float(np.linalg.norm(w.xz - goal)) <= errors.arrive_within_m


def _walk_leg(
    w: Body,
    judged_m: float,
    told_m: float,
    hands: Sequence[_Hand],
    last: bool,
    goal: FloatArray,
    k: int,
    *,
    stairs_from_m: float | None = None,
) -> str | None:
    """Walk one leg (step ``k``) of ``told_m`` (the walker judges ``judged_m``) with ``hands`` on
    the walls; before stairs (from ``stairs_from_m`` on) it stops where its cane finds their
    first step. A failure's words, or None."""
    errors = w.errors
    arriving = last and errors.app_says_arrive
    turning = next((h for h in hands if h.mode == "turn"), None)
    limit_m = judged_m
    if turning is not None:
        limit_m = turning.to_m
    elif arriving:
        limit_m = judged_m + _window_m(told_m, errors)
    first_steps = stairs_tops(w) if stairs_from_m is not None else np.zeros((0, 2, 2))
    walked_m = 0.0
    checked_m = 0.0
    set_out_rad = w.heading_rad
    holding: _Hand | None = None
    touching = False  # the hand is on the wall
    crossing = False  # … and lost it at an opening
    retry_m = 0.0
    while walked_m < limit_m:
        if arriving and float(np.linalg.norm(w.xz - goal)) <= errors.arrive_within_m:
            return None
        if (
            stairs_from_m is not None
            and walked_m >= stairs_from_m
            and any(to_polyline_m(w.xz, top) <= errors.cane_m for top in first_steps)
        ):
            return None  # the cane finds the stairs
        if walked_m - checked_m >= errors.check_every_m:
            checked_m = walked_m
            w.check(scanning=False)
        hand = next((h for h in hands if h.from_m <= walked_m < h.to_m), None)
        if hand is not holding:
            holding, touching, crossing, retry_m = hand, False, False, 0.0
        if hand is not None:
            if not touching and crossing:
                # across an opening, the hand reaches out for the wall as it walks on
                touching = w.wall_m(w.xz, w.side(hand.side)) is not None
            elif not touching and hand.mode == "turn":
                # it steps over to the wall; none there: open space on that side, it turns here
                if not w.sidestep(w.side(hand.side), errors.wall_find_m):
                    w.note(f"no wall on the turn's side to trail (step {k})")
                    return None
                touching = True
            elif not touching and walked_m >= retry_m:
                # following, it steps over to the wall; none there (an opening): it steps back
                # and walks on, to try again a metre on
                back = w.xz.copy()
                touching = w.sidestep(w.side(hand.side), errors.wall_find_m)
                if not touching:
                    w.move(back)
                    retry_m = walked_m + 1.0
            if touching:
                turn_max_deg = errors.corner_deg if hand.mode == "turn" else 90.0
                away_deg = w.trail(hand.side, turn_max_deg=turn_max_deg)
                at_opening = away_deg is None or away_deg >= errors.corner_deg
                if hand.mode == "turn" and at_opening:
                    # the wall is gone or turns away: the corner; step into it, then turn
                    for _ in range(round(errors.into_opening_m / errors.step_m)):
                        if not w.step():
                            break
                    return None
                elif hand.mode == "follow":
                    # following: across an opening the hand finds the wall again beyond it
                    touching = away_deg is not None
                    crossing = not touching
        # a wall well short of the told distance: it feels along it for the way on, up to
        # ``around_max_deg`` off the way it set out (so it never walks back)
        slide_max_deg = errors.slide_max_deg
        if walked_m < judged_m - errors.short_m:
            off_deg = abs(math.degrees(wrapped(w.heading_rad - set_out_rad)))
            slide_max_deg = max(slide_max_deg, errors.around_max_deg - off_deg)
        if not w.step(slide_max_deg=slide_max_deg):
            w.blocked = True
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
    if turning is not None:
        window_m = turning.to_m - judged_m
        w.note(
            f"no opening on the turn's side up to {window_m:.0f} m past the told distance "
            f"(step {k})"
        )
    return None
