"""Do walkers arrive? A simulated blind walker (``app.domain.evaluation.walker``) follows the spoken
steps of routes between tags through the *true* building (issue 39; DESIGN §10).

    .venv/bin/python -m bench.walker                       # both tables, every failure, ~1 min
    .venv/bin/python -m bench.walker --before              # the skeleton before issue 39
    .venv/bin/python -m bench.walker --from-tag            # routes from the start tag's node
    .venv/bin/python -m bench.walker --plot /tmp/walker    # … and a PNG of each map's failures
    .venv/bin/python -m bench.walker --quick               # seed 0 only, fewer routes

Maps (each a corridor skeleton as the worker builds it; the walker never sees it, only the steps):

- **Real floor 2** of the mac building: the building map of the three shipped walks (and
  floor_2_straight alone), in the ground truth's frame (``bench.navigation_quality``); the true
  building is the hand-drawn reference's corridors (``bench.mac_floor_2_reference``: centrelines,
  here widened by ``REAL_HALF_WIDTH_M``; floor 2's facing tags are 2.8–3.8 m apart). A tag more
  than ``arrive_within_m`` from those corridors cannot be arrived at in them and is left out.
- **Simulated buildings** with hooks, alcoves and oblique visits (``NookConfig()``;
  ``UNSEEN_BUILDING``, one and two floors, seeds 0–3): the building map of walks 1–3 of
  ``bench.agreement``'s six walkers; the true building is its free-space boxes and stairs.

The walker starts 0.5 m in front of the start tag, facing it. The app sees that tag, so it plans
from the phone's position (``PositionEnd``: the walker's true offset from the tag, put on the
map's tag; ``--from-tag`` plans from the tag's node as before) with the phone's heading, and the
first step turns the walker to face the way. It must end within 2 m of the goal tag, with no
turn-around told. Its errors are ``WalkerErrors()``: ±15° per turn, ±10% per leg, a trailing hand
before each turn. Each route is walked twice from the same start with the same errors (its own
seed): on the steps alone, and with the app's corrections (``walker_app.TagCorrections``: a tag
in the phone's view that shows the walker more than 3 m off its route, or any tag it sees when
lost, routes it again); both tables are printed, with every failure.
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import math
import re
import sys
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from app.cli.tables import render_markdown_table  # noqa: E402
from app.domain.evaluation.ground_truth import load_ground_truth  # noqa: E402
from app.domain.evaluation.simulate import UNSEEN_BUILDING, fused_skeleton  # noqa: E402
from app.domain.evaluation.simulate_building import NookConfig, nook_walks  # noqa: E402
from app.domain.evaluation.walker import (  # noqa: E402
    DEFAULT_WALKER,
    BoxFreeSpace,
    CapsuleFreeSpace,
    FreeSpace,
    Start,
    WalkOutcome,
    walk_steps,
)
from app.domain.evaluation.walker_app import SeenTag, TagCorrections  # noqa: E402
from app.domain.frames import FloatArray  # noqa: E402
from app.domain.navigation.instructions import plan_guided_route  # noqa: E402
from app.domain.navigation.path_graph import PathGraph  # noqa: E402
from app.domain.navigation.routing import Endpoint, PositionEnd, RouteError, TagEnd  # noqa: E402
from app.domain.navigation.skeleton import DEFAULT_SKELETON_PARAMS, SkeletonParams  # noqa: E402
from bench.agreement import WALKERS  # noqa: E402
from bench.mac_floor_2_reference import MAIN, SPURS  # noqa: E402
from bench.navigation import BEFORE_ISSUE_39, sampled_pairs  # noqa: E402
from bench.navigation_quality import GROUND_TRUTH, aligned_map, skeleton  # noqa: E402

#: Half the width of floor 2's corridors around the reference's centrelines, m.
REAL_HALF_WIDTH_M = 1.6
#: The real building maps walked.
REAL_MAPS: tuple[tuple[str, ...], ...] = (
    ("floor_2_straight",),
    ("floor_2_straight", "desnat_straight_once", "straight_209_occam"),
)
#: Simulated buildings: label → config; seeds.
SIMULATED = {
    "one floor": UNSEEN_BUILDING,
    "two floors": dataclasses.replace(UNSEEN_BUILDING, two_floors=True),
}
SEEDS = (0, 1, 2, 3)
#: Routes per map (sampled tag pairs).
ROUTES = 150
#: Route length bins, m.
LENGTH_BINS_M = (0.0, 15.0, 30.0, 60.0, math.inf)
#: The walker stands this far in front of the start tag, m.
START_OFF_WALL_M = 0.5
#: The two ways each route is walked.
ALONE = "steps alone"
HELPED = "with the app's corrections"


@dataclass(frozen=True, slots=True, kw_only=True)
class Tag:
    """A tag's true place: position (x, y, z) and +z (out of its wall), m; its floor."""

    position_m: FloatArray
    normal: FloatArray
    floor: int


