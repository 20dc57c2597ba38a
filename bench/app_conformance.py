"""Does the iPhone app survive our maps? One command, prints a table and the totals.

    .venv/bin/python bench/app_conformance.py

For each map — every session in ``data/sessions/``, ``data/archive/`` (the app's earlier
format) and ``data/demo/floor_2_pois.json`` (points of interest), app-made variants of a real
session (points of interest with empty and repeated names, as the app's "add location" button
allows), and simulated buildings (two floors joined by stairs, loops, dead ends) — the session is
optimized with the default parameters, its path graph built (the corridor skeleton, as the
worker builds it), and the app-map
(``GET /v1/maps/{id}/app-map``, the same document as ``invisible-map process --app-map``)
checked against the model of the app's decoder and route planner (``app.domain.formats.app_model``):
isolated odometry vertices, and (start vertex, destination) pairs on which the app would crash.
Totals last; the exit status is 1 if any map has either.
"""

from __future__ import annotations

import copy
import json
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from app.domain.errors import InvisibleMapError  # noqa: E402
from app.domain.evaluation.simulate import SimulationConfig, simulate_session  # noqa: E402
from app.domain.formats.app_model import ConformanceReport, check_app_map  # noqa: E402
from app.domain.formats.map_io import app_map_as_served  # noqa: E402
from app.domain.mapping.slam import optimize_session  # noqa: E402
from app.domain.navigation.skeleton import build_skeleton  # noqa: E402
from app.domain.upload.session import parse_session, read_json_document  # noqa: E402

DATA = REPO / "data"
#: Simulated buildings: name → config (10 Hz poses).
SIMULATED = {
    "sim_two_floors": SimulationConfig(num_poses=3000, two_floors=True, seed=1),
    "sim_loops_3x2": SimulationConfig(num_poses=3000, blocks=(3, 2), seed=2),
    "sim_dead_ends": SimulationConfig(
        num_poses=1500, blocks=(3, 1), num_points_of_interest=8, seed=3
    ),
}


def app_made_variants(upload: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """Uploads the app really makes from a walk: points of interest with an empty name and with
    a repeated name (the "add location" button checks neither), and an empty ``map_id``."""
    pose_ids = [pose["id"] for pose in upload["pose_data"]]
    placed = [pose_ids[len(pose_ids) * k // 5] + 1 for k in range(1, 5)]
    identity = [1.0, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]

    def location(name: str, pose_id: int) -> dict[str, Any]:
        return {"name": name, "pose_id": pose_id, "timestamp": 0.0, "transform": identity}

    named = copy.deepcopy(upload)
    named["map_id"] = ""
    named["location_data"] = [
        location("", placed[0]),
        location("Kitchen", placed[1]),
        location("Kitchen", placed[2]),
        location("  ", placed[3]),
    ]
    return {"pois_empty_and_repeated_names": named}


def uploads() -> Iterator[tuple[str, Callable[[], Any]]]:
    """(name, a function returning the upload) for every map the benchmark checks."""
    for path in sorted((DATA / "sessions").glob("*.json")):
        yield path.stem, lambda path=path: read_json_document(path)
    for path in sorted((DATA / "archive").glob("*.json")):
        yield f"archive/{path.stem}", lambda path=path: read_json_document(path)
    demo = DATA / "demo" / "floor_2_pois.json"
    yield "demo/floor_2_pois", lambda: read_json_document(demo)
    occam = read_json_document(DATA / "sessions" / "occam_room.json")
    for variant, upload in app_made_variants(occam).items():
        yield f"occam_room+{variant}", lambda upload=upload: upload
    for name, config in SIMULATED.items():
        yield name, lambda config=config: simulate_session(config).upload


def app_map_of(upload: Any) -> dict[str, Any]:
    """The app-map the server serves for ``upload``'s first version (default parameters)."""
    result = optimize_session(parse_session(upload))
    return app_map_as_served(result, path_graph=build_skeleton(result))


def main() -> int:
    rows: list[tuple[str, ConformanceReport | str, float]] = []
    notes: dict[str, list[str]] = {}
    for name, make in uploads():
        started_s = time.perf_counter()
        try:
            text = json.dumps(app_map_of(make()), separators=(",", ":"), allow_nan=False)
        except InvisibleMapError as err:
            rows.append((name, f"not a map: {err}", time.perf_counter() - started_s))
            continue
        document = json.loads(text)
        notes[name] = [f"{len(text) / 2**20:.2f} MiB", *document.get("notes", [])]
        rows.append((name, check_app_map(document), time.perf_counter() - started_s))
    width = max(len(name) for name, _, _ in rows)
    print(
        f"{'map':<{width}}  {'vertices':>8}  {'isolated':>8}  {'parts':>5}  "
        f"{'crashing pairs':>20}  {'s':>5}  notes"
    )
    maps = isolated = crashing = pairs = 0
    for name, report, seconds in rows:
        if isinstance(report, str):
            print(f"{name:<{width}}  {'':>8}  {'':>8}  {'':>5}  {'':>20}  {seconds:5.1f}  {report}")
            continue
        maps += 1
        isolated += len(report.isolated_vertices)
        crashing += report.crashing_pairs
        pairs += report.pairs
        share = f"{report.crashing_pairs}/{report.pairs}"
        said = [*notes[name], report.decode_error or "; ".join(report.traps[:1])]
        if report.unreachable_waypoints:
            said.append(f"waypoints shadowed: {', '.join(report.unreachable_waypoints)}")
        print(
            f"{name:<{width}}  {report.vertices:>8}  {len(report.isolated_vertices):>8}  "
            f"{report.components:>5}  {share:>20}  {seconds:5.1f}  {'; '.join(filter(None, said))}"
        )
    percent = 100.0 * crashing / pairs if pairs else 0.0
    print(
        f"\n{maps} maps checked: {isolated} isolated vertices, "
        f"{crashing}/{pairs} crashing (start, destination) pairs ({percent:.1f}%)"
    )
    return 0 if isolated == 0 and crashing == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
