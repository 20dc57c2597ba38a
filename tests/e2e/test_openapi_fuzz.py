"""Schemathesis against the server's own OpenAPI document, over HTTP, with a key of each role:
every operation, generated requests (examples, coverage, fuzzing, stateful): no 5xx, and every
response matches the schema the document gives for it."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

from app.cli.server_process import ServerProcess, WorkerProcess
from app.client import Client

pytestmark = [pytest.mark.db, pytest.mark.slow]

SCHEMATHESIS = Path(sys.executable).with_name("schemathesis")
#: Generated cases per operation and phase; fixed seed, so a failure can be replayed.
MAX_EXAMPLES = 15
SEED = 20261122


@pytest.fixture(scope="module")
def server(tmp_path_factory, data_dir):
    folder = tmp_path_factory.mktemp("fuzz")
    database_url = f"sqlite:///{folder / 'fuzz.sqlite3'}"
    with ServerProcess(database_url, workers=0, log_path=folder / "serve.log") as running:
        # a worker only to build the map the fuzzer reads: the sweeps and rebuilds it starts
        # would otherwise keep a core busy with trials while it runs
        with (
            WorkerProcess(database_url, log_path=folder / "worker.log"),
            Client(running.url, api_key=running.admin_key) as client,
        ):
            accepted = client.upload_session(data_dir / "sessions" / "onetag.json")
            client.wait_for_job(accepted["job_id"], timeout_s=120)
        yield running


@pytest.mark.parametrize("role", ["admin", "device"])
def test_no_server_errors_and_responses_match_the_schema(server, role, tmp_path):
    key = server.admin_key
    if role == "device":
        with Client(server.url, api_key=server.admin_key) as client:
            key = client.create_key(role="device", name="fuzz")["key"]
    result = subprocess.run(
        [
            str(SCHEMATHESIS),
            "--no-color",
            "run",
            f"{server.url}/openapi.json",
            "--header",
            f"Authorization: Bearer {key}",
            "--checks",
            "not_a_server_error,response_schema_conformance",
            "--max-examples",
            str(MAX_EXAMPLES),
            "--seed",
            str(SEED),
        ],
        capture_output=True,
        text=True,
        timeout=600,
        cwd=tmp_path,
    )
    summary = result.stdout[-3000:]
    assert result.returncode == 0, summary
    assert "Tested: 47" in result.stdout, summary
    counts = re.search(r"(\d+) generated, (\d+) passed(?P<rest>[^\n]*)", result.stdout)
    assert counts is not None, summary
    print(f"schemathesis, {role} key: {counts[0]}")  # for the README's Reliability figures
    assert int(counts[1]) > 500
    assert counts[1] == counts[2], summary
    assert "failed" not in counts["rest"], summary
