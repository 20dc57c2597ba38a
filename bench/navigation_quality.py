"""Turn-by-turn quality on real maps (issue 18): before (walked-line path graph, old steps) →
after (corridor skeleton, decision-point instructions), against ``bench.mac_floor_2_reference``.

    .venv/bin/python -m bench.navigation_quality        # (also printed by bench.navigation)

Each floor-2 map is optimized with default parameters and moved into the ground truth's frame by a
rigid fit on its tags (so both graphs and the reference share a frame); every ordered pair of its
tags that the reference knows is routed.
"""

from __future__ import annotations

import itertools
import math
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from app.cli.tables import render_markdown_table  # noqa: E402
from app.domain.evaluation.ground_truth import load_ground_truth  # noqa: E402
from app.domain.evaluation.metrics import umeyama_rigid  # noqa: E402
from app.domain.evaluation.turn_metrics import RouteScore, agreement, score_tag_routes  # noqa: E402
from app.domain.mapping.params import SlamParams  # noqa: E402
from app.domain.mapping.slam import optimize_session  # noqa: E402
from app.domain.navigation.instructions import plan_guided_route  # noqa: E402
from app.domain.navigation.path_graph import (  # noqa: E402
    JUNCTION,
    WALK,
    PathGraph,
    build_path_graph_from_arrays,
)
from app.domain.navigation.routing import plan_route  # noqa: E402
from app.domain.navigation.skeleton import build_skeleton_from_arrays  # noqa: E402
from app.domain.upload.session import load_session  # noqa: E402
from bench.mac_floor_2_reference import (  # noqa: E402
    FLOOR_2_Y_M,
    branch_points_xz,
    reference_graph,
)

SESSIONS = REPO / "data" / "sessions"
GROUND_TRUTH = REPO / "data" / "ground_truth" / "rtabmap_mac_1_2.txt"
FLOOR_2 = ("floor_2_straight", "desnat_straight_once", "straight_209_occam")
#: A skeleton junction this close (x–z, m) to a reference branch point is a real one.
JUNCTION_NEAR_M = 3.0
#: Poses within this height of floor 2 are on it, m.
FLOOR_2_BAND_M = 1.5
#: Reference corridor within this (x–z, m) of a walked pose is covered by the walk.
COVERED_WITHIN_M = 2.0


@dataclass(frozen=True, slots=True, kw_only=True)
class AlignedMap:
    """A map's poses and tags in the ground truth's frame."""

    name: str
    positions_m: np.ndarray
    tag_ids: list[int]
    tag_positions_m: np.ndarray


def aligned_map(name: str, gt: dict[int, np.ndarray]) -> AlignedMap:
    result = optimize_session(
        load_session(SESSIONS / f"{name}.json"), SlamParams(compute_marginals=False)
    )
    ids = [int(t) for t in result.tag_ids]
    common = [t for t in ids if t in gt]
    source = np.array([result.world_T_tag[ids.index(t)][:3, 3] for t in common])
    target = np.array([gt[t][:3, 3] for t in common])
    gt_T_world = umeyama_rigid(source, target)

    def move(p: np.ndarray) -> np.ndarray:
        return np.asarray(p @ gt_T_world[:3, :3].T + gt_T_world[:3, 3])

    return AlignedMap(
        name=name,
        positions_m=move(result.world_T_phone[:, :3, 3]),
        tag_ids=ids,
        tag_positions_m=move(result.world_T_tag[:, :3, 3]),
    )


def graphs(m: AlignedMap) -> dict[str, PathGraph]:
    kwargs = {"tag_ids": m.tag_ids, "tag_positions_m": m.tag_positions_m}
    return {
        "before": build_path_graph_from_arrays(m.positions_m, **kwargs),  # type: ignore[arg-type]
        "after": build_skeleton_from_arrays(m.positions_m, **kwargs),  # type: ignore[arg-type]
    }


def floor_2_index(pg: PathGraph) -> int:
    """The index of floor 2 (the level nearest the reference's height) in ``pg``."""
    levels = np.asarray(pg.floor_levels_m)
    return int(np.argmin(np.abs(levels - FLOOR_2_Y_M))) if levels.size else 0


def walk_length_m(pg: PathGraph) -> float:
    """Length of the walk edges on floor 2, m."""
    G, floor = pg.graph, floor_2_index(pg)
    return float(
        sum(
            d["length_m"]
            for _, _, d in G.edges(data=True)
            if d["kind"] == WALK and d["floor"] == floor
        )
    )


