"""HTTP benchmark (issue 16): what each hot endpoint costs next to doing nothing, one command.

    .venv/bin/python -m bench.http                     # SQLite (a new file), wrk if on PATH
    .venv/bin/python -m bench.http --both              # SQLite, then PostgreSQL
    .venv/bin/python -m bench.http --database-url postgresql+psycopg://postgres@127.0.0.1:5432/postgres
    .venv/bin/python -m bench.http --quick --no-wrk    # 1.5 s per endpoint, the Python client
    .venv/bin/python -m bench.http --serve-arg=--api-processes=2   # extra `serve` arguments
    .venv/bin/python -m bench.http --load              # also the load test (bench/load.py)
    (``.venv/bin/python bench/http.py …`` works too.)

Starts ``invisible-map serve --workers 2`` on a fresh database: a new SQLite file, or, given a
PostgreSQL URL, a new database ``im_http_<random>`` created on that server (the URL's own
database is only used to connect) and dropped at the end. With a device key (made with the admin
key, as a phone's), uploads ``floor_2_straight`` and then the other real sessions of
``data/sessions`` once, then the 3 smallest again and again (each upload a new map) until there
are ``--maps`` (50) maps, and waits for every build. Then, on loopback, each endpoint in turn for
``--duration-s`` (5 s; 1.5 s with ``--quick``, which wrk, counting whole seconds, makes 2 s) with
``--connections`` (8) keep-alive connections, each sending its next request as soon as the last is
answered (a closed loop):

- ``GET /healthz`` (no key), measured first and again last: the floor, "the cost of doing
  nothing"; the ratios divide by the mean of the two runs;
- ``GET /v1/maps/{id}``, ``/app-map``, ``/geojson`` of floor_2_straight (device key; no
  ``If-None-Match``: every answer is a full 200), ``GET /v1/maps?limit=50`` (50 maps),
  ``GET /v1/jobs/{id}`` (floor_2_straight's build job), ``GET /v1/info``;
- ``POST /v1/maps/{id}/routes``, tag 300 → tag 320 on floor_2_straight, the same body each time;
- ``POST /v1/localizations/{id}/updates``: each connection starts its own navigation session
  (``POST /v1/maps/{id}/localizations``) and sends ``desnat_straight_once`` into it, one update
  per second of the walk (``bench.load.walk_documents``, as the load test's phones), starting at
  its own point of the walk (connection k at k/8 of it) so that together they send every part of
  the walk alike; at the walk's end it starts a new session and walks from the beginning. The
  session starts are sent on the same connections but are not counted in requests/s (wrk's
  latency percentiles include them: about one request in 40);
- and, in this process: ``app.domain.localize.update`` alone on the same documents, walk after
  walk from a fresh state (the map's tags as the server has them): "what the update's computation
  alone allows in one process", updates/s = 1 / mean time of an update;
- one connection: ``GET /healthz`` and the route, p50 over HTTP.

The load generator is ``wrk`` (``apt-get install wrk``; Lua scripts written to a temporary
folder) when it is on PATH, else (or with ``--no-wrk``) asyncio + httpx in this process, one
``httpx.AsyncClient`` per connection. The Python client costs far more CPU per request than wrk,
and it shares the 2 cores with the server: it caps ``/healthz`` well below what the server can
do, so its ratios to ``/healthz`` look better than wrk's. Compare numbers from the same client.
"server CPU ms/req" is the CPU time of the server's process group (API process and its idle
worker processes) during the run divided by the requests answered: the cost of a request, much
less sensitive than requests/s to what else runs on the machine.

The table holds issue 16's targets (ratios to ``/healthz`` in the same run; the update against
the computation alone; route p50 at one connection) with pass/fail columns. Exit status 1 if a
request failed (non-2xx or no answer; with ``--load``, also if the load test failed as
``bench/load.py`` counts failure), not for a missed target.

The load test (50 uploaders + 200 navigators for 60 s, its targets: 0 errors, 0 lost, route p99
≤ 100 ms, localization update p99 ≤ 200 ms, upload → map p95 ≤ 5 s) is ``bench/load.py``;
``--load`` runs it after the HTTP table, on the same backend(s) (its own deployments: embedded
SQLite, scale-out PostgreSQL), and prints its report and a table against those targets. Alone:
``.venv/bin/python bench/load.py --sqlite`` (or ``--postgres``).
"""

from __future__ import annotations

import os
import sys

# ``python bench/http.py`` puts bench/ first on sys.path, where this file would shadow the
# standard library's ``http`` (httpx imports ``http.cookiejar``): take bench/ off it first.
_HERE = os.path.dirname(os.path.abspath(__file__))
sys.path[:] = [p for p in sys.path if os.path.abspath(p or os.curdir) != _HERE]
_REPO = os.path.dirname(_HERE)
if _REPO not in sys.path:
    sys.path.insert(0, _REPO)

import argparse  # noqa: E402
import asyncio  # noqa: E402
import datetime as dt  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import shutil  # noqa: E402
import subprocess  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
import uuid  # noqa: E402
from collections.abc import Iterator  # noqa: E402
from contextlib import contextmanager  # noqa: E402
from dataclasses import asdict, dataclass, field, replace  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import httpx  # noqa: E402
import numpy as np  # noqa: E402
from sqlalchemy import create_engine, make_url, text  # noqa: E402

