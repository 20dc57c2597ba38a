"""Navigation benchmark (in process, no server): one command, prints two tables.

    .venv/bin/python bench/navigation.py

1. Path-graph build time and size: the real sessions (optimized with default parameters) and
   simulated two-floor walks of 10,000 and 100,000 poses (true trajectory).
2. Route queries on the floor_2_straight path graph: p50/p99 over 2,000 queries between random
   tags, and between random positions (snapped onto the graph), as the API answers them (the
   graph already in memory, as the API's per-process cache keeps it).

The HTTP figures (50 concurrent clients) are in ``bench/server.py``; localization in
``bench/localize.py``.
"""

from __future__ import annotations

import random
import statistics
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from app.cli.tables import render_markdown_table  # noqa: E402
from app.domain.params import SlamParams  # noqa: E402
from app.domain.path_graph import (  # noqa: E402
    JUNCTION,
    PathGraph,
    build_path_graph,
    build_path_graph_from_arrays,
)
from app.domain.routing import PositionEnd, TagEnd, plan_route  # noqa: E402
from app.domain.session import load_session  # noqa: E402
from app.domain.simulate import SimulationConfig, simulate_session  # noqa: E402
from app.domain.slam import optimize_session  # noqa: E402

SESSIONS = REPO / "data" / "sessions"
#: Where a person stands relative to a node: beside the walked path, not on it.
OFF_PATH_M = np.array([0.3, 0.0, -0.3])
REAL = ("occam_room", "floor_2_straight", "straight_209_occam", "desnat_straight_once")


def _row(name: str, poses: int, build_ms: float, graph: PathGraph) -> list[str]:
    walk = graph.graph
    junctions = sum(1 for n in walk.nodes if walk.nodes[n]["kind"] == JUNCTION)
    changes = sum(1 for u, v in walk.edges if walk.edges[u, v]["kind"] != "walk")
    return [
        name,
        str(poses),
        f"{build_ms:.0f}",
        str(walk.number_of_nodes()),
        str(junctions),
        str(walk.number_of_edges()),
        str(len(graph.floor_levels_m)),
        str(changes),
    ]


def build_table() -> tuple[str, PathGraph]:
    rows = [["case", "poses", "build ms", "nodes", "junctions", "edges", "floors", "floor edges"]]
    floor_2: PathGraph | None = None
    for name in REAL:
        result = optimize_session(
            load_session(SESSIONS / f"{name}.json"), SlamParams(compute_marginals=False)
        )
        started = time.perf_counter()
        graph = build_path_graph(result)
        build_ms = (time.perf_counter() - started) * 1e3
        rows.append(_row(name, len(result.pose_id), build_ms, graph))
        if name == "floor_2_straight":
            floor_2 = graph
    for poses in (10_000, 100_000):
        sim = simulate_session(
            SimulationConfig(num_poses=poses, two_floors=True, seed=7, blocks=(6, 4))
        )
        positions = sim.world_T_phone_true[:, :3, 3]
        started = time.perf_counter()
        graph = build_path_graph_from_arrays(positions)
        rows.append(
            _row(f"simulated {poses // 1000}k", poses, (time.perf_counter() - started) * 1e3, graph)
        )
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
        plan_route(graph, *make())  # warm the snapping index
        times_ms, lengths = [], []
        for _ in range(queries):
            start, goal = make()
            started = time.perf_counter()
            route = plan_route(graph, start, goal)
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
    builds, floor_2 = build_table()
    print("path graph builds")
    print(builds)
    print("\nroute queries on the floor_2_straight path graph (in process)")
    print(route_table(floor_2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
