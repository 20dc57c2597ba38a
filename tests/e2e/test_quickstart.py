"""The README's quick start, run as printed against a live demo server.

The test starts ``invisible-map serve --demo`` as ``scripts/demo`` does (SQLite in a fresh data
directory, one worker process, a generated admin key), waits for the demo's maps, then runs every
command of the ``bash`` blocks under the README's "## Quick start" heading, in order, in one shell
state (variables carry over), from a scratch directory that sees the repository's ``data/``.
It runs them twice, in fresh shells, as a reader trying it again would. Only two lines are not
run as printed: ``HOST=`` gets the test server's port and ``ADMIN=`` the key the server printed,
as a reader would set them. Each command must exit 0 and give the answer
its expectation below describes; a command with no expectation, or an expectation with no
command, fails the test too, so the README and this file change together.
"""

from __future__ import annotations

import json
import os
import re
import shlex
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

import httpx
import pytest

pytestmark = pytest.mark.slow

REPO_ROOT = Path(__file__).resolve().parents[2]
README = REPO_ROOT / "README.md"
#: The console script of this interpreter's environment (what ``.venv/bin/invisible-map`` is).
INVISIBLE_MAP = Path(sys.executable).with_name("invisible-map")
DEMO_MAPS = 8
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
DEMO_POIS = {"Elevator", "Room 210", "Restroom"}


# --------------------------------------------------------------------------- the README


def quickstart_section(markdown: str) -> str:
    start = markdown.index("\n## Quick start\n")
    end = markdown.find("\n## ", start + 1)
    return markdown[start : end if end != -1 else len(markdown)]


def shell_commands(section: str) -> list[str]:
    """The commands of the section's ```bash blocks: comments and blank lines dropped, lines
    ending in a backslash joined to the next."""
    commands = []
    for block in re.findall(r"^```bash\n(.*?)^```", section, re.MULTILINE | re.DOTALL):
        pending = ""
        for line in block.splitlines():
            if not pending and (not line.strip() or line.lstrip().startswith("#")):
                continue
            if line.endswith("\\"):
                pending += line[:-1]
                continue
            commands.append((pending + line).strip())
            pending = ""
        assert not pending, f"a quick-start command ends in a backslash: {pending!r}"
    return commands


def test_the_parser_joins_continued_lines_and_drops_comments():
    section = (
        "## Quick start\n\n```bash\nA=1\n# a comment\ncurl -s x \\\n    -d '{}'\n```\n"
        "```console\n$ not this\n```\n```bash\necho $A\n```\n"
    )
    assert shell_commands(section) == ["A=1", "curl -s x     -d '{}'", "echo $A"]


# --------------------------------------------------------------------------- the demo server


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


@dataclass
class Demo:
    url: str
    admin_key: str
    log: str


def wait_for(condition: Callable[[], bool], *, timeout_s: float, what: str, log: Path) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if condition():
            return
        time.sleep(0.2)
    raise AssertionError(f"timed out waiting for {what}; the server's log:\n{log.read_text()}")


@pytest.fixture(scope="module")
def demo(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Demo]:
    """``invisible-map serve --demo`` with the embedded defaults, as ``scripts/demo`` runs it."""
    folder = tmp_path_factory.mktemp("quickstart-demo")
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    env = {
        name: value
        for name, value in os.environ.items()
        if name != "DATABASE_URL" and not name.startswith("INVISIBLE_MAP_")
    }
    env.update(INVISIBLE_MAP_DATA_DIR=str(folder / "var"), PYTHONUNBUFFERED="1")
    log_path = folder / "demo.log"
    log: IO[bytes] = log_path.open("wb")
    process = subprocess.Popen(
        [str(INVISIBLE_MAP), "serve", "--demo", "--port", str(port)],
        cwd=REPO_ROOT,
        env=env,
        stdout=log,
        stderr=subprocess.STDOUT,
        start_new_session=True,
    )
    try:
        key: list[str] = []

        def key_printed() -> bool:
            assert process.poll() is None, f"the demo exited:\n{log_path.read_text()}"
            key.extend(re.findall(r"^admin key for this run: (\S+)$", log_path.read_text(), re.M))
            return bool(key)

        wait_for(key_printed, timeout_s=60, what="the admin key", log=log_path)

        def maps_built() -> bool:
            assert process.poll() is None, f"the demo exited:\n{log_path.read_text()}"
            try:
                info = httpx.get(
                    f"{url}/v1/info", headers={"Authorization": f"Bearer {key[0]}"}, timeout=5
                )
            except httpx.TransportError:
                return False
            return info.status_code == 200 and (
                info.json()["jobs_by_state"]["succeeded"] == DEMO_MAPS
            )

        wait_for(maps_built, timeout_s=180, what="the demo's maps", log=log_path)
        yield Demo(url=url, admin_key=key[0], log=log_path.read_text())
    finally:
        if process.poll() is None:
            process.send_signal(signal.SIGTERM)
            try:
                process.wait(timeout=30)
            except subprocess.TimeoutExpired:
                os.killpg(process.pid, signal.SIGKILL)
                process.wait()
        log.close()


