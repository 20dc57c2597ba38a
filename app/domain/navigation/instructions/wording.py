"""The words of a route (step 6 of the package docstring): how they are worded
(:class:`GuidanceStyle`: units, clock, stride), turns, clock hours and distances as said, each
step's plain sentence for a screen reader (:func:`written_steps`) and a route's numbered text
(:func:`route_text`)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

from app.domain.errors import ParameterError
from app.domain.navigation.instructions.decisions import turn_class
from app.domain.navigation.instructions.landmarks import Landmark, landmark_near
from app.domain.navigation.routing import Point3, Route, Side, Step, TurnClass

#: "in N m" is said this far before a turn, m.
ANNOUNCE_BEFORE_M = 5.0
#: One walking step, m (units "steps"), unless the walker gives theirs (``GuidanceStyle.stride_m``).
STEP_LENGTH_M = 0.7
#: The strides a walker may give, m (a child's short step to a tall adult's long one).
STRIDE_MIN_M = 0.3
STRIDE_MAX_M = 1.5
#: Feet per metre.
FT_PER_M = 1 / 0.3048

Units = Literal["m", "ft", "steps"]


@dataclass(frozen=True, slots=True, kw_only=True)
class GuidanceStyle:
    """How instructions are worded: ``units`` of distances, ``clock`` for clock-face directions
    ("turn to 9 o'clock") instead of left/right in ``Step.instruction``; ``stride_m``: the
    walker's step, m, for distances in steps (``units="steps"``, ``Step.steps_count`` and the
    text form). ``Step.text`` always gives metres and steps, left/right and the clock."""

    units: Units = "m"
    clock: bool = False
    stride_m: float = STEP_LENGTH_M

    def __post_init__(self) -> None:
        if not STRIDE_MIN_M <= self.stride_m <= STRIDE_MAX_M:
            raise ParameterError(
                f"stride_m must be {STRIDE_MIN_M}-{STRIDE_MAX_M} m, not {self.stride_m}"
            )


DEFAULT_STYLE = GuidanceStyle()


def turn_words(turn_deg: float, style: GuidanceStyle = DEFAULT_STYLE) -> str:
    """ "bear left", "turn right", "turn sharp left", "turn around" (:func:`turn_class`), or with
    ``style.clock`` "turn to 9 o'clock"."""
    if style.clock:
        return f"turn to {clock_hour(turn_deg)} o'clock"
    side = "left" if turn_deg > 0 else "right"
    match turn_class(turn_deg):
        case "around":
            return "turn around"
        case "sharp":
            return f"turn sharp {side}"
        case "turn":
            return f"turn {side}"
        case "bear":
            return f"bear {side}"
    return "go straight on"


def clock_hour(turn_deg: float) -> int:
    """The clock-face hour of a direction ``turn_deg`` from straight ahead (+ left): 12 ahead,
    9 left, 3 right, 6 behind; the nearest hour, a half hour going away from 12 (so 45° is 2 or
    10 o'clock, a turn, and 135° is 5 or 7, sharp: each class of :func:`turn_class` from bear on
    has its own hours: bear 1/11, turn 2–4/8–10, sharp 5/7, around 5–7)."""
    hours = math.floor(abs(turn_deg) / 30.0 + 0.5)  # 0…6, half hours away from 12
    hour = (-hours if turn_deg > 0 else hours) % 12
    return 12 if hour == 0 else hour


def distance_words(distance_m: float, units: Units, stride_m: float = STEP_LENGTH_M) -> str:
    """ "12 m", "39 ft", "17 steps" (whole units, at least 1; steps of ``stride_m``)."""
    if units == "ft":
        return f"{max(1, round(distance_m * FT_PER_M))} ft"
    if units == "steps":
        return f"{steps_count(distance_m, stride_m)} steps"
    return f"{max(1, round(distance_m))} m"


def steps_count(distance_m: float, stride_m: float = STEP_LENGTH_M) -> int:
    """``distance_m`` in strides of ``stride_m``: whole steps, at least 1."""
    return max(1, round(distance_m / stride_m))


def spoken_distance(distance_m: float, stride_m: float = STEP_LENGTH_M) -> str:
    """ "12 metres (17 steps)", "1 metre (1 step)": whole metres and steps, at least 1, words a
    screen reader does not mangle (no "m" alone)."""
    metres = max(1, round(distance_m))
    strides = steps_count(distance_m, stride_m)
    return (
        f"{metres} {'metre' if metres == 1 else 'metres'} "
        f"({strides} {'step' if strides == 1 else 'steps'})"
    )


def clock_words(turn_deg: float) -> str:
    """ "turn right, to 3 o'clock", "bear left, to 11 o'clock", "turn around, to 6 o'clock"."""
    return f"{turn_words(turn_deg)}, to {clock_hour(turn_deg)} o'clock"


def written_steps(
    steps: list[Step],
    landmarks: Sequence[Landmark],
    *,
    goal_name: str,
    style: GuidanceStyle,
    floor_labels: Sequence[str] | None,
) -> list[Step]:
    """``steps`` with their structured words (``turn``, ``clock``, ``steps_count``,
    ``landmark``) and each one's ``text``: a plain sentence for a screen reader, in metres and
    the walker's steps, left/right and the clock, by landmarks. An announcement's landmark is its
    turn's."""
    written: list[Step] = []
    # (place, floor) → landmark_near: an announcement's landmark is its turn's, looked up once
    near_of: dict[tuple[Point3, int], tuple[str, str] | None] = {}

    def near(at: Step) -> tuple[str, str] | None:
        key = (at.position_m, at.floor)
        if key not in near_of:
            near_of[key] = landmark_near(landmarks, at.position_m, at.floor)
        return near_of[key]

    for k, step in enumerate(steps):
        turn: TurnClass | None = None
        clock: int | None = None
        count: int | None = None
        landmark: str | None = None
        match step.kind:
            case "face" | "turn" | "announce":
                turn_deg = step.turn_deg or 0.0
                turn, clock = turn_class(turn_deg), clock_hour(turn_deg)
                at = step
                if step.kind == "announce":
                    at = next((t for t in steps[k + 1 :] if t.kind == "turn"), step)
                found = near(at)
                landmark, phrase = found if found else (None, "")
                words = clock_words(turn_deg)
                if step.kind == "face":
                    text = f"{words}, to face the way"
                elif step.kind == "announce":
                    ahead = spoken_distance(ANNOUNCE_BEFORE_M, style.stride_m)
                    text = f"in {ahead}, {phrase + ', ' if phrase else ''}{words}"
                else:
                    text = f"{phrase + ', ' if phrase else ''}{words}"
            case "keep":
                found = near(step)
                landmark, phrase = found if found else (None, "")
                text = f"{phrase + ', ' if phrase else ''}{step.instruction}"
            case "go":
                count = steps_count(step.distance_m, style.stride_m)
                text = f"go straight {spoken_distance(step.distance_m, style.stride_m)}"
                if step.side is not None:
                    landmark = goal_name
                    text += f" to {goal_name}, {SIDE_WORDS[step.side]}"
            case "stairs" | "elevator":
                found = near(step)
                landmark, phrase = found if found else (None, "")
                following = steps[k + 1].floor if k + 1 < len(steps) else step.floor
                label = (
                    floor_labels[following]
                    if floor_labels is not None and 0 <= following < len(floor_labels)
                    else str(following + 1)
                )
                way = "up" if following > step.floor else "down"
                if step.kind == "stairs":
                    metres = max(1, round(step.distance_m))
                    length = f"{metres} {'metre' if metres == 1 else 'metres'}"
                    text = f"take the stairs {way}, {length}, to floor {label}"
                else:
                    text = f"take the elevator {way} to floor {label}"
                if phrase:
                    text = f"{phrase}, {text}"
            case _:  # arrive
                landmark = goal_name
                side = f", {SIDE_WORDS[step.side]}" if step.side else ""
                text = f"arrive at {goal_name}{side}"
        written.append(
            Step(  # not dataclasses.replace: a third of the time, on every route
                instruction=step.instruction,
                position_m=step.position_m,
                kind=step.kind,
                distance_m=step.distance_m,
                turn_deg=step.turn_deg,
                floor=step.floor,
                turn=turn,
                clock=clock,
                steps_count=count,
                landmark=landmark,
                side=step.side,
                text=text[:1].upper() + text[1:] + ".",
            )
        )
    return written


def route_text(route: Route) -> str:
    """The route as a screen reader reads it well: plain sentences, one numbered step a line,
    metres and steps spelled out, no symbols; the announcements ("in 5 metres, …"), which are for
    walking, are left out, since their turn follows::

        1. Go straight 29 metres (42 steps).
        2. At tag 305, turn right, to 3 o'clock.
        3. Go straight 7 metres (10 steps) to Room 210, on your right.
        4. Arrive at Room 210, on your right.
    """
    said = [step.text for step in route.steps if step.kind != "announce" and step.text]
    return "\n".join(f"{i}. {text}" for i, text in enumerate(said, start=1))


#: How each side is said.
SIDE_WORDS: dict[Side, str] = {
    "ahead": "ahead",
    "left": "on your left",
    "right": "on your right",
    "behind": "behind you",
}