from app.cli.server_process import ServerProcess  # noqa: E402
from app.cli.tables import render_markdown_table  # noqa: E402
from app.client import Client  # noqa: E402
from app.config import default_api_processes  # noqa: E402
from app.domain.frames import pose_from_xyz_quat_xyzw  # noqa: E402
from app.domain.localize import LocalizerState, parse_update, update  # noqa: E402
from bench import load as load_bench  # noqa: E402

REPO = Path(_REPO)
SESSIONS = REPO / "data" / "sessions"
ROUTING_SESSION = "floor_2_straight"
LOCALIZATION_WALK = "desnat_straight_once"
ROUTE_BODY = {"from": {"tag": 300}, "to": {"tag": 320}}
DEFAULT_POSTGRES_URL = load_bench.DEFAULT_POSTGRES_URL
WORKERS = 2
#: Requests sent to each endpoint before its run (the server's caches, the connection pools).
WARM_UP_REQUESTS = 3
#: The maps beyond one of each session are built from this many of the smallest sessions.
FILL_SESSIONS = 3
#: A /healthz p50 at one connection this long is a TCP stall (Nagle + delayed ACK), not work.
STALL_MS = 30.0


# --------------------------------------------------------------------------- what is measured


@dataclass(frozen=True, kw_only=True)
class Endpoint:
    """One row: a request sent over and over (or, for ``walk``, a localization walk)."""

    name: str  # as the table shows it
    method: str
    path: str
    body: bytes | None = None
    key: bool = True  # send the device key
    walk: bool = False  # per connection: a navigation session fed the walk's updates
    #: Minimum ratio of its requests/s to /healthz's (issue 16), if it has one.
    min_ratio: float | None = None


@dataclass
class Measured:
    """One run of one endpoint."""

    requests: int  # answered within the run, session starts not counted
    duration_s: float
    p50_ms: float
    p99_ms: float
    failed: int  # non-2xx answers and requests that got none
    server_cpu_s: float = 0.0
    #: Each busy server process's share of ``server_cpu_s``, the largest first.
    cpu_shares: list[float] = field(default_factory=list)
    extra_requests: int = 0  # navigation sessions started (walk only)

    @property
    def per_s(self) -> float:
        return self.requests / self.duration_s if self.duration_s > 0 else 0.0

    @property
    def cpu_ms_per_request(self) -> float:
        answered = self.requests + self.extra_requests
        return self.server_cpu_s / answered * 1000 if answered else float("nan")


@dataclass(frozen=True, kw_only=True)
class Target:
    """The server under test: its URL, the device key, and the ids the requests use."""

    url: str
    key: str
    map_id: int
    job_id: int
    maps: int
    walk: list[bytes]  # the walk's update documents, JSON
    process_group: int


def endpoints(target: Target) -> list[Endpoint]:
    m = target.map_id
    return [
        Endpoint(name="GET /v1/maps/{id}", method="GET", path=f"/v1/maps/{m}", min_ratio=0.40),
        Endpoint(
            name="GET /v1/maps/{id}/app-map",
            method="GET",
            path=f"/v1/maps/{m}/app-map",
            min_ratio=0.30,
        ),
        Endpoint(
            name="GET /v1/maps/{id}/geojson",
            method="GET",
            path=f"/v1/maps/{m}/geojson",
            min_ratio=0.30,
        ),
        Endpoint(
            name="POST /v1/maps/{id}/routes (tag 300 → 320)",
            method="POST",
            path=f"/v1/maps/{m}/routes",
            body=json.dumps(ROUTE_BODY).encode(),
            min_ratio=0.30,
        ),
        Endpoint(
            name="POST /v1/localizations/{id}/updates",
            method="POST",
            path="/v1/localizations/{id}/updates",
            walk=True,
        ),
        Endpoint(
            name=f"GET /v1/maps ({target.maps} maps)",
            method="GET",
            path=f"/v1/maps?limit={target.maps}",
            min_ratio=0.20,
        ),
        Endpoint(name="GET /v1/jobs/{id}", method="GET", path=f"/v1/jobs/{target.job_id}"),
        Endpoint(name="GET /v1/info", method="GET", path="/v1/info"),
    ]


HEALTHZ = Endpoint(name="GET /healthz", method="GET", path="/healthz", key=False)


# --------------------------------------------------------------------------- wrk

#: Shared by every script: per-thread tallies (each thread has one connection, its own Lua
#: state) and one JSON line from ``done``.
LUA_COMMON = r"""
bad = 0      -- answers other than 2xx (counted only where a response() is defined)
starts = 0   -- navigation sessions started (not counted as requests)
local threads = {}
local count = 0
function setup(thread)
  count = count + 1
  thread:set("index", count - 1)
  table.insert(threads, thread)
end
function done(summary, latency, requests)
  local b, s = 0, 0
  for _, t in ipairs(threads) do
    b = b + (t:get("bad") or 0)
    s = s + (t:get("starts") or 0)
  end
  local e = summary.errors
  io.write(string.format(
    'BENCH_RESULT {"requests": %d, "duration_us": %d, "p50_us": %.1f, "p99_us": %.1f, ' ..
    '"connect": %d, "read": %d, "write": %d, "status": %d, "timeout": %d, "bad": %d, ' ..
    '"starts": %d}\n',
    summary.requests, summary.duration, latency:percentile(50), latency:percentile(99),
    e.connect, e.read, e.write, e.status, e.timeout, b, s))
end
"""