@dataclass(frozen=True, slots=True, kw_only=True)
class Walked:
    """One route walked: its tags, length, outcome."""

    start: int
    goal: int
    length_m: float
    outcome: WalkOutcome


def start_at(tag: Tag, space: FreeSpace) -> Start:
    """0.5 m in front of the tag, facing it (or the nearest free point toward the tag's front)."""
    n = tag.normal[[0, 2]]
    n = n / max(float(np.linalg.norm(n)), 1e-12)
    p = tag.position_m[[0, 2]]
    for off_m in np.arange(START_OFF_WALL_M, 4.01, 0.1):
        xz = p + off_m * n
        if space.contains(xz[None, :], tag.floor)[0]:
            break
    facing = -n
    return Start(
        xz=(float(xz[0]), float(xz[1])),
        heading_rad=math.atan2(-facing[0], -facing[1]),
        floor=tag.floor,
    )


def walk_routes(
    pg: PathGraph,
    space: FreeSpace,
    tags: dict[int, Tag],
    pairs: Sequence[tuple[int, int]],
    *,
    seen: Sequence[SeenTag] = (),
    from_tag: bool = False,
) -> tuple[list[Walked], list[Walked]]:
    """Each route walked twice from the same start with the same errors: on its steps alone,
    and with the app's corrections (``seen``: the tags the phone can see)."""
    alone, helped = [], []
    for a, b in pairs:
        start = start_at(tags[a], space)
        goal = tags[b]
        origin: Endpoint = TagEnd(a)
        if not from_tag:  # the app plans from where it sees the phone: in front of tag a
            mapped = np.asarray(pg.tags[a].position_m, dtype=np.float64)
            x, z = np.asarray(start.xz) + (mapped[[0, 2]] - tags[a].position_m[[0, 2]])
            origin = PositionEnd((float(x), float(mapped[1]), float(z)))
        try:
            route = plan_guided_route(pg, origin, TagEnd(b), heading_rad=start.heading_rad)
        except RouteError:
            continue
        for out, app in ((alone, None), (helped, seen)):
            outcome = walk_steps(
                route.steps,
                space,
                start,
                goal_xz=(float(goal.position_m[0]), float(goal.position_m[2])),
                goal_floor=goal.floor,
                rng=np.random.default_rng([a, b]),
                errors=DEFAULT_WALKER,
                app=None
                if app is None
                else TagCorrections(pg, space, app, goal=TagEnd(b), route=route),
            )
            out.append(Walked(start=a, goal=b, length_m=route.length_m, outcome=outcome))
    return alone, helped


def seen_tags(pg: PathGraph, tags: dict[int, Tag]) -> list[SeenTag]:
    """The tags the phone can see: each true tag the map has, with the map's position."""
    return [
        SeenTag(
            tag_id=t,
            xz=tag.position_m[[0, 2]],
            normal_xz=tag.normal[[0, 2]] / max(float(np.linalg.norm(tag.normal[[0, 2]])), 1e-12),
            floor=tag.floor,
            map_xyz=np.asarray(pg.tags[t].position_m, dtype=np.float64),
        )
        for t, tag in sorted(tags.items())
        if t in pg.tags
    ]


