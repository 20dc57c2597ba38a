"""What one big session costs the server (docs/operations.md, Reliability): the API process's
memory growth while it accepts the upload (and while it refuses one with too many poses), then,
once a worker has built the map, the size and time of the app-map's first GET and of the
dashboard's map page and the memory they grow the API by; how long each build stage takes, the
``store`` stage being the build's one write transaction (on SQLite it holds the write lock that
long), and how soon a cancel stops the build's running optimization.

    .venv/bin/python bench/big_session.py                    # 100,000 poses (the most accepted)
    .venv/bin/python bench/big_session.py --poses 20000 --refused-poses 0
    .venv/bin/python bench/big_session.py --postgres-url postgresql+psycopg://postgres@127.0.0.1/x
    .venv/bin/python bench/big_session.py --refused-poses 0 --api-postgres-url postgresql+psycopg://…

The session is simulated (``app.domain.simulate``) and sent gzipped, as the app sends it. Memory
is the API process's peak resident set (``VmHWM`` of ``/proc/<pid>/status``) before and after
each request.
"""

from __future__ import annotations

import argparse
import gzip
import re
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
# ``python bench/big_session.py`` puts bench/ first on sys.path, where bench/http.py would shadow
# the standard library's http (which httpx imports)
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != REPO / "bench"]
sys.path.insert(0, str(REPO))

import httpx  # noqa: E402

from app.cli.server_process import ServerProcess  # noqa: E402
from app.config import Settings  # noqa: E402
from app.storage import queue  # noqa: E402
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
    answer = httpx.request(method, server.url + path, timeout=600, **kwargs)
    took_s = time.monotonic() - started_s
    peak_after = peak_mib(server.pid)
    print(
        f"{what}: {answer.status_code}, {len(answer.content) / 2**20:.2f} MiB in {took_s:.1f} s; "
        f"API peak memory {peak_before:.0f} → {peak_after:.0f} MiB "
        f"(+{peak_after - peak_before:.0f} MiB)"
    )
    return answer


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
            page = browser.get(path, headers={"Accept-Encoding": "identity"})
            took_s = time.monotonic() - started_s
            peak_after = peak_mib(server.pid)
            print(
                f"{what}: {page.status_code}, {len(page.content) / 2**20:.2f} MiB in "
                f"{took_s:.1f} s; API peak memory {peak_before:.0f} → {peak_after:.0f} MiB "
                f"(+{peak_after - peak_before:.0f} MiB)"
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
    db = Database(url)
    upgrade_to_head(db)
    job_id = insert_session(db, raw).job_id
    seconds: dict[str, float] = {}

    def timed(stage: pipeline.Stage) -> pipeline.Stage:
        def run(ctx: pipeline.JobContext) -> None:
            started_s = time.perf_counter()
            stage.run(ctx)
            seconds[stage.name] = time.perf_counter() - started_s

        return pipeline.Stage(name=stage.name, weight=stage.weight, run=run)

    stages = tuple(timed(stage) for stage in pipeline.BUILD_MAP_STAGES)
    settings = Settings(database_url=url, lease_s=120.0, heartbeat_s=5.0)
    Worker(db, settings, pipelines={"build_map": stages}).run_once()
    state = get_job(db, job_id).state.value
    db.dispose()
    times = ", ".join(f"{name} {value:.2f} s" for name, value in seconds.items())
    print(f"build on {db.backend}: {state}; {times} (store: one write transaction)")


def cancel_latency(raw: bytes, url: str) -> None:
    """Cancel the build 0.5 s into its optimization; how long until the job is canceled."""
    db = Database(url)
    upgrade_to_head(db)
    job_id = insert_session(db, raw).job_id
    settings = Settings(database_url=url, lease_s=30.0, heartbeat_s=5.0)
    thread = threading.Thread(target=Worker(db, settings).run_once)
    thread.start()
    while get_job(db, job_id).stage != "optimize":
        time.sleep(0.05)
    time.sleep(0.5)
    asked_s = time.monotonic()
    with db.transaction() as db_session:
        queue.request_cancel(db_session, job_id)
    while get_job(db, job_id).state.value == "running":
        time.sleep(0.02)
    latency_s = time.monotonic() - asked_s
    thread.join()
    state = get_job(db, job_id).state.value
    db.dispose()
    print(
        f"cancel 0.5 s into optimize (heartbeat 5 s): {state} {latency_s:.2f} s after it was asked"
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
        "--api-postgres-url",
        help="also upload the session through an API on this (empty) database: its memory growth",
    )
    args = parser.parse_args()
    raw = simulated_bytes(args.poses)
    print(f"a simulated session of {args.poses} poses")
    with tempfile.TemporaryDirectory() as folder:
        refused = simulated_bytes(args.refused_poses) if args.refused_poses else None
        api_memory_growth(raw, Path(folder), refused=refused)
        del refused
        stage_times(raw, f"sqlite:///{Path(folder) / 'build.sqlite3'}")
        cancel_latency(raw, f"sqlite:///{Path(folder) / 'cancel.sqlite3'}")
    if args.api_postgres_url:
        upgrade_to_head(Database(args.api_postgres_url))
        with tempfile.TemporaryDirectory() as folder:
            env = {"INVISIBLE_MAP_DATA_DIR": folder}
            log = Path(folder) / "serve.log"
            with ServerProcess(args.api_postgres_url, workers=0, env=env, log_path=log) as server:
                upload(server, raw, warmed(server), "accepted (PostgreSQL)")
    if args.postgres_url:
        stage_times(raw, args.postgres_url)
    return 0


if __name__ == "__main__":
    sys.exit(main())
