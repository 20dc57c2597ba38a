"""Routes answer exactly as they did before they were made fast (issue 16).

``data/route_answers.json.gz`` holds three path graphs as the API reads them (floor_2_straight and
the demo session with points of interest, both built by the worker's ``build_skeleton`` from the
optimized sessions, and a simulated two-floor building with stairs and an elevator) and the full
answer of ``plan_guided_route`` to each of ~3,300 questions on them — every ordered tag pair, points
of interest, nodes, positions, avoided stairs and elevators, headings, units, clock faces, and the
refusals — recorded from the code of 2026-11-25 before the route computation was optimized.
Every answer must stay the same: polylines, lengths and step positions within 1e-9, the rest
equal. To record again (only when an answer is meant to change):

    .venv/bin/python tests/unit/test_route_answers.py --record           # graphs and answers
    .venv/bin/python tests/unit/test_route_answers.py --record-answers   # answers, same graphs

Recorded again with ``--record-answers`` on 2026-12-02 (issue 39: one rule for turns, steps for
blind travellers): the graphs, questions, polylines, lengths, step positions, kinds, distances
and turn angles are those of 2026-11-25; the new step fields (``turn``, ``clock``,
``steps_count``, ``landmark``, ``side``, ``text``) were added, and 513 of the 21,176 instructions
changed words under the one rule: a facing turn of 135–150° is now "turn sharp left/right" (was
"turn left/right"), and a goal 20–30° off the last leg is now "on your left/right" (was "ahead").

Recorded again with ``--record-answers`` on 2026-12-02 (issue 39, forks and the goal's side):
752 of the 3,286 routes changed, nothing but these. 56 routes of floor_2_straight through the fork
by tag 307, where the corridor bends under 30° while a spur leaves within 45° of straight on,
gained a "keep left/right at the fork" step (kind ``keep``) and the go step before it
(``app.domain.navigation.forks``). Two routes from a position 1.2 m from tag 300, with nothing to
walk on the graph (0.19 m), now go straight to the tag ("go straight 1 m to tag 300, ahead")
instead of facing a way of 0.19 m. On 694 routes the goal's side changed (last go step and
arrival, words and ``side``): it is now told as the walker sees it where the app says "arrive",
2 m before the end, facing the way it walks the last leg there (it was told from the end, facing
the last 0.5 m-simplified leg, often a jog of under 2 m to the goal's node that is never told):
505 from left/right to "ahead" (a goal at the end, under 20° off the way from 2 m back), 189
from one side to the other (a jog at the end that the old rule faced).
"""

from __future__ import annotations

import gzip
import itertools
import json
import math
import sys
from functools import cache
from pathlib import Path
from typing import Any

import pytest

from app.domain.navigation.instructions import GuidanceStyle, plan_guided_route
from app.domain.navigation.path_graph import PathGraph, path_graph_from_json
from app.domain.navigation.routing import (
    Endpoint,
    NodeEnd,
    PoiEnd,
    PositionEnd,
    Route,
    RouteError,
    TagEnd,
)

ANSWERS = Path(__file__).parent / "data" / "route_answers.json.gz"
TOLERANCE = 1e-9
#: At most this many tag pairs are asked of a graph (every pair on floor 2).
MAX_TAG_PAIRS = 600


# --------------------------------------------------------------------------- questions


def endpoint_document(end: Endpoint) -> dict[str, Any]:
    match end:
        case TagEnd(tag_id=tag):
            return {"tag": tag}
        case PoiEnd(name=name):
            return {"poi": name}
        case NodeEnd(node_id=node):
            return {"node": node}
        case PositionEnd(position_m=position_m):
            return {"position_m": list(position_m)}
    raise AssertionError(end)  # pragma: no cover


def endpoint_from(document: dict[str, Any]) -> Endpoint:
    if "tag" in document:
        return TagEnd(document["tag"])
    if "poi" in document:
        return PoiEnd(document["poi"])
    if "node" in document:
        return NodeEnd(document["node"])
    x, y, z = document["position_m"]
    return PositionEnd((x, y, z))


