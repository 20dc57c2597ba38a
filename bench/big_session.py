"""What one big session costs the server (docs/operations.md, Reliability): the API process's
memory growth while it accepts the upload (and while it refuses one with too many poses), then,
once a worker has built the map, the size and time of the app-map's first GET and of the
dashboard's map page and the memory they grow the API by; how long each build stage takes, the
``store`` stage's write transactions (on SQLite each holds the write lock that long: the bulk data
in chunks of 1 MiB, then one small fenced write), and how soon a cancel stops the build's running
optimization, and a running sweep trial; and the worker's peak memory after each build stage
(``--only worker-memory``: the build in a process of its own).

    .venv/bin/python -m bench.big_session                    # 100,000 poses (the most accepted)
    .venv/bin/python -m bench.big_session --poses 20000 --refused-poses 0 --only sweep-cancel
    .venv/bin/python -m bench.big_session --postgres-url postgresql+psycopg://postgres@127.0.0.1/x
    .venv/bin/python -m bench.big_session --refused-poses 0 --api-postgres-url postgresql+psycopg://…

(``-m``: run as a file, ``bench/http.py`` would hide the standard library's ``http``.)

The session is simulated (``app.domain.evaluation.simulate``) and sent gzipped, as the app sends it.
Memory is the API process's peak resident set (``VmHWM`` of ``/proc/<pid>/status``) before and after
each request.
"""

from __future__ import annotations

import argparse
import gzip
import re
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
# ``python bench/big_session.py`` puts bench/ first on sys.path, where bench/http.py would shadow
# the standard library's http (which httpx imports)
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != REPO / "bench"]
sys.path.insert(0, str(REPO))

import httpx  # noqa: E402
from sqlalchemy.orm import Session  # noqa: E402

from app.cli.server_process import ServerProcess  # noqa: E402
from app.config import Settings  # noqa: E402
from app.domain.evaluation.sweep_plan import SweepPlan  # noqa: E402
from app.domain.evaluation.tuning import SearchSpace  # noqa: E402
from app.storage import queue, sweeps  # noqa: E402
from app.storage.db import Database  # noqa: E402
from app.storage.migrate import upgrade_to_head  # noqa: E402
from tests.service.helpers import get_job, insert_session, simulated_bytes  # noqa: E402
from workers import pipeline  # noqa: E402
from workers.main import Worker  # noqa: E402


def status_kib(pid: int, field: str) -> int:
    """A ``/proc/<pid>/status`` field in KiB (``VmRSS``, ``VmHWM``)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    raise LookupError(field)


def peak_mib(pid: int) -> float:
    return status_kib(pid, "VmHWM") / 1024


def timed_request(
    server: ServerProcess, method: str, path: str, what: str, **kwargs: Any
) -> httpx.Response:
    """One request to the API, printed with its status, size, time and the API's memory growth."""
    peak_before = peak_mib(server.pid)
    started_s = time.monotonic()
    with others_probed(server) as others_s:
        answer = httpx.request(method, server.url + path, timeout=600, **kwargs)
    took_s = time.monotonic() - started_s
    peak_after = peak_mib(server.pid)
    print(
        f"{what}: {answer.status_code}, {len(answer.content) / 2**20:.2f} MiB in {took_s:.1f} s; "
        f"API peak memory {peak_before:.0f} → {peak_after:.0f} MiB "
        f"(+{peak_after - peak_before:.0f} MiB); {others(others_s)}"
    )
    return answer


@contextmanager
def others_probed(server: ServerProcess) -> Iterator[list[float]]:
    """Another client's ``GET /v1/maps``, every 50 ms while the block runs (is anyone else kept
    waiting by this request?): their latencies, s."""
    latencies_s: list[float] = []
    stop = threading.Event()
    auth = {"Authorization": f"Bearer {server.admin_key}"}

    def probe() -> None:
        with httpx.Client(base_url=server.url, timeout=600, headers=auth) as client:
            while not stop.is_set():
                started_s = time.monotonic()
                client.get("/v1/maps")
                latencies_s.append(time.monotonic() - started_s)
                stop.wait(0.05)

    thread = threading.Thread(target=probe, daemon=True)
    thread.start()
    try:
        yield latencies_s
    finally:
        stop.set()
        thread.join()


