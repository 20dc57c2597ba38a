"""Load test (issue 7, item 3): many phones at once against a real server, one command.

    .venv/bin/python bench/load.py                    # SQLite (embedded), then PostgreSQL
    .venv/bin/python bench/load.py --sqlite --duration-s 10 --uploaders 10 --navigators 40
    .venv/bin/python bench/load.py --postgres --postgres-url postgresql+psycopg://u@host/postgres

Deployments, on loopback, each on a fresh database:
- SQLite, *embedded*: ``invisible-map serve --workers 2`` on a new SQLite file;
- PostgreSQL, *scale-out* (README, "Deployment"): ``invisible-map serve --workers 0`` and
  ``invisible-map worker --processes 2`` as separate commands, on a new database
  ``im_load_<random>`` created on the server of ``--postgres-url`` and dropped afterwards.

The phones (``--uploaders``, ``--navigators``; each has its own device key, made with the admin
key through ``POST /v1/keys``, and its own HTTP connection):
- an *uploader* has just finished a mapping walk: it uploads one of ``data/sessions/*.json``
  (chosen at random; half of the uploads gzip-compressed; a new ``Idempotency-Key`` for each
  upload, the same one for its retries after a timeout or a broken connection, as the app does),
  watches its job once a second (``GET /v1/jobs/{id}``) until the map is built, downloads the map
  (``GET /v1/maps/{id}/app-map``), then walks again for 30–90 s (``--walk-s``; a real mapping
  walk of a floor takes minutes, so even this population uploads more often than a building
  would: ~35 sessions a minute) and uploads its next session. The window opens with each
  uploader somewhere along a walk (its first upload comes uniformly within the longest walk),
  not with all of them uploading at once. Each uploader has at most one job in the queue, so the
  queue stays bounded (≤ ``--uploaders``). ``--walk-s 1 3`` is the stress population of earlier
  runs (100–150 uploads a minute, as fast as the 2 workers build: the queue stays ~45 deep, so
  upload → map is the queue's length times a build). With ``--no-wait`` an uploader does not
  wait for its map, only walks between uploads: the queue then grows during the window (the
  workers cannot keep up) and drains after it;
- a *navigator* uses one of two maps built before the window opens (``floor_2_straight`` and
  ``occam_room``, each with points of interest added where the walk passed given poses). Half
  are *routers*: once ``GET /v1/maps/{id}/pois``, then ``POST /v1/maps/{id}/routes`` between
  random tags and points of interest, once a second (a phone re-planning as its user walks).
  Half are *localizers*: ``POST /v1/maps/{id}/localizations``, then ``POST
  /v1/localizations/{id}/updates`` once a second, each update carrying that second of a real
  walk (its poses, and its detections of the map's tags: the app has the map;
  ``app.domain.localize.session_update_documents``): ``desnat_straight_once`` or
  ``floor_2_straight`` replayed into the floor_2 map, ``occam_room`` into the occam map; the
  first walk starts at a random point of it, and a walk that ends starts a new navigation
  session. Navigators arrive over the window's first ``--ramp-s`` (10) seconds, each at a
  random moment, not all in its first second. ``--pace-s 0`` sends back to back instead (a
  closed loop with no think time: latency is then clients / throughput, Little's law).

After the window (no new requests start; those in flight finish), the queue is left to drain
(``--drain-timeout-s``), then every accepted upload (202) is checked: its job ``succeeded`` and
its map has a version. A *lost session* is a 202 without that. A request that times out
(``--timeout-s``) or whose connection fails is counted apart from the statuses, per endpoint.

Latencies are per request, send to last byte of the answer, over every answer (any status).
The load generator runs on the same machine as the server, in ``--generator-processes``
processes (asyncio + httpx), at a higher priority than the server (nice
:data:`GENERATOR_NICE`, where the user may raise it: root), since real phones are other machines
whose CPU the server does not share; its CPU, priority and event loop's lag are printed: a loop
that lags adds its lag to every latency. CPU use of the API process, the worker processes, the
generator and the whole machine come from ``/proc``.

Exit status 1 if any answer was a 5xx, any request got no answer, or any session was lost.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import dataclasses
import gzip
import json
import multiprocessing
import os
import random
import re
import ssl
import sys
import tempfile
import time
import uuid
from collections import Counter
from collections.abc import AsyncIterator, Callable, Iterator
from contextlib import asynccontextmanager, contextmanager
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any, TypeVar

import httpx
import numpy as np
from sqlalchemy import Engine, create_engine, make_url, text

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from app.cli.server_process import ServerProcess, WorkerProcess  # noqa: E402
from app.cli.tables import render_markdown_table  # noqa: E402
from app.client import Client  # noqa: E402
from app.domain.localize import session_update_documents  # noqa: E402
from app.domain.upload.session import load_session  # noqa: E402

#: Every simulated phone connects from this machine's one address: no cap on connections per
#: address (``INVISIBLE_MAP_MAX_CONNECTIONS_PER_ADDRESS``), which real phones, each with its own
#: address, never reach.
ONE_ADDRESS = {"INVISIBLE_MAP_MAX_CONNECTIONS_PER_ADDRESS": "0"}

SESSIONS = REPO / "data" / "sessions"
UPLOAD_SESSIONS = sorted(SESSIONS.glob("*.json"))
DEFAULT_POSTGRES_URL = "postgresql+psycopg://postgres@127.0.0.1:5432/postgres"
IDENTITY_16 = [1.0, 0, 0, 0, 0, 1.0, 0, 0, 0, 0, 1.0, 0, 0, 0, 0, 1.0]
T = TypeVar("T")

#: The navigation maps: session → points of interest (name, the pose where the phone stood).
NAVIGATION_MAPS: dict[str, list[tuple[str, int]]] = {
    "floor_2_straight": [
        ("Room 201", 100),
        ("Room 209", 400),
        ("Kitchen", 650),
        ("Elevator lobby", 900),
    ],
    "occam_room": [("Door", 50), ("Desk", 250), ("Window", 450)],
}
#: Walks replayed into each navigation map by the localizers.
REPLAYS: dict[str, list[str]] = {
    "floor_2_straight": ["desnat_straight_once", "floor_2_straight"],
    "occam_room": ["occam_room"],
}

#: The navigators' arrival: each starts at random within this many seconds of the window's
#: opening (``--ramp-s``).
RAMP_S = 10.0
#: How often a phone polls its upload's job, s (as the app does).
JOB_POLL_S = 1.0
#: An uploader's walk between uploads, s (uniform; ``--walk-s``).
WALK_S = (30.0, 90.0)
#: Attempts of one upload (the same Idempotency-Key) when it gets no answer.
UPLOAD_ATTEMPTS = 3
#: How often the generator's loop-lag probe wakes, s.
LAG_PROBE_S = 0.05

# The endpoints as the table names them (ids replaced by {id}).
UPLOAD = "POST /v1/sessions"
JOB = "GET /v1/jobs/{id}"
APP_MAP = "GET /v1/maps/{id}/app-map"
POIS = "GET /v1/maps/{id}/pois"
ROUTE = "POST /v1/maps/{id}/routes"
START = "POST /v1/maps/{id}/localizations"
UPDATE = "POST /v1/localizations/{id}/updates"
ENDPOINTS = (UPLOAD, JOB, APP_MAP, POIS, ROUTE, START, UPDATE)


# --------------------------------------------------------------------------- what phones do


@dataclass
class Tally:
    """One endpoint's answers: latencies (ms), statuses, and requests that got no answer."""

    latencies_ms: list[float] = field(default_factory=list)
    statuses: Counter[int] = field(default_factory=Counter)
    no_answer: Counter[str] = field(default_factory=Counter)
    #: The first answer's body of each status other than 2xx (shortened).
    examples: dict[int, str] = field(default_factory=dict)

    def merge(self, other: Tally) -> None:
        self.latencies_ms += other.latencies_ms
        self.statuses.update(other.statuses)
        self.no_answer.update(other.no_answer)
        for status, body in other.examples.items():
            self.examples.setdefault(status, body)


