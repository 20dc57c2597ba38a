"""Sweep benchmark on the server: does a sweep get faster with more worker processes?

    .venv/bin/python bench/sweep_server.py                 # paper grid (1000 trials), 1 and 2
    .venv/bin/python bench/sweep_server.py --quick         # a 5×5×5 grid
    .venv/bin/python bench/sweep_server.py --database-url postgresql+psycopg://postgres@127.0.0.1/db

For each worker count: a fresh database, ``invisible-map serve`` (no embedded workers) and
``invisible-map worker --processes N``; the real session ``occam_room`` is uploaded over HTTP and
built, then ``POST /v1/maps/{id}/sweeps`` starts the grid and ``GET /v1/sweeps/{id}`` is polled
every 0.5 s until it succeeds. Wall time is from the POST to the last trial stored (±0.5 s).
Both runs use the same allocator: where the machine has jemalloc, the worker command gets it in
``LD_PRELOAD`` (one process runs its worker in itself, so it cannot preload it on its own; the
processes ``--processes 2`` starts would). Target (issue 4): 2 worker processes ≥ 1.8× faster
than 1.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import httpx

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from app.cli.server_process import ServerProcess, WorkerProcess  # noqa: E402
from app.cli.tables import render_markdown_table  # noqa: E402
from app.client import Client  # noqa: E402
from workers.allocator import jemalloc_path  # noqa: E402

SESSION = REPO / "data" / "sessions" / "occam_room.json"
PAPER_AXES = ("tag_orientation_var_rad2", "odom_linear_var_m2_per_s", "odom_angular_var_rad2_per_s")


def run_once(database_url: str, processes: int, values_per_axis: int, log_dir: Path) -> float:
    """Wall seconds of one grid sweep with ``processes`` worker processes."""
    with (
        ServerProcess(
            database_url, workers=0, log_path=log_dir / f"serve-{processes}.log"
        ) as server,
        WorkerProcess(
            database_url,
            processes=processes,
            env=_allocator_env(),
            log_path=log_dir / f"worker-{processes}.log",
        ),
    ):
        client = Client(server.url, api_key=server.admin_key)
        created = client.upload_session(SESSION.read_bytes())
        client.wait_for_job(created["job_id"], timeout_s=120)
        headers = {"Authorization": f"Bearer {server.admin_key}"}
        space = {name: {"low": 1e-8, "high": 1.0, "num": values_per_axis} for name in PAPER_AXES}
        started = time.perf_counter()
        response = httpx.post(
            f"{server.url}/v1/maps/{created['map_id']}/sweeps",
            json={"space": space},
            headers=headers,
        )
        response.raise_for_status()
        sweep_url = f"{server.url}/v1/sweeps/{response.json()['sweep_id']}"
        while True:
            sweep = httpx.get(sweep_url, headers=headers).json()
            if sweep["state"] != "running":
                break
            time.sleep(0.5)  # a person watching the page, not a busy loop on the same 2 cores
        wall_s = time.perf_counter() - started
        if sweep["state"] != "succeeded":
            raise RuntimeError(f"the sweep ended {sweep['state']}: {sweep['error']}")
        return wall_s


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="a 5×5×5 grid instead of 10×10×10")
    parser.add_argument("--database-url", help="PostgreSQL URL (default: a fresh SQLite file)")
    args = parser.parse_args()
    values = 5 if args.quick else 10
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        walls = {}
        for processes in (1, 2):
            url = args.database_url or f"sqlite:///{tmp}/sweep-{processes}.db"
            if args.database_url:
                _reset_postgres(url)
            walls[processes] = run_once(url, processes, values, Path(tmp))
            rows.append(
                [
                    str(processes),
                    str(values**3),
                    f"{walls[processes]:.1f}",
                    f"{values**3 / walls[processes]:.1f}",
                    f"{walls[1] / walls[processes]:.2f}×",
                ]
            )
    header = ["worker processes", "trials", "wall s", "trials/s", "speed-up"]
    print(render_markdown_table([header, *rows], justify="right"))
    print(f"allocator: {jemalloc_path() or 'malloc (no jemalloc on this machine)'}")
    print("target: 2 worker processes ≥ 1.8× faster than 1")
    return 0


def _allocator_env() -> dict[str, str]:
    library = jemalloc_path()
    return {"LD_PRELOAD": library} if library else {}


def _reset_postgres(url: str) -> None:
    from sqlalchemy import create_engine, text

    engine = create_engine(url)
    with engine.begin() as connection:
        connection.execute(text("DROP SCHEMA public CASCADE; CREATE SCHEMA public"))
    engine.dispose()


if __name__ == "__main__":
    raise SystemExit(main())