LUA_STATIC = r"""
wrk.method = {method}
wrk.path = {path}
{headers}
{body}
"""

#: Per connection: a navigation session, fed the walk from its own starting point.
LUA_WALK = r"""
local docs = {{}}
local headers = {{}}
{headers_table}
local loc = nil
local i = 1
local starting = false
function init(args)
  for line in io.lines({documents}) do docs[#docs + 1] = line end
  i = math.floor(index * #docs / {connections}) + 1
end
function request()
  if loc == nil then
    starting = true
    return wrk.format("POST", {start_path}, headers, "")
  end
  return wrk.format("POST", "/v1/localizations/" .. loc .. "/updates", headers, docs[i])
end
function response(status, hdrs, body)
  if starting then
    starting = false
    starts = starts + 1
    if status == 201 then
      loc = string.match(body, '"id"%s*:%s*(%d+)')
    else
      bad = bad + 1
    end
    return
  end
  if status < 200 or status > 299 then bad = bad + 1 end
  i = i + 1
  if i > #docs then
    i = 1
    loc = nil
  end
end
"""


def _lua_string(value: str) -> str:
    return json.dumps(value)  # a JSON string of ASCII is a valid Lua string literal


def _headers(target: Target, endpoint: Endpoint) -> dict[str, str]:
    headers = {}
    if endpoint.key:
        headers["Authorization"] = f"Bearer {target.key}"
    if endpoint.method == "POST":
        headers["Content-Type"] = "application/json"
    return headers


def wrk_script(target: Target, endpoint: Endpoint, folder: Path, connections: int) -> Path:
    headers = _headers(target, endpoint)
    if endpoint.walk:
        documents = folder / "walk.jsonl"
        documents.write_bytes(b"\n".join(target.walk) + b"\n")
        body = LUA_WALK.format(
            headers_table="\n".join(
                f"headers[{_lua_string(k)}] = {_lua_string(v)}" for k, v in headers.items()
            ),
            documents=_lua_string(str(documents)),
            connections=connections,
            start_path=_lua_string(f"/v1/maps/{target.map_id}/localizations"),
        )
    else:
        body = LUA_STATIC.format(
            method=_lua_string(endpoint.method),
            path=_lua_string(endpoint.path),
            headers="\n".join(
                f"wrk.headers[{_lua_string(k)}] = {_lua_string(v)}" for k, v in headers.items()
            ),
            body=f"wrk.body = {_lua_string(endpoint.body.decode())}" if endpoint.body else "",
        )
    script = folder / f"{uuid.uuid4().hex[:8]}.lua"
    script.write_text(LUA_COMMON + body)
    return script


def run_wrk(
    target: Target, endpoint: Endpoint, connections: int, duration_s: float, folder: Path
) -> Measured:
    script = wrk_script(target, endpoint, folder, connections)
    # One thread per connection: wrk's Lua state is per thread, so the walk's state is then
    # per connection.
    command = [
        "wrk",
        f"-t{connections}",
        f"-c{connections}",
        f"-d{max(1, math.ceil(duration_s))}s",  # wrk counts whole seconds
        "--timeout",
        "30s",
        "-s",
        str(script),
        target.url,
    ]
    cpu_before = load_bench.process_cpu_s([target.process_group])
    done = subprocess.run(command, capture_output=True, text=True, check=False)
    cpu_s, cpu_shares = _cpu_since(target.process_group, cpu_before)
    line = next((ln for ln in done.stdout.splitlines() if ln.startswith("BENCH_RESULT ")), None)
    if done.returncode != 0 or line is None:
        raise RuntimeError(f"wrk failed ({done.returncode}): {done.stdout}\n{done.stderr}")
    result = json.loads(line.removeprefix("BENCH_RESULT "))
    socket_errors = sum(result[k] for k in ("connect", "read", "write", "timeout"))
    starts = int(result["starts"])
    # Non-2xx: wrk's own count (≥ 400) where no response() is defined; the script's otherwise.
    bad = int(result["bad"]) if endpoint.walk else int(result["status"])
    return Measured(
        requests=int(result["requests"]) - starts,
        duration_s=result["duration_us"] / 1e6,
        p50_ms=result["p50_us"] / 1000,
        p99_ms=result["p99_us"] / 1000,
        failed=bad + socket_errors,
        server_cpu_s=cpu_s,
        cpu_shares=cpu_shares,
        extra_requests=starts,
    )


# --------------------------------------------------------------------------- Python fallback


