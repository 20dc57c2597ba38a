"""How good a route's turn-by-turn is, against a reference corridor graph (issue 18).

    turns = announced_turns(route)                  # the turns a walker is told (|turn| ≥ 45°)
    truth = reference_turns(reference, reference_route)   # the corridors' own turns
    hits = match_turns(turns, truth)                # (announced that are real, real that are told)
    has_zigzag(turns), has_turn_around(route)
    score = score_tag_routes(pg, reference, pairs, plan=plan_guided_route)   # all of it, per map
    map_agreement(first_pg, second_pg, plan=plan_guided_route)   # two maps of a floor, no reference

A turn is *matched* when a reference turn of the same side lies within ``MATCH_WITHIN_M`` (x–z) of
it; each reference turn matches at most one announced turn. Precision counts a told turn as real
when the reference corridor bends there, even right next to the route's end (a tag at a corner);
recall asks for the reference's decision points (not within ``END_MARGIN_M`` + ``END_BAND_M`` of
the ends).
Both use a band below the threshold (see :func:`score_tag_routes`).
A *zigzag* is two announced turns of opposite sides at most ``ZIGZAG_WITHIN_M`` apart along the
route. A *turn-around* is a mid-route "turn around" or a bend of the route's polyline of ≥ 150°
away from its ends and off the stairs (a switchback staircase turns round on its landing).
"""

from __future__ import annotations

import dataclasses
import itertools
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from app.domain.frames import FloatArray
from app.domain.navigation.instructions import (
    BEAR_MIN_DEG,
    END_MARGIN_M,
    TURN_AROUND_MIN_DEG,
    TURN_MIN_DEG,
    decision_points,
    walk_stretches,
)
from app.domain.navigation.path_graph import PathGraph
from app.domain.navigation.routing import (
    Endpoint,
    Route,
    RouteError,
    TagEnd,
    plan_walk,
    signed_turn_deg,
)

RoutePlanner = Callable[[PathGraph, Endpoint, Endpoint], Route]

#: A told turn within this (horizontal, m) of a real turn of the same side is that turn.
MATCH_WITHIN_M = 4.0
#: Opposite turns at most this far apart along the route are a zigzag, m.
ZIGZAG_WITHIN_M = 6.0
#: Recall does not ask for reference turns within this much more than ``END_MARGIN_M`` of a
#: stretch's ends (where the map's corner or tag anchor may sit a little differently), m.
END_BAND_M = 1.0
#: A polyline bend this far (m) from both ends of the route is mid-route.
MID_ROUTE_M = 1.0


@dataclass(frozen=True, slots=True, kw_only=True)
class Turn:
    """A turn of a route: where (x–z, m), how much (+ left, degrees), how far along (m)."""

    position_xz_m: tuple[float, float]
    turn_deg: float
    along_m: float


def announced_turns(route: Route, *, min_deg: float = TURN_MIN_DEG) -> list[Turn]:
    """The route's spoken turns of at least ``min_deg`` (its ``turn`` steps)."""
    xyz = np.asarray(route.polyline_m, dtype=np.float64).reshape(-1, 3)
    walked_m = _walked(xyz)
    turns = []
    for step in route.steps:
        if step.kind != "turn" or step.turn_deg is None or abs(step.turn_deg) < min_deg:
            continue
        p = np.asarray(step.position_m)
        k = int(np.argmin(np.linalg.norm(xyz - p, axis=1))) if len(xyz) else 0
        turns.append(
            Turn(
                position_xz_m=(float(p[0]), float(p[2])),
                turn_deg=float(step.turn_deg),
                along_m=float(walked_m[k]) if len(xyz) else 0.0,
            )
        )
    return turns


def reference_turns(
    reference: PathGraph,
    route: Route,
    *,
    min_deg: float = TURN_MIN_DEG,
    end_margin_m: float = END_MARGIN_M,
) -> list[Turn]:
    """The turns of a route on the reference corridor graph: the decision points of its walked
    stretches (stairs and elevators apart) turning at least ``min_deg``. ``end_margin_m`` = 0
    also counts bends next to a stretch's ends (where a guided route folds the turn into its
    first or last step)."""
    xyz = np.asarray(route.polyline_m, dtype=np.float64).reshape(-1, 3)
    walked_m = _walked(xyz)
    turns = []
    for points, junction in walk_stretches(reference, route):
        for d in decision_points(points, junction, end_margin_m=end_margin_m):
            if abs(d.turn_deg) < min_deg:
                continue
            p = points[d.index]
            k = int(np.argmin(np.linalg.norm(xyz - p, axis=1)))
            turns.append(
                Turn(
                    position_xz_m=(float(p[0]), float(p[2])),
                    turn_deg=d.turn_deg,
                    along_m=float(walked_m[k]),
                )
            )
    return turns