def others(latencies_s: list[float]) -> str:
    if not latencies_s:
        return "no other request meanwhile"
    return (
        f"another client's GET /v1/maps meanwhile: {len(latencies_s)} answered, the slowest in "
        f"{max(latencies_s) * 1000:.0f} ms"
    )


def api_memory_growth(raw: bytes, folder: Path, *, refused: bytes | None) -> None:
    """The upload of ``raw`` (and of ``refused``), then the map built by a worker, its app-map
    and the dashboard's pages fetched; each measured request in a server process of its own
    (the peak resident set only grows: a second request would show only what it adds to the
    first one's peak)."""
    log = folder / "serve.log"
    env = {"INVISIBLE_MAP_DATA_DIR": str(folder)}
    url = f"sqlite:///{folder / 'api.sqlite3'}"

    def fresh_server(database_url: str = url) -> ServerProcess:
        return ServerProcess(database_url, workers=0, env=env, log_path=log)

    if refused is not None:
        with fresh_server(f"sqlite:///{folder / 'refused.sqlite3'}") as server:
            upload(server, refused, warmed(server), "refused")
    with fresh_server() as server:
        created = upload(server, raw, warmed(server), "accepted").json()
    db = Database(url)
    started_s = time.monotonic()
    Worker(db, Settings(database_url=url, lease_s=600.0, heartbeat_s=5.0)).run_once()
    print(f"build (worker, path graph included): {time.monotonic() - started_s:.1f} s")
    db.dispose()
    app_map = f"/v1/maps/{created['map_id']}/app-map"
    for encoding in ("gzip", "identity"):
        with fresh_server() as server:
            auth = warmed(server)
            answer = timed_request(
                server,
                "GET",
                app_map,
                f"first GET of the app-map ({encoding})",
                headers={**auth, "Accept-Encoding": encoding},
            )
            timed_request(server, "GET", app_map, "  its second GET", headers=auth)
    document = answer.json()
    print(
        f"app-map: {len(document['odometry_vertices'])} odometry vertices; "
        f"notes: {document['notes']}"
    )
    for what, path in (
        ("dashboard map page", f"/admin/maps/{created['map_id']}"),
        ("dashboard session page", f"/admin/sessions/{created['session_id']}"),
        ("dashboard raw download", f"/admin/sessions/{created['session_id']}/raw"),
    ):
        with fresh_server() as server, httpx.Client(base_url=server.url, timeout=600) as browser:
            warmed(server)
            form = browser.get("/admin/login").text
            token = re.search(r'name="form_token" value="([^"]+)"', form)
            assert token is not None
            browser.post(
                "/admin/login",
                data={"form_token": token.group(1), "key": server.admin_key, "next": "/admin"},
            )
            browser.get("/admin")  # warm: the templates
            peak_before = peak_mib(server.pid)
            started_s = time.monotonic()
            with others_probed(server) as others_s:
                page = browser.get(path, headers={"Accept-Encoding": "identity"})
            took_s = time.monotonic() - started_s
            peak_after = peak_mib(server.pid)
            print(
                f"{what}: {page.status_code}, {len(page.content) / 2**20:.2f} MiB in "
                f"{took_s:.1f} s; API peak memory {peak_before:.0f} → {peak_after:.0f} MiB "
                f"(+{peak_after - peak_before:.0f} MiB); {others(others_s)}"
            )


def warmed(server: ServerProcess) -> dict[str, str]:
    """The admin's headers, after a first request (its imports are no part of a figure)."""
    auth = {"Authorization": f"Bearer {server.admin_key}"}
    httpx.get(server.url + "/v1/info", headers=auth)
    return auth


def upload(server: ServerProcess, raw: bytes, auth: dict[str, str], what: str) -> httpx.Response:
    body = gzip.compress(raw)
    return timed_request(
        server,
        "POST",
        "/v1/sessions",
        f"{what} upload of {len(body) / 2**20:.1f} MiB gzip ({len(raw) / 2**20:.1f} MiB JSON)",
        content=body,
        headers={**auth, "Content-Type": "application/json", "Content-Encoding": "gzip"},
    )