@dataclass(frozen=True, kw_only=True)
class Accepted:
    """An upload the server accepted (202)."""

    job_id: int
    map_id: int
    session_id: int


@dataclass(frozen=True, kw_only=True)
class NavigationMap:
    """A map built before the window, and what a navigator needs of it."""

    map_id: int
    tag_ids: list[int]
    poi_names: list[str]
    #: One list of update documents per replayed walk (one document per second of walking).
    walks: list[list[dict[str, Any]]]


@dataclass(frozen=True, kw_only=True)
class Phone:
    index: int
    key: str
    role: str  # "uploader", "router" or "localizer"
    map_index: int = 0


@dataclass(frozen=True, kw_only=True)
class Plan:
    """Everything a generator process needs (picklable)."""

    base_url: str
    run_id: str
    start_at: float  # time.time() at which the window opens (set by ``generate``)
    duration_s: float
    pace_s: float
    ramp_s: float
    walk_s: tuple[float, float]
    wait_for_map: bool
    timeout_s: float
    phones: list[Phone]
    maps: list[NavigationMap]


@dataclass
class GeneratorResult:
    tallies: dict[str, Tally]
    accepted: list[Accepted]
    cpu_s: float
    wall_s: float
    loop_lag_ms: list[float]
    #: How late this process opened its window (it was still setting up), s.
    late_s: float
    #: The process's nice value (:data:`GENERATOR_NICE` where it may raise its priority).
    nice: int


