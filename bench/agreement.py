"""Agreement of maps of one floor, needing no reference (issue 26): for two maps, the share of the
tag pairs both route on which they tell the same decisions.

    .venv/bin/python -m bench.agreement            # real floor 2 and simulated buildings, ~1 min

*Agreement* (``turn_metrics.decisions_agreement``): every turn (≥ 45°) one map tells on the route
is a bend of the same side of at least 30° within 4 m in the other, both ways (the band issue 18
scores precision and recall with). *Strict*: the sides of the told turns are the same string.

1. Real maps of floor 2 of the mac building (``bench.navigation_quality.MAPS``: each walk alone and
   building maps of several), each in its own frame, then moved into the first map's frame by the
   rigid transform its shared tags give (no ground truth), and every pair of maps compared: two
   single walks, maps of disjoint walks (at least one a building map), and a map before and after
   one more walk is added.
2. Simulated buildings, each walked by six walkers of different kinds (``UNSEEN_WALKERS`` and
   issue 18's walker) in the building's frame: single walks pairwise, the building maps of walks
   0–2 and 3–5 (disjoint), and walks 0–2 before and after walk 3 is added.

``--nooks``: table 2 only, on buildings with hooks, alcoves and oblique visits (issue 39).
"""

from __future__ import annotations

import dataclasses
import itertools
import statistics
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from app.cli.tables import render_markdown_table  # noqa: E402
from app.domain.evaluation.simulate import (  # noqa: E402
    UNSEEN_BUILDING,
    UNSEEN_WALKERS,
    SimulatedWalk,
    SimulationConfig,
    WalkerConfig,
    corridor_graph,
    fused_skeleton,
    walks_of_one_building,
)
from app.domain.evaluation.simulate_building import NookConfig, nook_walks  # noqa: E402
from app.domain.evaluation.turn_metrics import (  # noqa: E402
    Decisions,
    decisions_agreement,
    route_decisions,
    same_way_share,
    sides_agreement,
)
from app.domain.navigation.instructions import plan_guided_route  # noqa: E402
from app.domain.navigation.path_graph import PathGraph  # noqa: E402
from app.domain.navigation.routing import RouteError, TagEnd, plan_walk  # noqa: E402
from bench.navigation_quality import (  # noqa: E402
    MAPS,
    map_name,
    moved_onto,
    own_frame_map,
    skeleton,
    tag_positions,
)

#: Tag pairs sampled per simulated building (the same for every map of it; a map routes those
#: whose tags its walks saw).
SIMULATED_PAIRS = 400
#: Simulated buildings: (label, config, building seed).
BUILDINGS = (
    ("one floor, 3.2 m corridors", UNSEEN_BUILDING, 0),
    ("one floor, 3.2 m corridors", UNSEEN_BUILDING, 1),
    ("two floors, 3.2 m corridors", dataclasses.replace(UNSEEN_BUILDING, two_floors=True), 2),
    ("one floor, 2 m corridors (issue 18)", SimulationConfig(num_poses=2), 3),
)
#: A tag pair is walked by a walk when its route along the corridors that walk went along is no
#: longer than along the corridors all the building's walks went along, plus this share.
WALKED_SLACK = 0.02
#: The six walkers of a simulated building, in order.
WALKERS: tuple[tuple[str, WalkerConfig], ...] = (
    ("issue 18", WalkerConfig()),
    *UNSEEN_WALKERS.items(),
)

Sides = dict[tuple[int, int], Decisions]


def relation(a: Sequence[str], b: Sequence[str]) -> str | None:
    """How two maps' walks relate: single walks, disjoint walks, or one walk added."""
    sa, sb = set(a), set(b)
    if len(sa) == 1 and len(sb) == 1:
        return "single walks"
    if not sa & sb:
        return "disjoint walks"
    small, large = sorted((sa, sb), key=len)
    if small < large and len(large) == len(small) + 1:
        return "one walk added"
    return None


def _row(kind: str, first: str, second: str, a: Sides, b: Sides) -> list[str]:
    strict = sides_agreement({k: d.sides for k, d in a.items()}, {k: d.sides for k, d in b.items()})
    return [
        kind,
        first,
        second,
        str(len(a.keys() & b.keys())),
        f"{decisions_agreement(a, b):.0%}",
        f"{strict:.0%}",
        f"{same_way_share(a, b):.0%}",
        f"{decisions_agreement(a, b, same_way_only=True):.0%}",
        "",
    ]


HEADER = [
    "relation",
    "map",
    "other map",
    "tag pairs",
    "agreement",
    "strict",
    "same way",
    "agreement, same way",
    "agreement, both walked",
]


def real_table() -> str:
    base = own_frame_map(MAPS[0])
    decisions: dict[tuple[str, ...], Sides] = {}
    for walks in MAPS:
        m = moved_onto(own_frame_map(walks), tag_positions(base))
        pg = skeleton(m)
        tags = sorted(pg.tags)
        decisions[walks] = route_decisions(
            pg, list(itertools.permutations(tags, 2)), plan=plan_guided_route
        )
    rows = [HEADER]
    for a, b in itertools.combinations(MAPS, 2):
        kind = relation(a, b)
        if kind is not None:
            rows.append(_row(kind, map_name(a), map_name(b), decisions[a], decisions[b]))
    rows[1:] = sorted(rows[1:], key=lambda r: r[0])
    return render_markdown_table(rows, justify="right")


