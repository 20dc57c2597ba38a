"""The ``sweep`` and ``simulate`` commands of ``invisible-map`` (see ``app/cli/program.py``).

invisible-map sweep data/sessions/occam_room.json --gt data/ground_truth/occam_room_tape.json
invisible-map sweep SESSION --trials 100 --json           # Optuna's sampler, 100 trials
invisible-map simulate sim.json --poses 2000 --two-floors --noise outlier_fraction=0.05
invisible-map simulate sim.json --from-session data/sessions/floor_2_straight.json
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from app.cli.common import (
    add_param_option,
    load_ground_truth_file,
    load_session_file,
    read_input_file,
    slam_params,
)
from app.domain.errors import ParameterError

if TYPE_CHECKING:  # the mapping core is imported by the handlers, when they run
    from tqdm import tqdm

    from app.domain.evaluation.simulate import SimulatedSession
    from app.domain.evaluation.tuning import SearchSpace

#: The largest ``--space`` file read, bytes (a search space is a few lines of JSON).
MAX_SPACE_BYTES = 2**20
#: ``--noise`` may set these fields of ``SimulationConfig`` (its noise levels; written out so
#: that the parser does not import the simulator: ``tests/cli/test_tuning_cli.py`` checks them).
NOISE_FIELDS = (
    "odom_translation_drift_m_per_sqrt_s",
    "odom_vertical_drift_m_per_sqrt_s",
    "odom_rotation_drift_rad_per_sqrt_s",
    "odom_tilt_error_rad",
    "odom_scale_error",
    "tag_position_noise_m_at_1m",
    "tag_depth_noise_ratio",
    "tag_rotation_noise_rad",
    "corner_noise_px",
    "outlier_fraction",
)


def add_sweep_commands(commands: Any) -> None:
    sweep = commands.add_parser(
        "sweep",
        help="sweep the SLAM hyperparameters over a grid or with a sampler",
        description="Optimize SESSION once per trial and score every map by the shift metric "
        "(and by the ground-truth metric with --gt), then build the map with the chosen settings "
        "as `apply` does (a check: a converged trial is its build). Default: the paper-sized "
        "10×10×10 grid.",
    )
    sweep.add_argument("session", type=Path, metavar="SESSION")
    sweep.add_argument("--gt", type=Path, help="ground truth (RTAB-Map export or GT JSON)")
    how = sweep.add_mutually_exclusive_group()
    how.add_argument("--grid", action="store_true", help="every grid point (the default)")
    how.add_argument("--trials", type=int, help="Optuna's TPE sampler with this many trials")
    sweep.add_argument(
        "--objective",
        choices=("shift", "ground_truth"),
        default="shift",
        help="what chooses the best trial (ground_truth needs --gt)",
    )
    sweep.add_argument(
        "--space",
        help='swept parameters as JSON, {"NAME": {"low": L, "high": H, "num": N}, …} '
        "(default: the paper grid)",
    )
    sweep.add_argument("--processes", type=int, default=None, help="worker processes (all CPUs)")
    sweep.add_argument("--seed", type=int, default=0, help="sampler seed")
    add_param_option(sweep)
    sweep.add_argument("--plot-dir", type=Path, help="write heatmap.png (and shift_vs_gt.png)")
    sweep.add_argument("--runs-out", type=Path, help="write every trial as JSON here")
    sweep.add_argument("--json", action="store_true", help="print the summary as JSON")
    sweep.set_defaults(handler=sweep_command)

    simulate = commands.add_parser(
        "simulate",
        help="write a synthetic session in the app's upload format, with its ground truth",
        description="A procedural building walk (default) or, with --from-session, a real "
        "session's optimized trajectory and tags as the truth, with controlled noise.",
    )
    simulate.add_argument("out", type=Path, metavar="OUT.json", help="the session to write")
    simulate.add_argument("--gt-out", type=Path, help="ground truth (default OUT.gt.json)")
    simulate.add_argument("--from-session", type=Path, help="take the truth from this session")
    simulate.add_argument("--poses", type=int, default=1000, help="poses of a procedural walk")
    simulate.add_argument("--two-floors", action="store_true", help="a second floor with stairs")
    simulate.add_argument(
        "--noise",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help=f"a noise level; names: {', '.join(NOISE_FIELDS)}",
    )
    simulate.add_argument("--seed", type=int, default=0)
    simulate.add_argument(
        "--sessions",
        type=int,
        default=1,
        metavar="N",
        help="N walks of one building, each in its own world frame (OUT-1.json … OUT-N.json, "
        "one ground truth), for maps of several sessions (docs/multi-session.md)",
    )
    simulate.set_defaults(handler=simulate_command)


def sweep_command(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from app.cli.common import CommandError
    from app.domain.evaluation.sweep_plan import SweepPlan
    from app.domain.evaluation.tuning import SearchSpace, TuningTarget, sweep_result
    from app.domain.formats.map_io import save_json
    from workers.sweep_pool import run_sweep

    base_params = slam_params(args.param)
    ground_truth = load_ground_truth_file(args.gt) if args.gt else None
    session = load_session_file(args.session)
    space = SearchSpace.paper_grid() if args.space is None else _space(args.space)
    if args.trials is not None:
        plan = SweepPlan(
            method="sampler",
            space=space,
            trials=args.trials,
            objective=args.objective,
            seed=args.seed,
        )
    else:
        plan = SweepPlan(method="grid", space=space, objective=args.objective)
    if args.objective == "ground_truth" and ground_truth is None:
        raise CommandError("--objective ground_truth needs --gt")
    if args.processes is not None and args.processes < 1:
        raise CommandError(f"--processes must be ≥ 1, got {args.processes}")

    started = time.perf_counter()
    with tqdm(total=plan.total, desc="sweep", unit=" trials", disable=None, file=sys.stderr) as bar:
        trials = run_sweep(
            session,
            plan,
            base_params=base_params,
            ground_truth=ground_truth,
            processes=args.processes,
            on_progress=lambda n: _advance(bar, n),
        )
    trials_s = time.perf_counter() - started
    # The chosen settings built again as `apply` builds them: the check that they are the trials.
    result = sweep_result(
        TuningTarget.prepare(session, base_params, ground_truth), trials, plan.objective
    )
    wall_s = time.perf_counter() - started
    summary, scored = result.summary, result.to_dict()
    report = {
        "dataset": args.session.stem,
        "method": plan.method,
        "runs": len(trials),
        "best_params": summary.best_values,
        "best_shift": scored["best_shift"],
        "gt_metric_pre": scored["gt_metric_pre"],
        "gt_metric_at_best_shift": scored["gt_metric_at_best_shift"],
        "gt_metric_best": scored["gt_metric_best"],
        "wall_s": round(wall_s, 3),
        "trials_wall_s": round(trials_s, 3),
        **{k: v for k, v in scored.items() if k not in ("runs",)},
    }
    written = []
    if args.plot_dir:
        from app.render.sweep_plots import heatmap_png, shift_vs_gt_png

        args.plot_dir.mkdir(parents=True, exist_ok=True)
        (args.plot_dir / "heatmap.png").write_bytes(
            heatmap_png(space, trials, objective=plan.objective)
        )
        written.append(args.plot_dir / "heatmap.png")
        if ground_truth is not None:
            (args.plot_dir / "shift_vs_gt.png").write_bytes(
                shift_vs_gt_png(trials, gt_metric_pre=summary.gt_metric_pre)
            )
            written.append(args.plot_dir / "shift_vs_gt.png")
    if args.runs_out:
        save_json([t.to_dict() for t in trials], args.runs_out)
        written.append(args.runs_out)
    if args.json:
        print(json.dumps(report, indent=2))
    else:
        _print_summary(report)
        for path in written:
            print(f"wrote {path}")
    return 0


def _advance(bar: tqdm[Any], n: int) -> None:
    bar.update(n)


def _print_summary(report: dict[str, Any]) -> None:
    def fmt(value: Any) -> str:
        return "n/a" if value is None else f"{value:.4g}"

    runs, method, wall_s = report["runs"], report["method"], report["wall_s"]
    print(
        f"{report['dataset']}: {runs} trials ({method}) in {report['trials_wall_s']:.1f} s, "
        f"{wall_s:.1f} s with the builds of the chosen settings"
    )
    print(f"best by {report['objective']}: {report['best_params']}")
    print(f"shift metric: pre {fmt(report['shift_pre'])}  best {fmt(report['best_shift'])}")
    if report["gt_metric_pre"] is not None:
        print(
            f"ground-truth metric: pre {fmt(report['gt_metric_pre'])}  "
            f"shift-chosen {fmt(report['gt_metric_at_best_shift'])}  "
            f"ground-truth-chosen {fmt(report['gt_metric_best'])}"
        )
        print(f"Spearman ρ shift vs GT over the trials: {fmt(report['shift_gt_spearman'])}")
    if not report["builds_equal_trials"]:
        print(
            "warning: a build of a chosen setting does not score as its trial did; "
            f"the builds: {json.dumps(report['builds'])}"
        )


def _space(text: str) -> SearchSpace:
    """``--space``: a JSON object, or the path of a file holding one."""
    from app.domain.evaluation.tuning import SearchSpace

    source = (
        text
        if text.lstrip().startswith(("{", "[")) or not Path(text).exists()
        else read_input_file(Path(text), max_bytes=MAX_SPACE_BYTES)
    )
    try:
        document = json.loads(source)
    except (ValueError, RecursionError) as err:  # not UTF-8, not JSON, too many digits
        raise ParameterError(f"--space is not valid JSON: {err}") from err
    if not isinstance(document, dict):
        raise ParameterError("--space must be a JSON object of parameters")
    return SearchSpace.from_dict(document)


def simulate_command(args: argparse.Namespace) -> int:
    from app.domain.evaluation.simulate import SimulationConfig, simulate_session
    from app.domain.formats.map_io import save_json
    from app.domain.upload.session import parse_session

    noise = _noise(args.noise)
    if args.sessions != 1:
        return _simulate_building(args, noise)
    if args.from_session:
        simulated = _simulate_from_session(args.from_session, noise, args.seed)
    else:
        config = SimulationConfig(num_poses=args.poses, two_floors=args.two_floors, seed=args.seed)
        simulated = simulate_session(dataclasses.replace(config, **noise))
    parse_session(simulated.upload)  # what the server would do with it: must not raise
    gt_out = args.gt_out or args.out.with_suffix(".gt.json")
    save_json(simulated.upload, args.out)
    save_json(simulated.ground_truth_json(detected_only=True), gt_out)
    print(simulated)
    print(f"wrote {args.out}")
    print(f"wrote {gt_out}")
    return 0


def _simulate_building(args: argparse.Namespace, noise: dict[str, Any]) -> int:
    from app.cli.common import CommandError
    from app.domain.evaluation.ground_truth import ground_truth_to_json
    from app.domain.evaluation.simulate import SimulationConfig
    from app.domain.evaluation.simulate_building import simulate_building_sessions
    from app.domain.formats.map_io import save_json
    from app.domain.upload.session import parse_session

    if args.sessions < 1 or args.sessions > 100:
        raise CommandError(f"--sessions must be 1–100, got {args.sessions}")
    if args.from_session:
        raise CommandError("--sessions simulates a procedural building; not with --from-session")
    config = SimulationConfig(num_poses=args.poses, two_floors=args.two_floors, seed=args.seed)
    building = simulate_building_sessions(dataclasses.replace(config, **noise), count=args.sessions)
    seen: set[int] = set()
    for k, simulated in enumerate(building.sessions, start=1):
        parse_session(simulated.upload)  # what the server would do with it: must not raise
        out = args.out.with_name(f"{args.out.stem}-{k}{args.out.suffix}")
        save_json(simulated.upload, out)
        seen.update(simulated.detected_tag_ids)
        print(simulated)
        print(f"wrote {out}")
    gt_out = args.gt_out or args.out.with_suffix(".gt.json")
    save_json(ground_truth_to_json({t: building.world_T_tag_true[t] for t in sorted(seen)}), gt_out)
    print(f"wrote {gt_out}")
    return 0


def _noise(pairs: list[str]) -> dict[str, Any]:
    values: dict[str, Any] = {}
    for pair in pairs:
        name, sep, raw = pair.partition("=")
        name = name.strip()
        if not sep or name not in NOISE_FIELDS:
            raise ParameterError(
                f"--noise expects NAME=VALUE with NAME one of {', '.join(NOISE_FIELDS)}; "
                f"got {pair!r}"
            )
        try:
            values[name] = float(raw)
        except ValueError as err:
            raise ParameterError(f"--noise {name}: not a number: {raw!r}") from err
    return values


def _simulate_from_session(path: Path, noise: dict[str, Any], seed: int) -> SimulatedSession:
    """The paper's simulation: the optimized map of a real session is the truth."""
    from app.domain.evaluation.simulate import SimulationConfig, simulate_along_trajectory
    from app.domain.mapping.slam import optimize_session

    session = load_session_file(path)
    result = optimize_session(session, slam_params([]))
    used = result.residuals.tag_detection_index
    dt_s = float(
        max(
            1e-3, (session.timestamp_s[-1] - session.timestamp_s[0]) / max(1, session.num_poses - 1)
        )
    )
    rate_hz = 1.0 / dt_s
    config = SimulationConfig(
        num_poses=session.num_poses,
        rate_hz=rate_hz,
        detection_rate_hz=rate_hz,
        map_id=f"{session.map_id}_simulated",
        num_points_of_interest=0,
        seed=seed,
    )
    config = dataclasses.replace(config, **noise)
    truth = {int(t): result.world_T_tag[k] for k, t in enumerate(result.tag_ids)}
    return simulate_along_trajectory(
        config,
        result.world_T_phone,
        truth,
        session.detections.pose_index[used],
        session.detections.tag_id[used],
    )