class Load:
    """One generator process's phones: shared tallies and the window's deadline."""

    def __init__(self, plan: Plan, upload_bodies: list[tuple[bytes, bytes]]) -> None:
        self.plan = plan
        self.upload_bodies = upload_bodies
        self.tallies = {endpoint: Tally() for endpoint in ENDPOINTS}
        self.accepted: dict[int, Accepted] = {}
        self.deadline = 0.0  # perf_counter() at which the window closes

    def open(self) -> bool:
        return time.perf_counter() < self.deadline

    async def sleep(self, seconds: float) -> None:
        """Sleep, but not past the window's end."""
        await asyncio.sleep(max(0.0, min(seconds, self.deadline - time.perf_counter())))

    async def call(
        self, http: httpx.AsyncClient, endpoint: str, method: str, url: str, **kwargs: Any
    ) -> httpx.Response | None:
        """Send one request and tally it; None if it got no answer (timeout, broken
        connection)."""
        tally = self.tallies[endpoint]
        started = time.perf_counter()
        try:
            response = await http.request(method, url, **kwargs)
        except httpx.TimeoutException as err:
            tally.no_answer[f"timeout ({type(err).__name__})"] += 1
            return None
        except httpx.TransportError as err:
            tally.no_answer[type(err).__name__] += 1
            return None
        tally.latencies_ms.append((time.perf_counter() - started) * 1000)
        tally.statuses[response.status_code] += 1
        if not response.is_success:
            tally.examples.setdefault(response.status_code, response.text[:200])
        return response

    async def arrive(self, rng: random.Random) -> None:
        """A navigator's arrival: at random within the ramp (or one pace), so that the phones
        are not all in step and each keeps its own phase."""
        await self.sleep(rng.uniform(0, max(self.plan.ramp_s, self.plan.pace_s, 0.01)))

    async def paced(self, started: float) -> None:
        """Wait out the rest of this request's period (``pace_s`` after it started)."""
        if self.plan.pace_s > 0:
            await self.sleep(started + self.plan.pace_s - time.perf_counter())

    # ----------------------------------------------------------------------- phones

    async def uploader(self, http: httpx.AsyncClient, phone: Phone) -> None:
        rng = random.Random(f"{self.plan.run_id}-{phone.index}")
        uploads = 0
        # The window opens with each phone somewhere along its walk, not all at its end.
        await self.sleep(rng.uniform(0, self.plan.walk_s[1]))
        while self.open():
            raw, compressed = rng.choice(self.upload_bodies)
            gzipped = rng.random() < 0.5
            headers = {
                "Content-Type": "application/json",
                "Idempotency-Key": f"load-{self.plan.run_id}-{phone.index}-{uploads}",
            }
            if gzipped:
                headers["Content-Encoding"] = "gzip"
            uploads += 1
            accepted = None
            for _attempt in range(UPLOAD_ATTEMPTS):
                response = await self.call(
                    http,
                    UPLOAD,
                    "POST",
                    "/v1/sessions",
                    content=compressed if gzipped else raw,
                    headers=headers,
                )
                if response is not None:
                    if response.status_code == 202:
                        body = response.json()
                        accepted = Accepted(
                            job_id=body["job_id"],
                            map_id=body["map_id"],
                            session_id=body["session_id"],
                        )
                        self.accepted[accepted.job_id] = accepted
                    break
                if not self.open():
                    break
                await self.sleep(1.0)
            if accepted is not None and self.plan.wait_for_map:
                await self._watch_job(http, accepted)
            await self.sleep(rng.uniform(*self.plan.walk_s))

    async def _watch_job(self, http: httpx.AsyncClient, accepted: Accepted) -> None:
        """Poll the job once a second until it ends (or the window closes); download the map
        if it was built."""
        while self.open():
            await self.sleep(JOB_POLL_S)
            response = await self.call(http, JOB, "GET", f"/v1/jobs/{accepted.job_id}")
            if response is None or response.status_code != 200:
                continue
            state = response.json()["state"]
            if state == "succeeded":
                await self.call(http, APP_MAP, "GET", f"/v1/maps/{accepted.map_id}/app-map")
                return
            if state in ("failed", "canceled"):
                return

    async def router(self, http: httpx.AsyncClient, phone: Phone) -> None:
        rng = random.Random(f"{self.plan.run_id}-{phone.index}")
        nav = self.plan.maps[phone.map_index]
        await self.arrive(rng)
        await self.call(http, POIS, "GET", f"/v1/maps/{nav.map_id}/pois")
        ends: list[dict[str, int | str]] = [{"tag": tag_id} for tag_id in nav.tag_ids]
        ends += [{"poi": name} for name in nav.poi_names]
        while self.open():
            started = time.perf_counter()
            start, goal = rng.sample(ends, 2)
            await self.call(
                http,
                ROUTE,
                "POST",
                f"/v1/maps/{nav.map_id}/routes",
                json={"from": start, "to": goal},
            )
            await self.paced(started)

    async def localizer(self, http: httpx.AsyncClient, phone: Phone) -> None:
        rng = random.Random(f"{self.plan.run_id}-{phone.index}")
        nav = self.plan.maps[phone.map_index]
        walk = rng.choice(nav.walks)
        first = rng.randrange(len(walk))  # the first walk starts anywhere along it
        await self.arrive(rng)
        while self.open():
            response = await self.call(http, START, "POST", f"/v1/maps/{nav.map_id}/localizations")
            if response is None or response.status_code != 201:
                await self.sleep(1.0)
                continue
            localization_id = response.json()["id"]
            for document in walk[first:]:
                if not self.open():
                    return
                started = time.perf_counter()
                await self.call(
                    http,
                    UPDATE,
                    "POST",
                    f"/v1/localizations/{localization_id}/updates",
                    json=document,
                )
                await self.paced(started)
            walk, first = rng.choice(nav.walks), 0

    async def lag_probe(self, lags_ms: list[float]) -> None:
        """How late the event loop wakes a sleeping task: the generator's own queueing."""
        while self.open():
            before = time.perf_counter()
            await asyncio.sleep(LAG_PROBE_S)
            lags_ms.append((time.perf_counter() - before - LAG_PROBE_S) * 1000)

    async def run(self) -> tuple[float, float, list[float], float]:
        """Run every phone of this process through the window; (wall s, CPU s, loop lags ms,
        s late)."""
        roles = {"uploader": self.uploader, "router": self.router, "localizer": self.localizer}
        lags_ms: list[float] = []
        async with phone_clients(self.plan) as clients:
            await asyncio.sleep(max(0.0, self.plan.start_at - time.time()))
            late_s = max(0.0, time.time() - self.plan.start_at)  # a process that started late
            self.deadline = time.perf_counter() + self.plan.duration_s - late_s
            opened, cpu_before = time.perf_counter(), time.process_time()
            async with asyncio.TaskGroup() as group:
                group.create_task(self.lag_probe(lags_ms))
                for phone, http in zip(self.plan.phones, clients, strict=True):
                    group.create_task(roles[phone.role](http, phone))
            wall_s, cpu_s = time.perf_counter() - opened, time.process_time() - cpu_before
        return wall_s, cpu_s, lags_ms, late_s