def simulated_walks(config: SimulationConfig, seed: int) -> list[SimulatedWalk]:
    """The walks of the six walkers of one building (its frame)."""
    return walks_of_one_building(config, seed, [w for _, w in WALKERS])


def route_lengths_m(pg: PathGraph, pairs: list[tuple[int, int]]) -> dict[tuple[int, int], float]:
    """The length of the shortest route of each tag pair ``pg`` can route, m."""
    out = {}
    for a, b in pairs:
        try:
            out[(a, b)] = plan_walk(pg, TagEnd(a), TagEnd(b)).length_m
        except RouteError:
            continue
    return out


def walked_pairs(
    walk: SimulatedWalk, shortest_m: dict[tuple[int, int], float]
) -> set[tuple[int, int]]:
    """The tag pairs whose shortest way through the building (``shortest_m``: along the
    corridors any of its walks went along) ``walk`` went along: two single walks can only tell
    the same decisions on the pairs both walked; elsewhere one of them knows a shorter way than
    the other, through a corridor the other never saw."""
    own_m = route_lengths_m(corridor_graph(walk), list(shortest_m))
    return {k for k, m in own_m.items() if m <= shortest_m[k] * (1 + WALKED_SLACK)}


def only(sides: Sides, pairs: set[tuple[int, int]]) -> Sides:
    return {k: v for k, v in sides.items() if k in pairs}


def simulated_table(*, nooks: bool = False) -> str:
    """Table 2; with ``nooks``, the buildings with hooks, alcoves and oblique visits (issue 39:
    ``simulate_building.NookConfig()``)."""
    rows = [HEADER]
    summary: dict[str, list[float]] = {}
    for label, config, seed in BUILDINGS:
        walks = (
            nook_walks(config, seed, [w for _, w in WALKERS], NookConfig(), length_m=500.0)
            if nooks
            else simulated_walks(config, seed)
        )
        all_pairs = list(itertools.permutations(walks[0].tag_ids, 2))
        rng = np.random.default_rng(seed)
        chosen = rng.choice(
            len(all_pairs), size=min(SIMULATED_PAIRS, len(all_pairs)), replace=False
        )
        pairs = [all_pairs[i] for i in chosen]

        def decide(pg: PathGraph, pairs: list[tuple[int, int]] = pairs) -> Sides:
            return route_decisions(pg, pairs, plan=plan_guided_route)

        single = [decide(fused_skeleton([w])) for w in walks]
        singles = [decisions_agreement(a, b) for a, b in itertools.combinations(single, 2)]
        shortest_m = route_lengths_m(corridor_graph(walks), pairs)
        walked = [walked_pairs(w, shortest_m) for w in walks]
        both = [
            decisions_agreement(*(only(single[k], walked[i] & walked[j]) for k in (i, j)))
            for i, j in itertools.combinations(range(len(walks)), 2)
        ]
        same = [
            decisions_agreement(a, b, same_way_only=True)
            for a, b in itertools.combinations(single, 2)
        ]
        ways = [same_way_share(a, b) for a, b in itertools.combinations(single, 2)]
        summary.setdefault("single walks", []).extend(singles)
        summary.setdefault("single walks, same way", []).extend(same)
        summary.setdefault("single walks, both walked", []).extend(both)
        first_three, last_three = (
            decide(fused_skeleton(walks[:3])),
            decide(fused_skeleton(walks[3:])),
        )
        added = decide(fused_skeleton(walks[:4]))
        name = f"{label}, seed {seed}"
        rows.append(
            [
                "single walks",
                name,
                f"{len(single)} walkers",
                str(len(pairs)),
                f"{min(singles):.0%}–{max(singles):.0%}",
                "",
                f"{min(ways):.0%}–{max(ways):.0%}",
                f"{min(same):.0%}–{max(same):.0%}",
                f"{min(both):.0%}–{max(both):.0%}",
            ]
        )
        rows.append(
            _row("disjoint walks", f"{name}: walks 1–3", "walks 4–6", first_three, last_three)
        )
        rows.append(_row("one walk added", f"{name}: walks 1–3", "walks 1–4", first_three, added))
        summary.setdefault("disjoint walks", []).append(
            decisions_agreement(first_three, last_three)
        )
        summary.setdefault("one walk added", []).append(decisions_agreement(first_three, added))
    table = render_markdown_table(rows, justify="right")
    means = "; ".join(
        f"{k}: mean {statistics.fmean(v):.0%}, min {min(v):.0%}" for k, v in summary.items()
    )
    return f"{table}\n\n{means}\nwalkers: {', '.join(name for name, _ in WALKERS)}"


def main(argv: Sequence[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else list(argv)
    if "--nooks" in args:
        print("2c. agreement of simulated maps, buildings with hooks, alcoves, oblique visits")
        print(simulated_table(nooks=True))
        return 0
    print("1. agreement of real maps of floor 2 of the mac building (no reference)")
    print(real_table())
    print("\n2. agreement of simulated maps of one building by different walkers")
    print(simulated_table())
    return 0


if __name__ == "__main__":
    sys.exit(main())
