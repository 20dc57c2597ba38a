"""Many requests at once on one API process (``invisible-map serve``), as issue 7's load test
sends them: every one is answered, none waits for the database pool's 30 s timeout.

Routes and their dependencies run on threads of anyio's pool, and FastAPI validates a ``def``
route's answer on yet another. When a request kept its database connection from its
dependencies until its answer was validated, 150 requests at once left every thread waiting for
a connection while every connection was held by a request waiting for a thread: the API stood
still for 30 s, then answered 503s. Now a request holds a connection only while one of its
threads runs (``app.web.route_class``), so this holds with anyio's default of 40 threads too,
which is what the server runs with here.

The load takes longer than clients keep an idle connection (httpx: 5 s), so they reuse
connections that sat idle for seconds. uvicorn used to close idle connections after 5 s as well,
timed from its side, and now and then it closed one just as a client sent a request on it: that
request failed unanswered (``RemoteProtocolError`` or ``ReadError``). Now the server keeps idle
connections longer than clients and proxies do (``Settings.keep_alive_s``), so they close first.
"""

from __future__ import annotations

import asyncio
import time
from collections import Counter

import httpx
import pytest

from app.cli.server_process import ServerProcess

pytestmark = [pytest.mark.db, pytest.mark.slow]

#: Requests sent at once: more than 40 threads plus the largest pool (30, PostgreSQL).
CLIENTS = 150
ROUNDS = 3
#: Shorter than the pool's 30 s timeout, so that a stall fails the test instead of a 503.
TIMEOUT_S = 20.0
#: How long httpx keeps an idle connection to reuse it (its default, 5 s).
CLIENT_KEEP_ALIVE_S = httpx.Limits().keepalive_expiry


async def _at_once(url: str, key: str) -> Counter[int | str]:
    """CLIENTS clients, each sending ROUNDS requests; every client starts at the same moment."""
    outcomes: Counter[int | str] = Counter()
    start = asyncio.Event()
    limits = httpx.Limits(max_connections=CLIENTS, max_keepalive_connections=CLIENTS)
    headers = {"Authorization": f"Bearer {key}"}
    async with httpx.AsyncClient(
        base_url=url, headers=headers, limits=limits, timeout=TIMEOUT_S
    ) as http:

        async def client() -> None:
            await start.wait()
            for _ in range(ROUNDS):
                try:
                    response = await http.get("/v1/sessions")  # a read session, a response model
                except httpx.TransportError as err:
                    outcomes[type(err).__name__] += 1
                else:
                    outcomes[response.status_code] += 1

        tasks = [asyncio.create_task(client()) for _ in range(CLIENTS)]
        await asyncio.sleep(0.1)
        start.set()
        await asyncio.gather(*tasks)
    return outcomes


def test_many_requests_at_once_are_all_answered(database_url, tmp_path):
    with ServerProcess(
        database_url,
        workers=0,
        env={
            "INVISIBLE_MAP_DATA_DIR": str(tmp_path),
            "INVISIBLE_MAP_API_THREADS": "40",
            # 150 phones from one address (the test's): no cap on connections per address
            "INVISIBLE_MAP_MAX_CONNECTIONS_PER_ADDRESS": "0",
        },
        log_path=tmp_path / "api.log",
    ) as server:
        outcomes = asyncio.run(_at_once(server.url, server.admin_key))
    assert outcomes == Counter({200: CLIENTS * ROUNDS})


def test_an_idle_connection_stays_open_longer_than_clients_keep_it(tmp_path):
    """A client may send its next request on a connection it has kept idle for its whole
    keep-alive time: the server must not have closed it (or be closing it) by then."""
    assert CLIENT_KEEP_ALIVE_S is not None
    with (
        ServerProcess(
            f"sqlite:///{tmp_path / 'keep-alive.sqlite3'}",
            workers=0,
            env={"INVISIBLE_MAP_DATA_DIR": str(tmp_path)},
        ) as server,
        # no expiry of its own, so it shows which side closes the connection
        httpx.Client(base_url=server.url, limits=httpx.Limits(keepalive_expiry=None)) as http,
    ):
        first = http.get("/healthz")
        first_address = first.extensions["network_stream"].get_extra_info("client_addr")
        time.sleep(CLIENT_KEEP_ALIVE_S + 1.0)
        second = http.get("/healthz")
        second_address = second.extensions["network_stream"].get_extra_info("client_addr")
    assert (first.status_code, second.status_code) == (200, 200)
    assert second_address == first_address, "the server closed the idle connection"
