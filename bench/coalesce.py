"""Walks added to a building's map one after another (issue 25, item 4): how many builds run,
how many versions are stored, and how long from the last add until the map's current version
holds every walk. One command, prints a table:

    .venv/bin/python bench/coalesce.py                      # SQLite in a temporary file (2–4 min)
    .venv/bin/python bench/coalesce.py --postgres postgresql+psycopg://postgres@127.0.0.1/x

A simulated building (``simulate_building_sessions``, ``--poses`` poses per walk, every walk in
its own frame): walk 1 makes the map (built first); then walks 2–5 are added to it with
``add_session_to_map`` (``POST /v1/maps/{id}/sessions``), by one client, either back to back
(``quick``) or every ``--pace`` × one build's time (``paced``: each add arrives while the build
of the previous one runs), with one real worker (the real pipeline) running throughout.

Columns: ``builds started`` (build jobs of the map a worker claimed after the first version),
``versions`` (stored after the first), ``last add → current s`` (wall time from the last add's
commit until the current version holds all five walks and no build of the map is under way),
``worker CPU s`` (the worker thread's CPU time for all of it, ``time.thread_time``: the load of
other processes does not count). Runs the code of the checkout it is in, so the same file run
from an older checkout measures before.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # run from a checkout without installing

from app.cli.tables import render_markdown_table  # noqa: E402
from app.config import Settings  # noqa: E402
from app.domain.evaluation.simulate import SimulationConfig  # noqa: E402
from app.domain.evaluation.simulate_building import simulate_building_sessions  # noqa: E402
from app.domain.upload.session import parse_session  # noqa: E402
from app.services.maps import add_session_to_map  # noqa: E402
from app.storage import maps, queue, sessions  # noqa: E402
from app.storage.db import Database  # noqa: E402
from app.storage.migrate import upgrade_to_head  # noqa: E402
from workers.main import Worker  # noqa: E402

#: Walks added after the first.
ADDS = 4
#: How often the main thread looks at the map, s.
POLL_S = 0.02


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--poses", type=int, default=1_200, help="poses per walk (1200)")
    parser.add_argument("--repeat", type=int, default=3, help="rounds per scenario (3)")
    parser.add_argument(
        "--pace", type=float, default=0.5, help="paced adds: every PACE × one build's time (0.5)"
    )
    parser.add_argument("--postgres", help="an empty PostgreSQL database URL (else SQLite)")
    parser.add_argument("--json", type=Path, help="also write the rows here")
    args = parser.parse_args()

    building = simulate_building_sessions(SimulationConfig(num_poses=args.poses), count=1 + ADDS)
    uploads = [
        json.dumps(walk.upload, separators=(",", ":")).encode() for walk in building.sessions
    ]
    rows: list[dict[str, Any]] = []
    build_s = 0.0
    for scenario in ("quick", "paced"):
        rounds = []
        for _ in range(args.repeat):
            with tempfile.TemporaryDirectory() as tmp:
                url = args.postgres or f"sqlite:///{tmp}/bench.sqlite3"
                rounds.append(
                    one_round(url, uploads, pace_s=args.pace * build_s * (scenario == "paced"))
                )
            build_s = build_s or rounds[-1]["first_build_s"]
        rows.append(
            {
                "scenario": scenario,
                "builds started": statistics.median(r["builds"] for r in rounds),
                "versions": statistics.median(r["versions"] for r in rounds),
                "last add → current s": round(statistics.median(r["settle_s"] for r in rounds), 2),
                "worker CPU s": round(statistics.median(r["worker_cpu_s"] for r in rounds), 2),
                "one build s": round(statistics.median(r["first_build_s"] for r in rounds), 2),
            }
        )
    print(
        f"\n{ADDS} walks of {args.poses} poses added to a map of one, one worker, "
        f"median of {args.repeat} rounds ({'PostgreSQL' if args.postgres else 'SQLite'})\n"
    )
    header = list(rows[0])
    print(render_markdown_table([header, *([str(row[c]) for c in header] for row in rows)]))
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2))
    return 0


def one_round(url: str, uploads: list[bytes], *, pace_s: float) -> dict[str, float]:
    """The map of walk 1, built; then the adds with a worker running; what it took."""
    db = Database(url)
    try:
        if url.startswith("postgresql"):
            _empty(db)
        upgrade_to_head(db)
        ids = []
        for k, raw in enumerate(uploads):
            with db.transaction() as tx:
                created = sessions.create_session(
                    tx,
                    parsed=parse_session(json.loads(raw)),
                    upload=sessions.StoredUpload.of(raw),
                    uploaded_by="bench",
                )
                if k > 0:  # only the building's map is built
                    queue.request_cancel(tx, created.job_id)
            ids.append((created.session_id, created.map_id))
        map_id = ids[0][1]
        settings = Settings(database_url=url, lease_s=60, heartbeat_s=5, poll_s=POLL_S)
        worker = Worker(db, settings)
        started_s = time.perf_counter()
        while worker.run_once():
            pass
        first_build_s = time.perf_counter() - started_s
        with db.read() as tx:
            first_job_ids = {j.id for j in queue.list_jobs(tx, map_id=map_id)[0]}

        stop = threading.Event()
        cpu: dict[str, float] = {}

        def work() -> None:
            begun = time.thread_time()
            worker.run(stop)
            cpu["s"] = time.thread_time() - begun

        thread = threading.Thread(target=work)
        thread.start()
        for k, (session_id, _) in enumerate(ids[1:]):
            if k and pace_s:
                time.sleep(pace_s)
            with db.transaction() as tx:
                add_session_to_map(tx, map_id, session_id, max_attempts=3)
        last_add_s = time.perf_counter()
        wanted = [session_id for session_id, _ in ids]
        while True:
            with db.read() as tx:
                info = maps.get_map(tx, map_id)
                jobs, _ = queue.list_jobs(tx, map_id=map_id, limit=100)
            settled = all(j.state in queue.TERMINAL_STATES for j in jobs)
            if settled and info.current is not None and info.current.session_ids == wanted:
                break
            if settled:
                raise RuntimeError(f"the map settled without all walks: {info.current}")
            time.sleep(POLL_S)
        settle_s = time.perf_counter() - last_add_s
        stop.set()
        thread.join()
        with db.read() as tx:
            jobs, _ = queue.list_jobs(tx, map_id=map_id, limit=100)
            versions = len(maps.list_versions(tx, map_id))
        builds = sum(1 for j in jobs if j.id not in first_job_ids and j.started_at is not None)
        return {
            "builds": builds,
            "versions": versions - 1,
            "settle_s": settle_s,
            "worker_cpu_s": cpu["s"],
            "first_build_s": first_build_s,
        }
    finally:
        db.dispose()


def _empty(db: Database) -> None:
    """Drop everything in the PostgreSQL database (each round starts empty)."""
    from sqlalchemy import text

    with db.engine.begin() as connection:
        connection.execute(text("DROP SCHEMA public CASCADE; CREATE SCHEMA public"))


if __name__ == "__main__":
    sys.exit(main())