def real_case(
    walks: tuple[str, ...], params: SkeletonParams
) -> tuple[PathGraph, FreeSpace, dict[int, Tag], list[int], list[SeenTag]]:
    """Real floor 2: the map, the reference's free space, the tags walked between (and those
    left out, more than 2 m from the reference's corridors), the tags the phone can see."""
    m = aligned_map(walks)
    pg = skeleton(m, params)
    space = CapsuleFreeSpace.of_lines([MAIN, *SPURS], radius_m=REAL_HALF_WIDTH_M)
    truth = load_ground_truth(GROUND_TRUTH)
    tags = {}
    left_out = []
    visible = {}
    for t in m.tag_ids:
        if t not in truth or t not in pg.tags:
            continue
        T = truth[t]
        if abs(float(T[1, 3])) > 1.5:
            continue  # not on floor 2
        tag = Tag(position_m=T[:3, 3], normal=T[:3, 2], floor=0)
        visible[t] = tag
        start = start_at(tag, space)
        if math.dist(start.xz, (T[0, 3], T[2, 3])) > DEFAULT_WALKER.arrive_within_m:
            left_out.append(t)
            continue
        tags[t] = tag
    return pg, space, tags, left_out, seen_tags(pg, visible)


def simulated_case(
    config: object, seed: int, params: SkeletonParams
) -> tuple[PathGraph, FreeSpace, dict[int, Tag], list[SeenTag]]:
    """A simulated building: the building map of walks 1–3, its true free space, its tags, the
    tags the phone can see."""
    walks = nook_walks(config, seed, [w for _, w in WALKERS], NookConfig())  # type: ignore[arg-type]
    part = walks[:3]
    pg = fused_skeleton(part, params)
    building = part[0].building
    space = BoxFreeSpace.of_building(building)
    levels = np.asarray(building.floor_heights_m)
    tags = {
        t: Tag(
            position_m=T[:3, 3],
            normal=T[:3, 2],
            floor=int(np.argmin(np.abs(levels - (T[1, 3] - 1.4)))),
        )
        for t, T in building.world_T_tag.items()
        if t in pg.tags
    }
    return pg, space, tags, seen_tags(pg, tags)


def _share(walked: Sequence[Walked]) -> str:
    if not walked:
        return "—"
    return f"{sum(w.outcome.arrived for w in walked) / len(walked):.0%} ({len(walked)})"


def _kind(reason: str) -> str:
    """A failure's kind: its words up to the first place or step, numbers as "N"."""
    for stop in ("(", " at ", " after ", " within "):
        reason = reason.split(stop)[0]
    return re.sub(r"\d+(\.\d+)?", "N", reason).strip()


def table_rows(name: str, walked: list[Walked]) -> list[str]:
    bins = []
    for lo, hi in itertools.pairwise(LENGTH_BINS_M):
        bins.append(_share([w for w in walked if lo <= w.length_m < hi]))
    kinds = Counter(_kind(w.outcome.reason) for w in walked if not w.outcome.arrived)
    return [
        name,
        str(len(walked)),
        _share(walked),
        *bins,
        "; ".join(f"{k}: {n}" for k, n in kinds.most_common()) or "—",
    ]


