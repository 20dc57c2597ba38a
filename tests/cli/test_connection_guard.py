"""``serve`` closes slow connections and caps connections per address (issue 19, finding 5;
``app.api.connection_guard``): real sockets against a real server, with short limits."""

from __future__ import annotations

import contextlib
import socket
import time
from pathlib import Path

import httpx
import pytest

from app.cli.server_process import ServerProcess
from tests.service.helpers import wait_for

pytestmark = pytest.mark.slow

LIMITS = {
    "INVISIBLE_MAP_HEADER_TIMEOUT_S": "1.5",
    "INVISIBLE_MAP_BODY_TIMEOUT_S": "1.5",
    "INVISIBLE_MAP_MAX_CONNECTIONS_PER_ADDRESS": "5",
}


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory):  # type: ignore[no-untyped-def]
    folder = tmp_path_factory.mktemp("guard")
    env = {"INVISIBLE_MAP_DATA_DIR": str(folder), **LIMITS}
    with ServerProcess(
        f"sqlite:///{folder / 'db.sqlite3'}", workers=0, env=env, log_path=folder / "serve.log"
    ) as process:
        yield process


def connect(server: ServerProcess) -> socket.socket:
    return socket.create_connection(("127.0.0.1", server.port), timeout=10)


def closed_after_s(sock: socket.socket) -> float:
    """Seconds until the server closes ``sock`` (reading and dropping whatever it sends)."""
    started = time.monotonic()
    while sock.recv(4096):
        pass
    return time.monotonic() - started


def test_a_connection_that_sends_nothing_is_closed(server: ServerProcess) -> None:
    with connect(server) as sock:
        assert closed_after_s(sock) < 4


def test_headers_sent_a_byte_at_a_time_are_cut_off(server: ServerProcess) -> None:
    request = b"GET /healthz HTTP/1.1\r\nHost: x\r\nX-Slow: " + b"a" * 100
    started = time.monotonic()
    with connect(server) as sock:
        for byte in request[:30]:  # 3 s of a byte every 0.1 s: longer than the 1.5 s allowed
            try:
                sock.sendall(bytes([byte]))
            except OSError:  # reset: the server closed it already
                break
            time.sleep(0.1)
        with contextlib.suppress(ConnectionResetError):
            closed_after_s(sock)
        assert time.monotonic() - started < 5


def stalled_upload_closed_after_s(server: ServerProcess) -> float:
    """Seconds until the server closes an upload that sends its headers and a few bytes of a
    100 kB body, then nothing."""
    head = (
        f"POST /v1/sessions HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer {server.admin_key}\r\n"
        "Content-Type: application/json\r\nContent-Length: 100000\r\n\r\n"
    ).encode()
    with connect(server) as sock:
        sock.sendall(head + b'{"map_id": "slow')
        return closed_after_s(sock)


def test_a_stalled_body_is_cut_off(server: ServerProcess) -> None:
    assert stalled_upload_closed_after_s(server) < 5


def test_connections_per_address_are_capped(server: ServerProcess) -> None:
    held = [connect(server) for _ in range(5)]
    try:
        time.sleep(0.2)
        with connect(server) as extra:
            answer = extra.recv(4096)
            assert answer.startswith(b"HTTP/1.1 503"), answer
            assert b"Retry-After: 1" in answer
    finally:
        for sock in held:
            sock.close()
    time.sleep(0.3)
    assert httpx.get(server.url + "/healthz").status_code == 200


def test_keep_alive_and_ordinary_requests_still_work(server: ServerProcess) -> None:
    with httpx.Client(base_url=server.url) as client:
        for _ in range(3):
            assert client.get("/healthz").status_code == 200
            time.sleep(0.5)


