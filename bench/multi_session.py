"""Building maps of several sessions (issue 15): one command, prints the tables.

    .venv/bin/python bench/multi_session.py              # everything (≈ 30 s)
    .venv/bin/python bench/multi_session.py --json out.json

1. The three real mac-building sessions in ``data/`` (floor_2_straight, desnat_straight_once,
   straight_209_occam; ground truth ``rtabmap_mac_1_2.txt``): each session's map alone against the
   joint map of all three, the ground-truth metric and the tag RMSE on the tags that session has;
   the joint map on all its tags; and the tags seen in two or more sessions. ``naive`` is the
   joint map without the per-session weighting and the split of disagreeing tags
   (``optimize_sessions(reweight=False)``), for comparison.
2. Build time of the 3-session map against the sum of the three single builds (CPU time, median
   of ``--repeat`` rounds, marginals included, parsing not).
3. Simulated walks of one building with known truth (``app.domain.evaluation.simulate_building``:
   1,200
   poses = 2 minutes each, every walk in its own world frame): the joint map of the first 1, 2,
   5, 10, 20 walks, its tag RMSE over all its tags and over the first walk's tags, and its build
   time.

Targets (issue 15): the joint map better than every session alone on that session's tags, on both
measures; on tags seen in two or more sessions at least 25% better than the mean of the sessions
alone; never more than 5% worse anywhere; 3-session build ≤ 1.5 × the sum of single builds;
20 simulated sessions ≤ 2 s; the simulated tag error falls as sessions are added.
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import statistics
import sys
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # run from a checkout without installing

from app.cli.tables import render_markdown_table  # noqa: E402
from app.domain.evaluation.ground_truth import load_ground_truth  # noqa: E402
from app.domain.evaluation.metrics import ground_truth_metric, joint_shift_metric, tag_rmse_m  # noqa: E402
from app.domain.evaluation.simulate import SimulationConfig  # noqa: E402
from app.domain.evaluation.simulate_building import simulate_building_sessions  # noqa: E402
from app.domain.frames import FloatArray  # noqa: E402
from app.domain.mapping.joint import JointMap, optimize_sessions  # noqa: E402
from app.domain.mapping.slam import optimize_session  # noqa: E402
from app.domain.upload.session import Session, load_session, parse_session  # noqa: E402

SESSIONS = REPO / "data" / "sessions"
GROUND_TRUTH = REPO / "data" / "ground_truth" / "rtabmap_mac_1_2.txt"
MAC_SESSIONS = ("floor_2_straight", "desnat_straight_once", "straight_209_occam")
SIMULATED_COUNTS = (1, 2, 5, 10, 20)
SIMULATED_POSES = 1_200

Poses = Mapping[int, FloatArray]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeat", type=int, default=7, help="timing rounds (7)")
    parser.add_argument("--json", type=Path, help="also write the results here")
    args = parser.parse_args()

    results: dict[str, Any] = {}
    checks: list[tuple[str, bool]] = []
    sessions = [load_session(SESSIONS / f"{name}.json") for name in MAC_SESSIONS]
    truth = load_ground_truth(GROUND_TRUTH)
    results["real"] = real_sessions(sessions, truth, checks)
    results["timing"] = build_times(sessions, args.repeat, checks)
    results["simulated"] = simulated(checks)

    print("\nTargets")
    for label, ok in checks:
        print(f"- [{'x' if ok else ' '}] {label}")
    if args.json:
        args.json.write_text(json.dumps(results, indent=2, default=_finite_or_none))
        print(f"\nwrote {args.json}")
    return 0


# --------------------------------------------------------------------------- 1. real sessions


def real_sessions(
    sessions: list[Session], truth: Poses, checks: list[tuple[str, bool]]
) -> dict[str, Any]:
    alone = {
        n: optimize_session(s).tag_poses() for n, s in zip(MAC_SESSIONS, sessions, strict=True)
    }
    joint = optimize_sessions(sessions, names=MAC_SESSIONS)
    naive = optimize_sessions(sessions, names=MAC_SESSIONS, reweight=False)
    rows: list[dict[str, Any]] = []
    for name in MAC_SESSIONS:
        tags = sorted(set(alone[name]) & set(truth))
        rows.append(
            {
                "tags": f"{name} ({len(tags)})",
                **_pair("gt", alone[name], joint, naive, tags, truth, ground_truth_metric),
                **_pair("rmse", alone[name], joint, naive, tags, truth, tag_rmse_m),
            }
        )
    all_tags = sorted(set(joint.map.tag_poses()) & set(truth))
    rows.append(
        {
            "tags": f"joint map, all tags ({len(all_tags)})",
            "gt_alone": math.nan,
            "gt_joint": ground_truth_metric(_only(joint.map.tag_poses(), all_tags), truth),
            "gt_naive": ground_truth_metric(_only(naive.map.tag_poses(), all_tags), truth),
            "rmse_alone": math.nan,
            "rmse_joint": tag_rmse_m(_only(joint.map.tag_poses(), all_tags), truth),
            "rmse_naive": tag_rmse_m(_only(naive.map.tag_poses(), all_tags), truth),
        }
    )
    # tags seen in two or more sessions: each session's alone map on those it has, against the
    # joint map on the same tags; then the means over sessions
    seen = [set(alone[name]) for name in MAC_SESSIONS]
    shared = sorted({t for t in set.union(*seen) if sum(t in s for s in seen) >= 2} & set(truth))
    shared_rows = []
    for name in MAC_SESSIONS:
        tags = [t for t in shared if t in alone[name]]
        if len(tags) >= 2:
            shared_rows.append(
                {
                    **_pair("gt", alone[name], joint, naive, tags, truth, ground_truth_metric),
                    **_pair("rmse", alone[name], joint, naive, tags, truth, tag_rmse_m),
                }
            )
    mean = {key: statistics.fmean(r[key] for r in shared_rows) for key in shared_rows[0]}
    rows.append({"tags": f"seen in ≥ 2 sessions ({len(shared)}), mean over sessions", **mean})

    print("## Real sessions of the mac building (ground truth rtabmap_mac_1_2)\n")
    lines = [
        ["tags (with ground truth)", "GT alone", "GT joint", "Δ", "GT naive", "RMSE alone m",
         "RMSE joint m", "Δ", "RMSE naive m"]
    ]  # fmt: skip
    for row in rows:
        lines.append(
            [
                row["tags"],
                _fmt(row["gt_alone"]),
                _fmt(row["gt_joint"]),
                _change(row["gt_joint"], row["gt_alone"]),
                _fmt(row["gt_naive"]),
                _fmt(row["rmse_alone"], 3),
                _fmt(row["rmse_joint"], 3),
                _change(row["rmse_joint"], row["rmse_alone"]),
                _fmt(row["rmse_naive"], 3),
            ]
        )
    print(render_markdown_table(lines))
    print()
    for part in joint.parts:
        print(
            f"- {part.dataset}: placed by {len(part.alignment.inlier_tags)} of "
            f"{len(part.alignment.shared_tags)} shared tags, odometry variance ×"
            f"{part.odometry_variance_scale:.2f}, tag depth ×{part.tag_depth_scale:.2f}, "
            f"{part.detections_used} detections used"
        )
    print(f"- shift metric of the joint map over every session's detections: "
          f"{joint_shift_metric(joint):.4f}")  # fmt: skip
    print()

    per_session = rows[: len(MAC_SESSIONS)]
    checks.append(
        (
            "joint better than each session alone on its tags, GT metric and tag RMSE",
            all(
                r["gt_joint"] < r["gt_alone"] and r["rmse_joint"] < r["rmse_alone"]
                for r in per_session
            ),
        )
    )
    checks.append(
        (
            f"tags in ≥ 2 sessions: ≥ 25% better than the mean alone (GT "
            f"{_change(mean['gt_joint'], mean['gt_alone'])}, RMSE "
            f"{_change(mean['rmse_joint'], mean['rmse_alone'])})",
            mean["gt_joint"] <= 0.75 * mean["gt_alone"]
            and mean["rmse_joint"] <= 0.75 * mean["rmse_alone"],
        )
    )
    worst = max(
        max(r["gt_joint"] / r["gt_alone"], r["rmse_joint"] / r["rmse_alone"]) for r in per_session
    )
    checks.append((f"never more than 5% worse (worst ratio {worst:.3f})", worst <= 1.05))
    return {"rows": rows, "shared_tags": shared}


def _pair(
    prefix: str,
    alone: Poses,
    joint: JointMap,
    naive: JointMap,
    tags: list[int],
    truth: Poses,
    metric: Callable[[Poses, Poses], float],
) -> dict[str, float]:
    return {
        f"{prefix}_alone": metric(_only(alone, tags), truth),
        f"{prefix}_joint": metric(_only(joint.map.tag_poses(), tags), truth),
        f"{prefix}_naive": metric(_only(naive.map.tag_poses(), tags), truth),
    }


def _only(poses: Poses, tags: list[int]) -> dict[int, FloatArray]:
    return {t: poses[t] for t in tags if t in poses}


# --------------------------------------------------------------------------- 2. build time


def build_times(
    sessions: list[Session], repeat: int, checks: list[tuple[str, bool]]
) -> dict[str, float]:
    """Single builds and the joint build timed in turn, ``repeat`` rounds: CPU time of this
    process (gtsam is single-threaded here, so on a quiet machine it is the wall time, and other
    programs on a shared machine inflate it far less), and the wall time for reference."""
    optimize_sessions(sessions, names=MAC_SESSIONS)  # warm up (imports, gtsam)
    singles: list[list[tuple[float, float]]] = [[] for _ in sessions]
    joint_times: list[tuple[float, float]] = []
    ratios = []
    for _ in range(repeat):
        for k, session in enumerate(sessions):
            singles[k].append(_seconds(lambda session=session: optimize_session(session)))
        joint_times.append(_seconds(lambda: optimize_sessions(sessions, names=MAC_SESSIONS)))
        ratios.append(joint_times[-1][1] / sum(times[-1][1] for times in singles))
    single_cpu = [statistics.median(t[1] for t in times) for times in singles]
    single_wall = [statistics.median(t[0] for t in times) for times in singles]
    joint_cpu = statistics.median(t[1] for t in joint_times)
    joint_wall = statistics.median(t[0] for t in joint_times)
    ratio = statistics.median(ratios)
    print(f"## Build time (median of {repeat} rounds, marginals included)\n")
    lines = [["map", "CPU s", "wall s"]]
    for name, cpu, wall in zip(MAC_SESSIONS, single_cpu, single_wall, strict=True):
        lines.append([f"{name} alone", f"{cpu:.3f}", f"{wall:.3f}"])
    lines.append(["sum of the three", f"{sum(single_cpu):.3f}", f"{sum(single_wall):.3f}"])
    lines.append(["joint map of the three", f"{joint_cpu:.3f}", f"{joint_wall:.3f}"])
    lines.append(["joint / sum (CPU, median over rounds)", f"{ratio:.2f}", ""])
    print(render_markdown_table(lines))
    print()
    checks.append((f"3-session build ≤ 1.5 × the single builds ({ratio:.2f} ×)", ratio <= 1.5))
    return {"singles_cpu_s": sum(single_cpu), "joint_cpu_s": joint_cpu, "ratio": ratio}


def _seconds(run: Callable[[], object]) -> tuple[float, float]:
    """(wall, CPU) seconds of ``run()``."""
    wall, cpu = time.perf_counter(), time.process_time()
    run()
    return time.perf_counter() - wall, time.process_time() - cpu


# --------------------------------------------------------------------------- 3. simulated


def simulated(checks: list[tuple[str, bool]]) -> list[dict[str, Any]]:
    started = time.perf_counter()
    building = simulate_building_sessions(
        SimulationConfig(num_poses=SIMULATED_POSES), count=max(SIMULATED_COUNTS)
    )
    sessions = [parse_session(s.upload) for s in building.sessions]
    simulate_s = time.perf_counter() - started
    truth = building.world_T_tag_true
    first_tags = sorted(optimize_session(sessions[0]).tag_poses())
    rows = []
    for count in SIMULATED_COUNTS:
        started = time.perf_counter()
        joint = optimize_sessions(sessions[:count])
        build_s = time.perf_counter() - started
        poses = joint.map.tag_poses()
        rows.append(
            {
                "sessions": count,
                "poses": int(joint.map.world_T_phone.shape[0]),
                "tags": len(poses),
                "rmse_all_m": tag_rmse_m(poses, truth),
                "rmse_first_m": tag_rmse_m(_only(poses, first_tags), truth),
                "gt_all": ground_truth_metric(poses, truth),
                "build_s": build_s,
            }
        )
    print(
        f"## Simulated walks of one building ({SIMULATED_POSES} poses = 2 min each, own frames; "
        f"simulated in {simulate_s:.1f} s)\n"
    )
    lines = [["sessions", "poses", "tags", "tag RMSE m (all)", "tag RMSE m (walk 1's tags)",
              "GT metric", "build s"]]  # fmt: skip
    for row in rows:
        lines.append(
            [
                str(row["sessions"]),
                str(row["poses"]),
                str(row["tags"]),
                f"{row['rmse_all_m']:.4f}",
                f"{row['rmse_first_m']:.4f}",
                f"{row['gt_all']:.4f}",
                f"{row['build_s']:.3f}",
            ]
        )
    print(render_markdown_table(lines))
    last = rows[-1]
    checks.append(
        (
            f"{last['sessions']} simulated sessions ≤ 2 s ({last['build_s']:.2f} s)",
            last["build_s"] <= 2.0,
        )
    )
    falling = all(a["rmse_first_m"] > b["rmse_first_m"] for a, b in itertools.pairwise(rows))
    checks.append(("simulated tag error falls as sessions are added (walk 1's tags)", falling))
    return rows


# --------------------------------------------------------------------------- formatting


def _fmt(value: float, digits: int = 4) -> str:
    return "—" if math.isnan(value) else f"{value:.{digits}f}"


def _change(new: float, old: float) -> str:
    return "—" if math.isnan(new) or math.isnan(old) or old == 0 else f"{new / old - 1:+.1%}"


def _finite_or_none(value: object) -> object:
    return None if isinstance(value, float) and not math.isfinite(value) else value


if __name__ == "__main__":
    sys.exit(main())
