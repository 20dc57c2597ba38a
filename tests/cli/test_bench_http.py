"""``bench/http.py --quick --no-wrk`` on SQLite: the HTTP benchmark runs end to end with the Python
client and prints a row with positive requests/s and no failed request for every endpoint it
measures (2 maps instead of 50, 0.3 s per endpoint: about 30 s), and, on a machine of several cores,
the second table under ``serve``'s default API processes."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[2]

#: Every row the table must have (names as the benchmark prints them, ids as {id}).
ROWS = (
    "GET /healthz (first / last run:",
    "GET /v1/maps/{id}",
    "GET /v1/maps/{id}/app-map",
    "GET /v1/maps/{id}/geojson",
    "POST /v1/maps/{id}/routes (tag 300 → 320)",
    "POST /v1/localizations/{id}/updates",
    "GET /v1/maps (2 maps)",
    "GET /v1/jobs/{id}",
    "GET /v1/info",
    "update() alone, in process (same documents)",
    "GET /healthz, 1 connection",
    "POST …/routes, 1 connection",
)
#: The rows of the second table (serve's default API processes, one per core).
ALL_CORES_ROWS = (
    "GET /healthz (first / last run:",
    "GET /v1/maps/{id}",
    "POST /v1/maps/{id}/routes (tag 300 → 320)",
    "POST /v1/localizations/{id}/updates",
)
ALL_CORES_HEADING = "The same database under `serve`'s default:"


def table_rows(stdout: str) -> dict[str, list[str]]:
    """The Markdown table's rows by their first cell (header and rule left out)."""
    rows = {}
    for line in stdout.splitlines():
        if not line.startswith("| ") or re.fullmatch(r"\|[-|]+\|", line):
            continue
        cells = [cell.strip() for cell in line.strip("|").split("|")]
        rows[cells[0]] = cells[1:]
    return rows


@pytest.mark.slow
def test_quick_run_on_sqlite_with_the_python_client(tmp_path: Path) -> None:
    env = {
        name: value
        for name, value in os.environ.items()
        if name != "DATABASE_URL" and not name.startswith("INVISIBLE_MAP_")
    }
    env["INVISIBLE_MAP_DATA_DIR"] = str(tmp_path / "var")
    done = subprocess.run(
        [
            *(sys.executable, "-m", "bench.http", "--quick", "--no-wrk"),
            # A smoke run: every row measured, briefly, over few maps (building the default 50
            # takes 30 s on a busy machine; 20 took ~15 s of this test's 48 s, 4 took 7 s).
            *("--duration-s", "0.3", "--maps", "2"),
        ],
        cwd=REPO_ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=240,
        check=False,
    )
    assert done.returncode == 0, done.stdout + done.stderr
    assert "python (asyncio + httpx)" in done.stdout
    main, _, all_cores = done.stdout.partition(ALL_CORES_HEADING)
    assert_rows(table_rows(main), ROWS, failed_column=5, stdout=done.stdout)
    if (os.cpu_count() or 1) > 1 and len(os.sched_getaffinity(0)) > 1:
        assert all_cores, f"no second table under serve's default processes:\n{done.stdout}"
        assert_rows(table_rows(all_cores), ALL_CORES_ROWS, failed_column=6, stdout=done.stdout)


def assert_rows(
    rows: dict[str, list[str]], names: tuple[str, ...], *, failed_column: int, stdout: str
) -> None:
    for name in names:
        found = [cells for first, cells in rows.items() if first.startswith(name)]
        assert found, f"no row {name!r} in:\n{stdout}"
        per_s = float(found[0][0].replace(",", ""))
        assert per_s > 0, f"{name}: {found[0]}"
        assert found[0][failed_column] == "0", f"{name}: failed requests: {found[0]}"
