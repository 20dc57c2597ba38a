"""Mapping-core benchmark: one command, prints a table.

    .venv/bin/python bench/run.py                 # synthetic 1k, 10k, 100k poses + real sessions
    .venv/bin/python bench/run.py --quick         # 1k and 10k only
    .venv/bin/python bench/run.py --json out.json # also write the rows as JSON

Each case runs in a fresh process (so its peak memory is its own) and reports:

- build ms: screening and building the factor graph (Python);
- LM ms: Levenberg–Marquardt wall time (the median of ``--repeat`` runs on real sessions);
- iterations: LM iterations;
- solve ms: one linearize-and-solve of the same graph, the floor LM cannot beat; ``LM/solve`` is the
  ratio (target ≤ 6);
- peak MiB: the process's peak resident memory (Python, gtsam and the session included).

Synthetic sessions are building walks from ``app.domain.evaluation.simulate`` at 10 Hz with tags
every 4–10 m: a 2×1 corridor grid at 1k poses, 3×2 at 10k, 6×4 at 100k; two floors from 10k up.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import resource
import statistics
import sys
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # run from a checkout without installing

from app.cli.tables import render_markdown_table  # noqa: E402
from app.domain.evaluation.simulate import SimulationConfig, simulate_session  # noqa: E402
from app.domain.mapping.params import SlamParams  # noqa: E402
from app.domain.mapping.slam import linearize_and_solve_ms, optimize_session  # noqa: E402
from app.domain.upload.session import load_session, parse_session  # noqa: E402

SESSIONS = REPO / "data" / "sessions"
SYNTHETIC_POSES = (1_000, 10_000, 100_000)
#: Corridor grid per walk length, so longer walks map a larger building (more tags).
BLOCKS_FOR_POSES = {10_000: (3, 2), 100_000: (6, 4)}
TARGETS = "targets: real session LM ≤ 50 ms; 10k ≤ 600 ms; 100k ≤ 10 s and ≤ 1024 MiB; LM/solve ≤ 6"


def run_case(case: dict[str, Any]) -> dict[str, Any]:
    """Run one case in this process and measure it."""
    params = SlamParams(compute_marginals=case.get("marginals", True))
    if case["kind"] == "synthetic":
        config = SimulationConfig(
            num_poses=case["poses"],
            seed=7,
            two_floors=case["poses"] >= 10_000,
            blocks=BLOCKS_FOR_POSES.get(case["poses"], (2, 1)),
        )
        started = time.perf_counter()
        sim = simulate_session(config)
        session = parse_session(sim.upload)
        del sim
        prepare_s = time.perf_counter() - started
    else:
        started = time.perf_counter()
        session = load_session(case["path"])
        prepare_s = time.perf_counter() - started

    runs = []
    for _ in range(case["repeat"]):
        runs.append(optimize_session(session, params))
    result = runs[-1]
    solve_ms = statistics.median(
        linearize_and_solve_ms(session, params) for _ in range(case["repeat"])
    )
    lm_ms = statistics.median(r.stats.optimize_ms for r in runs)
    peak_mib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return {
        "case": case["name"],
        "poses": session.num_poses,
        "detections": len(session.detections),
        "tags": len(result.tag_ids),
        "build_ms": statistics.median(r.stats.build_ms for r in runs),
        "lm_ms": lm_ms,
        "iterations": result.stats.iterations,
        "solve_ms": solve_ms,
        "lm_over_solve": lm_ms / solve_ms if solve_ms > 0 else float("nan"),
        "marginals_ms": statistics.median(r.stats.marginals_ms for r in runs),
        "peak_mib": peak_mib,
        "prepare_s": prepare_s,
    }


def cases(quick: bool, repeat: int) -> list[dict[str, Any]]:
    out: list[dict[str, Any]] = [
        {"kind": "synthetic", "name": f"synthetic {n // 1000}k", "poses": n, "repeat": 1}
        for n in SYNTHETIC_POSES
        if not (quick and n > 10_000)
    ]
    out += [
        {"kind": "real", "name": path.stem, "path": str(path), "repeat": repeat}
        for path in sorted(SESSIONS.glob("*.json"))
    ]
    return out


def format_rows(rows: list[dict[str, Any]]) -> str:
    columns = [
        ("case", "case", "{}"),
        ("poses", "poses", "{}"),
        ("detections", "detections", "{}"),
        ("tags", "tags", "{}"),
        ("build ms", "build_ms", "{:.0f}"),
        ("LM ms", "lm_ms", "{:.1f}"),
        ("iterations", "iterations", "{}"),
        ("solve ms", "solve_ms", "{:.1f}"),
        ("LM/solve", "lm_over_solve", "{:.1f}"),
        ("marginals ms", "marginals_ms", "{:.0f}"),
        ("peak MiB", "peak_mib", "{:.0f}"),
    ]
    lines = [[title for title, _, _ in columns]]
    lines += [[pattern.format(row[key]) for _, key, pattern in columns] for row in rows]
    return render_markdown_table(lines, justify="right")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="skip the 100k-pose case")
    parser.add_argument("--repeat", type=int, default=5, help="runs per real session (median)")
    parser.add_argument("--json", type=Path, help="also write the rows here")
    args = parser.parse_args()

    context = multiprocessing.get_context("spawn")
    rows = []
    todo = cases(args.quick, args.repeat)
    for number, case in enumerate(todo, start=1):
        print(f"[{number}/{len(todo)}] {case['name']} …", file=sys.stderr, flush=True)
        with context.Pool(1) as pool:
            rows.append(pool.apply(run_case, (case,)))
    print(format_rows(rows))
    print(TARGETS)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