def match_turns(
    announced: Sequence[Turn], truth: Sequence[Turn], *, within_m: float = MATCH_WITHIN_M
) -> tuple[int, int]:
    """(announced turns that are real, real turns that are announced): a greedy one-to-one
    matching of same-side turns by distance."""
    pairs = sorted(
        (float(np.hypot(*np.subtract(a.position_xz_m, t.position_xz_m))), i, j)
        for (i, a), (j, t) in itertools.product(enumerate(announced), enumerate(truth))
        if (a.turn_deg > 0) == (t.turn_deg > 0)
    )
    used_a: set[int] = set()
    used_t: set[int] = set()
    for distance_m, i, j in pairs:
        if distance_m <= within_m and i not in used_a and j not in used_t:
            used_a.add(i)
            used_t.add(j)
    return len(used_a), len(used_t)


def has_zigzag(turns: Sequence[Turn], *, within_m: float = ZIGZAG_WITHIN_M) -> bool:
    """Two consecutive announced turns of opposite sides at most ``within_m`` apart."""
    return any(
        (a.turn_deg > 0) != (b.turn_deg > 0) and abs(b.along_m - a.along_m) <= within_m
        for a, b in itertools.pairwise(turns)
    )


#: A polyline vertex next to a segment this steep (rise over run) is on stairs or in a lift: its
#: bends are the staircase's (a switchback turns round on its landing), not the route's.
CLIMBING_MIN_RISE_PER_RUN = 0.25


def has_turn_around(route: Route) -> bool:
    """A "turn around" step, or a bend of the polyline of ≥ 150° mid-route (not on stairs)."""
    if any(s.kind == "turn" and "around" in s.instruction for s in route.steps):
        return True
    xyz = np.asarray(route.polyline_m, dtype=np.float64).reshape(-1, 3)
    walked_m = _walked(xyz)
    total_m = float(walked_m[-1]) if len(xyz) else 0.0
    for k in range(1, len(xyz) - 1):
        if walked_m[k] < MID_ROUTE_M or total_m - walked_m[k] < MID_ROUTE_M:
            continue
        before = xyz[k] - xyz[k - 1]
        after = xyz[k + 1] - xyz[k]
        run_before_m, run_after_m = np.hypot(before[0], before[2]), np.hypot(after[0], after[2])
        if run_before_m < 1e-9 or run_after_m < 1e-9:
            continue
        if max(abs(before[1]) / run_before_m, abs(after[1]) / run_after_m) >= (
            CLIMBING_MIN_RISE_PER_RUN
        ):
            continue
        if abs(signed_turn_deg(before, after)) >= TURN_AROUND_MIN_DEG:
            return True
    return False


def turn_sides(turns: Sequence[Turn]) -> str:
    """ "LRL": the sides of the turns in order (for comparing two maps' routes)."""
    return "".join("L" if t.turn_deg > 0 else "R" for t in turns)


def _walked(xyz: FloatArray) -> FloatArray:
    if len(xyz) == 0:
        return np.zeros(0)
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xyz, axis=0), axis=1))])


@dataclass(frozen=True, slots=True, kw_only=True)
class RouteScore:
    """Turn-by-turn quality over routes between pairs of tags (see the module docstring).

    precision: announced turns that are real / announced; recall: real turns announced / real
    (1.0 when there is nothing to count). zigzag_share, turn_around_share: share of routes with
    one. length_ratio_p90: 90th percentile of route length / reference route length.
    sides: (start, goal) → the sides of the announced turns, e.g. "LR".
    """

    routes: int
    announced: int
    real: int
    precision: float
    recall: float
    zigzag_share: float
    turn_around_share: float
    length_ratio_p90: float
    sides: dict[tuple[int, int], str]


