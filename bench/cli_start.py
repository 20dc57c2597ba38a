"""How long the ``invisible-map`` command takes to start (issue 28, finding 10): wall and CPU time
of ``--help``, ``process --help`` and ``process`` on real sessions, the median of N runs each,
and which heavy libraries the command imports before its handler runs.

    .venv/bin/python -m bench.cli_start              # 7 runs each
    .venv/bin/python -m bench.cli_start --runs 15

Each run is a process of its own (``os.wait4`` gives its CPU time: user + system, which the
machine's other load does not inflate the way it does wall time). Prints a Markdown table.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
COMMAND = [str(REPO / ".venv" / "bin" / "invisible-map")]
SESSIONS = REPO / "data" / "sessions"

CASES = (
    ("--help", ["--help"]),
    ("process --help", ["process", "--help"]),
    ("process onetag (15 kB)", ["process", str(SESSIONS / "onetag.json")]),
    ("process occam_room (0.9 MB)", ["process", str(SESSIONS / "occam_room.json")]),
)
HEAVY = ("numpy", "gtsam", "networkx", "fastapi", "sqlalchemy", "matplotlib", "tqdm")


def run_once(args: list[str]) -> tuple[float, float]:
    """(wall s, CPU s) of one run of the command."""
    started = time.perf_counter()
    process = subprocess.Popen(
        COMMAND + args, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, cwd=REPO
    )
    _, status, usage = os.wait4(process.pid, 0)
    wall_s = time.perf_counter() - started
    if os.waitstatus_to_exitcode(status) != 0:
        raise SystemExit(f"{' '.join(args)} failed")
    return wall_s, usage.ru_utime + usage.ru_stime


def imported_by_the_parser() -> list[str]:
    """The heavy libraries in ``sys.modules`` once the command's parser is built."""
    probe = (
        "import sys; from app.cli import program; program._parser(); "
        f"print(' '.join(m for m in {HEAVY!r} if m in sys.modules))"
    )
    out = subprocess.run(
        [sys.executable, "-c", probe], capture_output=True, text=True, check=True, cwd=REPO
    )
    return out.stdout.split()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=7, help="runs of each command (7)")
    args = parser.parse_args()
    print("| command | wall s (median) | CPU s (median) | CPU s (min–max) |")
    print("|---|---|---|---|")
    for name, command in CASES:
        run_once(command)  # warm the file cache
        results = [run_once(command) for _ in range(args.runs)]
        walls, cpus = [w for w, _ in results], [c for _, c in results]
        print(
            f"| `invisible-map {name}` | {statistics.median(walls):.3f} | "
            f"{statistics.median(cpus):.3f} | {min(cpus):.3f}–{max(cpus):.3f} |"
        )
    heavy = imported_by_the_parser()
    print(f"\nimported with the parser: {', '.join(heavy) if heavy else 'none of ' + str(HEAVY)}")
    print(f"({args.runs} runs each, {os.cpu_count()} cores, load {os.getloadavg()[0]:.1f})")


if __name__ == "__main__":
    main()
