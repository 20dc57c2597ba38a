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

4. **At scale** (``--scale``, alone: ``.venv/bin/python -m bench.corridor_edits --scale``, ~2
   min): the real floor_2_straight map built by the worker (SQLite, the API in process), with
   100, 1,000, 5,000 and 10,000 edits stored (quiets, moves, points of interest), CPU time of a
   POST of one more edit, the first route after it, a GET of the list (its first page, and its
   size), median of 5; and the first route after a delete, when every edit is applied again (what
   a new version, a restart and another API process pay once), median of 3. Before issue 39
   (each POST applied every edit twice and the list came whole) it measured
   :data:`BEFORE_SCALE`.
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


# --------------------------------------------------------------------------- 4. at scale

#: Table 4 before issue 39 (commit before it, same machine, CPU ms; the delete column did not
#: exist): edits on the map, add one edit, first route after it, the list (whole), its KB.
BEFORE_SCALE = (
    ("100", "42.1", "33.3", "19.9", "29"),
    ("1,000", "228.0", "141.7", "102.3", "272"),
    ("10,000", "7474.9", "4485.0", "1390.2", "2,723"),
)
#: How many edits a map has already in table 4.
SCALE_COUNTS = (100, 1_000, 5_000, 10_000)
#: Rounds of (add one edit, first route after it, list page) per count in table 4.
SCALE_ROUNDS = 5


def scale_edits(pg: PathGraph, count: int, start: int) -> list[dict[str, object]]:
    """``count`` edits of the kinds an operator makes (quiets, moves by 0 m, points of interest),
    spread over the graph's nodes, numbered from ``start``: each one applies."""
    nodes = sorted(pg.graph.nodes)
    documents: list[dict[str, object]] = []
    for k in range(start, start + count):
        p = [float(v) for v in pg.graph.nodes[nodes[(k * 7919) % len(nodes)]]["position_m"]]
        match k % 3:
            case 0:
                documents.append({"op": "quiet", "at": p})
            case 1:
                documents.append({"op": "move_node", "from": p, "to": p})
            case _:
                documents.append({"op": "add_poi", "name": f"Bench {k}", "at": p})
    return documents


def at_scale() -> list[list[str]]:
    """Table 4: on the real floor_2_straight map (built by the worker, SQLite), with 100, 1,000
    and 10,000 edits already stored: CPU time of a POST of one more edit, of the first route
    after it, and of a GET of the edits' list (its first page), through the API in process."""
    import tempfile

    from app.config import Settings
    from app.services.navigation import version_path_graph
    from app.storage import maps as map_storage
    from app.storage.db import Database
    from app.storage.migrate import upgrade_to_head
    from app.storage.orm import CorridorEditRow, MapRow, utc_now
    from tests.service.api_support import ADMIN, running_api
    from tests.service.test_api_navigation import build, floor_2_with_pois

    rows = [
        [
            "edits on the map",
            "add one edit ms",
            "first route after it ms",
            "list page ms",
            "list page KB",
            "first route after a delete ms",
        ]
    ]
    with tempfile.TemporaryDirectory() as folder:
        url = f"sqlite:///{folder}/bench.sqlite3"
        database = Database(url)
        upgrade_to_head(database)
        database.dispose()
        # room for the edits (a setting the code before the cap does not have)
        settings = (
            {"max_corridor_edits": max(SCALE_COUNTS) + 1_000}
            if "max_corridor_edits" in Settings.model_fields
            else {}
        )
        with running_api(url, **settings) as api:
            map_id = api.uploaded(floor_2_with_pois())["map_id"]
            build(api)
            with api.db.read() as db_session:
                version = map_storage.get_map(db_session, map_id).current
                assert version is not None
                pg = version_path_graph(api.app.state.version_cache, db_session, version)
            stored = 0
            for count in SCALE_COUNTS:
                with api.db.transaction() as db_session:  # the edits, stored straight
                    for document in scale_edits(pg, count - stored, stored):
                        db_session.add(
                            CorridorEditRow(
                                map_id=map_id,
                                edit=document,
                                created_by="env-admin",
                                created_by_name=None,
                                created_at=utc_now(),
                            )
                        )
                    row = db_session.get(MapRow, map_id)
                    assert row is not None
                    row.corridor_edits_revision += 1
                stored = count
                listing = api.client.get(f"/v1/maps/{map_id}/corridor-edits", headers=ADMIN)
                assert listing.status_code == 200, listing.text  # the edits applied once
                times: dict[str, list[float]] = {"add": [], "route": [], "list": []}
                page_bytes = 0
                for k in range(SCALE_ROUNDS):
                    at = [float(v) for v in pg.graph.nodes[sorted(pg.graph.nodes)[k]]["position_m"]]
                    edit = {"op": "add_poi", "name": f"New {count} {k}", "at": at}
                    for name, call in (
                        (
                            "add",
                            lambda edit=edit: api.client.post(
                                f"/v1/maps/{map_id}/corridor-edits", json=edit, headers=ADMIN
                            ),
                        ),
                        (
                            "route",
                            lambda: api.client.post(
                                f"/v1/maps/{map_id}/routes",
                                json={"from": {"tag": 300}, "to": {"tag": 324}},
                                headers=ADMIN,
                            ),
                        ),
                        (
                            "list",
                            lambda: api.client.get(
                                f"/v1/maps/{map_id}/corridor-edits", headers=ADMIN
                            ),
                        ),
                    ):
                        begin = time.process_time()
                        response = call()
                        times[name].append((time.process_time() - begin) * 1000)
                        assert response.status_code in (200, 201), response.text
                        if name == "list":
                            page_bytes = len(response.content)
                    stored += 1
                # a delete: every edit applied again (what a new version and another process pay)
                after_delete_ms = []
                for item in listing.json()["data"][:3]:
                    assert api.client.delete(
                        f"/v1/maps/{map_id}/corridor-edits/{item['id']}", headers=ADMIN
                    ).is_success
                    stored -= 1
                    begin = time.process_time()
                    response = api.client.post(
                        f"/v1/maps/{map_id}/routes",
                        json={"from": {"tag": 300}, "to": {"tag": 324}},
                        headers=ADMIN,
                    )
                    after_delete_ms.append((time.process_time() - begin) * 1000)
                    assert response.status_code == 200, response.text
                rows.append(
                    [
                        f"{count:,}",
                        *(f"{statistics.median(times[n]):.1f}" for n in ("add", "route", "list")),
                        f"{page_bytes / 1000:,.0f}",
                        f"{statistics.median(after_delete_ms):.0f}",
                    ]
                )
    return rows


if __name__ == "__main__":
    if "--scale" in sys.argv[1:]:
        print("4. At scale, before issue 39 (CPU ms)\n")
        header = ["edits on the map", "add one edit ms", "first route after it ms", "list ms"]
        print(render_markdown_table([[*header, "list KB"], *map(list, BEFORE_SCALE)]) + "\n")
        print("4. At scale, now (CPU ms, median of 5)\n")
        print(render_markdown_table(at_scale(), justify="left"))
    else:
        main()
