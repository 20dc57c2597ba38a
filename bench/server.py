"""Server benchmark: one command, prints a table.

    .venv/bin/python bench/server.py                       # embedded SQLite, 2 worker processes
    .venv/bin/python bench/server.py --database-url postgresql+psycopg://postgres@127.0.0.1/db
    .venv/bin/python bench/server.py --quick               # fewer uploads, shorter load

Starts ``invisible-map serve`` (uvicorn) with 2 worker processes on a fresh database and measures,
over HTTP on loopback:

1. upload → map-ready latency of a real session (``occam_room``, 621 poses) on an idle server:
   the time from sending the upload to seeing its job ``succeeded`` (polled every 10 ms);
2. sessions per minute sustained: many real sessions uploaded at once, the time until the last
   map is ready;
3. ``GET /v1/maps/{id}`` with 50 concurrent clients, next to ``GET /healthz`` on the same server
   as the floor (p50/p99 and their ratio).

Targets (issue 3): map-ready p95 ≤ 2 s; map GET p99 ≤ 3 × the /healthz p99.
The load generator runs on the same 2-core machine as the server, so it competes with it.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import httpx

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from app.client import Client  # noqa: E402
from app.server_process import ServerProcess  # noqa: E402
from app.storage.db import Database  # noqa: E402
from app.storage.migrate import upgrade_to_head  # noqa: E402
from app.tables import render_markdown_table  # noqa: E402

SESSIONS = REPO / "data" / "sessions"
LATENCY_SESSION = SESSIONS / "occam_room.json"
THROUGHPUT_SESSIONS = [
    SESSIONS / f"{name}.json"
    for name in ("occam_room", "floor_2_straight", "straight_209_occam", "desnat_straight_once")
]


def percentile(values: list[float], q: float) -> float:
    """The q-th percentile (0–100), linear interpolation between closest ranks."""
    ordered = sorted(values)
    if len(ordered) == 1:
        return ordered[0]
    rank = (len(ordered) - 1) * q / 100
    low = int(rank)
    high = min(low + 1, len(ordered) - 1)
    return ordered[low] + (ordered[high] - ordered[low]) * (rank - low)


def map_ready_latency_s(client: Client, uploads: int) -> list[float]:
    body = LATENCY_SESSION.read_bytes()
    latencies = []
    for _ in range(uploads):
        started = time.perf_counter()
        accepted = client.upload_session(body)
        client.wait_for_job(accepted["job_id"], timeout_s=120, poll_s=0.01)
        latencies.append(time.perf_counter() - started)
    return latencies


def sessions_per_minute(client: Client, uploads: int) -> tuple[float, float]:
    bodies = [path.read_bytes() for path in THROUGHPUT_SESSIONS]
    started = time.perf_counter()
    job_ids = [client.upload_session(bodies[i % len(bodies)])["job_id"] for i in range(uploads)]
    for job_id in job_ids:
        client.wait_for_job(job_id, timeout_s=600, poll_s=0.05)
    elapsed_s = time.perf_counter() - started
    return uploads / elapsed_s * 60, elapsed_s


async def _hammer(url: str, key: str, clients: int, duration_s: float) -> list[float]:
    latencies: list[float] = []
    limits = httpx.Limits(max_connections=clients, max_keepalive_connections=clients)
    headers = {"Authorization": f"Bearer {key}"}
    async with httpx.AsyncClient(limits=limits, headers=headers, timeout=30) as http:
        deadline = time.perf_counter() + duration_s

        async def one_client() -> None:
            while time.perf_counter() < deadline:
                started = time.perf_counter()
                response = await http.get(url)
                latencies.append(time.perf_counter() - started)
                if response.status_code != 200:
                    raise RuntimeError(f"GET {url}: {response.status_code} {response.text[:200]}")

        await asyncio.gather(*(one_client() for _ in range(clients)))
    return latencies


def concurrent_get_ms(url: str, key: str, clients: int, duration_s: float) -> list[float]:
    return [s * 1000 for s in asyncio.run(_hammer(url, key, clients, duration_s))]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--database-url", help="a migrated-or-empty database (default: SQLite)")
    parser.add_argument("--quick", action="store_true", help="fewer uploads, 5 s of load")
    parser.add_argument("--json", type=Path, help="also write the results as JSON")
    args = parser.parse_args(argv)
    latency_uploads, throughput_uploads, load_s = (10, 12, 5.0) if args.quick else (30, 40, 15.0)

    with tempfile.TemporaryDirectory() as folder:
        url = args.database_url or f"sqlite:///{Path(folder) / 'bench.sqlite3'}"
        database = Database(url)
        upgrade_to_head(database)
        database.dispose()
        log = Path(folder) / "server.log"
        with ServerProcess(url, workers=2, log_path=log) as server:
            client = Client(server.url, api_key=server.admin_key)
            client.wait_for_job(client.upload_session(LATENCY_SESSION)["job_id"])  # warm up
            latencies_s = map_ready_latency_s(client, latency_uploads)
            per_minute, throughput_s = sessions_per_minute(client, throughput_uploads)
            map_id = client.list_maps(limit=1)["data"][0]["id"]
            map_ms = concurrent_get_ms(
                f"{server.url}/v1/maps/{map_id}", server.admin_key, 50, load_s
            )
            health_ms = concurrent_get_ms(f"{server.url}/healthz", server.admin_key, 50, load_s)
            client.close()

    backend = "PostgreSQL" if url.startswith("postgresql") else "SQLite"
    results: dict[str, Any] = {
        "backend": backend,
        "map_ready_p50_s": statistics.median(latencies_s),
        "map_ready_p95_s": percentile(latencies_s, 95),
        "map_ready_uploads": len(latencies_s),
        "sessions_per_minute": per_minute,
        "throughput_uploads": throughput_uploads,
        "throughput_s": throughput_s,
        "get_map_p50_ms": percentile(map_ms, 50),
        "get_map_p99_ms": percentile(map_ms, 99),
        "get_map_requests": len(map_ms),
        "healthz_p50_ms": percentile(health_ms, 50),
        "healthz_p99_ms": percentile(health_ms, 99),
        "healthz_requests": len(health_ms),
    }
    results["get_map_over_healthz_p99"] = results["get_map_p99_ms"] / results["healthz_p99_ms"]
    rows = [
        ["measure", "value", "target"],
        [
            f"map ready p50 / p95 ({len(latencies_s)} × occam_room, idle)",
            f"{results['map_ready_p50_s']:.2f} s / {results['map_ready_p95_s']:.2f} s",
            "p95 ≤ 2 s",
        ],
        [
            f"sessions per minute, 2 workers ({throughput_uploads} real sessions)",
            f"{per_minute:.0f} ({throughput_s:.1f} s)",
            "—",
        ],
        [
            f"GET /v1/maps/{{id}} p50 / p99, 50 clients ({len(map_ms)} requests)",
            f"{results['get_map_p50_ms']:.1f} ms / {results['get_map_p99_ms']:.1f} ms",
            "p99 ≤ 3 × /healthz p99",
        ],
        [
            f"GET /healthz p50 / p99, 50 clients ({len(health_ms)} requests)",
            f"{results['healthz_p50_ms']:.1f} ms / {results['healthz_p99_ms']:.1f} ms",
            "(floor)",
        ],
        [
            "map p99 / healthz p99",
            f"{results['get_map_over_healthz_p99']:.2f}",
            "≤ 3",
        ],
    ]
    print(f"backend: {backend}, 2 worker processes, uvicorn on 127.0.0.1")
    print(render_markdown_table(rows))
    if args.json:
        args.json.write_text(json.dumps(results, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
