"""Navigation benchmark (in process, no server): one command, prints five tables.

    .venv/bin/python -m bench.navigation          # (or: .venv/bin/python bench/navigation.py)

1. Turn-by-turn on floor 2 of the mac building, single walks and building maps (fused skeleton,
   decision-point instructions), against the hand-drawn reference ``bench.mac_floor_2_reference``
   (``bench.navigation_quality``). Agreement of maps without a reference: ``bench.agreement``.
2. The same on simulated walkers: issue 18's (steps to tags, sway, offset passes, passes that do
   not meet) and the unseen ones of issue 26 (``UNSEEN_WALKERS``: oblique, corner cutting,
   lobbies, partial corridors, all together), in ``UNSEEN_BUILDING`` (3.2 m corridors, one and two
   floors) and issue 18's 2 m building, against each building's corridors.
2b. The same on simulated building maps: ``bench.agreement``'s four buildings, each walked by its
   six walkers, the map of walks 1–3 and that of walks 4–6 (fused skeletons), against the
   corridors any of their walks went along.
2c. (issue 39) Hooks, alcoves and oblique visits: ``UNSEEN_BUILDING`` (one and two floors,
   seeds 0–3) with ``simulate_building.NookConfig()`` (corridor ends hooking round a corner to
   their last tag, tags in alcoves 2–4 m off the corridor, walks that veer obliquely to a tag and
   back), walked by the six walkers of ``bench.agreement``: single walks, and building maps of
   walks 1–3 and 4–6, against the corridors their walks went along; the same buildings without
   them (``NO_NOOKS``) beside. ``--nooks`` prints only this table; ``--before`` builds the
   skeletons as before issue 39 (no tag spurs, oblique visits not straightened).
3. Skeleton build time (CPU, best of N) and size: the real sessions (optimized with default
   parameters), simulated two-floor walks of 10,000 and 100,000 poses (true trajectory), and a
   building map fused from 20 simulated walks.
4. Route queries on the floor_2_straight skeleton: p50/p99 over 2,000 queries between random
   tags, and between random positions (snapped onto the graph), as the API answers them (the
   graph already in memory, as the API's per-process cache keeps it), with guided steps.

The HTTP figures (50 concurrent clients) are in ``bench/server.py``; localization in
``bench/localize.py``.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import random
import statistics
import sys
import time
from collections.abc import Callable
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
    build_building,
    corridor_graph,
    fused_skeleton,
    simulate_session,
    simulate_walk,
)
from app.domain.evaluation.simulate_building import (  # noqa: E402
    NO_NOOKS,
    NookConfig,
    nook_walks,
)
from app.domain.evaluation.turn_metrics import RouteScore, score_tag_routes  # noqa: E402
from app.domain.mapping.params import SlamParams  # noqa: E402
from app.domain.mapping.slam import optimize_session  # noqa: E402
from app.domain.navigation.instructions import plan_guided_route  # noqa: E402
from app.domain.navigation.path_graph import JUNCTION, PathGraph  # noqa: E402
from app.domain.navigation.routing import PositionEnd, TagEnd  # noqa: E402
from app.domain.navigation.skeleton import (  # noqa: E402
    DEFAULT_SKELETON_PARAMS,
    SkeletonParams,
    build_skeleton,
    build_skeleton_from_arrays,
)
from app.domain.upload.session import load_session  # noqa: E402
from bench.agreement import BUILDINGS, WALKERS, simulated_walks  # noqa: E402
from bench.navigation_quality import quality_table  # noqa: E402

SESSIONS = REPO / "data" / "sessions"
#: Where a person stands relative to a node: beside the walked path, not on it.
OFF_PATH_M = np.array([0.3, 0.0, -0.3])
REAL = ("occam_room", "floor_2_straight", "straight_209_occam", "desnat_straight_once")
#: Simulated buildings of table 2: label → config.
SIMULATED_BUILDINGS = {
    "3.2 m, one floor": UNSEEN_BUILDING,
    "3.2 m, two floors": dataclasses.replace(UNSEEN_BUILDING, two_floors=True, blocks=(2, 2)),
    "2 m (issue 18)": SimulationConfig(num_poses=2),
}
#: Walker seeds of table 2 (0–1 chose the parameters of issue 26; 2–3 were held out).
SIMULATED_SEEDS = (0, 1, 2, 3)
#: Tag pairs routed per simulated walk.
SIMULATED_PAIRS = 80
#: Tag pairs routed per simulated building map (table 2b).
BUILDING_MAP_PAIRS = 200
#: Walkers of table 2: label → config.
SIMULATED_WALKERS: dict[str, WalkerConfig] = {"issue 18": WalkerConfig(), **UNSEEN_WALKERS}


def simulation_table() -> str:
    rows = [
        [
            "walker",
            "building",
            "walks",
            "turns told",
            "precision mean / min",
            "recall mean / min",
            "zigzag",
            "turn-around",
            "route p90 / ref, max",
        ]
    ]
    for walker_label, walker in SIMULATED_WALKERS.items():
        for building_label, config in SIMULATED_BUILDINGS.items():
            scores = []
            for seed in SIMULATED_SEEDS:
                walk = simulate_walk(config, dataclasses.replace(walker, seed=seed, length_m=600.0))
                ids, positions = walk.seen_tags()
                pairs = list(itertools.permutations(ids, 2))
                rng = np.random.default_rng(seed)
                chosen = rng.choice(
                    len(pairs), size=min(SIMULATED_PAIRS, len(pairs)), replace=False
                )
                skeleton = build_skeleton_from_arrays(
                    walk.positions_m,
                    tag_ids=ids,
                    tag_positions_m=positions,
                    tag_normals=walk.tag_normals(ids),
                )
                scores.append(
                    score_tag_routes(
                        skeleton,
                        corridor_graph(walk),
                        [pairs[i] for i in chosen],
                        plan=plan_guided_route,
                    )
                )
            rows.append(
                [
                    walker_label,
                    building_label,
                    str(len(scores)),
                    str(sum(s.announced for s in scores)),
                    f"{statistics.fmean(s.precision for s in scores):.0%} / "
                    f"{min(s.precision for s in scores):.0%}",
                    f"{statistics.fmean(s.recall for s in scores):.0%} / "
                    f"{min(s.recall for s in scores):.0%}",
                    f"{max(s.zigzag_share for s in scores):.0%}",
                    f"{max(s.turn_around_share for s in scores):.0%}",
                    f"{max(s.length_ratio_p90 for s in scores):.2f}",
                ]
            )
    return render_markdown_table(rows, justify="right")


def building_map_table() -> str:
    """Table 2b: building maps of simulated walks (walks 1–3, walks 4–6 of each of
    ``bench.agreement``'s buildings), scored against the corridors their walks went along."""
    rows = [["building", "walks", "routes", "turns told", "precision", "recall", "zigzag",
             "turn-around", "route p90 / ref"]]  # fmt: skip
    for label, config, seed in BUILDINGS:
        walks = simulated_walks(config, seed)
        for name, part in (("1–3", walks[:3]), ("4–6", walks[3:])):
            ids = sorted({t for w in part for t in w.seen_tags()[0]})
            pairs = list(itertools.permutations(ids, 2))
            rng = np.random.default_rng(seed)
            chosen = rng.choice(len(pairs), size=min(BUILDING_MAP_PAIRS, len(pairs)), replace=False)
            score = score_tag_routes(
                fused_skeleton(part),
                corridor_graph(part),
                [pairs[i] for i in chosen],
                plan=plan_guided_route,
            )
            rows.append(
                [
                    f"{label}, seed {seed}",
                    name,
                    str(score.routes),
                    str(score.announced),
                    f"{score.precision:.0%}",
                    f"{score.recall:.0%}",
                    f"{score.zigzag_share:.0%}",
                    f"{score.turn_around_share:.0%}",
                    f"{score.length_ratio_p90:.2f}",
                ]
            )
    return render_markdown_table(rows, justify="right")


#: The skeleton before issue 39: no tag spurs, oblique visits to tags not straightened.
BEFORE_ISSUE_39 = dataclasses.replace(
    DEFAULT_SKELETON_PARAMS, spur_min_m=0.0, straighten_tag_visits=False
)
#: Buildings of table 2c: label → config.
NOOK_BUILDINGS = {
    "3.2 m, one floor": UNSEEN_BUILDING,
    "3.2 m, two floors": dataclasses.replace(UNSEEN_BUILDING, two_floors=True),
}
#: Seeds of table 2c (0–1 chose issue 39's parameters; 2–3 were held out).
NOOK_SEEDS = (0, 1, 2, 3)


def walk_skeleton(walk: SimulatedWalk, params: SkeletonParams) -> PathGraph:
    """The skeleton of one simulated walk, with the tags it saw."""
    ids, positions = walk.seen_tags()
    return build_skeleton_from_arrays(
        walk.positions_m,
        tag_ids=ids,
        tag_positions_m=positions,
        tag_normals=walk.tag_normals(ids),
        params=params,
    )


def sampled_pairs(ids: list[int], count: int, seed: int) -> list[tuple[int, int]]:
    """``count`` ordered pairs of ``ids`` drawn with ``seed`` (all of them if fewer)."""
    pairs = list(itertools.permutations(ids, 2))
    chosen = np.random.default_rng(seed).choice(
        len(pairs), size=min(count, len(pairs)), replace=False
    )
    return [pairs[i] for i in chosen]


def nook_scores(
    config: SimulationConfig, seed: int, nooks: NookConfig, params: SkeletonParams
) -> tuple[list[RouteScore], list[RouteScore]]:
    """(each of the six walkers' single-walk scores, the building maps of walks 1–3 and 4–6)."""
    walks = nook_walks(config, seed, [w for _, w in WALKERS], nooks)
    singles = [
        score_tag_routes(
            walk_skeleton(w, params),
            corridor_graph(w),
            sampled_pairs(list(w.seen_tags()[0]), SIMULATED_PAIRS, seed),
            plan=plan_guided_route,
        )
        for w in walks
    ]
    maps = []
    for part in (walks[:3], walks[3:]):
        ids = sorted({t for w in part for t in w.seen_tags()[0]})
        maps.append(
            score_tag_routes(
                fused_skeleton(part, params),
                corridor_graph(part),
                sampled_pairs(ids, BUILDING_MAP_PAIRS, seed),
                plan=plan_guided_route,
            )
        )
    return singles, maps


def nook_table(params: SkeletonParams = DEFAULT_SKELETON_PARAMS) -> str:
    """Table 2c: per building and seed, with and without hooks, alcoves and oblique visits."""
    rows = [["building", "seed", "nooks", "single walks: precision mean / min",
             "recall mean / min", "building maps 1–3 / 4–6: precision", "recall",
             "turn-around"]]  # fmt: skip
    for label, config in NOOK_BUILDINGS.items():
        for seed in NOOK_SEEDS:
            for name, nooks in (("none", NO_NOOKS), ("hooks, alcoves, visits", NookConfig())):
                singles, maps = nook_scores(config, seed, nooks, params)
                rows.append(
                    [
                        label,
                        str(seed),
                        name,
                        f"{statistics.fmean(s.precision for s in singles):.0%} / "
                        f"{min(s.precision for s in singles):.0%}",
                        f"{statistics.fmean(s.recall for s in singles):.0%} / "
                        f"{min(s.recall for s in singles):.0%}",
                        " / ".join(f"{m.precision:.0%}" for m in maps),
                        " / ".join(f"{m.recall:.0%}" for m in maps),
                        f"{max(s.turn_around_share for s in [*singles, *maps]):.0%}",
                    ]
                )
    return render_markdown_table(rows, justify="right")


def _cpu_ms(build: Callable[[], PathGraph], repeats: int) -> float:
    """Best of ``repeats`` builds, CPU ms of this process (the machine is shared: CPU time and the
    best of several are the build's own cost)."""
    best = float("inf")
    for _ in range(repeats):
        started = time.process_time()
        build()
        best = min(best, (time.process_time() - started) * 1e3)
    return best


def _size(graph: PathGraph) -> str:
    walk = graph.graph
    junctions = sum(1 for n in walk.nodes if walk.nodes[n]["kind"] == JUNCTION)
    length_m = sum(d["length_m"] for _, _, d in walk.edges(data=True) if d["kind"] == "walk")
    return f"{walk.number_of_nodes()} / {junctions} / {length_m:.0f}"


#: Walks of the simulated building map of table 3.
BUILDING_WALKS = 20


def building_map_case() -> tuple[str, Callable[[], PathGraph], int]:
    """A building map of ``BUILDING_WALKS`` simulated walks (walkers of every kind, in turn) of
    one two-floor building, fused (true positions, the building's frame)."""
    config = dataclasses.replace(UNSEEN_BUILDING, two_floors=True, blocks=(3, 2))
    building = build_building(config, np.random.default_rng(11))
    kinds = list(SIMULATED_WALKERS.values())
    walks = [
        simulate_walk(
            config,
            dataclasses.replace(kinds[k % len(kinds)], seed=1000 + k, length_m=600.0),
            building=building,
        )
        for k in range(BUILDING_WALKS)
    ]
    positions = np.concatenate([w.positions_m for w in walks])
    starts = np.cumsum([0, *(len(w.positions_m) for w in walks[:-1])]).tolist()
    ids = list(walks[0].tag_ids)
    return (
        f"building map, {BUILDING_WALKS} simulated walks",
        lambda: build_skeleton_from_arrays(
            positions,
            walk_starts=starts,
            tag_ids=ids,
            tag_positions_m=walks[0].tag_positions_m,
            tag_normals=walks[0].tag_normals(ids),
        ),
        len(positions),
    )


def build_table() -> tuple[str, PathGraph]:
    rows = [["case", "poses", "skeleton CPU ms", "nodes / junctions / m"]]
    floor_2: PathGraph | None = None
    cases: list[tuple[str, Callable[[], PathGraph], int, int]] = []
    for name in REAL:
        result = optimize_session(
            load_session(SESSIONS / f"{name}.json"), SlamParams(compute_marginals=False)
        )
        cases.append(
            (name, functools.partial(build_skeleton, result), result.world_T_phone.shape[0], 5)
        )
    for poses in (10_000, 100_000):
        sim = simulate_session(
            SimulationConfig(num_poses=poses, two_floors=True, seed=7, blocks=(6, 4))
        )
        positions = sim.world_T_phone_true[:, :3, 3]
        cases.append(
            (
                f"simulated {poses // 1000}k",
                functools.partial(build_skeleton_from_arrays, positions),
                poses,
                1,
            )
        )
    label, build, poses = building_map_case()
    cases.append((label, build, poses, 3))
    for name, build, poses, repeats in cases:
        graph = build()
        rows.append([name, f"{poses:,}", f"{_cpu_ms(build, repeats):.0f}", _size(graph)])
        if name == "floor_2_straight":
            floor_2 = graph
    assert floor_2 is not None
    return render_markdown_table(rows, justify="right"), floor_2


def route_table(graph: PathGraph, queries: int = 2000) -> str:
    rng = random.Random(7)
    tags = sorted(graph.tags)
    positions = np.array([graph.graph.nodes[n]["position_m"] for n in graph.graph.nodes])
    rows = [["query", "queries", "p50 ms", "p99 ms", "mean length m"]]

    def near_node() -> PositionEnd:
        x, y, z = positions[rng.randrange(len(positions))] + OFF_PATH_M
        return PositionEnd((float(x), float(y), float(z)))

    for name, make in (
        ("tag → tag", lambda: (TagEnd(rng.choice(tags)), TagEnd(rng.choice(tags)))),
        ("position → position", lambda: (near_node(), near_node())),
    ):
        plan_guided_route(graph, *make())  # warm the snapping index
        times_ms, lengths = [], []
        for _ in range(queries):
            start, goal = make()
            started = time.perf_counter()
            route = plan_guided_route(graph, start, goal)
            times_ms.append((time.perf_counter() - started) * 1e3)
            lengths.append(route.length_m)
        ordered = sorted(times_ms)
        rows.append(
            [
                name,
                str(queries),
                f"{statistics.median(ordered):.2f}",
                f"{ordered[int(0.99 * (len(ordered) - 1))]:.2f}",
                f"{statistics.fmean(lengths):.0f}",
            ]
        )
    return render_markdown_table(rows, justify="right")


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    params = BEFORE_ISSUE_39 if "--before" in args else DEFAULT_SKELETON_PARAMS
    if "--nooks" in args:
        print("2c. hooks, alcoves and oblique visits (issue 39), simulated")
        print(nook_table(params))
        return 0
    print("1. turn-by-turn on floor 2 of the mac building (single walks and building maps)")
    print(quality_table())
    print("\n2. turn-by-turn on simulated walkers (fused skeleton of each walk)")
    print(simulation_table())
    print("\n2b. turn-by-turn on simulated building maps (walks 1–3 and 4–6 of six walkers, fused)")
    print(building_map_table())
    print("\n2c. hooks, alcoves and oblique visits (issue 39), simulated")
    print(nook_table(params))
    builds, floor_2 = build_table()
    print("\n3. skeleton build time (CPU, best of 5 / 1 / 3) and size")
    print(builds)
    print("\n4. guided route queries on the floor_2_straight skeleton (in process)")
    print(route_table(floor_2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
