"""Tuning benchmark (§5): the paper's grid on the real sessions, Optuna's sampler against it,
and the shift metric against ground truth on simulations. One command, prints its tables.

    .venv/bin/python -m bench.tuning                 # the full benchmark (about 5 minutes)
    .venv/bin/python -m bench.tuning --quick         # two sessions, smaller grids (about 1 minute)
    .venv/bin/python -m bench.tuning --json out.json # also write the raw numbers
    .venv/bin/python -m bench.tuning --timing        # (a), (a2) and (a3) only

(a) Wall time of the paper grid (10 × 10 × 10 over 1e-8..1, 1000 trials) per real session with
    ground truth, on 2 processes, and on 1 process for the first session (the speed-up); the
    workers' CPU time shows how much of the 2 cores the sweep actually got on a shared machine.
    The pool preloads jemalloc where the machine has it (``workers/allocator.py``; the "allocator"
    column says which one ran).
(a2) Where a trial's time goes, per session: CPU time per trial (``time.process_time`` in this
    one process, so other programs on the machine inflate it far less than the wall time) of its
    parts — the factor graph for its setting, Levenberg–Marquardt, scoring — and LM's iterations,
    over every ``COMPONENT_ROW_STRIDE``-th row of the grid, in grid order.
(a3) Keyframes (``SlamParams.keyframe_interval_s``, default 2 s) against every pose in the graph
    (0, the paper's graph): the graph's poses, the grid's wall time, and how far apart the two
    maps with the default parameters are (tag RMSE between them after a rigid alignment, the
    ground-truth metric of each).
(b) The paper's Table 2 from those grids: the ground-truth metric of the pre-optimized map, of the
    map built with the setting the shift metric chooses and of the map built with the best setting
    by ground truth (the % change against pre-optimized), the same three tag RMSEs, and the
    Spearman correlation of shift and GT metric over the grid's trials. "defaults" is our
    SlamParams() map, for reference. A converged trial is its build (``optimize_session`` with
    its setting, what ``apply`` makes): "= build" checks it for the chosen settings.
(b2) The chosen settings, and their builds' iterations.
(c) Optuna's TPE sampler (``SweepPlan(method="sampler")``, the shift metric, seeds 0–2) over the
    same box: how many trials it needs to come within 2% of the grid's best shift metric, and its
    best after all its trials against the grid's best.
(d) A simulated session (2000 poses) at three noise scales; a 5 × 5 × 5 grid ±2 decades around
    the generating variances (tag_position_var at its truth): the Spearman correlation of shift
    and GT metric, both metrics' choices (GT of their builds, and of a build at the generating
    variances), and how many decades each choice is off the generating value per axis
    (orientation / linear / angular).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import statistics
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # run from a checkout without installing

from app.cli.tables import render_markdown_table  # noqa: E402
from app.domain.evaluation.ground_truth import load_ground_truth  # noqa: E402
from app.domain.evaluation.metrics import ground_truth_metric, tag_rmse_m  # noqa: E402
from app.domain.evaluation.simulate import SimulationConfig, simulate_session  # noqa: E402
from app.domain.evaluation.sweep_plan import SweepPlan  # noqa: E402
from app.domain.evaluation.tuning import (  # noqa: E402
    PAPER_GRID_AXES,
    PAPER_GRID_RANGE,
    Axis,
    SearchSpace,
    Trial,
    TuningTarget,
    best_trial,
    sweep_result,
)
from app.domain.mapping.params import SlamParams  # noqa: E402
from app.domain.mapping.slam import optimize_session  # noqa: E402
from app.domain.upload.session import Session, load_session, parse_session  # noqa: E402
from workers.allocator import jemalloc_path  # noqa: E402
from workers.sweep_pool import run_sweep  # noqa: E402

SESSIONS = REPO / "data" / "sessions"
GROUND_TRUTH = REPO / "data" / "ground_truth"
#: The real sessions with ground truth (data/README.md).
REAL = (
    ("occam_room", "occam_room_tape.json"),
    ("floor_2_straight", "rtabmap_mac_1_2.txt"),
    ("straight_209_occam", "rtabmap_mac_1_2.txt"),
    ("desnat_straight_once", "rtabmap_mac_1_2.txt"),
)
SAMPLER_SEEDS = (0, 1, 2)
#: The sampler is "there" within this fraction of the grid's best shift metric.
WITHIN = 0.02
ORIENTATION, LINEAR, ANGULAR = PAPER_GRID_AXES
#: The simulation's generating noise at scale 1 (the identification test's moderate noise):
#: odometry drift 0.03 m/√s and 0.005 rad/√s, tags 1 cm at 1 m and 0.03 rad.
SIM_NOISE = {
    "odom_translation_drift_m_per_sqrt_s": 0.03,
    "odom_rotation_drift_rad_per_sqrt_s": 0.005,
    "tag_position_noise_m_at_1m": 0.01,
    "tag_rotation_noise_rad": 0.03,
}
SIM_DEPTH_RATIO = 3.0
#: (a2) times the trials of every this-many-th row of the grid (rows along the last axis).
COMPONENT_ROW_STRIDE = 4


@dataclass(frozen=True, slots=True, kw_only=True)
class Plan:
    """What to run; ``--quick`` shrinks every part."""

    sessions: tuple[tuple[str, str], ...]
    grid_values: int
    sampler_trials: int
    sim_poses: int
    sim_scales: tuple[float, ...]
    sim_values: int
    processes: int = 2


FULL = Plan(
    sessions=REAL,
    grid_values=10,
    sampler_trials=100,
    sim_poses=2000,
    sim_scales=(0.5, 1.0, 2.0),
    sim_values=5,
)
QUICK = Plan(
    sessions=(REAL[0], REAL[3]),
    grid_values=5,
    sampler_trials=40,
    sim_poses=1000,
    sim_scales=(0.5, 1.0, 2.0),
    sim_values=3,
)


def log(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def paper_space(values: int) -> SearchSpace:
    low, high = PAPER_GRID_RANGE
    return SearchSpace(tuple(Axis(name, low, high, values) for name in PAPER_GRID_AXES))


def timed_sweep(
    session: Session,
    plan: SweepPlan,
    *,
    ground_truth: dict[int, Any] | None,
    processes: int,
    base_params: SlamParams | None = None,
) -> tuple[list[Trial], float, float]:
    """The trials, the wall time and the CPU time of the pool's workers, s."""
    cpu_before = _children_cpu_s()
    started = time.perf_counter()
    trials = run_sweep(
        session, plan, base_params=base_params, ground_truth=ground_truth, processes=processes
    )
    return trials, time.perf_counter() - started, _children_cpu_s() - cpu_before


