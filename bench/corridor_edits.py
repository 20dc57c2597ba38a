"""Corridor edits (issue 27) benchmark, in process: one command, prints three tables.

    .venv/bin/python -m bench.corridor_edits

1. **Cost** (CPU time, ``time.process_time``, so the machine's load does not count) on the
   corridor skeleton of a simulated two-floor building walked 20 times: checking and applying a
   new edit to the graph with 20 edits already applied (``apply_new_edit``, what a POST adds to
   the edits already there), applying all 20 to a new version (``apply_edits``, once per version
   and revision per API process), and what a POST costs in the domain in all (the 20 edits
   applied, the new one checked, the 21 applied again for the answer). Median and worst of 30.
2. **Re-anchoring**: 20 edits made by clicking the nodes of the skeleton of walks 1–10 (quiets
   at junctions and bends, moves, shortcuts between dead ends, points of interest), applied to
   the skeleton of the same walks walked again (other sway: a rebuild), of walks 1–11 (a walk
   added), and of walks 11–20 only (other walks of the building: places the first walks covered
   may be gone). For each: applied, not applied with a place still there (must be 0), not
   applied with the place gone.
3. **How far nodes move** between those versions: for each node of the first skeleton, the
   distance to the nearest node of the other (same floor), p50 / p95 / max over the nodes whose
   corridor the other version has (nearest ≤ 3 m). ``NODE_TOLERANCE_M`` (1.5 m) must cover what
   a rebuild moves a node by, and stay under a corridor width apart.
"""

from __future__ import annotations

import math
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from app.cli.tables import render_markdown_table  # noqa: E402
from app.domain.evaluation.simulate import SimulationConfig  # noqa: E402
from app.domain.evaluation.simulate_building import simulate_building_sessions  # noqa: E402
from app.domain.navigation.corridor_edits import (  # noqa: E402
    NODE_TOLERANCE_M,
    CorridorEdit,
    EditError,
    apply_edits,
    apply_new_edit,
    edit_from_json,
)
from app.domain.navigation.path_graph import (  # noqa: E402
    PathGraph,
    build_path_graph_from_arrays,
)
from app.domain.navigation.skeleton import build_skeleton_from_arrays  # noqa: E402

WALKS = 20
REPEATS = 30
#: The building: 4 × 2 blocks of corridors on two floors; each walk 1,500 poses (150 s).
CONFIG = SimulationConfig(num_poses=1500, blocks=(4, 2), two_floors=True, seed=27)


def walked(positions: list[np.ndarray], seed: int, sway_m: float = 0.0) -> np.ndarray:
    """The walks one after the other, each followed by its way back (so no jump joins one walk's
    end to the next one's start), with ``sway_m`` of extra horizontal noise."""
    rng = np.random.default_rng(seed)
    parts = []
    for xyz in positions:
        parts += [xyz, xyz[::-1]]
    joined = np.vstack(parts).copy()
    joined[:, [0, 2]] += rng.normal(0.0, sway_m, (len(joined), 2))
    return joined


def skeleton(positions: np.ndarray, tags: dict[int, np.ndarray]) -> PathGraph:
    ids = sorted(tags)
    return build_skeleton_from_arrays(
        positions, tag_ids=ids, tag_positions_m=np.array([tags[t][:3, 3] for t in ids])
    )


def edits_on(pg: PathGraph, count: int) -> list[CorridorEdit]:
    """``count`` edits an operator would make by clicking nodes of ``pg``: quiets, moves by
    0.5 m, shortcuts between dead ends of one floor, points of interest at nodes; each one checked
    as the API checks it (those refused are skipped)."""
    G = pg.graph
    degree = dict(G.degree())
    nodes = sorted(G.nodes)
    rng = np.random.default_rng(1)
    ends = [n for n in nodes if degree[n] == 1]
    picks = [int(n) for n in rng.permutation(nodes)]
    documents: list[dict[str, object]] = []
    for k, n in enumerate(picks):
        p = [float(v) for v in G.nodes[n]["position_m"]]
        kind = k % 4
        if kind == 0:
            documents.append({"op": "quiet", "at": p})
        elif kind == 1:
            documents.append({"op": "move_node", "from": p, "to": [p[0] + 0.5, p[1], p[2]]})
        elif kind == 2 and len(ends) >= 2:
            a, b = ends.pop(), ends.pop(0)
            documents.append(
                {
                    "op": "add_edge",
                    "from": list(G.nodes[a]["position_m"]),
                    "to": list(G.nodes[b]["position_m"]),
                    "kind": "walk",
                }
            )
        else:
            documents.append({"op": "add_poi", "name": f"Room {k}", "at": [p[0], p[1], p[2] + 1.0]})
    chosen: list[CorridorEdit] = []
    edited = pg
    for document in documents:
        edit = edit_from_json(document)
        try:
            edited = apply_new_edit(edited, edit)
        except EditError:
            continue
        chosen.append(edit)
        if len(chosen) == count:
            break
    return chosen


def cpu_ms(work: Callable[[], object]) -> list[float]:
    times = []
    for _ in range(REPEATS):
        start = time.process_time()
        work()
        times.append((time.process_time() - start) * 1000)
    return times


