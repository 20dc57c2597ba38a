"""The ``invisible-map`` command.

    invisible-map process SESSION [--gt GT] [--param NAME=VALUE …] [-o MAP.json]
                          [--app-map FILE] [--plot FILE.png]
    invisible-map evaluate SESSION… --gt GT [--gt GT …] [--param NAME=VALUE …] [--json]
    invisible-map evaluate A.json B.json … --gt GT --joint [--json]   (one map of all sessions)
    invisible-map evaluate-samples [--out DIR]
    invisible-map sweep SESSION [--gt GT] [--grid | --trials N] [--objective shift|ground_truth]
                        [--space JSON] [--processes N] [--plot-dir DIR] [--json]
    invisible-map simulate OUT.json [--gt-out GT.json] [--from-session SESSION] [--poses N]
                        [--two-floors] [--noise NAME=VALUE …] [--seed N] [--sessions N]
    invisible-map serve | worker | migrate | keys …   (the server: see app/cli/server.py)
    invisible-map export OUT.zip [--include-keys] [--force]
    invisible-map import ARCHIVE.zip [--include-keys] [--merge]   (backups: app/cli/backup.py)
    invisible-map import-firebase DIR     (a lab's Firebase export: app/cli/firebase.py)

Every failure on bad input is one line on stderr, ``invisible-map: error: …``, and exit status 1
(2 for a malformed command line, as argparse does).

Building the parser imports no library heavier than the standard one: each handler imports what
its command needs when it runs (the mapping core with numpy and gtsam for ``process``, the web
stack and the database for ``serve``, plotting for ``--plot``), so that ``--help`` and the light
commands start at once (``tests/cli/test_cli.py`` checks ``sys.modules``; ``bench/cli_start.py``
measures it).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from app.cli.backup import add_backup_commands
from app.cli.common import (
    DATA_DIR,
    DEMO_SESSIONS,
    PROGRAM,
    CommandError,
    load_ground_truth_file,
    load_session_file,
)
from app.cli.common import add_param_option as _add_param_option
from app.cli.common import slam_params as _params
from app.cli.firebase import add_firebase_commands
from app.cli.server import add_server_commands
from app.cli.tables import before_after_cell, change_cell, fixed_cell, render_markdown_table
from app.cli.tuning import add_sweep_commands
from app.domain.errors import InvisibleMapError

if TYPE_CHECKING:
    from app.domain.evaluation.table import Evaluation, JointEvaluation
    from app.domain.frames import FloatArray
    from app.domain.mapping.map_result import MapResult
    from app.domain.mapping.params import SlamParams
    from app.domain.upload.session import Session


def main(argv: Sequence[str] | None = None) -> int:
    parser = _parser()
    args = parser.parse_args(argv)
    try:
        return int(args.handler(args))
    except (InvisibleMapError, CommandError) as err:
        print(f"{PROGRAM}: error: {err}", file=sys.stderr)
        return 1
    except OSError as err:
        where = f" {err.filename}" if err.filename else ""
        print(f"{PROGRAM}: error:{where}: {err.strerror or err}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"{PROGRAM}: interrupted", file=sys.stderr)
        return 130


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=PROGRAM,
        description="Graph SLAM on Invisible Map mapping sessions.",
    )
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    process = commands.add_parser(
        "process", help="optimize one session into a map", description="Optimize one session."
    )
    process.add_argument("session", type=Path, help="the app's upload (JSON, may be gzipped)")
    process.add_argument("--gt", type=Path, help="ground truth (RTAB-Map export or GT JSON)")
    _add_param_option(process)
    process.add_argument("-o", "--output", type=Path, help="write our map JSON here")
    process.add_argument("--app-map", type=Path, help="write the app's download format here")
    process.add_argument("--plot", type=Path, help="write a top-down PNG here")
    process.add_argument(
        "--no-poi-correction",
        action="store_true",
        help="take points of interest's pose_id as written (the app writes it one too high)",
    )
    process.set_defaults(handler=_process)

    evaluate = commands.add_parser(
        "evaluate",
        help="compare optimized maps with pre-optimized ones and ground truth",
        description="Optimize each session and compare it with its pre-optimized map and with "
        "ground truth. One --gt applies to every session; several pair up with the sessions "
        "in order.",
    )
    evaluate.add_argument("sessions", type=Path, nargs="+", metavar="SESSION")
    evaluate.add_argument("--gt", type=Path, action="append", required=True, metavar="GT")
    _add_param_option(evaluate)
    evaluate.add_argument("--json", action="store_true", help="print a JSON array, not a table")
    evaluate.add_argument(
        "--joint",
        action="store_true",
        help="also optimize all the sessions together into one map (docs/multi-session.md): one "
        'more row, "dataset": "joint", with each session alone against the joint map '
        '("by_session")',
    )
    evaluate.set_defaults(handler=_evaluate)

    demo = commands.add_parser(
        "evaluate-samples",
        help="process the sample sessions shipped in data/ offline and write maps, plots and a "
        "table (the server's demo is `serve --demo`)",
    )
    demo.add_argument("--out", type=Path, default=Path("out"), help="output folder (./out)")
    _add_param_option(demo)
    demo.set_defaults(handler=_demo)
    add_sweep_commands(commands)
    add_server_commands(commands)
    add_backup_commands(commands)
    add_firebase_commands(commands)
    return parser


# --------------------------------------------------------------------------- process


def _process(args: argparse.Namespace) -> int:
    from app.domain.evaluation.table import evaluate_map

    params = _params(args.param)
    ground_truth = load_ground_truth_file(args.gt) if args.gt else None
    session = load_session_file(args.session, correct_poi_pose_id=not args.no_poi_correction)
    result = _optimize_with_progress(session, params)
    evaluation = evaluate_map(session, result, ground_truth, dataset=args.session.stem)

    if args.output or args.app_map:  # (the map formats import the path graph: networkx)
        from app.domain.formats.map_io import app_map_as_served, map_to_json, save_json
    if args.output:
        save_json(map_to_json(result), args.output)
    if args.app_map:
        from app.domain.navigation.skeleton import build_skeleton

        # the document the server serves for this version: the same graph (the worker's corridor
        # skeleton), the same exporter
        save_json(app_map_as_served(result, path_graph=build_skeleton(result)), args.app_map)
    if args.plot:
        from app.render.map_plot import render_map_png

        render_map_png(result, session, ground_truth=ground_truth, path=args.plot)

    print(session)
    print(
        f"map: {len(result.tag_ids)} tags, {result.detections_used} detections used, "
        f"{len(result.rejections)} rejected, {result.stats.iterations} LM iterations, "
        f"error {result.stats.initial_error:.4g} → {result.stats.final_error:.4g}, "
        f"{result.stats.optimize_ms:.1f} ms"
    )
    for reason, count in sorted(result.rejection_counts().items()):
        print(f"rejected ({reason}): {count}")
    for warning in result.warnings:
        print(f"warning: {warning}")
    print(
        f"shift metric: pre {fixed_cell(evaluation.shift_pre)}  "
        f"opt {fixed_cell(evaluation.shift_opt)}"
    )
    if ground_truth is not None:
        print(
            f"ground-truth metric: pre {fixed_cell(evaluation.gt_metric_pre)}  "
            f"opt {fixed_cell(evaluation.gt_metric_opt)}  "
            f"({evaluation.tags_with_ground_truth} tags with ground truth)"
        )
        print(
            f"tag RMSE: pre {fixed_cell(evaluation.tag_rmse_pre_m, 3)} m  "
            f"opt {fixed_cell(evaluation.tag_rmse_opt_m, 3)} m"
        )
        if evaluation.ground_truth_ids_ignored:
            print(_ignored_line(evaluation))
    for path in (args.output, args.app_map, args.plot):
        if path:
            print(f"wrote {path}")
    return 0


def _optimize_with_progress(session: Session, params: SlamParams) -> MapResult:
    from tqdm import tqdm

    from app.domain.mapping.slam import optimize_session

    with tqdm(
        desc="optimizing", unit=" it", leave=False, disable=None, file=sys.stderr
    ) as progress:

        def on_iteration(_iteration: int, error: float) -> None:
            progress.set_postfix(error=f"{error:.4g}")
            progress.update(1)

        return optimize_session(session, params, on_iteration=on_iteration)


# --------------------------------------------------------------------------- evaluate


def _evaluate(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    params = _params(args.param)
    ground_truth_paths: list[Path] = args.gt
    if len(ground_truth_paths) not in (1, len(args.sessions)):
        raise CommandError(
            f"give one --gt for all sessions or one per session; got {len(ground_truth_paths)} "
            f"for {len(args.sessions)} sessions"
        )
    truths = {path: load_ground_truth_file(path) for path in dict.fromkeys(ground_truth_paths)}
    if args.joint:
        return _evaluate_joint(args, params, truths)
    pairs = list(zip(args.sessions, ground_truth_paths * len(args.sessions), strict=False))
    rows = []
    for session_path, truth_path in tqdm(
        pairs, desc="evaluating", unit=" session", leave=False, disable=None, file=sys.stderr
    ):
        rows.append(_evaluate_one(session_path, params, truths[truth_path]))
    if args.json:
        print(json.dumps([row.to_dict() for row in rows], indent=2))
    else:
        print(format_table(rows))
        for row in rows:
            if row.ground_truth_ids_ignored:
                print(f"{row.dataset}: {_ignored_line(row)}")
    return 0


def _evaluate_joint(
    args: argparse.Namespace, params: SlamParams, truths: dict[Path, dict[int, FloatArray]]
) -> int:
    """Each session alone, then the joint map of all of them (``--joint``), and each session
    alone against the joint map on all its tags, its shared ones and its own ones."""
    from tqdm import tqdm

    from app.domain.evaluation.table import evaluate_joint, evaluate_map
    from app.domain.mapping.joint import optimize_sessions

    if len(truths) != 1:
        raise CommandError("--joint compares every session with one ground truth: give one --gt")
    ground_truth = next(iter(truths.values()))
    names = [_dataset_name(path) for path in args.sessions]
    if len(set(names)) != len(names):
        raise CommandError(f"--joint needs sessions with different names, got {names}")
    sessions = [load_session_file(path) for path in args.sessions]
    with tqdm(
        total=len(sessions) + 1, desc="joint map", unit=" step", leave=False, disable=None,
        file=sys.stderr,
    ) as bar:  # fmt: skip

        def progress(step: str, fraction: float) -> None:
            done = fraction * len(sessions) if step == "walks" else len(sessions) + fraction
            bar.update(max(0.0, done - bar.n))

        joint = optimize_sessions(sessions, params, names=names, on_progress=progress)
    # each walk alone is the map optimize_session makes of it (its depth scale applied)
    alone = {part.dataset: part.alone for part in joint.parts if part.alone is not None}
    rows: list[Evaluation] = [
        evaluate_map(part_session, alone[name], ground_truth, dataset=name)
        for name, part_session in zip(names, joint.sessions, strict=True)
    ]
    joint_evaluation = evaluate_joint(joint, alone, ground_truth)
    if args.json:
        out = [row.to_dict() for row in rows] + [joint_evaluation.to_dict()]
        print(json.dumps(out, indent=2))
        return 0
    print(format_table([*rows, joint_evaluation.row]))
    print()
    print(render_markdown_table(joint_report_lines(joint_evaluation)))
    print()
    for name, comparison in joint_evaluation.by_session.items():
        print(f"- {name}: {comparison.weighting}")
    for warning in joint.map.warnings:
        print(f"warning: {warning}")
    return 0


def joint_report_lines(evaluation: JointEvaluation) -> list[list[str]]:
    """The per-walk table of ``evaluate --joint``: each walk alone → in the building map, on all
    its tags, its shared ones and its own ones (tag RMSE, m), the ground-truth metric on all,
    and the factor its variances were raised by."""
    lines = [
        [
            "session",
            "tags all/shared/own",
            "GT alone → joint",
            "RMSE all m",
            "Δ",
            "RMSE shared m",
            "RMSE own m",
            "weight ×",
        ]
    ]
    for name, c in evaluation.by_session.items():
        lines.append(
            [
                name,
                f"{c.tags_compared}/{c.shared.with_truth}/{c.own.with_truth}",
                before_after_cell(c.gt_metric_alone, c.gt_metric_joint),
                before_after_cell(c.tag_rmse_alone_m, c.tag_rmse_joint_m, 3),
                change_cell(c.tag_rmse_joint_m, c.tag_rmse_alone_m),
                before_after_cell(c.shared.tag_rmse_alone_m, c.shared.tag_rmse_joint_m, 3),
                before_after_cell(c.own.tag_rmse_alone_m, c.own.tag_rmse_joint_m, 3),
                f"{c.disagreement_factor:.3g}",
            ]
        )
    return lines


def _dataset_name(path: Path) -> str:
    return path.stem.split(".")[0]


def _evaluate_one(
    session_path: Path, params: SlamParams, ground_truth: dict[int, FloatArray] | None
) -> Evaluation:
    from app.domain.evaluation.table import evaluate_map
    from app.domain.mapping.slam import optimize_session

    session = load_session_file(session_path)
    result = optimize_session(session, params)
    return evaluate_map(session, result, ground_truth, dataset=_dataset_name(session_path))


TABLE_COLUMNS = (
    ("dataset", "dataset", "{}"),
    ("poses", "poses", "{}"),
    ("tags", "tags", "{}"),
    ("used", "detections_used", "{}"),
    ("rejected", "detections_rejected", "{}"),
    ("opt ms", "optimize_ms", "{:.1f}"),
    ("GT pre", "gt_metric_pre", "{:.4f}"),
    ("GT opt", "gt_metric_opt", "{:.4f}"),
    ("Δ GT", None, None),
    ("RMSE pre m", "tag_rmse_pre_m", "{:.3f}"),
    ("RMSE opt m", "tag_rmse_opt_m", "{:.3f}"),
    ("shift pre", "shift_pre", "{:.4f}"),
    ("shift opt", "shift_opt", "{:.4f}"),
)


def format_table(rows: Sequence[Evaluation]) -> str:
    """A Markdown table of evaluation rows (also readable in a terminal)."""
    header = [title for title, _, _ in TABLE_COLUMNS]
    lines = [header]
    for row in rows:
        cells = []
        for _, attribute, pattern in TABLE_COLUMNS:
            if attribute is None:
                change = (
                    row.gt_metric_opt / row.gt_metric_pre - 1 if row.gt_metric_pre else math.nan
                )
                cells.append("—" if math.isnan(change) else f"{change:+.0%}")
                continue
            value = getattr(row, attribute)
            is_nan = isinstance(value, float) and math.isnan(value)
            cells.append("—" if is_nan else str(pattern).format(value))
        lines.append(cells)
    return render_markdown_table(lines)


# --------------------------------------------------------------------------- demo


def _demo(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from app.domain.evaluation.table import evaluate_map
    from app.domain.formats.map_io import app_map_as_served, map_to_json, save_json
    from app.domain.mapping.slam import optimize_session
    from app.domain.navigation.skeleton import build_skeleton
    from app.render.map_plot import render_map_png

    params = _params(args.param)

    sessions_dir, truth_dir = DATA_DIR / "sessions", DATA_DIR / "ground_truth"
    if not sessions_dir.is_dir():
        raise CommandError(f"demo data not found at {sessions_dir}")
    args.out.mkdir(parents=True, exist_ok=True)
    rows = []
    for name, truth_file in tqdm(
        DEMO_SESSIONS, desc="samples", unit=" session", disable=None, file=sys.stderr
    ):
        session = load_session_file(sessions_dir / f"{name}.json")
        ground_truth = load_ground_truth_file(truth_dir / truth_file) if truth_file else None
        result = optimize_session(session, params)
        save_json(map_to_json(result), args.out / f"{name}.map.json")
        app_map = app_map_as_served(result, path_graph=build_skeleton(result))
        save_json(app_map, args.out / f"{name}.app-map.json")
        render_map_png(result, session, ground_truth=ground_truth, path=args.out / f"{name}.png")
        rows.append(evaluate_map(session, result, ground_truth, dataset=name))
    table = format_table(rows)
    (args.out / "evaluation.md").write_text(table + "\n")
    print(table)
    print(f"\nwrote maps (*.map.json), app maps (*.app-map.json) and plots (*.png) to {args.out}/")
    return 0


def _ignored_line(row: Evaluation) -> str:
    ids = list(row.ground_truth_ids_ignored)
    shown = ", ".join(str(i) for i in ids[:10]) + (", …" if len(ids) > 10 else "")
    return f"{len(ids)} ground-truth tags are not in this map and were ignored ({shown})"


if __name__ == "__main__":
    sys.exit(main())
