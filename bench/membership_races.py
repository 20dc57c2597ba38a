"""Changes of maps' sessions racing each other over HTTP (issue 25, item 2): what a real server
with two worker processes answers, and whether every map's current version ends up built from
the map's sessions. One command, prints a table:

    .venv/bin/python -m bench.membership_races            # PostgreSQL at 127.0.0.1 (≈ 1 min)
    .venv/bin/python -m bench.membership_races --sqlite   # the same on SQLite

Each round uploads three copies of a small real walk (``pgt_tester3``: maps A, B, C, each built
by a worker), adds C's session to A, then sends eight requests at the same moment (a barrier):
merge B into A, merge A into B, add B's session to A twice, take A's two sessions out of A,
rebuild A, delete B. Then it waits until no job is queued or running and reads every map.

Printed: how many answers had each status (before issue 25, PostgreSQL answered 500 for
foreign-key and unique violations here), and how many maps end with a current version built from
exactly the map's sessions (``current_version.session_ids == session_ids``). Traffic goes to
127.0.0.1 only; the rounds and the wait are bounded. Runs the code of the checkout it is in (the
server is ``python -m app.cli`` from the working directory), so run it from an older checkout to
measure before.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import threading
import time
import uuid
from collections import Counter
from pathlib import Path
from typing import Any

import httpx
from sqlalchemy import create_engine, text

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # run from a checkout without installing

from app.cli.server_process import ServerProcess  # noqa: E402

WALK = REPO / "data" / "sessions" / "pgt_tester3.json"
POSTGRES_ADMIN_URL = "postgresql+psycopg://postgres@127.0.0.1:5432/postgres"
#: The longest wait for the workers to finish every job, s.
SETTLE_TIMEOUT_S = 120.0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=6, help="rounds of racing requests (6)")
    parser.add_argument("--sqlite", action="store_true", help="SQLite instead of PostgreSQL")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        if args.sqlite:
            answers, maps = run(f"sqlite:///{tmp}/races.sqlite3", Path(tmp), args.rounds)
        else:
            name = "im_bench_races_" + uuid.uuid4().hex[:8]
            admin = create_engine(POSTGRES_ADMIN_URL, isolation_level="AUTOCOMMIT")
            with admin.connect() as connection:
                connection.execute(text(f'CREATE DATABASE "{name}"'))
            try:
                url = POSTGRES_ADMIN_URL.rsplit("/", 1)[0] + f"/{name}"
                answers, maps = run(url, Path(tmp), args.rounds)
            finally:
                with admin.connect() as connection:
                    connection.execute(text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))
                admin.dispose()
    database = "SQLite" if args.sqlite else "PostgreSQL"
    print(f"\n{args.rounds} rounds of 8 racing requests, 2 worker processes, {database}\n")
    print("| answer | requests |\n|---|---|")
    for status, count in sorted(answers.items()):
        print(f"| {status} | {count} |")
    matching = sum(1 for m in maps if m["matches"])
    print(f"\nmaps whose current version holds exactly their sessions: {matching} of {len(maps)}")
    for m in maps:
        if not m["matches"]:
            print(f"- map {m['id']}: sessions {m['session_ids']}, current version of {m['built']}")
    return 0


def run(url: str, tmp: Path, rounds: int) -> tuple[Counter[str], list[dict[str, Any]]]:
    walk = WALK.read_bytes()
    answers: Counter[str] = Counter()
    env = {"INVISIBLE_MAP_DATA_DIR": str(tmp), "INVISIBLE_MAP_MAX_CONNECTIONS_PER_ADDRESS": "0"}
    with ServerProcess(url, workers=2, env=env, log_path=tmp / "api.log") as server:
        headers = {"Authorization": f"Bearer {server.admin_key}"}
        with httpx.Client(base_url=server.url, headers=headers, timeout=60) as http:

            def upload() -> dict[str, Any]:
                response = http.post(
                    "/v1/sessions", content=walk, headers={"Content-Type": "application/json"}
                )
                response.raise_for_status()
                body: dict[str, Any] = response.json()
                return body

            for _ in range(rounds):
                a, b, c = upload(), upload(), upload()
                http.post(f"/v1/maps/{a['map_id']}/sessions", json={"session_id": c["session_id"]})
                calls: list[tuple[str, str, dict[str, Any] | None]] = [
                    ("POST", f"/v1/maps/{a['map_id']}/merge", {"map_id": b["map_id"]}),
                    ("POST", f"/v1/maps/{b['map_id']}/merge", {"map_id": a["map_id"]}),
                    ("POST", f"/v1/maps/{a['map_id']}/sessions", {"session_id": b["session_id"]}),
                    ("POST", f"/v1/maps/{a['map_id']}/sessions", {"session_id": b["session_id"]}),
                    ("DELETE", f"/v1/maps/{a['map_id']}/sessions/{a['session_id']}", None),
                    ("DELETE", f"/v1/maps/{a['map_id']}/sessions/{c['session_id']}", None),
                    ("POST", f"/v1/maps/{a['map_id']}/rebuild", {"params": {"huber_k": 2.0}}),
                    ("DELETE", f"/v1/maps/{b['map_id']}", None),
                ]
                answers.update(at_once(server.url, headers, calls))
            deadline_s = time.monotonic() + SETTLE_TIMEOUT_S
            while time.monotonic() < deadline_s:
                states = http.get("/v1/info").json()["jobs_by_state"]
                if states["queued"] == 0 and states["running"] == 0:
                    break
                time.sleep(0.5)
            maps = []
            for summary in http.get("/v1/maps?limit=200").json()["data"]:
                current = summary["current_version"]
                built = current["session_ids"] if current else None
                maps.append(
                    {
                        "id": summary["id"],
                        "session_ids": summary["session_ids"],
                        "built": built,
                        "matches": built == summary["session_ids"],
                    }
                )
    return answers, maps


def at_once(
    url: str, headers: dict[str, str], calls: list[tuple[str, str, dict[str, Any] | None]]
) -> Counter[str]:
    """Send ``calls`` at the same moment, each on its own connection; their answers' statuses
    (with the error code for 4xx and 5xx)."""
    barrier = threading.Barrier(len(calls))
    answers: Counter[str] = Counter()
    lock = threading.Lock()

    def send(method: str, path: str, body: dict[str, Any] | None) -> None:
        with httpx.Client(base_url=url, headers=headers, timeout=60) as client:
            barrier.wait()
            response = client.request(method, path, json=body)
        code = response.json().get("code") if response.status_code >= 400 else None
        with lock:
            answers[f"{response.status_code} {code}" if code else str(response.status_code)] += 1

    threads = [threading.Thread(target=send, args=call) for call in calls]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    return answers


if __name__ == "__main__":
    sys.exit(main())