async def _python_run(
    target: Target, endpoint: Endpoint, connections: int, duration_s: float
) -> tuple[list[float], int, int, float]:
    """(latencies s, failed, session starts, wall s) of ``connections`` closed loops."""
    latencies: list[float] = []
    failed = 0
    starts = 0
    headers = _headers(target, endpoint)
    clients = [
        httpx.AsyncClient(
            base_url=target.url,
            headers=headers,
            timeout=30,
            limits=httpx.Limits(max_connections=1, max_keepalive_connections=1),
        )
        for _ in range(connections)
    ]

    async def loop(index: int, http: httpx.AsyncClient, deadline: float) -> None:
        nonlocal failed, starts
        walk = target.walk
        position = index * len(walk) // connections
        localization: int | None = None
        while time.perf_counter() < deadline:
            if endpoint.walk and localization is None:
                started = await http.post(f"/v1/maps/{target.map_id}/localizations")
                starts += 1
                if started.status_code != 201:
                    failed += 1
                    continue
                localization = int(started.json()["id"])
            method, path, body = endpoint.method, endpoint.path, endpoint.body
            if endpoint.walk:
                path, body = f"/v1/localizations/{localization}/updates", walk[position]
            began = time.perf_counter()
            try:
                response = await http.request(method, path, content=body)
            except httpx.TransportError:
                failed += 1
                continue
            latencies.append(time.perf_counter() - began)
            if not response.is_success:
                failed += 1
            if endpoint.walk:
                position += 1
                if position == len(walk):
                    position, localization = 0, None

    try:
        opened = time.perf_counter()
        deadline = opened + duration_s
        await asyncio.gather(*(loop(k, http, deadline) for k, http in enumerate(clients)))
        wall_s = time.perf_counter() - opened
    finally:
        for http in clients:
            await http.aclose()
    return latencies, failed, starts, wall_s


def run_python(target: Target, endpoint: Endpoint, connections: int, duration_s: float) -> Measured:
    cpu_before = load_bench.process_cpu_s([target.process_group])
    latencies, failed, starts, wall_s = asyncio.run(
        _python_run(target, endpoint, connections, duration_s)
    )
    cpu_s, cpu_shares = _cpu_since(target.process_group, cpu_before)
    values = np.array(latencies) * 1000 if latencies else np.full(1, np.nan)
    return Measured(
        requests=len(latencies),
        duration_s=wall_s,
        p50_ms=float(np.percentile(values, 50)),
        p99_ms=float(np.percentile(values, 99)),
        failed=failed,
        server_cpu_s=cpu_s,
        cpu_shares=cpu_shares,
        extra_requests=starts,
    )


def _cpu_since(process_group: int, before: dict[int, float]) -> tuple[float, list[float]]:
    """The process group's CPU time since ``before`` (s), and each process's share of it, the
    largest first (the busy ones: more than 5% of it)."""
    spent = {
        pid: cpu_s - before.get(pid, 0.0)
        for pid, cpu_s in load_bench.process_cpu_s([process_group]).items()
    }
    total_s = sum(spent.values())
    shares = sorted((s / total_s for s in spent.values() if total_s), reverse=True)
    return total_s, [share for share in shares if share > 0.05]


# --------------------------------------------------------------------------- in process


def computation_alone(
    walk: list[dict[str, Any]], map_tags: dict[int, Any], duration_s: float
) -> Measured:
    """``update`` alone, walk after walk from a fresh state, for at least ``duration_s``."""
    batches = [parse_update(document) for document in walk]
    times: list[float] = []
    spent = 0.0
    while spent < duration_s or not times:
        state = LocalizerState.initial()
        for batch in batches:
            began = time.perf_counter()
            state, _result = update(state, batch, map_tags)
            elapsed = time.perf_counter() - began
            times.append(elapsed)
            spent += elapsed
    values = np.array(times) * 1000
    return Measured(
        requests=len(times),
        duration_s=spent,
        p50_ms=float(np.percentile(values, 50)),
        p99_ms=float(np.percentile(values, 99)),
        failed=0,
    )


# --------------------------------------------------------------------------- the server


@contextmanager
def database(url: str | None, folder: Path) -> Iterator[tuple[str, str]]:
    """(backend name, URL of a fresh database): a new SQLite file, or a new PostgreSQL database
    on the server of ``url``, dropped afterwards."""
    if url is None or url.startswith("sqlite"):
        yield "SQLite", f"sqlite:///{folder / 'http.sqlite3'}"
        return
    name = f"im_http_{uuid.uuid4().hex[:8]}"
    admin = create_engine(url, isolation_level="AUTOCOMMIT")
    try:
        with admin.connect() as connection:
            connection.execute(text(f'CREATE DATABASE "{name}"'))
        try:
            yield (
                "PostgreSQL",
                make_url(url).set(database=name).render_as_string(hide_password=False),
            )
        finally:
            with admin.connect() as connection:
                connection.execute(text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))
    finally:
        admin.dispose()


