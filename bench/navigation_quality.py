"""Turn-by-turn quality on real maps of floor 2 of the mac building, single walks and building maps
(issues 18 and 26), against the hand-drawn reference ``bench.mac_floor_2_reference``.

    .venv/bin/python -m bench.navigation_quality        # (also printed by bench.navigation)
    .venv/bin/python -m bench.navigation_quality --plot /tmp/floor2   # and a PNG per map

Each map is optimized with default parameters (a building map of several walks by the joint
optimizer, ``optimize_sessions``) and moved into the ground truth's frame by a rigid fit on its
tags, so that its skeleton and the reference share a frame; every ordered pair of its tags that
the reference knows is routed. A building map's skeleton is fused from all its walks
(``build_skeleton(…, walk_starts=…)``).
"""

from __future__ import annotations

import argparse
import itertools
import math
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cache
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from app.cli.tables import render_markdown_table  # noqa: E402
from app.domain.evaluation.ground_truth import load_ground_truth  # noqa: E402
from app.domain.evaluation.metrics import umeyama_rigid  # noqa: E402
from app.domain.evaluation.turn_metrics import (  # noqa: E402
    END_BAND_M,
    RouteScore,
    Turn,
    announced_turns,
    leaning_toward,
    match_turns,
    reference_turns,
    score_tag_routes,
)
from app.domain.mapping.joint import optimize_sessions  # noqa: E402
from app.domain.mapping.params import SlamParams  # noqa: E402
from app.domain.mapping.slam import optimize_session  # noqa: E402
from app.domain.navigation.instructions import (  # noqa: E402
    BEAR_MIN_DEG,
    END_MARGIN_M,
    TURN_MIN_DEG,
    plan_guided_route,
)
from app.domain.navigation.path_graph import JUNCTION, WALK, PathGraph  # noqa: E402
from app.domain.navigation.routing import RouteError, TagEnd, plan_walk  # noqa: E402
from app.domain.navigation.skeleton import (  # noqa: E402
    DEFAULT_SKELETON_PARAMS,
    SkeletonParams,
    build_skeleton_from_arrays,
)
from app.domain.upload.session import load_session  # noqa: E402
from bench.mac_floor_2_reference import (  # noqa: E402
    FLOOR_2_Y_M,
    branch_points_xz,
    reference_graph,
)

SESSIONS = REPO / "data" / "sessions"
GROUND_TRUTH = REPO / "data" / "ground_truth" / "rtabmap_mac_1_2.txt"
FLOOR_2 = ("floor_2_straight", "desnat_straight_once", "straight_209_occam")
#: The maps scored: each walk alone, and building maps of several (walks in upload order).
MAPS: tuple[tuple[str, ...], ...] = (
    ("floor_2_straight",),
    ("desnat_straight_once",),
    ("straight_209_occam",),
    ("desnat_straight_once", "straight_209_occam"),
    ("floor_2_straight", "desnat_straight_once"),
    ("floor_2_straight", "desnat_straight_once", "straight_209_occam"),
)
#: A skeleton junction this close (x–z, m) to a reference branch point is a real one.
JUNCTION_NEAR_M = 3.0
#: Poses within this height of floor 2 are on it, m.
FLOOR_2_BAND_M = 1.5
#: Reference corridor within this (x–z, m) of a walked pose is covered by the walk.
COVERED_WITHIN_M = 2.0


@dataclass(frozen=True, slots=True, kw_only=True)
class AlignedMap:
    """A map's poses and tags in one frame (``tag_normals``: each tag's +z, out of its wall);
    ``walk_starts``: the first pose row of each walk."""

    name: str
    positions_m: np.ndarray
    tag_ids: list[int]
    tag_positions_m: np.ndarray
    tag_normals: np.ndarray
    walk_starts: tuple[int, ...] = (0,)


def map_name(walks: Sequence[str]) -> str:
    return " + ".join(walks)