# --------------------------------------------------------------------------- expectations


@dataclass
class Ran:
    """What a command did: its output, the shell's variables after it, and the scratch folder."""

    command: str
    stdout: str
    variables: dict[str, str]
    folder: Path

    def json(self) -> Any:
        try:
            return json.loads(self.stdout)
        except json.JSONDecodeError as err:
            raise AssertionError(f"{self.command}\nprinted no JSON: {self.stdout!r}") from err


def check_readyz(ran: Ran) -> None:
    assert ran.json()["status"] == "ready"


def check_info(ran: Ran) -> None:
    answer = ran.json()
    assert answer["jobs_by_state"]["succeeded"] >= DEMO_MAPS  # more on the second run
    assert answer["principal"]["role"] == "admin"


def check_device_key(ran: Ran) -> None:
    assert re.fullmatch(r"im_[0-9a-f]{8}_[A-Za-z0-9_-]+", ran.variables["DEV"]), ran.variables


def check_upload(ran: Ran) -> None:
    answer = json.loads(ran.variables["UPLOAD"])
    assert set(answer) >= {"session_id", "map_id", "job_id", "job_url", "statistics"}, answer


def check_echo_upload(ran: Ran) -> None:
    assert ran.json() == json.loads(ran.variables["UPLOAD"])


def check_job_id(ran: Ran) -> None:
    assert ran.variables["JOB"] == str(json.loads(ran.variables["UPLOAD"])["job_id"])


def check_job(ran: Ran) -> None:
    answer = ran.json()
    assert answer["id"] == int(ran.variables["JOB"])
    assert answer["kind"] == "build_map"
    assert answer["state"] in {"queued", "running", "succeeded"}


def check_map(ran: Ran) -> None:
    answer = ran.json()
    assert answer["name"] == "floor_2 with points of interest (demo)"
    assert answer["current_version"]["number"] == 1
    assert len(answer["current_version"]["tags"]) > 0


def check_app_map(ran: Ran) -> None:
    app_map = json.loads((ran.folder / "floor_2_pois.app-map.json").read_text())
    assert set(app_map) == {"tag_vertices", "odometry_vertices", "waypoints_vertices", "notes"}
    assert {waypoint["id"] for waypoint in app_map["waypoints_vertices"]} == DEMO_POIS


def check_plot(ran: Ran) -> None:
    assert (ran.folder / "floor_2_pois.png").read_bytes().startswith(PNG_MAGIC)


def check_pois(ran: Ran) -> None:
    answer = ran.json()
    assert "Room 210" in {poi["name"] for poi in answer["data"]}
    assert answer["map_version"] == 1


def check_route(ran: Ran) -> None:
    answer = ran.json()
    assert answer.get("length_m", 0) > 0, answer
    assert answer["steps"][-1]["instruction"].startswith("arrive at Room 210")


def check_localization(ran: Ran) -> None:
    assert ran.variables["LOC"].isdigit(), ran.variables


def check_update(ran: Ran) -> None:
    answer = ran.json()
    assert answer["status"] == "localized", answer
    assert len(answer["position"]) == 3
    assert answer["tags_used"] == [300]


def check_process(ran: Ran) -> None:
    assert (ran.folder / "occam_room.png").read_bytes().startswith(PNG_MAGIC)
    assert "shift metric" in ran.stdout


def check_evaluate(ran: Ran) -> None:
    assert re.search(r"^\| occam_room +\| 621 ", ran.stdout, re.MULTILINE), ran.stdout


def no_check(ran: Ran) -> None:
    pass


