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
   as the floor (p50/p99 and their ratio);
4. ``POST /v1/maps/{id}/routes`` (between random tags of the ``floor_2_straight`` map) and
   ``POST /v1/localizations/{id}/updates`` (each client replays ``desnat_straight_once`` into that
   map, 20 poses per update, in its own navigation session) with 50 concurrent clients.

Targets: map-ready p95 ≤ 2 s; map GET p99 ≤ 3 × the /healthz p99 (issue 3); route p99 ≤ 10 ms,
localization update p99 ≤ 20 ms at 50 concurrent clients (issue 5).
The load generator runs on the same 2-core machine as the server, so it competes with it.
"""

from __future__ import annotations

import argparse
import asyncio
import itertools
import json
import random
import statistics
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from app.cli.server_process import ServerProcess  # noqa: E402
from app.cli.tables import render_markdown_table  # noqa: E402
from app.client import Client  # noqa: E402
from app.domain.localize import session_update_documents  # noqa: E402
from app.domain.upload.session import load_session  # noqa: E402
from app.storage.db import Database  # noqa: E402
from app.storage.migrate import upgrade_to_head  # noqa: E402

SESSIONS = REPO / "data" / "sessions"
LATENCY_SESSION = SESSIONS / "occam_room.json"
ROUTING_SESSION = SESSIONS / "floor_2_straight.json"
LOCALIZATION_SESSION = SESSIONS / "desnat_straight_once.json"
THROUGHPUT_SESSIONS = [
    SESSIONS / f"{name}.json"
    for name in ("occam_room", "floor_2_straight", "straight_209_occam", "desnat_straight_once")
]


def percentile(values: list[float], q: float) -> float:
    """The q-th percentile (0–100), linear interpolation between closest ranks."""
    return float(np.percentile(values, q))


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


#: One client's requests: given its index, yields (method, url, json body) forever.
RequestPlan = Callable[[int], Iterator[tuple[str, str, Any]]]


async def _hammer(key: str, clients: int, duration_s: float, plan: RequestPlan) -> list[float]:
    latencies: list[float] = []
    limits = httpx.Limits(max_connections=clients, max_keepalive_connections=clients)
    headers = {"Authorization": f"Bearer {key}"}
    async with httpx.AsyncClient(limits=limits, headers=headers, timeout=60) as http:
        deadline = time.perf_counter() + duration_s

        async def one_client(index: int) -> None:
            requests = plan(index)
            while time.perf_counter() < deadline:
                method, url, body = next(requests)
                started = time.perf_counter()
                response = await http.request(method, url, json=body)
                latencies.append(time.perf_counter() - started)
                if response.status_code >= 300:
                    raise RuntimeError(f"{method} {url}: {response.status_code} {response.text}")

        await asyncio.gather(*(one_client(k) for k in range(clients)))
    return latencies


def concurrent_ms(key: str, clients: int, duration_s: float, plan: RequestPlan) -> list[float]:
    return [s * 1000 for s in asyncio.run(_hammer(key, clients, duration_s, plan))]


def repeat_get(url: str) -> RequestPlan:
    return lambda _index: itertools.repeat(("GET", url, None))


def random_routes(base: str, map_id: int, tag_ids: list[int]) -> RequestPlan:
    def plan(index: int) -> Iterator[tuple[str, str, Any]]:
        rng = random.Random(index)
        while True:
            start, goal = rng.sample(tag_ids, 2)
            body = {"from": {"tag": start}, "to": {"tag": goal}}
            yield "POST", f"{base}/v1/maps/{map_id}/routes", body

    return plan


def localization_replays(base: str, map_id: int, key: str) -> RequestPlan:
    updates = session_update_documents(load_session(LOCALIZATION_SESSION), 20)

    def plan(_index: int) -> Iterator[tuple[str, str, Any]]:
        while True:  # a new navigation session each time the walk is over
            response = httpx.post(
                f"{base}/v1/maps/{map_id}/localizations",
                headers={"Authorization": f"Bearer {key}"},
                timeout=60,
            )
            response.raise_for_status()
            session_id = response.json()["id"]
            for document in updates:
                yield "POST", f"{base}/v1/localizations/{session_id}/updates", document

    return plan


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
            floor_2 = client.upload_session(ROUTING_SESSION)
            client.wait_for_job(floor_2["job_id"])
            map_id = floor_2["map_id"]
            key = server.admin_key
            map_ms = concurrent_ms(key, 50, load_s, repeat_get(f"{server.url}/v1/maps/{map_id}"))
            health_ms = concurrent_ms(key, 50, load_s, repeat_get(f"{server.url}/healthz"))
            tag_ids = [tag["tag_id"] for tag in client.get_map(map_id)["current_version"]["tags"]]
            route_ms = concurrent_ms(key, 50, load_s, random_routes(server.url, map_id, tag_ids))
            update_ms = concurrent_ms(
                key, 50, load_s, localization_replays(server.url, map_id, key)
            )
            # One client at a time: the cost of a request without queueing behind 49 others.
            health_1_ms = concurrent_ms(key, 1, load_s / 3, repeat_get(f"{server.url}/healthz"))
            route_1_ms = concurrent_ms(
                key, 1, load_s / 3, random_routes(server.url, map_id, tag_ids)
            )
            update_1_ms = concurrent_ms(
                key, 1, load_s / 3, localization_replays(server.url, map_id, key)
            )
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
    results.update(
        route_p50_ms=percentile(route_ms, 50),
        route_p99_ms=percentile(route_ms, 99),
        route_requests=len(route_ms),
        localization_update_p50_ms=percentile(update_ms, 50),
        localization_update_p99_ms=percentile(update_ms, 99),
        localization_update_requests=len(update_ms),
        healthz_1_client_p50_ms=percentile(health_1_ms, 50),
        healthz_1_client_p99_ms=percentile(health_1_ms, 99),
        route_1_client_p50_ms=percentile(route_1_ms, 50),
        route_1_client_p99_ms=percentile(route_1_ms, 99),
        localization_update_1_client_p50_ms=percentile(update_1_ms, 50),
        localization_update_1_client_p99_ms=percentile(update_1_ms, 99),
    )
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
        [
            f"POST /v1/maps/{{id}}/routes p50 / p99, 50 clients ({len(route_ms)} requests)",
            f"{results['route_p50_ms']:.1f} ms / {results['route_p99_ms']:.1f} ms",
            "p99 ≤ 10 ms",
        ],
        [
            f"POST /v1/localizations/{{id}}/updates p50 / p99, 50 clients ({len(update_ms)})",
            f"{results['localization_update_p50_ms']:.1f} ms / "
            f"{results['localization_update_p99_ms']:.1f} ms",
            "p99 ≤ 20 ms",
        ],
        [
            f"GET /healthz p50 / p99, 1 client ({len(health_1_ms)})",
            f"{results['healthz_1_client_p50_ms']:.1f} ms / "
            f"{results['healthz_1_client_p99_ms']:.1f} ms",
            "(floor)",
        ],
        [
            f"POST …/routes p50 / p99, 1 client ({len(route_1_ms)})",
            f"{results['route_1_client_p50_ms']:.1f} ms / "
            f"{results['route_1_client_p99_ms']:.1f} ms",
            "—",
        ],
        [
            f"POST …/updates p50 / p99, 1 client ({len(update_1_ms)})",
            f"{results['localization_update_1_client_p50_ms']:.1f} ms / "
            f"{results['localization_update_1_client_p99_ms']:.1f} ms",
            "—",
        ],
    ]
    print(f"backend: {backend}, 2 worker processes, uvicorn on 127.0.0.1")
    print(render_markdown_table(rows))
    if args.json:
        args.json.write_text(json.dumps(results, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