def fill(server: ServerProcess, maps: int) -> tuple[Target, list[dict[str, Any]], dict[int, Any]]:
    """Upload ``maps`` real sessions with a device key (floor_2_straight first), wait for their
    builds; the target, the walk's documents and the floor_2 map's tags (tag id → 4×4)."""
    with Client(server.url, api_key=server.admin_key, timeout_s=120) as admin:
        key = admin.create_key(role="device", name="http benchmark")["key"]
    # floor_2_straight, every other session once, then the smallest ones again (quick builds).
    others = sorted(p for p in SESSIONS.glob("*.json") if p.stem != ROUTING_SESSION)
    small = sorted(others, key=lambda p: p.stat().st_size)[:FILL_SESSIONS]
    order = [SESSIONS / f"{ROUTING_SESSION}.json", *others]
    order = (order + [small[k % len(small)] for k in range(maps)])[:maps]
    run = uuid.uuid4().hex[:8]
    with Client(server.url, api_key=key, timeout_s=120) as phone:
        accepted = [
            phone.upload_session(path, idempotency_key=f"http-{run}-{k}")
            for k, path in enumerate(order)
        ]
        for upload in accepted:
            job = phone.wait_for_job(upload["job_id"], timeout_s=600, poll_s=0.05)
            if job["state"] != "succeeded":
                raise RuntimeError(f"the build of map {upload['map_id']} {job['state']}: {job}")
        floor_2 = accepted[0]
        version = phone.get_map(floor_2["map_id"])["current_version"]
    tags = {
        tag["tag_id"]: pose_from_xyz_quat_xyzw([*tag["position_m"], *tag["quat_xyzw"]])
        for tag in version["tags"]
    }
    missing = {300, 320} - set(tags)
    if missing:
        raise RuntimeError(f"floor_2_straight's map has no tag {sorted(missing)}")
    walk = load_bench.walk_documents(LOCALIZATION_WALK, sorted(tags))
    target = Target(
        url=server.url,
        key=key,
        map_id=floor_2["map_id"],
        job_id=floor_2["job_id"],
        maps=maps,
        walk=[json.dumps(document, separators=(",", ":")).encode() for document in walk],
        process_group=server.pid,
    )
    return target, walk, tags


def warm_up(target: Target, endpoint: Endpoint) -> None:
    """A few requests first (the server's caches, the connection pools)."""
    if endpoint.walk:
        run_python(target, endpoint, 1, 0.2)
        return
    headers = _headers(target, endpoint)
    with httpx.Client(base_url=target.url, headers=headers, timeout=60) as http:
        for _ in range(WARM_UP_REQUESTS):
            response = http.request(endpoint.method, endpoint.path, content=endpoint.body)
            if not response.is_success:
                raise RuntimeError(
                    f"{endpoint.method} {endpoint.path}: {response.status_code} {response.text}"
                )


# --------------------------------------------------------------------------- one backend


@dataclass
class BackendResult:
    backend: str
    client: str
    connections: int
    duration_s: float
    serve_args: list[str]
    healthz: list[Measured] = field(default_factory=list)
    rows: list[tuple[Endpoint, Measured]] = field(default_factory=list)
    computation: Measured | None = None
    healthz_1: Measured | None = None
    route_1: Measured | None = None
    #: The same server's database again under ``serve``'s default API processes (one per
    #: core), when that is more than one: their number, /healthz first and last, the rows.
    all_cores: int = 0
    all_cores_healthz: list[Measured] = field(default_factory=list)
    all_cores_rows: list[tuple[Endpoint, Measured]] = field(default_factory=list)
    load_before: tuple[float, float, float] = (0.0, 0.0, 0.0)
    load_after: tuple[float, float, float] = (0.0, 0.0, 0.0)

    @property
    def healthz_per_s(self) -> float:
        return float(np.mean([m.per_s for m in self.healthz]))

    @property
    def failed(self) -> int:
        runs = [*self.healthz, *(m for _, m in self.rows), self.healthz_1, self.route_1]
        runs += [*self.all_cores_healthz, *(m for _, m in self.all_cores_rows)]
        return sum(m.failed for m in runs if m is not None)


def run_backend(database_url: str | None, args: argparse.Namespace) -> BackendResult:
    result = BackendResult(
        backend="",
        client="wrk" if uses_wrk(args) else "python (asyncio + httpx)",
        connections=args.connections,
        duration_s=args.duration_s,
        serve_args=list(args.serve_arg),
        load_before=os.getloadavg(),
    )
    with tempfile.TemporaryDirectory(prefix="im-http-") as temp:
        folder = Path(temp)
        with database(database_url, folder) as (backend, url):
            result.backend = backend
            with bench_server(url, folder, args, log_name="server.log") as server:
                log(f"{backend}: server up at {server.url}; uploading {args.maps} sessions…")
                began = time.perf_counter()
                target, walk, tags = fill(server, args.maps)
                log(f"{backend}: {args.maps} maps built in {time.perf_counter() - began:.0f} s")

                def measure(endpoint: Endpoint, connections: int) -> Measured:
                    return measure_endpoint(target, endpoint, connections, args, folder, backend)

                c = args.connections
                result.healthz.append(measure(HEALTHZ, c))
                for endpoint in endpoints(target):
                    result.rows.append((endpoint, measure(endpoint, c)))
                result.healthz.append(measure(HEALTHZ, c))
                result.healthz_1 = measure(HEALTHZ, 1)
                route = next(e for e in endpoints(target) if e.path.endswith("/routes"))
                result.route_1 = measure(route, 1)
            chosen = any("api-processes" in arg for arg in args.serve_arg)
            if args.all_cores and default_api_processes() > 1 and not chosen:
                result.all_cores = default_api_processes()
                measure_all_cores(result, url, folder, target, args)
            result.computation = computation_alone(walk, tags, min(3.0, args.duration_s))
            log(f"{backend}: update() in process: {result.computation.per_s:.0f}/s")
    result.load_after = os.getloadavg()
    return result