def questions_for(pg: PathGraph) -> list[dict[str, Any]]:
    """The questions asked of one graph, as JSON documents."""
    tags = sorted(pg.tags)
    heading = math.radians(30.0)
    asked: list[dict[str, Any]] = []

    def ask(start: Endpoint, goal: Endpoint, **options: Any) -> None:
        asked.append({"from": endpoint_document(start), "to": endpoint_document(goal), **options})

    pairs = list(itertools.permutations(tags, 2))
    pairs = pairs[:: math.ceil(len(pairs) / MAX_TAG_PAIRS)]
    for a, b in pairs:
        ask(TagEnd(a), TagEnd(b), heading_rad=heading)
    for a, b in pairs[::7]:
        ask(TagEnd(a), TagEnd(b))
        ask(TagEnd(a), TagEnd(b), heading_rad=-2.5, units="ft", clock=True)
        ask(TagEnd(a), TagEnd(b), heading_rad=1.2, units="steps")
        ask(TagEnd(a), TagEnd(b), avoid=["stairs"])
        ask(TagEnd(a), TagEnd(b), avoid=["elevator"])
        ask(TagEnd(a), TagEnd(b), avoid=["elevator", "stairs"])
    names = sorted({poi.name for poi in pg.pois})
    for name in names:
        for tag in tags[::3]:
            ask(TagEnd(tag), PoiEnd(name), heading_rad=heading)
            ask(PoiEnd(name.upper()), TagEnd(tag))
    for a, b in itertools.permutations(names, 2):
        ask(PoiEnd(a), PoiEnd(b))
    nodes = sorted(pg.graph.nodes)
    for i, node in enumerate(nodes[:: math.ceil(len(nodes) / 40)]):
        x, y, z = pg.graph.nodes[node]["position_m"]
        near = (x + 0.3, y + 0.1, z - 0.3)
        ask(PositionEnd(near), TagEnd(tags[i % len(tags)]), heading_rad=heading)
        ask(TagEnd(tags[-1 - i % len(tags)]), PositionEnd(near))
        ask(NodeEnd(node), NodeEnd(nodes[-1 - i]))
        ask(PositionEnd(near), PositionEnd((x - 2.0, y, z + 1.5)))
    ask(TagEnd(tags[0]), TagEnd(tags[0]))
    ask(TagEnd(999_999), TagEnd(tags[0]))
    ask(TagEnd(tags[0]), PoiEnd("Room 999"))
    ask(NodeEnd(-1), TagEnd(tags[0]))
    ask(TagEnd(tags[0]), TagEnd(tags[1]), avoid=["ramps"])
    ask(PositionEnd((math.nan, 0.0, 0.0)), TagEnd(tags[0]))
    return asked


def answer(pg: PathGraph, question: dict[str, Any]) -> dict[str, Any]:
    """The full answer to one question: the route, or the refusal's class and message."""
    try:
        route = plan_guided_route(
            pg,
            endpoint_from(question["from"]),
            endpoint_from(question["to"]),
            avoid=frozenset(question.get("avoid", ())),
            heading_rad=question.get("heading_rad"),
            style=GuidanceStyle(
                units=question.get("units", "m"), clock=question.get("clock", False)
            ),
        )
    except RouteError as err:
        return {"refused": type(err).__name__, "message": str(err)}
    return route_document(route)


def route_document(route: Route) -> dict[str, Any]:
    return {
        "polyline_m": [list(p) for p in route.polyline_m],
        "length_m": route.length_m,
        "floors": route.floors,
        "nodes": route.nodes,
        "steps": [
            {
                "instruction": s.instruction,
                "position_m": list(s.position_m),
                "kind": s.kind,
                "distance_m": s.distance_m,
                "turn_deg": s.turn_deg,
                "floor": s.floor,
                "turn": s.turn,
                "clock": s.clock,
                "steps_count": s.steps_count,
                "landmark": s.landmark,
                "side": s.side,
                "text": s.text,
            }
            for s in route.steps
        ],
    }


# --------------------------------------------------------------------------- the test


@cache
def recorded() -> dict[str, Any]:
    with gzip.open(ANSWERS, "rt", encoding="utf-8") as f:
        document: dict[str, Any] = json.load(f)
    return document


@cache
def recorded_graph(name: str) -> PathGraph:
    return path_graph_from_json(recorded()["maps"][name]["path_graph"])


def assert_same(got: Any, want: Any, where: str) -> None:
    if isinstance(want, float) or isinstance(got, float):
        assert isinstance(got, (int, float)), where
        assert isinstance(want, (int, float)), where
        assert math.isclose(got, want, rel_tol=0.0, abs_tol=TOLERANCE), f"{where}: {got} != {want}"
    elif isinstance(want, dict):
        assert isinstance(got, dict), where
        assert got.keys() == want.keys(), f"{where}: {got} != {want}"
        for key in want:
            assert_same(got[key], want[key], f"{where}.{key}")
    elif isinstance(want, list):
        assert isinstance(got, list), where
        assert len(got) == len(want), f"{where}: {got} != {want}"
        for i, (g, w) in enumerate(zip(got, want, strict=True)):
            assert_same(g, w, f"{where}[{i}]")
    else:
        assert got == want, f"{where}: {got!r} != {want!r}"


def test_the_recorded_answers_cover_routes_refusals_and_floor_changes():
    maps = recorded()["maps"]
    answers = [a for m in maps.values() for a in m["answers"]]
    routes = [a for a in answers if "steps" in a]
    kinds = {s["kind"] for a in routes for s in a["steps"]}
    assert len(routes) > 1000
    assert {"face", "go", "announce", "turn", "keep", "stairs", "elevator", "arrive"} <= kinds
    assert {a["refused"] for a in answers if "refused" in a} >= {
        "UnknownEndpoint",
        "Unreachable",
        "RouteError",
    }