def stage_times(raw: bytes, url: str) -> None:
    """Each stage's time, and the longest write transaction of the ``store`` stage (on SQLite
    the write lock is held that long: BEGIN IMMEDIATE to commit)."""
    db = Database(url)
    upgrade_to_head(db)
    job_id = insert_session(db, raw).job_id
    seconds: dict[str, float] = {}
    store_transactions_s: list[float] = []
    fenced_s: list[float] = []
    transaction, finish = db.transaction, queue.finish

    @contextmanager
    def timed_transaction() -> Iterator[Session]:
        started_s = time.perf_counter()
        try:
            with transaction() as db_session:
                yield db_session
        finally:
            took_s = time.perf_counter() - started_s
            store_transactions_s.append(took_s)
            if db_session.info.pop("finished_job", False):
                fenced_s.append(took_s)

    def noted_finish(db_session: Session, *args: Any, **kwargs: Any) -> Any:
        db_session.info["finished_job"] = True
        return finish(db_session, *args, **kwargs)

    def timed(stage: pipeline.Stage) -> pipeline.Stage:
        def run(ctx: pipeline.JobContext) -> None:
            started_s = time.perf_counter()
            if stage.name == "store":
                db.transaction = timed_transaction  # type: ignore[method-assign]
                queue.finish = noted_finish
            try:
                stage.run(ctx)
            finally:
                db.transaction = transaction  # type: ignore[method-assign]
                queue.finish = finish
            seconds[stage.name] = time.perf_counter() - started_s

        return pipeline.Stage(name=stage.name, weight=stage.weight, run=run)

    stages = tuple(timed(stage) for stage in pipeline.BUILD_MAP_STAGES)
    settings = Settings(database_url=url, lease_s=120.0, heartbeat_s=5.0)
    Worker(db, settings, pipelines={"build_map": stages}).run_once()
    state = get_job(db, job_id).state.value
    db.dispose()
    times = ", ".join(f"{name} {value:.2f} s" for name, value in seconds.items())
    print(f"build on {db.backend}: {state}; {times}")
    print(
        f"store on {db.backend}: {len(store_transactions_s)} write transactions, the longest "
        f"{max(store_transactions_s) * 1e3:.0f} ms (the fenced one, that makes the version "
        f"visible: {fenced_s[0] * 1e3:.0f} ms)"
    )


#: Run by :func:`worker_memory` in a process of its own: one build, the peak resident set after
#: each stage (MiB).
_WORKER_PEAKS = """
import sys
from app.config import Settings
from app.storage.db import Database
from bench.big_session import peak_mib
from workers import pipeline
from workers.main import Worker
import os

url = sys.argv[1]
peaks = {"start": peak_mib(os.getpid())}

def measured(stage):
    def run(ctx):
        stage.run(ctx)
        peaks[stage.name] = peak_mib(os.getpid())
    return pipeline.Stage(name=stage.name, weight=stage.weight, run=run)

stages = tuple(measured(stage) for stage in pipeline.BUILD_MAP_STAGES)
settings = Settings(database_url=url, lease_s=600.0, heartbeat_s=5.0)
Worker(Database(url), settings, pipelines={"build_map": stages}).run_once()
print(", ".join(f"{name} {mib:.0f}" for name, mib in peaks.items()))
"""


def worker_memory(raw: bytes, url: str) -> None:
    """The worker's peak resident set after each stage of one build, in a process of its own
    (the bench's own process holds the simulated session)."""
    db = Database(url)
    upgrade_to_head(db)
    insert_session(db, raw)
    db.dispose()
    done = subprocess.run(
        [sys.executable, "-c", _WORKER_PEAKS, url],
        cwd=REPO,
        capture_output=True,
        text=True,
        check=True,
    )
    print(f"worker peak memory after each stage, MiB: {done.stdout.strip()}")


def cancel_latency(raw: bytes, url: str) -> None:
    """Cancel the build 0.5 s into its optimization; how long until the job is canceled."""
    db = Database(url)
    upgrade_to_head(db)
    job_id = insert_session(db, raw).job_id
    settings = Settings(database_url=url, lease_s=30.0, heartbeat_s=5.0)
    state, latency_s = cancel_during(db, settings, job_id, stage="optimize", after_s=0.5)
    print(
        f"cancel 0.5 s into optimize (heartbeat 5 s): {state} {latency_s:.2f} s after it was asked"
    )