def _children_cpu_s() -> float:
    """User + system time of the finished (joined) child processes, s."""
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def pct(value: float, reference: float) -> str:
    return f"{(value / reference - 1) * 100:+.0f}%"


def fmt(value: float | None, pattern: str = "{:.4f}") -> str:
    return "—" if value is None or not math.isfinite(value) else pattern.format(value)


def with_pct(value: float, reference: float) -> str:
    """``value`` and its change against ``reference``: "0.0428 (-10%)"."""
    return f"{fmt(value)} ({pct(value, reference)})"


# --------------------------------------------------------------------------- (a) and (b)


def real_sessions(plan: Plan) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """Grid timings and the Table 2 numbers per session."""
    space = paper_space(plan.grid_values)
    timing_rows: list[dict[str, Any]] = []
    table2_rows: list[dict[str, Any]] = []
    for number, (name, gt_file) in enumerate(plan.sessions):
        session = load_session(SESSIONS / f"{name}.json")
        ground_truth = load_ground_truth(GROUND_TRUTH / gt_file)
        sweep = SweepPlan(method="grid", space=space)
        runs = [plan.processes, 1] if number == 0 else [plan.processes]
        trials: list[Trial] = []
        walls: dict[int, float] = {}
        cpus: dict[int, float] = {}
        for processes in runs:
            log(f"grid {name}: {space.grid_size} trials on {processes} process(es) …")
            trials, walls[processes], cpus[processes] = timed_sweep(
                session, sweep, ground_truth=ground_truth, processes=processes
            )
        for processes in runs:
            timing_rows.append(
                {
                    "session": name,
                    "poses": session.num_poses,
                    "trials": len(trials),
                    "processes": processes,
                    "wall_s": walls[processes],
                    "cpu_s": cpus[processes],
                    "ms_per_trial": walls[processes] / len(trials) * 1e3,
                    "speedup": walls[1] / walls[processes] if 1 in walls else None,
                    "mean_iterations": statistics.fmean(t.iterations for t in trials),
                    "unconverged": sum(1 for t in trials if not t.converged and t.error is None),
                    "failed": sum(1 for t in trials if t.error is not None),
                    "allocator": "jemalloc" if jemalloc_path() else "malloc",
                }
            )
        target = TuningTarget.prepare(session, SlamParams(), ground_truth)
        started = time.perf_counter()
        result = sweep_result(target, trials, "shift")
        builds_s = time.perf_counter() - started
        defaults = target.build({})
        converged = [t for t in trials if t.converged]
        table2_rows.append(
            {
                "session": name,
                "tags": len(target.pre_map),
                **result.to_dict(),
                "builds_wall_s": builds_s,
                "gt_metric_defaults": defaults.gt_metric,
                "tag_rmse_defaults_m": defaults.tag_rmse_m,
                "distinct_shift_values": len({t.shift for t in converged}),
                "converged_trials": len(converged),
            }
        )
    return timing_rows, table2_rows