#: For each quick-start command: a pattern that picks it out, and what its run must show.
EXPECTATIONS: list[tuple[str, Callable[[Ran], None]]] = [
    (r"^HOST=", no_check),
    (r"^ADMIN=", no_check),
    (r"^MAP=8$", no_check),
    (r"/readyz$", check_readyz),
    (r"/v1/info ", check_info),
    (r"^DEV=\$\(curl .*/v1/keys ", check_device_key),
    (r"^UPLOAD=\$\(curl -s -X POST \$HOST/v1/sessions .*@data/sessions/", check_upload),
    (r'^echo "\$UPLOAD"$', check_echo_upload),
    (r"^JOB=\$\(echo ", check_job_id),
    (r"\$HOST/v1/jobs/\$JOB ", check_job),
    (r"^curl -s \$HOST/v1/maps/\$MAP -H", check_map),
    (r"-o floor_2_pois\.app-map\.json .*/app-map ", check_app_map),
    (r"-o floor_2_pois\.png .*/plot\.png ", check_plot),
    (r"/pois", check_pois),
    (r"/routes ", check_route),
    (r"^LOC=\$\(curl .*/localizations ", check_localization),
    (r"/localizations/\$LOC/updates .*@data/demo/localization_update\.json", check_update),
    (r"invisible-map process ", check_process),
    (r"invisible-map evaluate ", check_evaluate),
]


def expectation(command: str) -> Callable[[Ran], None]:
    matches = [check for pattern, check in EXPECTATIONS if re.search(pattern, command)]
    assert len(matches) == 1, (
        f"the quick-start command {command!r} matches {len(matches)} expectations of "
        "tests/e2e/test_quickstart.py (it needs exactly one): update EXPECTATIONS with the README"
    )
    return matches[0]


# --------------------------------------------------------------------------- the run


def run(command: str, variables: dict[str, str], folder: Path) -> tuple[str, dict[str, str]]:
    """Run ``command`` in bash with ``variables``; return its stdout and the variables after."""
    after = folder / ".variables"
    script = f"set -euo pipefail\nset -a\n{command}\nenv -0 > {shlex.quote(str(after))}\n"
    done = subprocess.run(
        ["bash", "-c", script],
        cwd=folder,
        env=variables,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert done.returncode == 0, (
        f"the quick-start command failed (exit {done.returncode}):\n{command}\n"
        f"stdout: {done.stdout}\nstderr: {done.stderr}"
    )
    pairs = (item.split("=", 1) for item in after.read_text().split("\0") if "=" in item)
    return done.stdout, dict(pairs)


def test_every_quick_start_command_runs_as_printed(demo: Demo, tmp_path: Path) -> None:
    commands = shell_commands(quickstart_section(README.read_text()))
    checks = [expectation(command) for command in commands]
    unused = [p for p, check in EXPECTATIONS if check is not no_check and check not in checks]
    assert not unused, f"no quick-start command matches {unused}: the README lost a step"

    # The demo data the quick start relies on: map 8 is the session with points of interest.
    assert re.search(r"^demo: floor_2_pois: session 8, map 8, job 8$", demo.log, re.MULTILINE)
    printed_host = next(c for c in commands if c.startswith("HOST="))
    assert printed_host == "HOST=http://127.0.0.1:8000", "scripts/demo serves on port 8000"
    assert re.fullmatch(r"ADMIN=im_admin_\S+", next(c for c in commands if c.startswith("ADMIN=")))
    assert not [c for c in commands if "8000" in c and not c.startswith("HOST=")]

    # Twice, in fresh shells: a reader may well run the quick start again.
    for attempt in ("first", "second"):
        folder = tmp_path / attempt
        folder.mkdir()
        (folder / "data").symlink_to(REPO_ROOT / "data")
        variables = {n: os.environ[n] for n in ("PATH", "HOME", "LANG") if n in os.environ}
        for command, check in zip(commands, checks, strict=True):
            if command.startswith("HOST="):
                command = f"HOST={demo.url}"
            elif command.startswith("ADMIN="):
                command = f"ADMIN={demo.admin_key}"
            command = re.sub(r"^\.venv/bin/invisible-map ", f"{INVISIBLE_MAP} ", command)
            stdout, variables = run(command, variables, folder)
            check(Ran(command=command, stdout=stdout, variables=variables, folder=folder))