@asynccontextmanager
async def phone_clients(plan: Plan) -> AsyncIterator[list[httpx.AsyncClient]]:
    """One ``httpx.AsyncClient`` per phone: its own key and its own connection."""
    # (The URL is http://, but each client would load the CA certificates for its own TLS
    # context otherwise: ~0.1 s apiece, 20 s for 200 phones on a busy machine.)
    tls = ssl.create_default_context()
    clients = [
        httpx.AsyncClient(
            base_url=plan.base_url,
            headers={"Authorization": f"Bearer {phone.key}"},
            timeout=httpx.Timeout(plan.timeout_s),
            limits=httpx.Limits(max_connections=1, max_keepalive_connections=1),
            verify=tls,
        )
        for phone in plan.phones
    ]
    try:
        yield clients
    finally:
        for client in clients:
            await client.aclose()


#: The generator processes' priority (``nice``), ahead of the server's processes: the phones
#: are other machines, so the server should not get their CPU time, nor they wait for its.
GENERATOR_NICE = -5


def raise_priority(nice: int = GENERATOR_NICE) -> int:
    """Run this process at ``nice`` if allowed (root, or CAP_SYS_NICE); the nice value it runs
    at."""
    with contextlib.suppress(PermissionError):
        os.setpriority(os.PRIO_PROCESS, 0, nice)
    return os.getpriority(os.PRIO_PROCESS, 0)


def run_generator(plan: Plan) -> GeneratorResult:
    """One generator process: its phones, from the window's opening to its end."""
    nice = raise_priority()
    bodies = []
    for path in UPLOAD_SESSIONS:
        raw = path.read_bytes()
        bodies.append((raw, gzip.compress(raw)))
    load = Load(plan, bodies)
    wall_s, cpu_s, lags_ms, late_s = asyncio.run(load.run())
    return GeneratorResult(
        tallies=load.tallies,
        accepted=list(load.accepted.values()),
        cpu_s=cpu_s,
        wall_s=wall_s,
        loop_lag_ms=lags_ms,
        late_s=late_s,
        nice=nice,
    )


# --------------------------------------------------------------------------- the server


@dataclass(frozen=True, kw_only=True)
class Deployment:
    """A running server: its URL, admin key, and processes (for CPU and logs)."""

    backend: str
    description: str
    server: ServerProcess
    #: Process groups of the commands started (the API's, and the workers' if separate).
    process_groups: list[int]
    log_paths: list[Path]
    #: The database's size on disk now, bytes.
    size_bytes: Callable[[], int]


def _processes(api_processes: int | None) -> str:
    return "" if api_processes is None else f" --api-processes {api_processes}"


@contextmanager
def sqlite_deployment(folder: Path, api_processes: int | None) -> Iterator[Deployment]:
    """Embedded: ``serve --workers 2`` on a new SQLite file (``api_processes`` None: serve's
    default, one per core)."""
    url = f"sqlite:///{folder / 'load.sqlite3'}"
    log = folder / "server.log"
    env = {
        "INVISIBLE_MAP_DATA_DIR": str(folder),
        **ONE_ADDRESS,
    }
    with ServerProcess(
        url, workers=2, env=env, log_path=log, api_processes=api_processes
    ) as server:
        yield Deployment(
            backend="SQLite",
            description=f"embedded: `invisible-map serve --workers 2{_processes(api_processes)}`, "
            "a new SQLite file",
            server=server,
            process_groups=[server.pid],
            log_paths=[log],
            size_bytes=lambda: sum(f.stat().st_size for f in folder.glob("load.sqlite3*")),
        )


@contextmanager
def postgres_deployment(
    folder: Path, admin_url: str, api_processes: int | None
) -> Iterator[Deployment]:
    """Scale-out: ``serve --workers 0`` and ``worker --processes 2`` on a new database, dropped
    at the end."""
    name = f"im_load_{uuid.uuid4().hex[:8]}"
    admin = create_engine(admin_url, isolation_level="AUTOCOMMIT")
    with admin.connect() as connection:
        connection.execute(text(f'CREATE DATABASE "{name}"'))
    try:
        url = make_url(admin_url).set(database=name).render_as_string(hide_password=False)
        env = {
            "INVISIBLE_MAP_DATA_DIR": str(folder),
            **ONE_ADDRESS,
        }
        api_log, worker_log = folder / "api.log", folder / "worker.log"
        with (
            ServerProcess(
                url, workers=0, env=env, log_path=api_log, api_processes=api_processes
            ) as server,
            WorkerProcess(url, processes=2, env=env, log_path=worker_log) as workers,
        ):
            yield Deployment(
                backend="PostgreSQL",
                description="scale-out: `invisible-map serve --workers 0"
                f"{_processes(api_processes)}` and "
                f"`invisible-map worker --processes 2`, database {name}",
                server=server,
                process_groups=[server.pid, workers.pid],
                log_paths=[api_log, worker_log],
                size_bytes=lambda: database_size_bytes(admin, name),
            )
    finally:
        with admin.connect() as connection:
            connection.execute(text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))
        admin.dispose()