def measured_on_all_cores(endpoint: Endpoint) -> bool:
    """The rows measured again under serve's default API processes: map GET, route, update."""
    return (
        endpoint.walk or endpoint.path.endswith("/routes") or endpoint.name == "GET /v1/maps/{id}"
    )


def uses_wrk(args: argparse.Namespace) -> bool:
    """Whether the run uses wrk: on PATH and not ``--no-wrk``."""
    return not args.no_wrk and shutil.which("wrk") is not None


def bench_server(
    url: str,
    folder: Path,
    args: argparse.Namespace,
    *,
    log_name: str,
    api_processes: int | None = 1,
) -> ServerProcess:
    """``serve --workers 2`` on ``url`` with the ``--serve-arg`` arguments (``api_processes``
    None: serve's default)."""
    server = ServerProcess(
        url,
        workers=WORKERS,
        # The benchmark's one device key uploads every map: no per-key upload limit.
        env={"INVISIBLE_MAP_DATA_DIR": str(folder), "INVISIBLE_MAP_UPLOADS_PER_MINUTE": "0"},
        log_path=folder / log_name,
        api_processes=api_processes,
    )
    server.args += list(args.serve_arg)
    return server


def measure_endpoint(
    target: Target,
    endpoint: Endpoint,
    connections: int,
    args: argparse.Namespace,
    folder: Path,
    label: str,
) -> Measured:
    """``endpoint`` warmed up, then run for ``--duration-s`` with wrk (or the Python client);
    the figures logged under ``label``."""
    warm_up(target, endpoint)
    if uses_wrk(args):
        measured = run_wrk(target, endpoint, connections, args.duration_s, folder)
    else:
        measured = run_python(target, endpoint, connections, args.duration_s)
    log(
        f"{label}: {endpoint.name}, {connections} connection(s): "
        f"{measured.per_s:.0f}/s, p50 {measured.p50_ms:.2f} ms, "
        f"p99 {measured.p99_ms:.2f} ms, {measured.failed} failed"
    )
    return measured


def measure_all_cores(
    result: BackendResult, url: str, folder: Path, target: Target, args: argparse.Namespace
) -> None:
    """``serve`` again on the same database with its default API processes (one per core, as a
    user runs it): /healthz first and last, and the rows :func:`measured_on_all_cores`."""
    server = bench_server(url, folder, args, log_name="server-all-cores.log", api_processes=None)
    with server:
        again = replace(target, url=server.url, process_group=server.pid)
        label = f"{result.backend}, {result.all_cores} API processes"

        def measure(endpoint: Endpoint) -> Measured:
            return measure_endpoint(again, endpoint, args.connections, args, folder, label)

        result.all_cores_healthz.append(measure(HEALTHZ))
        for endpoint in filter(measured_on_all_cores, endpoints(again)):
            result.all_cores_rows.append((endpoint, measure(endpoint)))
        result.all_cores_healthz.append(measure(HEALTHZ))


# --------------------------------------------------------------------------- the report


def _verdict(ok: bool | None) -> str:
    return "—" if ok is None else ("pass" if ok else "**FAIL**")


def target_of(
    endpoint: Endpoint, m: Measured, ratio: float, computation: Measured
) -> tuple[str, bool | None]:
    """The row's target as the table words it, and whether it is met (None: no target)."""
    if endpoint.walk:
        share = m.per_s / computation.per_s if computation.per_s else 0.0
        return f"≥ 60% of update() alone: {share:.0%}", share >= 0.60
    if endpoint.min_ratio is not None:
        return f"≥ {endpoint.min_ratio:.0%} of /healthz", ratio >= endpoint.min_ratio
    return "—", None


def _shares(m: Measured) -> str:
    return " / ".join(f"{share:.0%}" for share in m.cpu_shares) or "—"


def _cells(m: Measured, ratio: str, *, shares: bool) -> list[str]:
    """A row's figures, from req/s to failed (with each process's CPU share if ``shares``)."""
    cells = [f"{m.per_s:,.0f}", f"{m.p50_ms:.2f}", f"{m.p99_ms:.2f}", ratio]
    cells.append(f"{m.cpu_ms_per_request:.2f}" if m.server_cpu_s else "—")
    if shares:
        cells.append(_shares(m))
    return [*cells, str(m.failed)]


def _floor_row(healthz: list[Measured], *, shares: bool) -> list[str]:
    """/healthz's row: the mean of its first and last run."""
    first, last = healthz
    return [
        f"GET /healthz (first / last run: {first.per_s:,.0f} / {last.per_s:,.0f})",
        f"{np.mean([first.per_s, last.per_s]):,.0f}",
        f"{np.mean([first.p50_ms, last.p50_ms]):.2f}",
        f"{np.mean([first.p99_ms, last.p99_ms]):.2f}",
        "1",
        f"{np.mean([first.cpu_ms_per_request, last.cpu_ms_per_request]):.2f}",
        *([_shares(last)] if shares else []),
        str(first.failed + last.failed),
        "(the floor)",
        "—",
    ]