@pytest.mark.parametrize("name", ["floor_2_straight", "floor_2_pois", "simulated_two_floors"])
def test_every_answer_is_the_one_recorded(name):
    pg = recorded_graph(name)
    recorded_map = recorded()["maps"][name]
    questions = recorded_map["questions"]
    assert json.dumps(questions) == json.dumps(questions_for(pg))  # the same questions (NaN too)
    for i, (question, want) in enumerate(zip(questions, recorded_map["answers"], strict=True)):
        assert_same(answer(pg, question), want, f"{name} #{i} {question}")


def test_a_changed_answer_is_noticed():
    pg = recorded_graph("floor_2_straight")
    question = recorded()["maps"]["floor_2_straight"]["questions"][0]
    want = recorded()["maps"]["floor_2_straight"]["answers"][0]
    got = answer(pg, question)
    got["polyline_m"][-1][0] += 1e-6
    with pytest.raises(AssertionError, match="polyline_m"):
        assert_same(got, want, "route")


# --------------------------------------------------------------------------- recording


def record() -> None:  # pragma: no cover (run by hand, see the module docstring)
    sys.path.insert(0, str(Path(__file__).parents[2]))
    from app.domain.evaluation.simulate import SimulationConfig, WalkerConfig, simulate_walk
    from app.domain.navigation.path_graph import path_graph_to_json
    from app.domain.navigation.skeleton import build_skeleton_from_arrays
    from bench.route_cost import DEMO_POIS, SESSIONS, worker_graph_of_session

    walk = simulate_walk(
        SimulationConfig(num_poses=2, two_floors=True, blocks=(2, 2)),
        WalkerConfig(seed=0, length_m=700.0),
    )
    simulated = build_skeleton_from_arrays(
        walk.positions_m, tag_ids=walk.tag_ids, tag_positions_m=walk.tag_positions_m
    )
    add_an_elevator(simulated)
    graphs = {
        "floor_2_straight": worker_graph_of_session(SESSIONS / "floor_2_straight.json"),
        "floor_2_pois": worker_graph_of_session(DEMO_POIS),
        "simulated_two_floors": simulated,
    }
    maps = {}
    for name, graph in graphs.items():
        document = path_graph_to_json(graph)
        pg = path_graph_from_json(json.loads(json.dumps(document)))
        questions = questions_for(pg)
        maps[name] = {
            "path_graph": document,
            "questions": questions,
            "answers": [answer(pg, q) for q in questions],
        }
    ANSWERS.parent.mkdir(exist_ok=True)
    text = json.dumps({"maps": maps}, separators=(",", ":"))
    ANSWERS.write_bytes(gzip.compress(text.encode(), mtime=0))


def record_answers() -> None:  # pragma: no cover (run by hand, see the module docstring)
    """Record the answers again on the recorded graphs and questions (what changed in wording
    alone, not in the graphs the current skeleton code would build)."""
    document = recorded()
    for name, recorded_map in document["maps"].items():
        pg = recorded_graph(name)
        recorded_map["answers"] = [answer(pg, q) for q in recorded_map["questions"]]
    text = json.dumps(document, separators=(",", ":"))
    ANSWERS.write_bytes(gzip.compress(text.encode(), mtime=0))


def add_an_elevator(pg: PathGraph) -> None:  # pragma: no cover (run by hand)
    """An elevator between the floor-0 and floor-1 nodes nearest each other in x–z, farthest from
    the stairs (the simulated building has stairs only)."""
    from app.domain.navigation.path_graph import ELEVATOR, STAIRS

    G = pg.graph
    stairs = [n for u, v, d in G.edges(data=True) if d["kind"] == STAIRS for n in (u, v)]
    stairs_xz = [(G.nodes[n]["position_m"][0], G.nodes[n]["position_m"][2]) for n in stairs]

    def away(n: int) -> float:
        x, _, z = G.nodes[n]["position_m"]
        return min(math.dist((x, z), s) for s in stairs_xz)

    lower = max((n for n in G.nodes if G.nodes[n]["floor"] == 0), key=away)
    x, _, z = G.nodes[lower]["position_m"]
    upper = min(
        (n for n in G.nodes if G.nodes[n]["floor"] == 1),
        key=lambda n: math.dist((x, z), G.nodes[n]["position_m"][::2]),
    )
    length_m = math.dist(G.nodes[lower]["position_m"], G.nodes[upper]["position_m"])
    G.add_edge(lower, upper, length_m=length_m, kind=ELEVATOR, floor=0)


if __name__ == "__main__":  # pragma: no cover
    if sys.argv[1:] == ["--record"]:
        record()
    elif sys.argv[1:] == ["--record-answers"]:
        sys.path.insert(0, str(Path(__file__).parents[2]))
        record_answers()
    else:
        sys.exit("usage: python tests/unit/test_route_answers.py --record | --record-answers")
