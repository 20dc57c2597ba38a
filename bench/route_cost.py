"""What one route costs to compute, in process: ``planned_route`` as the API calls it (issue 16).

    .venv/bin/python -m bench.route_cost              # the table
    .venv/bin/python -m bench.route_cost --profile    # … and where the time goes (cProfile)

Each map's path graph is built as the worker builds it (the session optimized with default
parameters, :func:`app.domain.navigation.skeleton.build_skeleton`) and read back from its JSON
document as the API reads it (``path_graph_to_json`` → ``path_graph_from_json``): floor_2_straight
and occam_room of ``data/sessions``, the demo session with points of interest
(``data/demo/floor_2_pois.json``) and a simulated two-floor building. The graph is then in memory,
as the API's per-process cache keeps it, and each route is timed as ``planned_route(graph, from, to,
avoid=…, heading_rad=…, style=…)`` with the arguments the API passes for a request body.

Rows: tag 300 → tag 320 on floor_2_straight (the HTTP benchmark's route, no heading), and every
ordered tag pair of each map (with a heading of 30°, as a phone that has localized sends), as
p50/p90/max µs of the best of ``--repeats`` runs of each route (the machine is shared: the best of
a few runs is the route's cost, the spread across routes is the table's).
"""

from __future__ import annotations

import argparse
import contextlib
import cProfile
import io
import itertools
import math
import pstats
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from app.cli.tables import render_markdown_table  # noqa: E402
from app.domain.evaluation.simulate import SimulationConfig, simulate_session  # noqa: E402
from app.domain.mapping.params import SlamParams  # noqa: E402
from app.domain.mapping.slam import optimize_session  # noqa: E402
from app.domain.navigation.instructions import DEFAULT_STYLE, GuidanceStyle  # noqa: E402
from app.domain.navigation.path_graph import PathGraph, path_graph_from_json, path_graph_to_json  # noqa: E402
from app.domain.navigation.routing import Endpoint, TagEnd  # noqa: E402
from app.domain.navigation.skeleton import build_skeleton  # noqa: E402
from app.domain.upload.session import load_session, parse_session  # noqa: E402
from app.services.errors import ServiceError  # noqa: E402
from app.services.navigation import planned_route  # noqa: E402

SESSIONS = REPO / "data" / "sessions"
DEMO_POIS = REPO / "data" / "demo" / "floor_2_pois.json"
#: The simulated building: two floors joined by stairs and an elevator.
SIMULATED = SimulationConfig(num_poses=3000, two_floors=True, blocks=(2, 2), seed=7)
#: The phone's heading sent with the all-pairs routes, degrees (as the API converts it).
HEADING_DEG = 30.0


@dataclass(frozen=True, slots=True, kw_only=True)
class RouteQuestion:
    """One route as the API asks it of ``planned_route``."""

    start: Endpoint
    goal: Endpoint
    avoid: frozenset[str] = frozenset()
    heading_rad: float | None = None
    style: GuidanceStyle = DEFAULT_STYLE


def served_graph(graph: PathGraph) -> PathGraph:
    """``graph`` as the API holds it: read back from the JSON document the worker stored."""
    return path_graph_from_json(path_graph_to_json(graph))


def worker_graph_of_session(path: Path) -> PathGraph:
    result = optimize_session(load_session(path), SlamParams())
    return served_graph(build_skeleton(result))


def simulated_graph() -> PathGraph:
    upload = simulate_session(SIMULATED).upload
    return served_graph(build_skeleton(optimize_session(parse_session(upload), SlamParams())))


def route_maps() -> dict[str, PathGraph]:
    """The maps the benchmark routes on, by name."""
    return {
        "floor_2_straight": worker_graph_of_session(SESSIONS / "floor_2_straight.json"),
        "occam_room": worker_graph_of_session(SESSIONS / "occam_room.json"),
        "floor_2_pois (demo)": worker_graph_of_session(DEMO_POIS),
        "simulated 2 floors": simulated_graph(),
    }


def all_tag_pairs(graph: PathGraph) -> list[RouteQuestion]:
    heading_rad = math.radians(HEADING_DEG)
    return [
        RouteQuestion(start=TagEnd(a), goal=TagEnd(b), heading_rad=heading_rad)
        for a, b in itertools.permutations(sorted(graph.tags), 2)
    ]


def route_cost_us(graph: PathGraph, question: RouteQuestion, repeats: int) -> float | None:
    """Best of ``repeats`` runs of one route, µs (None when the route is refused)."""
    best = math.inf
    for _ in range(repeats):
        started = time.perf_counter()
        try:
            ask(graph, question)
        except ServiceError:
            return None
        best = min(best, time.perf_counter() - started)
    return best * 1e6


def ask(graph: PathGraph, question: RouteQuestion) -> object:
    return planned_route(
        graph,
        question.start,
        question.goal,
        avoid=question.avoid,
        heading_rad=question.heading_rad,
        style=question.style,
    )


def cost_row(
    label: str, graph: PathGraph, questions: list[RouteQuestion], repeats: int
) -> list[str]:
    costs = [route_cost_us(graph, q, repeats) for q in questions]
    served = np.array([c for c in costs if c is not None])
    if served.size == 0:
        return [label, str(len(questions)), "0", "–", "–", "–"]
    p50, p90 = np.percentile(served, [50, 90])
    return [
        label,
        str(len(questions)),
        str(served.size),
        f"{p50:.0f}",
        f"{p90:.0f}",
        f"{served.max():.0f}",
    ]


def cost_table(maps: dict[str, PathGraph], repeats: int) -> str:
    rows = [["routes", "asked", "served", "p50 µs", "p90 µs", "max µs"]]
    floor_2 = maps["floor_2_straight"]
    rows.append(
        cost_row(
            "floor_2_straight: tag 300 → tag 320",
            floor_2,
            [RouteQuestion(start=TagEnd(300), goal=TagEnd(320))],
            max(repeats, 50),
        )
    )
    for name, graph in maps.items():
        nodes, tags = graph.graph.number_of_nodes(), len(graph.tags)
        label = f"{name}: all tag pairs ({nodes} nodes, {tags} tags)"
        rows.append(cost_row(label, graph, all_tag_pairs(graph), repeats))
    return render_markdown_table(rows, justify="right")


def profile(run: Callable[[], object], top: int) -> str:
    profiler = cProfile.Profile()
    profiler.enable()
    run()
    profiler.disable()
    out = io.StringIO()
    pstats.Stats(profiler, stream=out).sort_stats("cumulative").print_stats(top)
    return out.getvalue()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.route_cost", description=__doc__)
    parser.add_argument("--repeats", type=int, default=5, help="runs of each route (best kept)")
    parser.add_argument("--profile", action="store_true", help="also print cProfile's top entries")
    parser.add_argument("--top", type=int, default=30, help="profile entries printed")
    args = parser.parse_args(argv)
    if args.repeats < 1:
        parser.error("--repeats must be at least 1")
    maps = route_maps()
    print(cost_table(maps, args.repeats))
    if args.profile:

        def every_pair() -> None:
            for graph in maps.values():
                for question in all_tag_pairs(graph):
                    with contextlib.suppress(ServiceError):
                        ask(graph, question)

        print()
        print(profile(every_pair, args.top))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