def database_size_bytes(admin: Engine, name: str) -> int:
    with admin.connect() as connection:
        return int(
            connection.execute(text("SELECT pg_database_size(:n)"), {"n": name}).scalar_one()
        )


CLOCK_TICKS_PER_S = os.sysconf("SC_CLK_TCK")


def process_cpu_s(process_groups: list[int]) -> dict[int, float]:
    """CPU time (user + system, s) of each live process in these process groups, by pid."""
    cpu_s = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
        except OSError:  # gone meanwhile
            continue
        fields = stat[stat.rindex(")") + 2 :].split()  # after "pid (comm) "
        if int(fields[2]) in process_groups:  # pgrp
            cpu_s[int(entry.name)] = (int(fields[11]) + int(fields[12])) / CLOCK_TICKS_PER_S
    return cpu_s


def machine_ticks() -> tuple[int, int]:
    """(busy, total) clock ticks of all CPUs since boot, from /proc/stat."""
    values = [int(v) for v in Path("/proc/stat").read_text().splitlines()[0].split()[1:]]
    idle = values[3] + values[4]  # idle + iowait
    total = sum(values[:8])  # without guest time, which is counted in user already
    return total - idle, total


# --------------------------------------------------------------------------- before the window


def with_pois(path: Path, pois: list[tuple[str, int]]) -> bytes:
    """The session at ``path`` with points of interest where the phone stood at given poses."""
    document = json.loads(path.read_bytes())
    timestamps = {pose["id"]: pose["timestamp"] for pose in document["pose_data"]}
    document["location_data"] = [
        {
            "name": name,
            "pose_id": pose_id + 1,  # the app writes it one too high; the parser corrects it
            "timestamp": timestamps[pose_id],
            "transform": IDENTITY_16,
        }
        for name, pose_id in pois
    ]
    return json.dumps(document).encode()


def walk_documents(name: str, tag_ids: list[int]) -> list[dict[str, Any]]:
    """The updates of the walk ``name``, one per second of walking, with the detections of the
    map's tags only (the app has the map, so it knows them; the server refuses an update with
    a tag the map does not have, and floor_2_straight's map leaves out tag 323)."""
    session = load_session(SESSIONS / f"{name}.json")
    duration_s = float(session.timestamp_s[-1] - session.timestamp_s[0])
    poses_per_s = max(1, round(session.num_poses / duration_s))
    return session_update_documents(session, poses_per_s, tag_ids=tag_ids)


def build_navigation_maps(url: str, admin: Client, run_id: str) -> list[NavigationMap]:
    """Upload the navigation maps with a device key (as a surveyor's phone), wait for them."""
    surveyor = admin.create_key(role="device", name="load test surveyor")["key"]
    maps = []
    with Client(url, api_key=surveyor, timeout_s=60) as phone:
        for name, pois in NAVIGATION_MAPS.items():
            accepted = phone.upload_session(
                with_pois(SESSIONS / f"{name}.json", pois), idempotency_key=f"load-{run_id}-{name}"
            )
            phone.wait_for_job(accepted["job_id"], timeout_s=300)
            map_id = accepted["map_id"]
            version = phone.get_map(map_id)["current_version"]
            tag_ids = sorted(tag["tag_id"] for tag in version["tags"])
            maps.append(
                NavigationMap(
                    map_id=map_id,
                    tag_ids=tag_ids,
                    poi_names=[poi["name"] for poi in phone.search_pois(map_id)],
                    walks=[walk_documents(walk, tag_ids) for walk in REPLAYS[name]],
                )
            )
    return maps