def covered_reference_m(reference: PathGraph, positions_m: np.ndarray) -> float:
    """Length of the reference within ``COVERED_WITHIN_M`` of the walk (what the map can know)."""
    G = reference.graph
    on_floor = np.abs(positions_m[:, 1] - FLOOR_2_Y_M) < FLOOR_2_BAND_M
    walk_xz = positions_m[on_floor][:, [0, 2]]
    covered = 0.0
    for u, v in G.edges:
        a = np.asarray(G.nodes[u]["position_m"])[[0, 2]]
        b = np.asarray(G.nodes[v]["position_m"])[[0, 2]]
        length = float(np.linalg.norm(b - a))
        pieces = max(1, math.ceil(length / 0.25))
        t = (np.arange(pieces) + 0.5) / pieces
        samples = a + t[:, None] * (b - a)
        near = np.min(np.linalg.norm(samples[:, None, :] - walk_xz[None], axis=2), axis=1)
        covered += length * float(np.mean(near <= COVERED_WITHIN_M))
    return covered


def junction_stats(pg: PathGraph) -> tuple[int, float]:
    """(junctions, share within ``JUNCTION_NEAR_M`` of a reference branch point)."""
    G, floor = pg.graph, floor_2_index(pg)
    junctions = [
        np.asarray(G.nodes[n]["position_m"])[[0, 2]]
        for n in G.nodes
        if G.nodes[n]["kind"] == JUNCTION and G.nodes[n]["floor"] == floor
    ]
    branches = np.array(branch_points_xz())
    near = [
        float(np.min(np.linalg.norm(branches - j, axis=1))) <= JUNCTION_NEAR_M for j in junctions
    ]
    return len(junctions), (sum(near) / len(near) if near else 1.0)


PLANNERS: dict[str, Callable[..., object]] = {"before": plan_route, "after": plan_guided_route}


def quality_table() -> str:
    gt = load_ground_truth(GROUND_TRUTH)
    gt_xyz = {t: tuple(float(v) for v in p[:3, 3]) for t, p in gt.items()}
    reference = reference_graph(gt_xyz)  # type: ignore[arg-type]
    scores: dict[tuple[str, str], RouteScore] = {}
    rows = [
        [
            "map",
            "graph",
            "routes",
            "turns told",
            "real",
            "precision",
            "recall",
            "zigzag",
            "turn-around",
            "length / ref",
            "junctions",
            "near branch",
            "route p90 / ref",
        ]
    ]
    for name in FLOOR_2:
        m = aligned_map(name, gt)
        tags = [t for t in m.tag_ids if t in reference.tags]
        pairs = list(itertools.permutations(tags, 2))
        covered_m = covered_reference_m(reference, m.positions_m)
        for label, pg in graphs(m).items():
            score = score_tag_routes(pg, reference, pairs, plan=PLANNERS[label])  # type: ignore[arg-type]
            scores[(name, label)] = score
            junctions, near = junction_stats(pg)
            rows.append(
                [
                    name,
                    label,
                    str(score.routes),
                    str(score.announced),
                    str(score.real),
                    f"{score.precision:.0%}",
                    f"{score.recall:.0%}",
                    f"{score.zigzag_share:.0%}",
                    f"{score.turn_around_share:.0%}",
                    f"{walk_length_m(pg) / covered_m:.2f}",
                    str(junctions),
                    f"{near:.0%}",
                    f"{score.length_ratio_p90:.2f}",
                ]
            )
    table = render_markdown_table(rows, justify="right")
    agree = [
        f"{a} / {b}: "
        + " → ".join(
            f"{agreement(scores[(a, g)], scores[(b, g)]):.0%}" for g in ("before", "after")
        )
        for a, b in itertools.combinations(FLOOR_2, 2)
    ]
    return (
        f"{table}\n\nsame turns announced by two maps of the floor (tag pairs in both), "
        f"before → after: {'; '.join(agree)}\n"
        f"reference: {walk_length_m(reference):.0f} m of corridor, "
        f"{len(branch_points_xz())} branch points, {len(reference.tags)} tags"
    )


def main() -> int:
    print("turn-by-turn on floor 2 of the mac building, before → after")
    print(quality_table())
    return 0


if __name__ == "__main__":
    sys.exit(main())