def place_exists(pg: PathGraph, edit: CorridorEdit) -> bool:
    """Whether ``pg`` still has a node (or, for a point of interest, its floor a corridor) near
    each place the edit names: the independent check of an edit reported not applied."""
    points = [p for p in (edit.at_m, edit.from_m) if p is not None]
    if edit.op == "add_edge" and edit.to_m is not None:
        points.append(edit.to_m)
    if edit.op == "add_poi":
        return True
    G = pg.graph
    for p in points:
        near = min(
            (
                math.hypot(d["position_m"][0] - p[0], d["position_m"][2] - p[2])
                for _, d in G.nodes(data=True)
                if abs(d["position_m"][1] - p[1]) < 1.5
            ),
            default=math.inf,
        )
        if near > NODE_TOLERANCE_M:
            return False
    return True


def moved_m(first: PathGraph, other: PathGraph) -> list[float]:
    out = []
    theirs = [(d["position_m"], d["floor"]) for _, d in other.graph.nodes(data=True)]
    for _, d in first.graph.nodes(data=True):
        p = d["position_m"]
        near = min(
            (math.hypot(q[0] - p[0], q[2] - p[2]) for q, f in theirs if f == d["floor"]),
            default=math.inf,
        )
        if near <= 3.0:
            out.append(near)
    return out


def main() -> None:
    building = simulate_building_sessions(CONFIG, count=WALKS)
    positions = [s.world_T_phone_true[:, :3, 3] for s in building.sessions]
    tags = building.world_T_tag_true
    everything = skeleton(walked(positions, seed=0, sway_m=0.1), tags)
    print(
        f"20-walk building: {everything.graph.number_of_nodes()} nodes, "
        f"{everything.graph.number_of_edges()} edges, {len(everything.floor_levels_m)} floors, "
        f"{len(everything.tags)} tags\n"
    )

    # 1. cost, on the skeleton and on the walked line (maps of several walks are built on it
    # until the fused skeleton replaces it: many more nodes)
    walked_line = build_path_graph_from_arrays(walked(positions, seed=0, sway_m=0.1))
    rows = [["graph", "what", "median ms", "max ms"]]
    for graph_name, pg in (("skeleton", everything), ("walked line", walked_line)):
        edits = edits_on(pg, WALKS + 1)
        older, new = edits[:-1], edits[-1]
        edited = apply_edits(pg, older).path_graph
        check_ms = cpu_ms(lambda: apply_new_edit(edited, new))  # noqa: B023 (used at once)
        all_ms = cpu_ms(lambda: apply_edits(pg, older))  # noqa: B023

        def post() -> None:
            graph = apply_edits(pg, older).path_graph  # noqa: B023
            apply_new_edit(graph, new)  # noqa: B023
            apply_edits(pg, edits)  # noqa: B023

        post_ms = cpu_ms(post)
        label = f"{graph_name} ({pg.graph.number_of_nodes()} nodes)"
        for name, times in (
            ("check and apply a new edit (20 applied before)", check_ms),
            ("apply 20 edits to a new version", all_ms),
            ("a POST in the domain: 20 applied, 1 checked, 21 applied", post_ms),
        ):
            rows.append([label, name, f"{statistics.median(times):.1f}", f"{max(times):.1f}"])
    print("1. Cost, CPU time (target: under 50 ms per edit)\n")
    print(render_markdown_table(rows, justify="left") + "\n")

    # 2. re-anchoring
    first = skeleton(walked(positions[:10], seed=1, sway_m=0.1), tags)
    made = edits_on(first, 20)
    versions = {
        "the same walks again (a rebuild)": skeleton(
            walked(positions[:10], seed=2, sway_m=0.1), tags
        ),
        "a walk added (walks 1–11)": skeleton(walked(positions[:11], seed=3, sway_m=0.1), tags),
        "other walks only (walks 11–20)": skeleton(
            walked(positions[10:], seed=4, sway_m=0.1), tags
        ),
    }
    rows = [["version", "edits", "applied", "not applied, place there", "not applied, place gone"]]
    reasons: dict[str, list[str]] = {}
    for name, pg in versions.items():
        result = apply_edits(pg, made)
        applied = sum(o.applied for o in result.outcomes)
        there = [
            e
            for e, o in zip(made, result.outcomes, strict=True)
            if not o.applied and place_exists(pg, e)
        ]
        gone = len(made) - applied - len(there)
        rows.append([name, str(len(made)), str(applied), str(len(there)), str(gone)])
        reasons[name] = [
            f"{e.op}: {o.reason}"
            for e, o in zip(made, result.outcomes, strict=True)
            if not o.applied
        ]
    print(f"2. Re-anchoring: {len(made)} edits made on walks 1–10\n")
    print(render_markdown_table(rows, justify="left") + "\n")
    for name, listed in reasons.items():
        for reason in listed[:3]:
            print(f"   {name}: {reason}")
    print()

    # 3. how far nodes move
    rows = [["version", "nodes matched", "p50 m", "p95 m", "max m"]]
    for name, pg in versions.items():
        distances = moved_m(first, pg)
        rows.append(
            [
                name,
                f"{len(distances)} of {first.graph.number_of_nodes()}",
                f"{np.percentile(distances, 50):.2f}",
                f"{np.percentile(distances, 95):.2f}",
                f"{max(distances):.2f}",
            ]
        )
    print("3. How far the nodes of walks 1–10 move in the other versions (nearest ≤ 3 m)\n")
    print(render_markdown_table(rows, justify="left"))


if __name__ == "__main__":
    main()