def trial_components(plan: Plan) -> list[dict[str, Any]]:
    """(a2): per-trial CPU of each part of a trial, ms, and LM's iterations, per session."""
    space = paper_space(plan.grid_values)
    rows = []
    for name, gt_file in plan.sessions:
        session = load_session(SESSIONS / f"{name}.json")
        target = TuningTarget.prepare(
            session, SlamParams(), load_ground_truth(GROUND_TRUTH / gt_file)
        )
        start = target.warm_start
        last = space.axes[-1].num
        grid = space.grid()
        values = [v for k, v in enumerate(grid) if (k // last) % COMPONENT_ROW_STRIDE == 0]
        log(f"trial parts {name}: {len(values)} trials in this process …")
        graph_s = lm_s = score_s = 0.0
        iterations = 0
        for trial_values in values:
            params = target.trial_params(trial_values)
            started = time.process_time()
            target.graph.graph(params)
            built = time.process_time()
            map_T_tag, trial_iterations, _ = target.graph.refine(params, start)
            optimized = time.process_time()
            target.score_map(map_T_tag)
            scored = time.process_time()
            graph_s += built - started
            lm_s += optimized - built  # its graph comes from the cache the line above filled
            score_s += scored - optimized
            iterations += trial_iterations
        count = len(values)
        rows.append(
            {
                "session": name,
                "trials": count,
                "graph_ms": graph_s / count * 1e3,
                "lm_ms": lm_s / count * 1e3,
                "score_ms": score_s / count * 1e3,
                "total_ms": (graph_s + lm_s + score_s) / count * 1e3,
                "mean_iterations": iterations / count,
                "lm_ms_per_iteration": lm_s / max(iterations, 1) * 1e3,
            }
        )
    return rows


def components_table(rows: list[dict[str, Any]]) -> str:
    lines = [
        [
            "session",
            "trials",
            "graph ms",
            "LM ms",
            "scoring ms",
            "total ms",
            "LM iterations",
            "LM ms/iteration",
        ]
    ]
    for row in rows:
        lines.append(
            [
                row["session"],
                str(row["trials"]),
                f"{row['graph_ms']:.2f}",
                f"{row['lm_ms']:.1f}",
                f"{row['score_ms']:.2f}",
                f"{row['total_ms']:.1f}",
                f"{row['mean_iterations']:.2f}",
                f"{row['lm_ms_per_iteration']:.2f}",
            ]
        )
    return render_markdown_table(lines, justify="right")


def timing_table(rows: list[dict[str, Any]]) -> str:
    lines = [
        [
            "session",
            "poses",
            "trials",
            "processes",
            "wall s",
            "worker CPU s",
            "ms/trial",
            "speed-up",
            "mean iterations",
            "unconverged",
            "failed",
            "allocator",
        ]
    ]
    for row in rows:
        lines.append(
            [
                row["session"],
                str(row["poses"]),
                str(row["trials"]),
                str(row["processes"]),
                f"{row['wall_s']:.1f}",
                f"{row['cpu_s']:.1f}",
                f"{row['ms_per_trial']:.0f}",
                fmt(row["speedup"], "{:.2f}×"),
                f"{row['mean_iterations']:.1f}",
                str(row["unconverged"]),
                str(row["failed"]),
                row["allocator"],
            ]
        )
    return render_markdown_table(lines, justify="right")


def keyframe_runs(plan: Plan) -> list[dict[str, Any]]:
    """(a3): every pose against keyframes, per session: graph size, grid wall time, and the two
    default maps against each other and against ground truth."""
    space = paper_space(plan.grid_values)
    rows = []
    for name, gt_file in plan.sessions:
        session = load_session(SESSIONS / f"{name}.json")
        ground_truth = load_ground_truth(GROUND_TRUTH / gt_file)
        row: dict[str, Any] = {"session": name, "poses": session.num_poses}
        maps = {}
        for label, interval_s in (
            ("every_pose", 0.0),
            ("keyframes", SlamParams().keyframe_interval_s),
        ):
            params = SlamParams(keyframe_interval_s=interval_s)
            log(f"keyframes {name}: {label}, {space.grid_size} trials …")
            _, wall_s, _ = timed_sweep(
                session,
                SweepPlan(method="grid", space=space),
                ground_truth=ground_truth,
                processes=plan.processes,
                base_params=params,
            )
            result = optimize_session(session, params)
            maps[label] = result.tag_poses()
            row[f"{label}_graph_poses"] = int(result.residuals.keyframe_index.size)
            row[f"{label}_grid_wall_s"] = wall_s
            row[f"{label}_gt_metric"] = ground_truth_metric(maps[label], ground_truth)
        row["tag_rmse_between_m"] = tag_rmse_m(maps["keyframes"], maps["every_pose"])
        rows.append(row)
    return rows


def keyframe_table(rows: list[dict[str, Any]]) -> str:
    lines = [
        [
            "session",
            "poses",
            "graph poses: every / keyframes",
            "grid wall s: every / keyframes",
            "speed-up",
            "GT defaults: every / keyframes",
            "tag RMSE between the maps mm",
        ]
    ]
    for row in rows:
        every_s, keyframe_s = row["every_pose_grid_wall_s"], row["keyframes_grid_wall_s"]
        lines.append(
            [
                row["session"],
                str(row["poses"]),
                f"{row['every_pose_graph_poses']} / {row['keyframes_graph_poses']}",
                f"{every_s:.1f} / {keyframe_s:.1f}",
                f"{every_s / keyframe_s:.1f}×",
                f"{fmt(row['every_pose_gt_metric'])} / {fmt(row['keyframes_gt_metric'])}",
                f"{row['tag_rmse_between_m'] * 1e3:.1f}",
            ]
        )
    return render_markdown_table(lines, justify="right")


def table2(rows: list[dict[str, Any]]) -> str:
    """The defaults and the chosen settings (a converged trial is its build)."""
    lines = [
        [
            "session",
            "tags",
            "GT pre",
            "GT defaults",
            "GT shift-chosen",
            "GT GT-chosen",
            "= build",
            "RMSE pre m",
            "RMSE shift-chosen m",
            "RMSE GT-chosen m",
            "Spearman",
        ]
    ]
    for row in rows:
        pre = row["gt_metric_pre"]
        lines.append(
            [
                row["session"],
                str(row["tags"]),
                fmt(pre),
                with_pct(row["gt_metric_defaults"], pre),
                with_pct(row["gt_metric_at_best_shift"], pre),
                with_pct(row["gt_metric_best"], pre),
                "yes" if row["builds_equal_trials"] else "NO",
                fmt(row["tag_rmse_pre_m"], "{:.3f}"),
                fmt(row["tag_rmse_at_best_shift_m"], "{:.3f}"),
                fmt(row["tag_rmse_at_best_gt_m"], "{:.3f}"),
                fmt(row["shift_gt_spearman"], "{:+.2f}"),
            ]
        )
    return render_markdown_table(lines, justify="right")


def chosen_table(rows: list[dict[str, Any]]) -> str:
    """(b2): the chosen settings and their builds."""
    lines = [
        [
            "session",
            "choice",
            "orientation / linear / angular",
            "GT · shift · RMSE m",
            "LM iterations (second stage)",
        ]
    ]
    for row in rows:
        for choice, key in (("shift", "shift_chosen"), ("GT", "gt_chosen")):
            build = row["builds"][key]
            if build is None:
                continue
            lines.append(
                [
                    row["session"],
                    choice,
                    " / ".join(f"{build['values'][n]:.1e}" for n in PAPER_GRID_AXES),
                    f"{fmt(build['gt_metric'])} · {fmt(build['shift'], '{:.5f}')} · "
                    f"{fmt(build['tag_rmse_m'], '{:.3f}')}",
                    str(build["iterations"]),
                ]
            )
    return render_markdown_table(lines, justify="right")


# --------------------------------------------------------------------------- (c)


def sampler_runs(plan: Plan, grid_best: dict[str, float]) -> list[dict[str, Any]]:
    space = paper_space(plan.grid_values)
    rows = []
    for name, _ in plan.sessions:
        session = load_session(SESSIONS / f"{name}.json")
        for seed in SAMPLER_SEEDS:
            log(f"sampler {name}: {plan.sampler_trials} trials, seed {seed} …")
            sweep = SweepPlan(method="sampler", space=space, trials=plan.sampler_trials, seed=seed)
            trials, wall_s, _ = timed_sweep(
                session, sweep, ground_truth=None, processes=plan.processes
            )
            best_so_far = np.minimum.accumulate([t.score("shift") for t in trials])
            reached = np.flatnonzero(best_so_far <= (1 + WITHIN) * grid_best[name])
            rows.append(
                {
                    "session": name,
                    "seed": seed,
                    "trials": len(trials),
                    "trials_to_within": int(reached[0]) + 1 if reached.size else None,
                    "sampler_best_shift": float(best_so_far[-1]),
                    "grid_best_shift": grid_best[name],
                    "wall_s": wall_s,
                    "best_so_far": [float(v) for v in best_so_far],
                }
            )
    return rows


def sampler_table(rows: list[dict[str, Any]], grid_trials: int) -> str:
    lines = [
        [
            "session",
            "seed",
            f"trials to ≤ {WITHIN:.0%} of grid best",
            "sampler best shift",
            f"grid best shift ({grid_trials})",
            "sampler vs grid",
            "sampler wall s",
        ]
    ]
    for row in rows:
        lines.append(
            [
                row["session"],
                str(row["seed"]),
                "—" if row["trials_to_within"] is None else str(row["trials_to_within"]),
                f"{row['sampler_best_shift']:.5f}",
                f"{row['grid_best_shift']:.5f}",
                f"{(row['sampler_best_shift'] / row['grid_best_shift'] - 1) * 100:+.1f}%",
                f"{row['wall_s']:.1f}",
            ]
        )
    return render_markdown_table(lines, justify="right")


# --------------------------------------------------------------------------- (d)


def simulation_runs(plan: Plan) -> list[dict[str, Any]]:
    rows = []
    for scale in plan.sim_scales:
        noise = {name: sigma * scale for name, sigma in SIM_NOISE.items()}
        config = SimulationConfig(
            num_poses=plan.sim_poses,
            seed=0,
            odom_vertical_drift_m_per_sqrt_s=noise["odom_translation_drift_m_per_sqrt_s"],
            odom_tilt_error_rad=0.0,
            tag_depth_noise_ratio=SIM_DEPTH_RATIO,
            **noise,
        )
        sim = simulate_session(config)
        truth = {
            ORIENTATION: noise["tag_rotation_noise_rad"] ** 2,
            LINEAR: noise["odom_translation_drift_m_per_sqrt_s"] ** 2,
            ANGULAR: noise["odom_rotation_drift_rad_per_sqrt_s"] ** 2,
        }
        base = SlamParams(
            tag_position_var_m2=noise["tag_position_noise_m_at_1m"] ** 2,
            tag_depth_var_ratio=SIM_DEPTH_RATIO**2,
        )
        space = SearchSpace(
            tuple(
                Axis(name, truth[name] * 1e-2, truth[name] * 1e2, plan.sim_values)
                for name in PAPER_GRID_AXES
            )
        )
        log(f"simulation ×{scale:g}: {space.grid_size} trials …")
        session = parse_session(sim.upload)
        trials, wall_s, _ = timed_sweep(
            session,
            SweepPlan(method="grid", space=space),
            ground_truth=sim.world_T_tag_true,
            processes=plan.processes,
            base_params=base,
        )
        target = TuningTarget.prepare(session, base, sim.world_T_tag_true)
        result = sweep_result(target, trials, "shift")
        summary, reported = result.summary, result.to_dict()
        by_shift = best_trial(trials, "shift")
        by_gt = best_trial(trials, "ground_truth")

        def off(trial: Trial | None, truth: dict[str, float] = truth) -> list[float] | None:
            if trial is None:
                return None
            return [round(math.log10(trial.values[n] / truth[n]), 2) for n in PAPER_GRID_AXES]

        rows.append(
            {
                "scale": scale,
                "noise": noise,
                "poses": plan.sim_poses,
                "detections": len(session.detections),
                "odometry_end_error_m": sim.odometry_end_error_m(),
                "trials": len(trials),
                "wall_s": wall_s,
                "gt_metric_pre": summary.gt_metric_pre,
                "gt_metric_at_truth": target.build(truth).gt_metric,
                "gt_metric_at_best_shift": reported["gt_metric_at_best_shift"],
                "gt_metric_best": reported["gt_metric_best"],
                "builds_equal_trials": reported["builds_equal_trials"],
                "spearman": summary.shift_gt_spearman,
                "shift_chosen_decades_off": off(by_shift),
                "gt_chosen_decades_off": off(by_gt),
            }
        )
    return rows


def simulation_table(rows: list[dict[str, Any]]) -> str:
    def decades(values: list[float] | None) -> str:
        return "—" if values is None else " / ".join(f"{v:+.0f}" for v in values)

    lines = [
        [
            "noise ×",
            "drift at end m",
            "trials",
            "GT pre",
            "GT at truth",
            "GT shift-chosen",
            "GT GT-chosen",
            "= build",
            "Spearman",
            "shift-chosen off (decades)",
            "GT-chosen off (decades)",
        ]
    ]
    for row in rows:
        lines.append(
            [
                f"{row['scale']:g}",
                f"{row['odometry_end_error_m']:.2f}",
                str(row["trials"]),
                fmt(row["gt_metric_pre"]),
                fmt(row["gt_metric_at_truth"]),
                fmt(row["gt_metric_at_best_shift"]),
                fmt(row["gt_metric_best"]),
                "yes" if row["builds_equal_trials"] else "NO",
                fmt(row["spearman"], "{:+.2f}"),
                decades(row["shift_chosen_decades_off"]),
                decades(row["gt_chosen_decades_off"]),
            ]
        )
    return render_markdown_table(lines, justify="right")


# --------------------------------------------------------------------------- main


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument(
        "--quick", action="store_true", help="two sessions, 5³ grids, 40 sampler trials"
    )
    parser.add_argument("--json", type=Path, help="also write the raw numbers here")
    parser.add_argument("--timing", action="store_true", help="only (a) and (a2)")
    args = parser.parse_args()
    plan = QUICK if args.quick else FULL
    started = time.perf_counter()
    load_before = os.getloadavg()

    timing_rows, table2_rows = real_sessions(plan)
    component_rows = trial_components(plan)
    keyframe_rows = keyframe_runs(plan)
    sampler_rows: list[dict[str, Any]] = []
    simulation_rows: list[dict[str, Any]] = []
    if not args.timing:
        grid_best = {row["session"]: row["best_shift"] for row in table2_rows}
        sampler_rows = sampler_runs(plan, grid_best)
        simulation_rows = simulation_runs(plan)

    grid_size = plan.grid_values**3
    print(f"(a) Grid of {grid_size} trials (paper range 1e-8..1), wall time\n")
    print(timing_table(timing_rows))
    print("\n(a2) Where a trial's time goes: CPU per trial in one process\n")
    print(components_table(component_rows))
    print("\n(a3) Keyframes (2 s) against every pose in the graph, the same grid\n")
    print(keyframe_table(keyframe_rows))
    if not args.timing:
        print(
            f"\n(b) Table 2: ground-truth metric and tag RMSE over the {grid_size}-trial grid "
            "(maps built with the chosen settings)\n"
        )
        print(table2(table2_rows))
        print("\n(b2) The chosen settings\n")
        print(chosen_table(table2_rows))
        print(f"\n(c) Optuna TPE, {plan.sampler_trials} trials, shift metric, against the grid\n")
        print(sampler_table(sampler_rows, grid_size))
        print(
            f"\n(d) Simulation ({plan.sim_poses} poses), {plan.sim_values}³ grid ±2 decades "
            "around the generating variances; offsets orientation / linear / angular\n"
        )
        print(simulation_table(simulation_rows))
    total_s = time.perf_counter() - started
    load_after = os.getloadavg()
    print(
        f"\ntotal {total_s / 60:.1f} min; {os.cpu_count()} CPUs, load average (1 min) "
        f"{load_before[0]:.1f} before and {load_after[0]:.1f} after (the machine is shared)"
    )
    if args.json:
        document = {
            "quick": args.quick,
            "plan": {
                "sessions": [name for name, _ in plan.sessions],
                "grid_values": plan.grid_values,
                "sampler_trials": plan.sampler_trials,
                "sampler_seeds": list(SAMPLER_SEEDS),
                "sim_poses": plan.sim_poses,
                "sim_scales": list(plan.sim_scales),
                "sim_values": plan.sim_values,
                "processes": plan.processes,
            },
            "grid_timing": timing_rows,
            "trial_components": component_rows,
            "keyframes": keyframe_rows,
            "table2": table2_rows,
            "sampler": sampler_rows,
            "simulation": simulation_rows,
            "total_s": total_s,
            "load_average_before_after": [load_before[0], load_after[0]],
        }
        args.json.write_text(json.dumps(_finite(document), indent=2))
    return 0


def _finite(value: Any) -> Any:
    """JSON-ready: NaN and inf become None."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_finite(v) for v in value]
    return value


if __name__ == "__main__":
    sys.exit(main())