def plot(
    path: Path,
    name: str,
    pg: PathGraph,
    space: FreeSpace,
    tags: dict[int, Tag],
    walked: list[Walked],
) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(12, 10))
    if isinstance(space, BoxFreeSpace):
        for box in space.boxes_m:
            ax.add_patch(
                plt.Rectangle(
                    (box[0, 0], box[0, 2]),
                    box[1, 0] - box[0, 0],
                    box[1, 2] - box[0, 2],
                    fc="0.92",
                    ec="0.8",
                )
            )
    else:
        assert isinstance(space, CapsuleFreeSpace)
        ends = space.segments_m.reshape(-1, 2)
        low, high = ends.min(axis=0) - space.radius_m, ends.max(axis=0) + space.radius_m
        xs, zs = np.meshgrid(np.arange(low[0], high[0], 0.1), np.arange(low[1], high[1], 0.1))
        free = space.contains(np.column_stack([xs.ravel(), zs.ravel()]), 0).reshape(xs.shape)
        ax.contourf(xs, zs, free.astype(float), levels=[0.5, 1.5], colors=["0.92"])
    G = pg.graph
    for u, v in G.edges:
        p, q = G.nodes[u]["position_m"], G.nodes[v]["position_m"]
        ax.plot([p[0], q[0]], [p[2], q[2]], color="tab:blue", lw=1)
    for t, tag in tags.items():
        ax.plot(tag.position_m[0], tag.position_m[2], "k^", ms=4)
        ax.text(tag.position_m[0], tag.position_m[2], str(t), fontsize=6)
    for w in walked:
        if w.outcome.arrived:
            continue
        ax.plot(
            w.outcome.path_xz[:, 0], w.outcome.path_xz[:, 1], color="tab:red", lw=0.5, alpha=0.5
        )
        ax.plot(*w.outcome.where_xz, "rx", ms=8)
    ax.set_aspect("equal")
    ax.set_title(f"{name}: walker failures (red: their walks, x where they failed)")
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--before", action="store_true", help="the skeleton before issue 39")
    parser.add_argument("--plot", type=Path, help="write a PNG of each map's failures here")
    parser.add_argument("--quick", action="store_true", help="seed 0 only, 60 routes a map")
    parser.add_argument(
        "--from-tag", action="store_true", help="plan from the start tag's node, not the phone"
    )
    args = parser.parse_args(argv)
    params = BEFORE_ISSUE_39 if args.before else DEFAULT_SKELETON_PARAMS
    routes = 60 if args.quick else ROUTES
    header = ["map", "routes", "arrived"]
    header += [f"{lo:g}–{hi:g} m" for lo, hi in itertools.pairwise(LENGTH_BINS_M)]
    header += ["failures"]
    header[-2] = f"≥ {LENGTH_BINS_M[-2]:g} m"
    rows: dict[str, list[list[str]]] = {ALONE: [header], HELPED: [[*header, "corrections"]]}
    failures: dict[str, list[str]] = {ALONE: [], HELPED: []}
    everything: dict[str, list[Walked]] = {ALONE: [], HELPED: []}
    notes: list[str] = []

    def record(
        name: str,
        pg: PathGraph,
        space: FreeSpace,
        tags: dict[int, Tag],
        walked: tuple[list[Walked], list[Walked]],
    ) -> None:
        for variant, runs in zip((ALONE, HELPED), walked, strict=True):
            row = table_rows(name, runs)
            if variant == HELPED:
                row.append(_corrections(runs))
            rows[variant].append(row)
            everything[variant].extend(runs)
            for w in runs:
                if not w.outcome.arrived:
                    x, z = w.outcome.where_xz
                    failures[variant].append(
                        f"{name}: tag {w.start} → tag {w.goal} ({w.length_m:.0f} m): "
                        f"{w.outcome.reason}; ended at ({x:.1f}, {z:.1f}), "
                        f"{w.outcome.distance_to_goal_m:.1f} m from tag {w.goal}"
                    )
            if args.plot:
                stem = f"{name.replace(' ', '_').replace('+', '').replace(':', '')}"
                plot(args.plot / f"{stem}_{variant.split()[0]}.png", name, pg, space, tags, runs)

    for walks in REAL_MAPS:
        pg, space, tags, left_out, seen = real_case(walks, params)
        name = "real: " + " + ".join(walks)
        pairs = sampled_pairs(sorted(tags), routes, 0)
        record(
            name,
            pg,
            space,
            tags,
            walk_routes(pg, space, tags, pairs, seen=seen, from_tag=args.from_tag),
        )
        if left_out:
            notes.append(
                f"{name}: tags {left_out} left out (more than 2 m from the reference's corridors)"
            )
    for label, config in SIMULATED.items():
        for seed in SEEDS[:1] if args.quick else SEEDS:
            pg, space, tags, seen = simulated_case(config, seed, params)
            name = f"simulated {label}, seed {seed}"
            pairs = sampled_pairs(sorted(tags), routes, seed)
            record(
                name,
                pg,
                space,
                tags,
                walk_routes(pg, space, tags, pairs, seen=seen, from_tag=args.from_tag),
            )
    for variant in (ALONE, HELPED):
        total = table_rows("all", everything[variant])
        if variant == HELPED:
            total.append(_corrections(everything[variant]))
        rows[variant].append(total)
        print(f"## {variant}\n")
        print(render_markdown_table(rows[variant], justify="right"))
        print()
    for line in notes:
        print(f"- {line}")
    for variant in (ALONE, HELPED):
        print(f"\n{len(failures[variant])} failures, {variant}:")
        for line in failures[variant]:
            print(f"- {line}")
    return 0


def _corrections(walked: Sequence[Walked]) -> str:
    """How often the app routed again: routes corrected, corrections in all."""
    helped = [w for w in walked if w.outcome.corrections]
    return f"{len(helped)} routes, {sum(w.outcome.corrections for w in helped)} in all"


if __name__ == "__main__":
    sys.exit(main())