def make_phones(admin: Client, uploaders: int, navigators: int, maps: int) -> list[Phone]:
    """Uploaders, then navigators alternating router and localizer over the maps; each phone
    with a new device key."""
    phones = []
    for index in range(uploaders + navigators):
        key = admin.create_key(role="device", name=f"load test phone {index}")["key"]
        if index < uploaders:
            phones.append(Phone(index=index, key=key, role="uploader"))
        else:
            k = index - uploaders
            role = "router" if k % 2 == 0 else "localizer"
            phones.append(Phone(index=index, key=key, role=role, map_index=(k // 2) % maps))
    return phones


# --------------------------------------------------------------------------- after the window


def drain(admin: Client, timeout_s: float) -> tuple[float, int, int]:
    """Wait until no job is queued or running; (seconds waited, jobs left, jobs at the start)."""
    started = time.monotonic()
    at_start = None
    while True:
        left = sum(admin.list_jobs(state=s, limit=1)["count"] for s in ("queued", "running"))
        at_start = left if at_start is None else at_start
        waited_s = time.monotonic() - started
        if left == 0 or waited_s > timeout_s:
            return waited_s, left, at_start
        time.sleep(0.25)


def lost_sessions(
    admin: Client, accepted: list[Accepted], map_ready_s: list[float] | None = None
) -> list[str]:
    """Why each accepted upload that did not end in a map did not (empty if all did); appends
    to ``map_ready_s`` the upload → map time of each that did (its job's ``created_at`` to
    ``finished_at``, the server's clock: the job is created in the upload's transaction)."""
    lost = []
    for upload in accepted:
        job = admin.get_job(upload.job_id)
        if job["state"] == "succeeded" and map_ready_s is not None and job["finished_at"]:
            created = datetime.fromisoformat(job["created_at"])
            map_ready_s.append(
                (datetime.fromisoformat(job["finished_at"]) - created).total_seconds()
            )
        if job["state"] != "succeeded":
            lost.append(f"job {upload.job_id} {job['state']}: {job.get('error') or ''}".strip())
        elif admin.get_map(upload.map_id)["current_version"] is None:
            lost.append(f"job {upload.job_id} succeeded but map {upload.map_id} has no version")
    return lost


#: Log lines worth reporting (uvicorn's access lines are not).
LOG_PROBLEM = re.compile(
    r"Traceback|ERROR|CRITICAL|WARNING|database is locked|QueuePool|unhandled", re.IGNORECASE
)


def log_problems(paths: list[Path]) -> Counter[str]:
    """Problem lines of the server's logs, counted (numbers and ids masked so alike lines
    group)."""
    problems: Counter[str] = Counter()
    for path in paths:
        if not path.exists():
            continue
        for line in path.read_text(errors="replace").splitlines():
            if LOG_PROBLEM.search(line) and '" 2' not in line:
                problems[re.sub(r"\d+", "N", line.strip())[:160]] += 1
    return problems


# --------------------------------------------------------------------------- one run


@dataclass
class Outcome:
    backend: str
    description: str
    tallies: dict[str, Tally]
    accepted: list[Accepted]
    lost: list[str]
    stored_sessions: int
    window_s: float
    drain_s: float
    drain_left: int
    queue_at_close: int
    generator_cpu_s: float
    generator_lag_ms: list[float]
    generator_late_s: float
    generator_nice: int
    api_cpu_s: float
    workers_cpu_s: float
    machine_busy: float
    log_problems: Counter[str]
    database_bytes: int
    #: Upload → map of each accepted upload that got one, s (job created → finished).
    map_ready_s: list[float] = field(default_factory=list)

    @property
    def failed(self) -> bool:
        return bool(
            self.lost
            or any(code >= 500 for t in self.tallies.values() for code in t.statuses)
            or any(t.no_answer for t in self.tallies.values())
        )


def run_backend(backend: str, args: argparse.Namespace) -> Outcome:
    with tempfile.TemporaryDirectory(prefix="im-load-") as temp:
        folder = Path(temp)
        deployment = (
            sqlite_deployment(folder, args.api_processes)
            if backend == "sqlite"
            else postgres_deployment(folder, args.postgres_url, args.api_processes)
        )
        try:
            with deployment as running:
                return load_server(running, args)
        finally:
            if args.log_dir:
                args.log_dir.mkdir(parents=True, exist_ok=True)
                for path in folder.glob("*.log"):
                    (args.log_dir / f"{backend}-{path.name}").write_bytes(path.read_bytes())


def load_server(deployment: Deployment, args: argparse.Namespace) -> Outcome:
    server = deployment.server
    run_id = uuid.uuid4().hex[:8]
    with Client(server.url, api_key=server.admin_key, timeout_s=120) as admin:
        maps = build_navigation_maps(server.url, admin, run_id)
        phones = make_phones(admin, args.uploaders, args.navigators, len(maps))
        processes = max(1, min(args.generator_processes, len(phones)))
        dealt = random.Random(run_id).sample(phones, len(phones))  # every kind in each process
        print(
            f"{deployment.backend}: {len(phones)} phones ready; {args.duration_s:g} s of load "
            f"from {processes} generator process(es)…",
            file=sys.stderr,
            flush=True,
        )
        plans = [
            Plan(
                base_url=server.url,
                run_id=run_id,
                start_at=0.0,
                duration_s=args.duration_s,
                pace_s=args.pace_s,
                ramp_s=args.ramp_s,
                walk_s=tuple(args.walk_s),
                wait_for_map=not args.no_wait,
                timeout_s=args.timeout_s,
                phones=dealt[k::processes],
                maps=maps,
            )
            for k in range(processes)
        ]
        results, (cpu_before, ticks_before) = generate(
            plans, lambda: (process_cpu_s(deployment.process_groups), machine_ticks())
        )
        ticks_after = machine_ticks()
        cpu_after = process_cpu_s(deployment.process_groups)
        # The worker processes say who they are; every other process of the groups is the API
        # (`serve` and, with --api-processes N, its API processes).
        worker_pids = {worker["pid"] for worker in admin.info()["workers"]}
        queue_at_close = sum(
            admin.list_jobs(state=s, limit=1)["count"] for s in ("queued", "running")
        )
        drain_s, drain_left, _ = drain(admin, args.drain_timeout_s)
        accepted = [a for result in results for a in result.accepted]
        map_ready_s: list[float] = []
        lost = lost_sessions(admin, accepted, map_ready_s)
        stored = admin.list_sessions(limit=1)["count"] - len(maps)
        size_bytes = deployment.size_bytes()

    tallies = {endpoint: Tally() for endpoint in ENDPOINTS}
    for result in results:
        for endpoint, tally in result.tallies.items():
            tallies[endpoint].merge(tally)
    spent = {pid: cpu_after[pid] - cpu_before.get(pid, 0.0) for pid in cpu_after}
    api_cpu_s = sum(cpu for pid, cpu in spent.items() if pid not in worker_pids)
    busy = (ticks_after[0] - ticks_before[0]) / max(1, ticks_after[1] - ticks_before[1])
    return Outcome(
        backend=deployment.backend,
        description=deployment.description,
        tallies=tallies,
        accepted=accepted,
        lost=lost,
        stored_sessions=stored,
        window_s=max(result.wall_s for result in results),
        drain_s=drain_s,
        drain_left=drain_left,
        queue_at_close=queue_at_close,
        generator_cpu_s=sum(result.cpu_s for result in results),
        generator_lag_ms=[lag for result in results for lag in result.loop_lag_ms],
        generator_late_s=max(result.late_s for result in results),
        generator_nice=max(result.nice for result in results),
        api_cpu_s=api_cpu_s,
        workers_cpu_s=sum(spent.values()) - api_cpu_s,
        machine_busy=busy,
        log_problems=log_problems(deployment.log_paths),
        database_bytes=size_bytes,
        map_ready_s=map_ready_s,
    )


#: Seconds between starting the generator processes and opening the window (they import the
#: project first).
GENERATOR_START_S = 5.0


def generate(plans: list[Plan], at_open: Callable[[], T]) -> tuple[list[GeneratorResult], T]:
    """Run each plan in a process of its own; also ``at_open()``'s value when the window opens
    (the CPU counters)."""
    context = multiprocessing.get_context("spawn")
    with context.Pool(len(plans)) as pool:
        start_at = time.time() + GENERATOR_START_S
        timed = [dataclasses.replace(plan, start_at=start_at) for plan in plans]
        running = pool.map_async(run_generator, timed, chunksize=1)
        time.sleep(max(0.0, start_at - time.time()))
        opened = at_open()
        return running.get(), opened


# --------------------------------------------------------------------------- the report


def endpoint_table(tallies: dict[str, Tally]) -> str:
    rows = [["endpoint", "requests", "p50 ms", "p99 ms", "max ms", "non-2xx", "5xx", "no answer"]]
    for endpoint, tally in tallies.items():
        requests = sum(tally.statuses.values())
        if requests == 0 and not tally.no_answer:
            continue
        latencies = np.array(tally.latencies_ms) if tally.latencies_ms else np.zeros(1)
        others = sorted((code, n) for code, n in tally.statuses.items() if not 200 <= code < 300)
        no_answer = sum(tally.no_answer.values())
        rows.append(
            [
                endpoint,
                str(requests),
                f"{np.percentile(latencies, 50):.0f}",
                f"{np.percentile(latencies, 99):.0f}",
                f"{latencies.max():.0f}",
                ", ".join(f"{code}×{n}" for code, n in others) or "0",
                str(sum(n for code, n in others if code >= 500)),
                (
                    f"{no_answer} ("
                    + ", ".join(f"{kind}×{n}" for kind, n in tally.no_answer.items())
                    + ")"
                    if no_answer
                    else "0"
                ),
            ]
        )
    return render_markdown_table(rows)


def totals_table(outcome: Outcome, args: argparse.Namespace) -> str:
    accepted = len(outcome.accepted)
    window_s = outcome.window_s
    requests = sum(sum(t.statuses.values()) for t in outcome.tallies.values())
    navigation = sum(sum(outcome.tallies[e].statuses.values()) for e in (ROUTE, START, UPDATE))
    offered = f"{args.navigators / args.pace_s:.0f}" if args.pace_s > 0 else "as many as answered"
    lags = np.array(outcome.generator_lag_ms) if outcome.generator_lag_ms else np.zeros(1)
    drained = (
        f"{outcome.drain_s:.1f} s ({outcome.queue_at_close} jobs queued or running when the "
        "window closed)"
        if outcome.drain_left == 0
        else f"**not drained**: {outcome.drain_left} jobs left after {outcome.drain_s:.0f} s"
    )
    rows = [
        ["measure", "value"],
        ["uploads accepted (202)", str(accepted)],
        ["sessions that ended with a map", str(accepted - len(outcome.lost))],
        ["lost sessions (202 but no map)", str(len(outcome.lost))],
        [
            "upload → map p50 / p95 (job created → finished, server clock)",
            (
                f"{np.percentile(outcome.map_ready_s, 50):.1f} s / "
                f"{np.percentile(outcome.map_ready_s, 95):.1f} s"
                if outcome.map_ready_s
                else "—"
            ),
        ],
        ["sessions stored whose 202 never arrived", str(outcome.stored_sessions - accepted)],
        ["draining the queue after the window", drained],
        [
            "uploads accepted per minute (window) / maps built per minute (window + drain)",
            f"{accepted / window_s * 60:.0f} / "
            f"{(accepted - len(outcome.lost)) / (window_s + outcome.drain_s) * 60:.0f}",
        ],
        [
            "navigation requests per second: offered / answered",
            f"{offered} / {navigation / window_s:.0f}",
        ],
        [
            "all requests answered (window: until the last answer)",
            f"{requests} in {window_s:.1f} s: {requests / window_s:.0f}/s"
            + (
                f" (a generator opened the window {outcome.generator_late_s:.1f} s late)"
                if outcome.generator_late_s > 0.5
                else ""
            ),
        ],
        [
            "CPU, % of one core: API process / workers / load generator",
            f"{outcome.api_cpu_s / window_s:.0%} / {outcome.workers_cpu_s / window_s:.0%} / "
            f"{outcome.generator_cpu_s / window_s:.0%}",
        ],
        [
            f"machine CPU busy ({os.cpu_count()} cores, every process on it)",
            f"{outcome.machine_busy:.0%}",
        ],
        [
            "generator event-loop lag p50 / p99 / max",
            f"{np.percentile(lags, 50):.0f} / {np.percentile(lags, 99):.0f} / {lags.max():.0f} ms",
        ],
        [
            "generator priority (nice; the server's API processes run at 0)",
            str(outcome.generator_nice),
        ],
        ["database size at the end", f"{outcome.database_bytes / 2**20:.0f} MiB"],
        ["problem lines in the server's logs", str(sum(outcome.log_problems.values()))],
    ]
    return render_markdown_table(rows)


def report(outcome: Outcome, args: argparse.Namespace) -> str:
    low_s, high_s = args.walk_s
    walk = f"walk {low_s:g}–{high_s:g} s"
    uploaders = (
        f"upload, poll the job once a second until the map is built, download it, {walk}"
        if not args.no_wait
        else f"upload, {walk} (without waiting for the map)"
    )
    pace = f"once every {args.pace_s:g} s" if args.pace_s > 0 else "back to back"
    lines = [
        f"## {outcome.backend}: {outcome.description}",
        "",
        f"{args.duration_s:g} s on loopback; {args.uploaders} uploaders ({uploaders}); "
        f"{args.navigators} navigators (half route, half localize, each {pace}, arriving "
        f"within the first {args.ramp_s:g} s); "
        f"{args.generator_processes} generator process(es) on the same machine.",
        "",
        endpoint_table(outcome.tallies),
        "",
        totals_table(outcome, args),
    ]
    examples = [
        f"- {endpoint} {status}: {body}"
        for endpoint, tally in outcome.tallies.items()
        for status, body in sorted(tally.examples.items())
    ]
    if examples:
        lines += ["", "Answers other than 2xx (the first of each):", *examples]
    if outcome.lost:
        lines += ["", "Lost sessions (first 10):", *(f"- {why}" for why in outcome.lost[:10])]
    if outcome.log_problems:
        lines += ["", "Problem lines in the server's logs (most frequent first, digits as N):"]
        lines += [f"- {n}× {line}" for line, n in outcome.log_problems.most_common(8)]
    lines.append("")
    lines.append("FAILED: 5xx, unanswered requests or lost sessions" if outcome.failed else "OK")
    return "\n".join(lines)


def build_parser() -> argparse.ArgumentParser:
    """The command's arguments (also used by ``bench/http.py --load``)."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    which = parser.add_mutually_exclusive_group()
    which.add_argument("--sqlite", action="store_true", help="only SQLite (embedded)")
    which.add_argument("--postgres", action="store_true", help="only PostgreSQL (scale-out)")
    parser.add_argument(
        "--postgres-url",
        default=DEFAULT_POSTGRES_URL,
        help="a PostgreSQL server's URL (any database on it); the test creates its own database "
        f"there and drops it afterwards ({DEFAULT_POSTGRES_URL})",
    )
    parser.add_argument("--duration-s", type=float, default=60.0, help="the load window (60)")
    parser.add_argument("--uploaders", type=int, default=50, help="uploading phones (50)")
    parser.add_argument("--navigators", type=int, default=200, help="navigating phones (200)")
    parser.add_argument(
        "--pace-s",
        type=float,
        default=1.0,
        help="a navigator's request period, s; 0: back to back (1)",
    )
    parser.add_argument(
        "--ramp-s",
        type=float,
        default=RAMP_S,
        help="navigators start at random within the window's first seconds, not all at once "
        f"(as phones arrive; {RAMP_S:g}; 0: within one pace)",
    )
    parser.add_argument(
        "--walk-s",
        type=float,
        nargs=2,
        metavar=("LOW", "HIGH"),
        default=list(WALK_S),
        help="an uploader's walk between one map and its next upload, s, uniform (30 90; a real "
        "mapping walk takes minutes; 1 3: the stress population of earlier runs)",
    )
    parser.add_argument(
        "--no-wait",
        action="store_true",
        help="uploaders do not wait for their map between uploads (the queue grows)",
    )
    parser.add_argument(
        "--generator-processes", type=int, default=2, help="load generator processes (2)"
    )
    parser.add_argument(
        "--timeout-s", type=float, default=60.0, help="a request with no answer by then fails (60)"
    )
    parser.add_argument(
        "--drain-timeout-s", type=float, default=600.0, help="longest wait for the queue (600)"
    )
    parser.add_argument(
        "--api-processes",
        type=int,
        help="the API processes of `serve` (default: serve's own, one per core)",
    )
    parser.add_argument("--log-dir", type=Path, help="keep the server's logs here")
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.uploaders < 0 or args.navigators < 0 or args.uploaders + args.navigators == 0:
        parser.error("--uploaders and --navigators must be ≥ 0, and not both 0")
    if args.ramp_s < 0 or args.ramp_s >= args.duration_s:
        parser.error("--ramp-s must be ≥ 0 and shorter than --duration-s")
    if not 0 <= args.walk_s[0] <= args.walk_s[1]:
        parser.error("--walk-s LOW HIGH needs 0 ≤ LOW ≤ HIGH")

    backends = ["sqlite"] if args.sqlite else ["postgresql"] if args.postgres else []
    backends = backends or ["sqlite", "postgresql"]
    failed = False
    for backend in backends:
        outcome = run_backend(backend, args)
        print(report(outcome, args), flush=True)
        print()
        failed |= outcome.failed
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