def score_tag_routes(
    pg: PathGraph,
    reference: PathGraph,
    pairs: Sequence[tuple[int, int]],
    *,
    plan: RoutePlanner,
    min_deg: float = TURN_MIN_DEG,
    slack_deg: float = BEAR_MIN_DEG,
) -> RouteScore:
    """Route every (start tag, goal tag) pair on ``pg`` with ``plan`` and on ``reference`` (plain
    shortest path; its turns are the corridors' turns) and compare. Pairs either graph cannot
    route are skipped. Among reference routes of (nearly) the same length, the one along the
    route on ``pg`` is taken (:func:`leaning_toward`): in a grid of corridors many routes tie, and
    the map is not wrong to pick another of them. Turns of at least ``min_deg`` are scored with a
    band below it: a told turn is real when the corridor bends at least ``slack_deg`` there, and a
    real turn is told when a turn or bear of at least ``slack_deg`` is (a 43° corner told as 47°
    is neither wrong nor missed)."""

    told = hit_told = real = hit_real = zigzags = turn_arounds = 0
    ratios: list[float] = []
    sides: dict[tuple[int, int], str] = {}
    for a, b in pairs:
        try:
            route = plan(pg, TagEnd(a), TagEnd(b))
            truth_route = plan_walk(leaning_toward(reference, route), TagEnd(a), TagEnd(b))
        except RouteError:
            continue
        turns = announced_turns(route, min_deg=min_deg)
        told_any = announced_turns(route, min_deg=slack_deg)
        truth = reference_turns(
            reference, truth_route, min_deg=min_deg, end_margin_m=END_MARGIN_M + END_BAND_M
        )
        bends = reference_turns(reference, truth_route, min_deg=slack_deg, end_margin_m=0.0)
        matched_told = match_turns(turns, bends)[0]
        matched_real = match_turns(told_any, truth)[1]
        told += len(turns)
        hit_told += matched_told
        real += len(truth)
        hit_real += matched_real
        zigzags += has_zigzag(turns)
        turn_arounds += has_turn_around(route)
        if truth_route.length_m > 1.0:
            ratios.append(route.length_m / truth_route.length_m)
        sides[(a, b)] = turn_sides(turns)
    routes = len(sides)
    return RouteScore(
        routes=routes,
        announced=told,
        real=real,
        precision=hit_told / told if told else 1.0,
        recall=hit_real / real if real else 1.0,
        zigzag_share=zigzags / routes if routes else 0.0,
        turn_around_share=turn_arounds / routes if routes else 0.0,
        length_ratio_p90=float(np.percentile(ratios, 90)) if ratios else float("nan"),
        sides=sides,
    )


#: Reference edges farther than this from the route being scored cost this much more, m and ratio.
_TIE_BREAK_M = 3.0
_TIE_BREAK_RATIO = 0.02


def leaning_toward(reference: PathGraph, route: Route) -> PathGraph:
    """``reference`` with its edges away from ``route`` (midpoint farther than ``_TIE_BREAK_M``)
    made ``_TIE_BREAK_RATIO`` longer, so that ties between equally short routes go its way."""
    xz = np.asarray(route.polyline_m, dtype=np.float64).reshape(-1, 3)[:, [0, 2]]
    if len(xz) == 0:
        return reference
    G = reference.graph.copy()
    for u, v, data in G.edges(data=True):
        middle = (np.asarray(G.nodes[u]["position_m"]) + np.asarray(G.nodes[v]["position_m"])) / 2
        if _distance_to_polyline(middle[[0, 2]], xz) > _TIE_BREAK_M:
            data["length_m"] = float(data["length_m"]) * (1 + _TIE_BREAK_RATIO)
    return dataclasses.replace(reference, graph=G)


def _distance_to_polyline(p: FloatArray, polyline: FloatArray) -> float:
    """Distance from point ``p`` (2,) to the polyline (K, 2), m."""
    if len(polyline) == 1:
        return float(np.linalg.norm(polyline[0] - p))
    a, b = polyline[:-1], polyline[1:]
    ab = b - a
    t = np.clip(((p - a) * ab).sum(axis=1) / np.maximum((ab * ab).sum(axis=1), 1e-12), 0.0, 1.0)
    return float(np.min(np.linalg.norm(a + t[:, None] * ab - p, axis=1)))


def agreement(first: RouteScore, second: RouteScore) -> float:
    """Share of the tag pairs routed in both whose announced turns have the same sides."""
    return sides_agreement(first.sides, second.sides)


@dataclass(frozen=True, slots=True, kw_only=True)
class Decisions:
    """What a map tells on one route: its told turns (≥ 45°) and its bends of at least the band's
    lower edge (30°, told or not), for comparing two maps in one frame; ``way_xz_m``: (P, 2) the
    route's polyline in the horizontal plane, m."""

    turns: tuple[Turn, ...]
    bends: tuple[Turn, ...]
    way_xz_m: FloatArray = dataclasses.field(default_factory=lambda: np.zeros((0, 2)))

    @property
    def sides(self) -> str:
        return turn_sides(self.turns)