@cache
def own_frame_map(walks: tuple[str, ...]) -> AlignedMap:
    """The map of ``walks`` (one: ``optimize_session``; several: the joint optimizer) in its own
    frame."""
    sessions = [load_session(SESSIONS / f"{name}.json") for name in walks]
    params = SlamParams(compute_marginals=False)
    if len(walks) == 1:
        result, starts = optimize_session(sessions[0], params), (0,)
    else:
        joint = optimize_sessions(sessions, params, names=list(walks))
        result, starts = joint.map, tuple(p.pose_rows.start for p in joint.parts)
    return AlignedMap(
        name=map_name(walks),
        positions_m=result.world_T_phone[:, :3, 3],
        tag_ids=[int(t) for t in result.tag_ids],
        tag_positions_m=result.world_T_tag[:, :3, 3],
        tag_normals=result.world_T_tag[:, :3, 2],
        walk_starts=starts,
    )


def moved_onto(m: AlignedMap, target: dict[int, np.ndarray]) -> AlignedMap:
    """``m`` moved by the rigid transform that best fits its tags onto ``target``'s (tag id →
    (3,) position): the tags both hold give it."""
    common = [t for t in m.tag_ids if t in target]
    source = np.array([m.tag_positions_m[m.tag_ids.index(t)] for t in common])
    target_T_source = umeyama_rigid(source, np.array([target[t] for t in common]))

    def move(p: np.ndarray) -> np.ndarray:
        return np.asarray(p @ target_T_source[:3, :3].T + target_T_source[:3, 3])

    return AlignedMap(
        name=m.name,
        positions_m=move(m.positions_m),
        tag_ids=m.tag_ids,
        tag_positions_m=move(m.tag_positions_m),
        tag_normals=m.tag_normals @ target_T_source[:3, :3].T,
        walk_starts=m.walk_starts,
    )


def tag_positions(m: AlignedMap) -> dict[int, np.ndarray]:
    return {t: m.tag_positions_m[k] for k, t in enumerate(m.tag_ids)}


@cache
def ground_truth_xyz() -> dict[int, np.ndarray]:
    return {t: p[:3, 3] for t, p in load_ground_truth(GROUND_TRUTH).items()}


def aligned_map(walks: tuple[str, ...]) -> AlignedMap:
    """The map of ``walks`` in the ground truth's frame."""
    return moved_onto(own_frame_map(walks), ground_truth_xyz())


def skeleton(
    m: AlignedMap, params: SkeletonParams = DEFAULT_SKELETON_PARAMS, *, with_normals: bool = True
) -> PathGraph:
    return build_skeleton_from_arrays(
        m.positions_m,
        walk_starts=m.walk_starts,
        tag_ids=m.tag_ids,
        tag_positions_m=m.tag_positions_m,
        tag_normals=m.tag_normals if with_normals else None,
        params=params,
    )


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


@cache
def reference() -> PathGraph:
    gt = {t: tuple(float(v) for v in p) for t, p in ground_truth_xyz().items()}
    return reference_graph(gt)  # type: ignore[arg-type]


def score_map(m: AlignedMap, pg: PathGraph) -> RouteScore:
    tags = [t for t in m.tag_ids if t in reference().tags]
    return score_tag_routes(
        pg, reference(), list(itertools.permutations(tags, 2)), plan=plan_guided_route
    )


