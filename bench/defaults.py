"""How the default noise variances are chosen, and how well that choice generalizes.

    .venv/bin/python bench/defaults.py            # the paper grid on every session with truth
    .venv/bin/python bench/defaults.py --quick    # a 5×5×5 grid

The same grid is swept on every shared real session with ground truth and on simulated sessions
(a procedural two-loop walk and a real trajectory re-simulated, each with known truth). Every grid
point gets, per dataset, its ground-truth metric relative to that dataset's pre-optimized map
(``gt / gt_pre``; < 1 is better than not optimizing). The default is the grid point with the
lowest *mean* relative metric over all datasets (no dataset is tuned by name). Generalization is
checked by leaving each dataset out: choose on the others, report the left-out dataset's relative
metric at that choice next to its own best (its ground-truth-chosen) and the current defaults'.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from app.cli.tables import render_markdown_table  # noqa: E402
from app.domain.evaluation.ground_truth import load_ground_truth, parse_ground_truth_json  # noqa: E402
from app.domain.evaluation.simulate import SimulationConfig, simulate_session  # noqa: E402
from app.domain.evaluation.sweep_plan import SweepPlan  # noqa: E402
from app.domain.evaluation.tuning import Axis, SearchSpace, TuningTarget  # noqa: E402
from app.domain.mapping.params import SlamParams  # noqa: E402
from app.domain.upload.session import Session, load_session, parse_session  # noqa: E402
from bench.tuning import REAL  # noqa: E402  (the real sessions with ground truth)
from workers.sweep_pool import run_sweep  # noqa: E402

DATA = REPO / "data"


def datasets() -> list[tuple[str, Session, dict[int, Any]]]:
    out = []
    for name, gt in REAL:
        out.append(
            (
                name,
                load_session(DATA / "sessions" / f"{name}.json"),
                load_ground_truth(DATA / "ground_truth" / gt),
            )
        )
    simulated = simulate_session(SimulationConfig(num_poses=1500, seed=11, outlier_fraction=0.02))
    out.append(
        (
            "simulated_walk",
            parse_session(simulated.upload),
            parse_ground_truth_json(simulated.ground_truth_json(detected_only=True)),
        )
    )
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--processes", type=int, default=2)
    parser.add_argument("--json", type=Path, help="write every dataset's grid here")
    args = parser.parse_args()
    num = 5 if args.quick else 10
    space = SearchSpace(
        tuple(
            Axis(name, 1e-8, 1.0, num)
            for name in (
                "tag_orientation_var_rad2",
                "odom_linear_var_m2_per_s",
                "odom_angular_var_rad2_per_s",
            )
        )
    )
    grid = space.grid()
    names, relative = [], []
    defaults = SlamParams()
    default_relative = []
    for name, session, truth in datasets():
        trials = run_sweep(
            session,
            SweepPlan(method="grid", space=space),
            ground_truth=truth,
            processes=args.processes,
        )
        target = TuningTarget.prepare(session, defaults, truth)
        gt_pre = target.baseline()[1]
        at_defaults = target.run({n: getattr(defaults, n) for n in space.names})
        names.append(name)
        relative.append(
            [
                t.gt_metric / gt_pre if t.converged and math.isfinite(t.gt_metric) else math.inf
                for t in trials
            ]
        )
        default_relative.append(at_defaults.gt_metric / gt_pre)
        print(f"{name}: {len(trials)} trials, gt_pre {gt_pre:.4f}", file=sys.stderr)
    table = np.array(relative)  # (datasets, grid points)
    if args.json:
        args.json.write_text(
            json.dumps({"datasets": names, "grid": grid, "relative": table.tolist()})
        )

    chosen = int(np.argmin(np.mean(table, axis=0)))
    print("Chosen by the lowest mean relative ground-truth metric over all datasets:")
    print(json.dumps(grid[chosen]))
    rows = [["left out", "at leave-one-out choice", "own best", "all-data choice", "old defaults"]]
    for k, name in enumerate(names):
        others = np.delete(table, k, axis=0)
        pick = int(np.argmin(np.mean(others, axis=0)))
        rows.append(
            [
                name,
                f"{table[k, pick]:.3f}",
                f"{np.min(table[k]):.3f}",
                f"{table[k, chosen]:.3f}",
                f"{default_relative[k]:.3f}",
            ]
        )
    print(render_markdown_table(rows))
    print("(ground-truth metric ÷ pre-optimized; < 1 is better than not optimizing)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