def test_the_log_says_why_in_one_line_each(server: ServerProcess) -> None:
    """Its own slow connections (xdist may run this module's other tests in another process):
    each cut is one line of the log, and the upload whose body was cut off is one line too, not
    an unhandled error with a traceback (a client gone mid-body has nobody to answer)."""
    with connect(server) as sock:
        closed_after_s(sock)
    stalled_upload_closed_after_s(server)
    assert server.log_path is not None
    log_path = Path(server.log_path)
    disconnected = "client disconnected while sending POST /v1/sessions"
    wait_for(lambda: disconnected in log_path.read_text(), timeout_s=10, what="the log line")
    text = log_path.read_text()
    assert "its request's headers did not arrive within 1.5 s" in text
    assert "no byte of its request's body came for 1.5 s" in text
    assert "Traceback" not in text, text


PROBE_LIMITS = {
    "INVISIBLE_MAP_HEADER_TIMEOUT_S": "2",
    "INVISIBLE_MAP_BODY_TIMEOUT_S": "2",
    "INVISIBLE_MAP_MAX_CONNECTIONS_PER_ADDRESS": "0",  # the probe's 100 from one address
}
#: Seconds between two bytes of a slow client (each connection trickles, never stalls).
TRICKLE_S = 0.25


def test_a_hundred_slow_clients_are_all_closed_and_others_are_answered(
    tmp_path: Path,
) -> None:
    """The outside probe of issue 19 (finding 5): 50 clients sending their headers a byte at a
    time with no key, and 50 sending a body a byte at a time after whole headers with a key;
    every one of them is closed by the server within its limit (2 s, plus the time to notice),
    and ordinary requests are answered meanwhile."""
    env = {"INVISIBLE_MAP_DATA_DIR": str(tmp_path), **PROBE_LIMITS}
    with ServerProcess(
        f"sqlite:///{tmp_path / 'db.sqlite3'}", workers=0, env=env, log_path=tmp_path / "log"
    ) as server:
        header_bytes = b"GET /v1/maps HTTP/1.1\r\nHost: x\r\nX-Slow: " + b"a" * 1000
        body_head = (
            f"POST /v1/sessions HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer {server.admin_key}"
            "\r\nContent-Type: application/json\r\nContent-Length: 100000\r\n\r\n"
        ).encode()
        clients: list[tuple[socket.socket, bytes]] = []
        for k in range(100):
            sock = connect(server)
            sock.setblocking(False)
            if k % 2:  # a slow body: whole headers, then the body a byte at a time
                sock.sendall(body_head)
                clients.append((sock, b'{"map_id": "' + b"s" * 1000))
            else:
                clients.append((sock, header_bytes))
        started_s = time.monotonic()
        closed_after: dict[int, float] = {}
        answered = []
        sent = 0
        while len(closed_after) < len(clients) and time.monotonic() - started_s < 8:
            for k, (sock, trickle) in enumerate(clients):
                if k in closed_after:
                    continue
                try:
                    if sock.recv(4096) == b"":
                        closed_after[k] = time.monotonic() - started_s
                        continue
                except BlockingIOError:
                    pass
                except OSError:  # reset
                    closed_after[k] = time.monotonic() - started_s
                    continue
                try:
                    sock.send(trickle[sent : sent + 1])
                except BlockingIOError:
                    pass
                except OSError:
                    closed_after[k] = time.monotonic() - started_s
            sent += 1
            if sent % 4 == 0:  # someone else, meanwhile
                answer = httpx.get(server.url + "/healthz", timeout=5)
                answered.append(answer.status_code)
            time.sleep(TRICKLE_S)
        for sock, _ in clients:
            sock.close()
        assert len(closed_after) == 100, f"{100 - len(closed_after)} slow clients still open"
        print(
            f"100 slow clients closed {min(closed_after.values()):.1f}–"
            f"{max(closed_after.values()):.1f} s in; {len(answered)} other requests answered"
        )
        assert max(closed_after.values()) < 5  # each within its 2 s (and the loop's rounds)
        assert answered, answered
        assert set(answered) == {200}
        log = Path(server.log_path or "").read_text()
        assert log.count("its request's headers did not arrive within 2 s") >= 50
        assert log.count("its request's body brought") >= 50