def _endpoint_rows(
    healthz: list[Measured],
    measured: list[tuple[Endpoint, Measured]],
    computation: Measured,
    *,
    shares: bool,
) -> list[list[str]]:
    """The header, /healthz's row and a row per endpoint, each against its target."""
    floor = float(np.mean([m.per_s for m in healthz]))
    header = ["endpoint", "req/s", "p50 ms", "p99 ms", "÷ /healthz", "server CPU ms/req"]
    header += [*(["CPU by process"] if shares else []), "failed", "target", "pass"]
    rows = [header, _floor_row(healthz, shares=shares)]
    for endpoint, m in measured:
        ratio = m.per_s / floor if floor else 0.0
        target, ok = target_of(endpoint, m, ratio, computation)
        rows.append(
            [endpoint.name, *_cells(m, f"{ratio:.1%}", shares=shares), target, _verdict(ok)]
        )
    return rows


def all_cores_table(result: BackendResult) -> str:
    """The rows measured under serve's default API processes, against that server's /healthz
    and against ``update()`` alone in one process."""
    assert result.computation is not None
    rows = _endpoint_rows(
        result.all_cores_healthz, result.all_cores_rows, result.computation, shares=True
    )
    return (
        f"The same database under `serve`'s default: {result.all_cores} API processes (one per "
        "core), the rows that use them:\n\n" + render_markdown_table(rows)
    )


def table(result: BackendResult) -> str:
    computation = result.computation
    assert computation is not None
    rows = _endpoint_rows(result.healthz, result.rows, computation, shares=False)

    def row(name: str, m: Measured, ratio: str, target: str, ok: bool | None) -> None:
        rows.append([name, *_cells(m, ratio, shares=False), target, _verdict(ok)])

    row(
        "update() alone, in process (same documents)",
        computation,
        "—",
        "(the update's floor)",
        None,
    )
    assert result.healthz_1 is not None
    assert result.route_1 is not None
    row("GET /healthz, 1 connection", result.healthz_1, "—", "—", None)
    row(
        "POST …/routes, 1 connection",
        result.route_1,
        "—",
        f"p50 ≤ 1.5 ms: {result.route_1.p50_ms:.2f} ms",
        result.route_1.p50_ms <= 1.5,
    )
    notes = []
    if result.healthz_1.p50_ms >= STALL_MS:
        notes.append(
            f"Note: `GET /healthz` takes {result.healthz_1.p50_ms:.0f} ms at one connection "
            "(p50): that is a TCP stall, not work: the server's answers wait for the client's "
            "delayed ACK (≈ 40 ms on Linux), as when the accepted sockets lack TCP_NODELAY "
            "(Nagle's algorithm holds the body back until the headers are acknowledged). Every "
            "figure above includes it."
        )
    if result.all_cores_rows:
        notes.append(all_cores_table(result))
    return "\n\n".join([render_markdown_table(rows), *notes])


def heading(result: BackendResult) -> str:
    serve = " ".join(["invisible-map serve", f"--workers {WORKERS}", *result.serve_args])
    return (
        f"### {result.backend}: `{serve}`, {result.client}, {result.connections} connections "
        f"(keep-alive), {result.duration_s:g} s per endpoint\n\n"
        f"{describe_run()}; load average before / after: "
        f"{' '.join(f'{v:.2f}' for v in result.load_before)} / "
        f"{' '.join(f'{v:.2f}' for v in result.load_after)} ({os.cpu_count()} cores)"
    )