def route_decisions(
    pg: PathGraph,
    pairs: Sequence[tuple[int, int]],
    *,
    plan: RoutePlanner,
    min_deg: float = TURN_MIN_DEG,
    slack_deg: float = BEAR_MIN_DEG,
) -> dict[tuple[int, int], Decisions]:
    """(start tag, goal tag) → what ``pg`` tells on that route, for every pair it can route:
    what a walker hears, needing no reference."""
    out = {}
    for a, b in pairs:
        try:
            route = plan(pg, TagEnd(a), TagEnd(b))
        except RouteError:
            continue
        out[(a, b)] = Decisions(
            turns=tuple(announced_turns(route, min_deg=min_deg)),
            bends=tuple(reference_turns(pg, route, min_deg=slack_deg, end_margin_m=0.0)),
            way_xz_m=np.asarray(route.polyline_m, dtype=np.float64).reshape(-1, 3)[:, [0, 2]],
        )
    return out


def decision_sides(
    pg: PathGraph, pairs: Sequence[tuple[int, int]], *, plan: RoutePlanner
) -> dict[tuple[int, int], str]:
    """(start tag, goal tag) → the sides of the turns told on ``pg`` ("LR")."""
    return {k: d.sides for k, d in route_decisions(pg, pairs, plan=plan).items()}


def sides_agreement(first: dict[tuple[int, int], str], second: dict[tuple[int, int], str]) -> float:
    """*Strict agreement* of two maps of one floor: the share of the tag pairs both route whose
    told turns have the same sides in the same order (nan when they share none)."""
    common = first.keys() & second.keys()
    if not common:
        return float("nan")
    return sum(first[k] == second[k] for k in common) / len(common)


def decisions_agree(
    first: Decisions, second: Decisions, *, within_m: float = MATCH_WITHIN_M
) -> bool:
    """Two maps (in one frame) tell the same decisions on a route: every turn told by one is a
    bend of the same side within ``within_m`` in the other, both ways, one to one. So a 44°
    corner told as a 47° turn by one map and measured 43° by the other is no disagreement (the
    band of :func:`score_tag_routes`), while a turn one map tells and the other does not bend at
    all, or of the other side, is."""
    return match_turns(first.turns, second.bends, within_m=within_m)[0] == len(
        first.turns
    ) and match_turns(second.turns, first.bends, within_m=within_m)[0] == len(second.turns)


#: Two routes whose polylines stay within this of each other (both ways, x–z) go the same way, m.
SAME_WAY_WITHIN_M = 3.0


def same_way(first: Decisions, second: Decisions, *, within_m: float = SAME_WAY_WITHIN_M) -> bool:
    """Whether the two routes take the same corridors: every vertex of each is within
    ``within_m`` of the other's polyline (a grid of corridors has routes of equal length round a
    block; two maps may take either)."""
    a, b = first.way_xz_m, second.way_xz_m
    if len(a) == 0 or len(b) == 0:
        return len(a) == len(b)
    return all(_distance_to_polyline(p, b) <= within_m for p in a) and all(
        _distance_to_polyline(p, a) <= within_m for p in b
    )


def decisions_agreement(
    first: dict[tuple[int, int], Decisions],
    second: dict[tuple[int, int], Decisions],
    *,
    same_way_only: bool = False,
) -> float:
    """*Agreement* of two maps of one floor in one frame (issue 26): the share of the tag pairs
    both route on which they tell the same decisions (:func:`decisions_agree`); with
    ``same_way_only``, of those both route the same way (:func:`same_way`). nan when there are
    none."""
    common = list(first.keys() & second.keys())
    if same_way_only:
        common = [k for k in common if same_way(first[k], second[k])]
    if not common:
        return float("nan")
    return sum(decisions_agree(first[k], second[k]) for k in common) / len(common)


def same_way_share(
    first: dict[tuple[int, int], Decisions], second: dict[tuple[int, int], Decisions]
) -> float:
    """The share of the tag pairs both route that they route the same way (nan: none)."""
    common = first.keys() & second.keys()
    if not common:
        return float("nan")
    return sum(same_way(first[k], second[k]) for k in common) / len(common)


def map_agreement(
    first: PathGraph,
    second: PathGraph,
    *,
    plan: RoutePlanner,
    pairs: Sequence[tuple[int, int]] | None = None,
) -> float:
    """:func:`decisions_agreement` of two maps in one frame (their shared tags give the rigid
    transform) over ``pairs`` (default: every ordered pair of the tags both maps hold)."""
    if pairs is None:
        shared = sorted(first.tags.keys() & second.tags.keys())
        pairs = list(itertools.permutations(shared, 2))
    return decisions_agreement(
        route_decisions(first, pairs, plan=plan), route_decisions(second, pairs, plan=plan)
    )