QUALITY_HEADER = [
    "map",
    "walks",
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


def quality_rows(walks: str, m: AlignedMap, pg: PathGraph) -> list[str]:
    score = score_map(m, pg)
    junctions, near = junction_stats(pg)
    covered_m = covered_reference_m(reference(), m.positions_m)
    return [
        m.name,
        walks,
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


def quality_table() -> str:
    """Table 1: every map of ``MAPS``."""
    rows = [QUALITY_HEADER]
    for walks in MAPS:
        m = aligned_map(walks)
        rows.append(quality_rows(str(len(m.walk_starts)), m, skeleton(m)))
    table = render_markdown_table(rows, justify="right")
    return (
        f"{table}\n\nreference: {walk_length_m(reference()):.0f} m of corridor, "
        f"{len(branch_points_xz())} branch points, {len(reference().tags)} tags"
    )


def wrong_turns(m: AlignedMap, pg: PathGraph) -> tuple[list[Turn], list[Turn]]:
    """(told turns that are not real, real turns not told) over every routed tag pair, as
    ``score_tag_routes`` counts them."""
    ref = reference()
    false, missed = [], []
    tags = [t for t in m.tag_ids if t in ref.tags]
    for a, b in itertools.permutations(tags, 2):
        try:
            route = plan_guided_route(pg, TagEnd(a), TagEnd(b))
            truth = plan_walk(leaning_toward(ref, route), TagEnd(a), TagEnd(b))
        except RouteError:
            continue
        bends = reference_turns(ref, truth, min_deg=BEAR_MIN_DEG, end_margin_m=0.0)
        real = reference_turns(
            ref, truth, min_deg=TURN_MIN_DEG, end_margin_m=END_MARGIN_M + END_BAND_M
        )
        told = announced_turns(route)
        false += [t for t in told if match_turns([t], bends)[0] == 0]
        told_any = announced_turns(route, min_deg=BEAR_MIN_DEG)
        missed += [t for t in real if match_turns(told_any, [t])[1] == 0]
    return false, missed


def plot_map(m: AlignedMap, pg: PathGraph, path: Path) -> None:
    """A top-down PNG of floor 2: the walks (grey), the skeleton (blue, junctions as dots), the
    reference (green, dashed), the tags, and where routes tell a false turn (red) or miss a real
    one (orange)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 9))
    on_floor = np.abs(m.positions_m[:, 1] - FLOOR_2_Y_M) < FLOOR_2_BAND_M
    for first, end in itertools.pairwise([*m.walk_starts, len(m.positions_m)]):
        walk = m.positions_m[first:end][on_floor[first:end]]
        ax.plot(walk[:, 0], walk[:, 2], color="0.7", lw=0.4)
    G, floor = pg.graph, floor_2_index(pg)
    for u, v, data in G.edges(data=True):
        if data["floor"] == floor and data["kind"] == WALK:
            a, b = G.nodes[u]["position_m"], G.nodes[v]["position_m"]
            ax.plot([a[0], b[0]], [a[2], b[2]], color="tab:blue", lw=1.6)
    for _, data in G.nodes(data=True):
        if data["kind"] == JUNCTION and data["floor"] == floor:
            ax.plot(data["position_m"][0], data["position_m"][2], "o", color="tab:blue")
    R = reference().graph
    for u, v in R.edges:
        a, b = R.nodes[u]["position_m"], R.nodes[v]["position_m"]
        ax.plot([a[0], b[0]], [a[2], b[2]], color="tab:green", lw=0.9, ls="--")
    for k, t in enumerate(m.tag_ids):
        if t in reference().tags:
            x, _, z = m.tag_positions_m[k]
            ax.plot(x, z, "k^", ms=3)
            ax.annotate(str(t), (x, z), fontsize=6)
    false, missed = wrong_turns(m, pg)
    for turns, colour, label in (
        (false, "tab:red", "false turn"),
        (missed, "tab:orange", "missed"),
    ):
        if turns:
            xz = np.array([t.position_xz_m for t in turns])
            ax.scatter(
                xz[:, 0], xz[:, 1], s=30, color=colour, alpha=0.3, label=f"{label} ×{len(turns)}"
            )
    ax.set_aspect("equal")
    ax.set_xlabel("x, m")
    ax.set_ylabel("z, m")
    ax.set_title(f"{m.name}\nskeleton (blue), reference (green)", fontsize=8)
    if false or missed:
        ax.legend(fontsize=7)
    fig.savefig(path, dpi=90, bbox_inches="tight")
    plt.close(fig)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--plot", type=Path, help="write a PNG of each map's floor 2 here")
    args = parser.parse_args(argv)
    print("turn-by-turn on floor 2 of the mac building (single walks and building maps)")
    print(quality_table())
    if args.plot is not None:
        args.plot.mkdir(parents=True, exist_ok=True)
        for walks in MAPS:
            m = aligned_map(walks)
            path = args.plot / f"{'+'.join(walks)}.png"
            plot_map(m, skeleton(m), path)
            print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