def cancel_during(
    db: Database, settings: Settings, job_id: int, *, stage: str, after_s: float
) -> tuple[str, float]:
    """Run one job on a worker thread, cancel it ``after_s`` into ``stage``: its final state and
    how long after the cancel was asked it stopped running, s."""
    thread = threading.Thread(target=Worker(db, settings).run_once)
    thread.start()
    while get_job(db, job_id).stage != stage:
        time.sleep(0.05)
    time.sleep(after_s)
    asked_s = time.monotonic()
    with db.transaction() as db_session:
        queue.request_cancel(db_session, job_id)
    while get_job(db, job_id).state.value == "running":
        time.sleep(0.02)
    latency_s = time.monotonic() - asked_s
    thread.join()
    state = get_job(db, job_id).state.value
    db.dispose()
    return state, latency_s


def sweep_cancel_latency(raw: bytes, url: str) -> None:
    """A sweep of the session (2 grid trials in one job) canceled 1 s into its first trial (the
    warm start, a Levenberg–Marquardt run of the whole session, is part of it); how long until
    its job is canceled. The heartbeat is 0.5 s (served: 5 s, which adds up to 5 s to any
    cancel) so that what is measured is how soon a running trial stops."""
    db = Database(url)
    upgrade_to_head(db)
    inserted = insert_session(db, raw)
    plan = SweepPlan(
        method="grid",
        space=SearchSpace.from_dict(
            {"odom_linear_var_m2_per_s": {"low": 1e-6, "high": 1e-1, "num": 2}}
        ),
    )
    with db.transaction() as db_session:
        queue.request_cancel(db_session, inserted.job_id)  # the build: not measured here
        sweeps.create_sweep(
            db_session,
            map_id=inserted.map_id,
            session_id=inserted.session_id,
            plan=plan,
            base_params={},
            ground_truth=None,
            max_attempts=3,
        )
    job_id = inserted.job_id + 1
    settings = Settings(database_url=url, lease_s=30.0, heartbeat_s=0.5)
    state, latency_s = cancel_during(db, settings, job_id, stage="trials", after_s=1.0)
    print(
        f"cancel 1 s into a sweep's first trial (heartbeat 0.5 s): {state} {latency_s:.2f} s "
        "after it was asked"
    )


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--poses", type=int, default=100_000, help="poses of the session")
    parser.add_argument(
        "--refused-poses",
        type=int,
        default=120_000,
        help="poses of a session the API refuses (more than INVISIBLE_MAP_MAX_POSES); 0: none",
    )
    parser.add_argument("--postgres-url", help="also build on this (empty, migrated) database")
    parser.add_argument(
        "--only",
        choices=("memory", "stages", "worker-memory", "cancel", "sweep-cancel"),
        help="one measurement",
    )
    parser.add_argument(
        "--api-postgres-url",
        help="also upload the session through an API on this (empty) database: its memory growth",
    )
    args = parser.parse_args()
    raw = simulated_bytes(args.poses)
    print(f"a simulated session of {args.poses} poses")
    with tempfile.TemporaryDirectory() as folder:
        if args.only in (None, "memory"):
            refused = simulated_bytes(args.refused_poses) if args.refused_poses else None
            api_memory_growth(raw, Path(folder), refused=refused)
            del refused
        if args.only in (None, "stages"):
            stage_times(raw, f"sqlite:///{Path(folder) / 'build.sqlite3'}")
        if args.only in (None, "worker-memory"):
            worker_memory(raw, f"sqlite:///{Path(folder) / 'worker.sqlite3'}")
        if args.only in (None, "cancel"):
            cancel_latency(raw, f"sqlite:///{Path(folder) / 'cancel.sqlite3'}")
        if args.only in (None, "sweep-cancel"):
            sweep_cancel_latency(raw, f"sqlite:///{Path(folder) / 'sweep.sqlite3'}")
    if args.api_postgres_url and args.only in (None, "memory"):
        upgrade_to_head(Database(args.api_postgres_url))
        with tempfile.TemporaryDirectory() as folder:
            env = {"INVISIBLE_MAP_DATA_DIR": folder}
            log = Path(folder) / "serve.log"
            with ServerProcess(args.api_postgres_url, workers=0, env=env, log_path=log) as server:
                upload(server, raw, warmed(server), "accepted (PostgreSQL)")
    if args.postgres_url and args.only in (None, "stages"):
        stage_times(raw, args.postgres_url)
    return 0


if __name__ == "__main__":
    sys.exit(main())