def describe_run() -> str:
    try:
        commit = subprocess.run(
            ["git", "-C", str(REPO), "describe", "--always", "--dirty"],
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        commit = "unknown"
    now = dt.datetime.now(dt.UTC).strftime("%Y-%m-%d %H:%M UTC")
    return f"{now}, commit {commit}"


def as_json(result: BackendResult) -> dict[str, Any]:
    def measured(m: Measured | None) -> dict[str, Any] | None:
        if m is None:
            return None
        return {**asdict(m), "per_s": m.per_s, "cpu_ms_per_request": m.cpu_ms_per_request}

    return {
        "backend": result.backend,
        "client": result.client,
        "connections": result.connections,
        "duration_s": result.duration_s,
        "serve_args": result.serve_args,
        "when": describe_run(),
        "load_before": result.load_before,
        "load_after": result.load_after,
        "healthz_per_s": result.healthz_per_s,
        "healthz": [measured(m) for m in result.healthz],
        "endpoints": {
            e.name: {
                **(measured(m) or {}),
                "over_healthz": m.per_s / result.healthz_per_s if result.healthz_per_s else None,
            }
            for e, m in result.rows
        },
        "update_alone": measured(result.computation),
        "healthz_1_connection": measured(result.healthz_1),
        "route_1_connection": measured(result.route_1),
        "all_cores": {
            "api_processes": result.all_cores,
            "healthz": [measured(m) for m in result.all_cores_healthz],
            "endpoints": {e.name: measured(m) for e, m in result.all_cores_rows},
        },
    }


# --------------------------------------------------------------------------- the load test


def run_load(backend: str, args: argparse.Namespace) -> tuple[str, bool]:
    """bench/load.py's default run (50 uploaders + 200 navigators, 60 s; shorter with
    ``--quick``) on ``backend``; its report and a table against issue 16's targets, and whether
    it did not fail as bench/load.py counts failure (a 5xx, a request with no answer, a lost
    session)."""
    load_argv = ["--postgres-url", args.postgres_url]
    if args.quick:
        load_argv += [
            "--duration-s",
            "10",
            "--ramp-s",
            "2",
            "--walk-s",  # (uploads within the short window)
            "1",
            "3",
            "--uploaders",
            "10",
            "--navigators",
            "40",
        ]
    load_args = load_bench.build_parser().parse_args(load_argv)
    outcome = load_bench.run_backend("sqlite" if backend == "SQLite" else "postgresql", load_args)
    tallies = outcome.tallies
    errors = sum(
        n for t in tallies.values() for code, n in t.statuses.items() if code >= 500
    ) + sum(sum(t.no_answer.values()) for t in tallies.values())
    non_2xx = sum(
        n for t in tallies.values() for code, n in t.statuses.items() if not 200 <= code < 300
    )

    def p(endpoint: str, q: float) -> float:
        values = tallies[endpoint].latencies_ms
        return float(np.percentile(values, q)) if values else float("nan")

    route_p99, update_p99 = p(load_bench.ROUTE, 99), p(load_bench.UPDATE, 99)
    ready_p95 = (
        float(np.percentile(outcome.map_ready_s, 95)) if outcome.map_ready_s else float("nan")
    )
    rows = [
        ["load test target", "measured", "pass"],
        [
            "0 errors (5xx, no answer)",
            f"{errors} (non-2xx of any kind: {non_2xx})",
            _verdict(errors == 0),
        ],
        ["0 lost sessions", str(len(outcome.lost)), _verdict(not outcome.lost)],
        ["route p99 ≤ 100 ms", f"{route_p99:.0f} ms", _verdict(route_p99 <= 100)],
        ["localization update p99 ≤ 200 ms", f"{update_p99:.0f} ms", _verdict(update_p99 <= 200)],
        ["upload → map p95 ≤ 5 s", f"{ready_p95:.1f} s", _verdict(ready_p95 <= 5)],
    ]
    text_ = "\n\n".join([load_bench.report(outcome, load_args), render_markdown_table(rows)])
    return text_, not outcome.failed


# --------------------------------------------------------------------------- main


_STARTED = time.perf_counter()


def log(message: str) -> None:
    print(f"[{time.perf_counter() - _STARTED:6.1f} s] {message}", file=sys.stderr, flush=True)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0])
    parser.add_argument(
        "--database-url",
        help="SQLite (default: a new file) or a PostgreSQL server's URL, on which a new database "
        "is created for the run and dropped after it",
    )
    parser.add_argument(
        "--both",
        action="store_true",
        help="SQLite, then PostgreSQL (on --postgres-url, or --database-url if PostgreSQL)",
    )
    parser.add_argument(
        "--postgres-url",
        default=DEFAULT_POSTGRES_URL,
        help=f"the PostgreSQL server for --both and --load ({DEFAULT_POSTGRES_URL})",
    )
    parser.add_argument("--quick", action="store_true", help="1.5 s per endpoint (a smoke run)")
    parser.add_argument("--duration-s", type=float, help="seconds per endpoint (5; --quick 1.5)")
    parser.add_argument("--connections", type=int, default=8, help="keep-alive connections (8)")
    parser.add_argument("--maps", type=int, default=50, help="maps uploaded and built (50)")
    parser.add_argument(
        "--no-wrk", action="store_true", help="the Python client even if wrk is on PATH"
    )
    parser.add_argument(
        "--serve-arg",
        action="append",
        default=[],
        help="an extra argument of `invisible-map serve` (repeatable; e.g. "
        "--serve-arg=--api-processes=2)",
    )
    parser.add_argument(
        "--no-all-cores",
        dest="all_cores",
        action="store_false",
        help="skip the second pass under serve's default API processes (one per core)",
    )
    parser.add_argument(
        "--load",
        action="store_true",
        help="then bench/load.py's load test on the same backend(s) (60 s each; --quick: 10 s, "
        "10 uploaders + 40 navigators)",
    )
    parser.add_argument("--json", type=Path, help="also write the measurements as JSON")
    args = parser.parse_args(argv)
    if args.duration_s is None:
        args.duration_s = 1.5 if args.quick else 5.0
    if args.maps < 1 or args.connections < 1 or args.duration_s <= 0:
        parser.error("--maps, --connections and --duration-s must be positive")

    url = args.database_url
    if url and not url.startswith("sqlite"):
        args.postgres_url = url
    urls: list[str | None] = [None, args.postgres_url] if args.both else [url]

    results = []
    for database_url in urls:
        result = run_backend(database_url, args)
        results.append(result)
        print(heading(result), flush=True)
        print(flush=True)
        print(table(result), flush=True)
        print(flush=True)
    load_ok = True
    if args.load:
        for result in results:
            log(f"{result.backend}: the load test (bench/load.py)…")
            report, ok = run_load(result.backend, args)
            load_ok &= ok
            print(f"### Load test, {result.backend}\n\n{report}\n", flush=True)
    if args.json:
        args.json.write_text(json.dumps([as_json(result) for result in results], indent=2) + "\n")
    failed = sum(result.failed for result in results)
    if failed:
        log(f"{failed} request(s) failed (non-2xx or no answer)")
    return 1 if failed or not load_ok else 0


if __name__ == "__main__":
    sys.exit(main())
