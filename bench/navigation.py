"""Navigation benchmark (in process, no server): one command, prints four tables.

    .venv/bin/python -m bench.navigation          # (or: .venv/bin/python bench/navigation.py)

1. Turn-by-turn on floor 2 of the mac building, before (walked-line path graph, old steps) →
   after (corridor skeleton, decision-point instructions), against the hand-drawn reference
   ``bench.mac_floor_2_reference`` (``bench.navigation_quality``).
2. The same on simulated walkers who step to tags, sway, walk corridors twice with an offset and
   leave passes that do not meet (``app.domain.evaluation.simulate.simulate_walk``), against the
   simulated building's corridors.
3. Build time and size, walked line → skeleton: the real sessions (optimized with default
   parameters) and simulated two-floor walks of 10,000 and 100,000 poses (true trajectory).
4. Route queries on the floor_2_straight skeleton: p50/p99 over 2,000 queries between random
   tags, and between random positions (snapped onto the graph), as the API answers them (the
   graph already in memory, as the API's per-process cache keeps it), with guided steps.

The HTTP figures (50 concurrent clients) are in ``bench/server.py``; localization in
``bench/localize.py``.
"""

from __future__ import annotations

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
    SimulationConfig,
    WalkerConfig,
    corridor_graph,
    simulate_session,
    simulate_walk,
)
from app.domain.evaluation.turn_metrics import score_tag_routes  # noqa: E402
from app.domain.mapping.params import SlamParams  # noqa: E402
from app.domain.mapping.slam import optimize_session  # noqa: E402
from app.domain.navigation.instructions import plan_guided_route  # noqa: E402
from app.domain.navigation.path_graph import (  # noqa: E402
    JUNCTION,
    PathGraph,
    build_path_graph_from_arrays,
)
from app.domain.navigation.routing import PositionEnd, TagEnd, plan_route  # noqa: E402
from app.domain.navigation.skeleton import build_skeleton_from_arrays  # noqa: E402
from app.domain.upload.session import load_session  # noqa: E402
from bench.navigation_quality import quality_table  # noqa: E402

SESSIONS = REPO / "data" / "sessions"
#: Where a person stands relative to a node: beside the walked path, not on it.
OFF_PATH_M = np.array([0.3, 0.0, -0.3])
REAL = ("occam_room", "floor_2_straight", "straight_209_occam", "desnat_straight_once")
#: Simulated walks scored in table 2: (label, building, seed).
SIMULATED = (
    ("one floor, seed 0", SimulationConfig(num_poses=2), 0),
    ("one floor, seed 1", SimulationConfig(num_poses=2), 1),
    ("one floor, seed 2", SimulationConfig(num_poses=2), 2),
    ("two floors, seed 0", SimulationConfig(num_poses=2, two_floors=True, blocks=(2, 2)), 0),
    ("two floors, seed 1", SimulationConfig(num_poses=2, two_floors=True, blocks=(2, 2)), 1),
)
#: Tag pairs routed per simulated walk.
SIMULATED_PAIRS = 300

Builder = Callable[..., PathGraph]
BUILDERS: dict[str, Builder] = {
    "walked line": build_path_graph_from_arrays,
    "skeleton": build_skeleton_from_arrays,
}


def simulation_table() -> str:
    rows = [
        [
            "walk",
            "graph",
            "routes",
            "turns told",
            "real",
            "precision",
            "recall",
            "zigzag",
            "turn-around",
            "route p90 / ref",
        ]
    ]
    for label, config, seed in SIMULATED:
        walk = simulate_walk(config, WalkerConfig(seed=seed, length_m=700.0))
        reference = corridor_graph(walk)
        pairs = list(itertools.permutations(walk.tag_ids, 2))
        rng = np.random.default_rng(seed)
        chosen = rng.choice(len(pairs), size=min(SIMULATED_PAIRS, len(pairs)), replace=False)
        pairs = [pairs[i] for i in chosen]
        kwargs = {"tag_ids": walk.tag_ids, "tag_positions_m": walk.tag_positions_m}
        for graph_label, builder, plan in (
            ("before", build_path_graph_from_arrays, plan_route),
            ("after", build_skeleton_from_arrays, plan_guided_route),
        ):
            score = score_tag_routes(
                builder(walk.positions_m, **kwargs), reference, pairs, plan=plan
            )
            rows.append(
                [
                    label,
                    graph_label,
                    str(score.routes),
                    str(score.announced),
                    str(score.real),
                    f"{score.precision:.0%}",
                    f"{score.recall:.0%}",
                    f"{score.zigzag_share:.0%}",
                    f"{score.turn_around_share:.0%}",
                    f"{score.length_ratio_p90:.2f}",
                ]
            )
    return render_markdown_table(rows, justify="right")


def _timed_ms(build: Builder, positions_m: np.ndarray, repeats: int, **kwargs: object) -> float:
    """Best of ``repeats`` builds, ms (the machine is shared: the best is the build's cost)."""
    best = float("inf")
    for _ in range(repeats):
        started = time.perf_counter()
        build(positions_m, **kwargs)
        best = min(best, (time.perf_counter() - started) * 1e3)
    return best


def _size(graph: PathGraph) -> str:
    walk = graph.graph
    junctions = sum(1 for n in walk.nodes if walk.nodes[n]["kind"] == JUNCTION)
    length_m = sum(d["length_m"] for _, _, d in walk.edges(data=True) if d["kind"] == "walk")
    return f"{walk.number_of_nodes()} / {junctions} / {length_m:.0f}"


def build_table() -> tuple[str, PathGraph]:
    rows = [
        [
            "case",
            "poses",
            "walked line ms",
            "skeleton ms",
            "walked line nodes / junctions / m",
            "skeleton nodes / junctions / m",
        ]
    ]
    floor_2: PathGraph | None = None
    cases: list[tuple[str, np.ndarray, dict[str, object], int]] = []
    for name in REAL:
        result = optimize_session(
            load_session(SESSIONS / f"{name}.json"), SlamParams(compute_marginals=False)
        )
        kwargs: dict[str, object] = {
            "tag_ids": [int(t) for t in result.tag_ids],
            "tag_positions_m": result.world_T_tag[:, :3, 3],
        }
        cases.append((name, result.world_T_phone[:, :3, 3], kwargs, 5))
    for poses in (10_000, 100_000):
        sim = simulate_session(
            SimulationConfig(num_poses=poses, two_floors=True, seed=7, blocks=(6, 4))
        )
        cases.append((f"simulated {poses // 1000}k", sim.world_T_phone_true[:, :3, 3], {}, 1))
    for name, positions_m, kwargs, repeats in cases:
        graphs = {label: build(positions_m, **kwargs) for label, build in BUILDERS.items()}
        times = {
            label: _timed_ms(build, positions_m, repeats, **kwargs)
            for label, build in BUILDERS.items()
        }
        rows.append(
            [
                name,
                str(len(positions_m)),
                f"{times['walked line']:.0f}",
                f"{times['skeleton']:.0f}",
                _size(graphs["walked line"]),
                _size(graphs["skeleton"]),
            ]
        )
        if name == "floor_2_straight":
            floor_2 = graphs["skeleton"]
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


def main() -> int:
    print("1. turn-by-turn on floor 2 of the mac building, before → after")
    print(quality_table())
    print("\n2. turn-by-turn on simulated walkers, before → after")
    print(simulation_table())
    builds, floor_2 = build_table()
    print("\n3. build time (best of 5 for real sessions) and size, walked line → skeleton")
    print(builds)
    print("\n4. guided route queries on the floor_2_straight skeleton (in process)")
    print(route_table(floor_2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
