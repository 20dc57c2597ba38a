"""What estimating a walk's noise costs, and what it gains (issue 37, item 4): one command.

    .venv/bin/python bench/noise_cost.py              # every shipped walk and six simulated ones
    .venv/bin/python bench/noise_cost.py --repeat 5   # more timing rounds

Each walk is optimized alone twice: with its noise estimated from its own residuals (the default,
``SlamParams().estimate_noise``: iterated variance-component estimation, several LM solves) and
with the configured variances as given (``SlamParams(estimate_noise=False)``: one LM solve of the
same graph). CPU time is ``time.process_time`` of this process, the median of ``--repeat``
rounds, OpenBLAS held to one thread (its threads spin on these small matrices on a shared
machine); the machine is shared, so read the ratios rather than the seconds. Both builds compute
the tags' marginals, as a map version does.

Where the walk has ground truth: the GT metric and the tag RMSE (rigid fit) of both maps and of
the pre-optimized one. "tuned on": whether the walk was among those that chose the estimate's one
tuned setting (``noise_prior_dof``, docs/multi-session.md: the four real walks with ground truth
and a simulated building of seed 3); the others are held out from every choice the estimate
makes. The issue's target: estimation at most 2× one solve, or off by default where it shows no
gain on the held-out walks. This bench reports; it changes no default.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import math
import statistics
import sys
import time
from collections.abc import Mapping
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # run from a checkout without installing

from app.cli.tables import render_markdown_table  # noqa: E402
from app.domain.evaluation.ground_truth import load_ground_truth  # noqa: E402
from app.domain.evaluation.metrics import ground_truth_metric, tag_rmse_m  # noqa: E402
from app.domain.evaluation.simulate import (  # noqa: E402
    REAL_WALK_SOURCES,
    REGION_ERROR_SOURCES,
    SimulationConfig,
)
from app.domain.evaluation.simulate_building import (  # noqa: E402
    MIXED_WALKS,
    WalkStyle,
    simulate_building_sessions,
)
from app.domain.frames import FloatArray  # noqa: E402
from app.domain.mapping.map_result import MapResult  # noqa: E402
from app.domain.mapping.params import SlamParams  # noqa: E402
from app.domain.mapping.slam import optimize_session  # noqa: E402
from app.domain.upload.session import Session, load_session, parse_session  # noqa: E402

SESSIONS = REPO / "data" / "sessions"
SHARED_SESSIONS = REPO.parent / "shared" / "data" / "sessions"
GROUND_TRUTH = REPO / "data" / "ground_truth"
#: The shipped walks' ground truth, where they have one.
TRUTH_OF = {
    "occam_room": "occam_room_tape.json",
    "floor_2_straight": "rtabmap_mac_1_2.txt",
    "straight_209_occam": "rtabmap_mac_1_2.txt",
    "desnat_straight_once": "rtabmap_mac_1_2.txt",
    "oblique_209_occam": "rtabmap_mac_1_2.txt",
}
#: The walks ``noise_prior_dof`` was chosen on (docs/multi-session.md, bench/multi_session.py 6).
TUNED_ON = {"occam_room", "floor_2_straight", "straight_209_occam", "desnat_straight_once"}

Poses = Mapping[int, FloatArray]


def walks() -> list[tuple[str, Session, Poses | None, bool]]:
    """(name, session, truth or None, tuned on it) of every walk this bench measures."""
    out: list[tuple[str, Session, Poses | None, bool]] = []
    shipped = sorted(p.stem for p in SESSIONS.glob("*.json"))
    extra = [p.stem for p in sorted(SHARED_SESSIONS.glob("*.json")) if p.stem not in shipped]
    for name in [*shipped, *extra]:
        path = SESSIONS / f"{name}.json"
        session = load_session(path if path.exists() else SHARED_SESSIONS / f"{name}.json")
        truth = load_ground_truth(GROUND_TRUTH / TRUTH_OF[name]) if name in TRUTH_OF else None
        label = name if name in shipped else f"{name} (../shared/data only)"
        out.append((label, session, truth, name in TUNED_ON))
    # simulated: issue 25's four kinds of walk (the building of bench/multi_session.py's table 5,
    # seed 5), and the two walkers of a two-floor building with the real walks' error sources
    mixed = simulate_building_sessions(
        SimulationConfig(num_poses=1_200, seed=5), count=len(MIXED_WALKS), styles=MIXED_WALKS
    )
    for sim, style in zip(mixed.sessions, mixed.styles, strict=True):
        out.append(
            (f"simulated ({style.label})", parse_session(sim.upload), mixed.world_T_tag_true, False)
        )
    sources = {k: v for n in REAL_WALK_SOURCES for k, v in REGION_ERROR_SOURCES[n].items()}
    regions = simulate_building_sessions(
        SimulationConfig(num_poses=2_400, two_floors=True, seed=0, **sources),  # type: ignore[arg-type]
        count=2,
        styles=(WalkStyle(), WalkStyle(oblique=True)),
    )
    for sim, label in zip(regions.sessions, ("turning to the tags", "oblique"), strict=True):
        out.append(
            (
                f"simulated two floors, real sources ({label})",
                parse_session(sim.upload),
                regions.world_T_tag_true,
                False,
            )
        )
    return out


def timed(session: Session, params: SlamParams, repeat: int) -> tuple[float, MapResult]:
    """Median CPU seconds of ``repeat`` builds, and the map (the last build's)."""
    seconds = []
    result = None
    for _ in range(repeat):
        started = time.process_time()
        result = optimize_session(session, params)
        seconds.append(time.process_time() - started)
    assert result is not None
    return statistics.median(seconds), result


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeat", type=int, default=3, help="timing rounds per build (3)")
    args = parser.parse_args()

    lines = [
        [
            "walk",
            "poses",
            "tuned on",
            "CPU s: estimated / one solve",
            "×",
            "rounds / LM iterations",
            "GT: pre / estimated / one solve",
            "tag RMSE m: pre / estimated / one solve",
        ]
    ]
    ratios, held_out = [], []
    for name, session, truth, tuned in walks():
        if not len(session.detections):
            continue
        estimated_s, estimated = timed(session, SlamParams(), args.repeat)
        fixed_s, fixed = timed(session, SlamParams(estimate_noise=False), args.repeat)
        ratio = estimated_s / fixed_s
        ratios.append(ratio)
        noise = estimated.noise
        scores = _scores(estimated, fixed, truth)
        if truth is not None and not tuned:
            held_out.append((name, scores))
        lines.append(
            [
                name,
                str(session.num_poses),
                "yes" if tuned else "no",
                f"{estimated_s:.3f} / {fixed_s:.3f}",
                f"{ratio:.1f}",
                f"{noise.rounds if noise else 0} / {estimated.stats.iterations}"
                f" vs {fixed.stats.iterations}",
                " / ".join(_fmt(v, 4) for v in scores[0]),
                " / ".join(_fmt(v, 3) for v in scores[1]),
            ]
        )
    print(render_markdown_table(lines))
    print(
        f"\nCPU ratio estimated / one solve: median {statistics.median(ratios):.1f}×, "
        f"{min(ratios):.1f}–{max(ratios):.1f}× (target ≤ 2×)."
    )
    better = [n for n, (gt, _) in held_out if gt[1] < 0.99 * gt[2]]
    worse = [n for n, (gt, _) in held_out if gt[1] > 1.01 * gt[2]]
    print(
        f"Held-out walks with ground truth (not among those noise_prior_dof was tuned on), the "
        f"estimate's GT metric against one solve's: lower by more than 1% on {len(better)} of "
        f"{len(held_out)}"
        + (f" ({', '.join(better)})" if better else "")
        + f"; higher by more than 1% on {len(worse)}"
        + (f" ({', '.join(worse)})" if worse else "")
        + "; the rest within 1%."
    )
    return 0


def _scores(
    estimated: MapResult, fixed: MapResult, truth: Poses | None
) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
    """(GT metric, tag RMSE) each as (pre-optimized, estimated, one solve); NaN without truth."""
    if truth is None:
        nan = (math.nan, math.nan, math.nan)
        return nan, nan
    maps = (estimated.tag_poses_pre(), estimated.tag_poses(), fixed.tag_poses())
    gt = tuple(ground_truth_metric(m, truth) for m in maps)
    rmse = tuple(tag_rmse_m(m, truth) for m in maps)
    return (gt[0], gt[1], gt[2]), (rmse[0], rmse[1], rmse[2])


def _fmt(value: float, digits: int) -> str:
    return "—" if math.isnan(value) else f"{value:.{digits}f}"


if __name__ == "__main__":
    sys.exit(main())
