"""Turn-by-turn instructions at decision points only (issue 18): what a blind walker hears.

    route = plan_guided_route(pg, TagEnd(300), TagEnd(311), heading_rad=0.4)
    [s.instruction for s in route.steps]
    # ['turn right to face the way', 'go straight 23 m', 'in 5 m, turn left', 'turn left',
    #  'go straight 9 m to tag 311, on your right', 'arrive at tag 311, on your right']
    plan_guided_route(pg, …, style=GuidanceStyle(units="ft", clock=True))   # "turn to 9 o'clock"
    route_text(route)   # "1. Go straight 23 metres (33 steps).\n2. At tag 305, turn left, to …"

How instructions are chosen (angles in the horizontal x–z plane, + is left, as in routing):

1. **Legs.** Each walked stretch of the route is simplified (Douglas–Peucker, ``LEG_TOLERANCE_M``)
   into straight legs; on a corridor skeleton these are the corridors' straight segments.
2. **Decision points.** A bend's turn is the change between the directions over ``CHORD_M``
   before and after it, so a zig and its zag cancel and a curve taken in small bends adds up;
   bends closer than ``MIN_SPACING_M`` to a stronger one are the same decision, and a bend near a
   junction is placed at the junction. A decision is announced when |turn| ≥ ``TURN_MIN_DEG``,
   and when ``BEAR_MIN_DEG`` ≤ |turn| < ``TURN_MIN_DEG`` at a junction (a node where three or
   more corridors meet); else it is silent. Its words follow one rule of its angle alone
   (:func:`turn_class`: straight < 20°, bear 20–45°, turn 45–135°, sharp 135–150°, around
   ≥ 150°), whatever the map. So instructions are at least ``MIN_SPACING_M`` apart except at
   junctions. A decision at a node an operator quieted (a corridor edit,
   ``app.domain.navigation.corridor_edits``) is silent too. A bend within ``CHORD_M`` of a
   stronger decision that bends under ``BEAR_MIN_DEG`` measured with its chords stopping there is
   that decision's tail (:func:`_tail_of`). At a junction the route goes through silently while
   another branch leaves near straight on, "keep left at the fork" (:mod:`.forks`).
3. **Announcements.** Before a turn, a leg long enough to keep them ``MIN_SPACING_M`` apart gets
   "in N m, turn left" ``ANNOUNCE_BEFORE_M`` before the corner.
4. **First and last steps.** Given the phone's heading (``heading_rad``: the walking direction's
   angle in the x–z plane, atan2(−x, −z), 0 = facing −z, + turning left), the first step says how
   to turn to face the way — from where the walker stands, for a route from a position more than
   ``LEG_TOLERANCE_M`` off the graph (toward the end of the first go step; with nothing to walk
   on the graph, toward the goal, and straight to it). The last walked step gives the remaining
   distance and the side of the tag or point of interest ("on your left"), which the arrival
   repeats: as the walker sees it where the app says "arrive", ``END_MARGIN_M`` before the end,
   facing the way it walks there.
5. **Stairs and elevators** say their length and the floor you arrive at, by the building's floor
   labels when given (``floor_labels``), else numbered from 1.
6. **The conventions blind travellers use** (issue 39). Each step also gets ``turn`` (its class),
   ``clock`` (its clock hour), ``steps_count`` (in the walker's stride), ``landmark`` (the point
   of interest or tag within ``LANDMARK_NEAR_M``, or the goal), ``side`` (of the goal) and
   ``text``, a plain sentence for a screen reader ("At the tag by Room 150, turn left, to 9
   o'clock."); :func:`route_text` numbers them.

Distances are rounded to whole units (m, ft or steps of ``GuidanceStyle.stride_m``), at least 1.

The modules, in the order a route is made:

    stretches.py   a route cut into walked stretches and floor changes (walk_stretches)
    decisions.py   where the turns are (decision_points, turn_class)
    landmarks.py   the tags and points of interest a step is told by (landmark_near)
    wording.py     the words (GuidanceStyle, turn_words, clock_hour, distance_words, route_text)
    steps.py       the steps of a guided route (plan_guided_route, guidance_steps)
"""

from __future__ import annotations

from app.domain.navigation.instructions.decisions import (
    BEAR_MIN_DEG,
    CHORD_M,
    END_MARGIN_M,
    JUNCTION_SNAP_M,
    MIN_SPACING_M,
    SHARP_MIN_DEG,
    STRAIGHT_MAX_DEG,
    TAIL_MIN_CHORD_M,
    TURN_AROUND_MIN_DEG,
    TURN_MIN_DEG,
    Decision,
    decision_points,
    turn_class,
    walked_distances_m,
)
from app.domain.navigation.instructions.landmarks import (
    LANDMARK_NEAR_M,
    Landmark,
    landmark_near,
)
from app.domain.navigation.instructions.steps import (
    FACING_OK_DEG,
    KEEP_MIN_LEG_M,
    LEG_TOLERANCE_M,
    SIDE_MIN_M,
    direction,
    guidance_steps,
    heading_direction,
    plan_guided_route,
)
from app.domain.navigation.instructions.stretches import (
    point_floors,
    segment_kinds,
    walk_stretches,
)
from app.domain.navigation.instructions.wording import (
    ANNOUNCE_BEFORE_M,
    DEFAULT_STYLE,
    FT_PER_M,
    SIDE_WORDS,
    STEP_LENGTH_M,
    STRIDE_MAX_M,
    STRIDE_MIN_M,
    GuidanceStyle,
    Units,
    clock_hour,
    clock_words,
    distance_words,
    route_text,
    spoken_distance,
    steps_count,
    turn_words,
)

# direction, point_floors, segment_kinds: tests/unit/test_guidance_reference.py checks them.
__all__ = [
    "ANNOUNCE_BEFORE_M",
    "BEAR_MIN_DEG",
    "CHORD_M",
    "DEFAULT_STYLE",
    "END_MARGIN_M",
    "FACING_OK_DEG",
    "FT_PER_M",
    "JUNCTION_SNAP_M",
    "KEEP_MIN_LEG_M",
    "LANDMARK_NEAR_M",
    "LEG_TOLERANCE_M",
    "MIN_SPACING_M",
    "SHARP_MIN_DEG",
    "SIDE_MIN_M",
    "SIDE_WORDS",
    "STEP_LENGTH_M",
    "STRAIGHT_MAX_DEG",
    "STRIDE_MAX_M",
    "STRIDE_MIN_M",
    "TAIL_MIN_CHORD_M",
    "TURN_AROUND_MIN_DEG",
    "TURN_MIN_DEG",
    "Decision",
    "GuidanceStyle",
    "Landmark",
    "Units",
    "clock_hour",
    "clock_words",
    "decision_points",
    "direction",
    "distance_words",
    "guidance_steps",
    "heading_direction",
    "landmark_near",
    "plan_guided_route",
    "point_floors",
    "route_text",
    "segment_kinds",
    "spoken_distance",
    "steps_count",
    "turn_class",
    "turn_words",
    "walk_stretches",
    "walked_distances_m",
]
