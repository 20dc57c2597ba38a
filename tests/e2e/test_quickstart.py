"""The README's quick start, run as printed against a live demo server.

The test takes the ``demo`` fixture: ``invisible-map serve --demo`` as ``scripts/demo`` runs it
(SQLite in a fresh data directory, one worker process, a generated admin key), once its maps are
built (``tests/demo_support.py``; shared with serve --demo's own test), then runs every
command of the ``bash`` blocks under the README's "## Quick start" heading, in order, in one shell
state (variables carry over), from a scratch directory that sees the repository's ``data/``.
It runs them twice, in fresh shells, as a reader trying it again would. Only two lines are not
run as printed: ``HOST=`` gets the test server's port and ``ADMIN=`` the key the server printed,
as a reader would set them. Each command must exit 0 and give the answer
its expectation below describes; a command with no expectation, or an expectation with no
command, fails the test too, so the README and this file change together.

The docs are also the expected answers: on the first run, the ``# …`` comment lines after each
command (JSON with ``…`` for what is left out, or command-line output) are compared with what the
demo answered, as are the demo's printed lines under "## Set up", and docs/api.md's navigation
examples and Python client examples are run and compared the same way
(``tests/e2e/doc_answers.py`` says how; what differs per run is in its ``VARYING``). A failure
lists every line of the docs that no longer matches, with its file and line.
"""

from __future__ import annotations

import json
import os
import re
import shlex
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from tests.demo_support import DEMO_JOBS, INVISIBLE_MAP, Demo
from tests.e2e.doc_answers import (
    VARYING,
    ElidedJsonError,
    compare_json,
    compare_text,
    parse_elided_json,
)

#: The demo is shared with serve --demo's own test (tests/demo_support.py): one process.
pytestmark = [pytest.mark.slow, pytest.mark.xdist_group("demo")]

REPO_ROOT = Path(__file__).resolve().parents[2]
README = REPO_ROOT / "README.md"
API_DOC = REPO_ROOT / "docs" / "api.md"
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
DEMO_POIS = {"Elevator", "Room 210", "Restroom"}


# --------------------------------------------------------------------------- the README


def quickstart_section(markdown: str) -> str:
    start = markdown.index("\n## Quick start\n")
    end = markdown.find("\n## ", start + 1)
    return markdown[start : end if end != -1 else len(markdown)]


@dataclass(frozen=True)
class Documented:
    """A command as the docs print it, the answer they show after it, and where."""

    command: str
    answer: tuple[str, ...]
    where: str  # file:line of the command


def shell_commands(section: str, *, source: str = "README.md", first_line: int = 1) -> list[str]:
    """The commands of the section's ```bash blocks: comments and blank lines dropped, lines
    ending in a backslash joined to the next."""
    return [doc.command for doc in documented_commands(section, source, first_line)]


def documented_commands(section: str, source: str, first_line: int) -> list[Documented]:
    """The commands of the section's ```bash blocks, each with the ``# …`` comment lines right
    after it: the answer the docs show (a comment line before any command is no answer)."""
    documented: list[Documented] = []
    for block in re.finditer(r"^```bash\n(.*?)^```", section, re.MULTILINE | re.DOTALL):
        line_number = first_line + section.count("\n", 0, block.start(1))
        pending = ""
        pending_at = 0
        answer: list[str] = []
        previous_was_command = False
        for offset, line in enumerate(block.group(1).splitlines()):
            stripped = line.strip()
            if not pending and stripped.startswith("#"):
                if previous_was_command:
                    answer.append(stripped[2:] if stripped.startswith("# ") else stripped[1:])
                continue
            if not pending:
                if answer or previous_was_command:
                    last = documented.pop()
                    documented.append(
                        Documented(command=last.command, answer=tuple(answer), where=last.where)
                    )
                answer = []
                previous_was_command = False
                if not stripped:
                    continue
                pending_at = line_number + offset
            if line.endswith("\\"):
                pending += line[:-1]
                continue
            documented.append(
                Documented(
                    command=(pending + line).strip(), answer=(), where=f"{source}:{pending_at}"
                )
            )
            pending = ""
            previous_was_command = True
        assert not pending, f"a quick-start command ends in a backslash: {pending!r}"
        if answer:
            last = documented.pop()
            documented.append(
                Documented(command=last.command, answer=tuple(answer), where=last.where)
            )
    return documented


def console_commands(section: str, source: str, first_line: int) -> list[Documented]:
    """The ``$ `` commands of a section's ```console blocks, each with the lines after it up to
    the next command (its answer; a trailing ``  # note`` and trailing blank lines dropped)."""
    documented: list[Documented] = []
    for block in re.finditer(r"^```console\n(.*?)^```", section, re.MULTILINE | re.DOTALL):
        line_number = first_line + section.count("\n", 0, block.start(1))
        lines = block.group(1).splitlines()
        index = 0
        while index < len(lines):
            if not lines[index].startswith("$ "):
                index += 1
                continue
            where = f"{source}:{line_number + index}"
            command = lines[index][2:]
            while command.endswith("\\"):
                index += 1
                command = command[:-1] + lines[index]
            index += 1
            answer: list[str] = []
            while index < len(lines) and not lines[index].startswith("$ "):
                answer.append(re.sub(r"\s{2,}# .*$", "", lines[index]))
                index += 1
            while answer and not answer[-1].strip():
                answer.pop()
            command = re.sub(r"\s{2,}# .*$", "", command).strip()
            documented.append(Documented(command=command, answer=tuple(answer), where=where))
    return documented


def test_the_parser_joins_continued_lines_and_drops_comments():
    section = (
        "## Quick start\n\n```bash\nA=1\n# a comment\ncurl -s x \\\n    -d '{}'\n```\n"
        "```console\n$ not this\n```\n```bash\necho $A\n```\n"
    )
    assert shell_commands(section) == ["A=1", "curl -s x     -d '{}'", "echo $A"]


def test_the_parser_takes_the_comment_lines_after_a_command_as_its_answer():
    section = (
        "## Quick start\n\n```bash\n# not an answer\nA=1\ncurl -s x \\\n    -d '{}'\n"
        '# {"a":1,\n#  "b":2}\n\necho $A\n```\n'
    )
    documented = documented_commands(section, "README.md", 10)
    assert [(doc.command, doc.answer, doc.where) for doc in documented] == [
        ("A=1", (), "README.md:14"),
        ("curl -s x     -d '{}'", ('{"a":1,', ' "b":2}'), "README.md:15"),
        ("echo $A", (), "README.md:20"),
    ]


def test_a_console_block_gives_each_command_its_answer_without_notes():
    section = (
        '```console\n$ curl -s a \\\n    -d 1\n{"x":1}          # 404\n\n'
        "$ curl -si b\nHTTP/1.1 201 Created\nlocation: /b/1\n\n{}\n```\n"
    )
    documented = console_commands(section, "docs/api.md", 1)
    assert [(doc.command, doc.answer, doc.where) for doc in documented] == [
        ("curl -s a     -d 1", ('{"x":1}',), "docs/api.md:2"),
        ("curl -si b", ("HTTP/1.1 201 Created", "location: /b/1", "", "{}"), "docs/api.md:6"),
    ]


def test_an_elided_answer_matches_what_it_shows_and_names_what_differs():
    pattern = parse_elided_json(
        '{"id":8,"length_m":95.36,"polyline":[…],"steps":[{"instruction":"go 5 m",…},…,'
        '{"instruction":"arrive",…}],"log":"… optimize: 3 iterations, …",…}'
    )
    answer = {
        "id": 8,
        "length_m": 95.3649,
        "polyline": [[0, 1]],
        "steps": [{"instruction": "go 5 m", "at": 1}, {"x": 1}, {"instruction": "arrive"}],
        "log": "t load\nt optimize: 3 iterations, error 2\n",
        "more": True,
    }
    assert compare_json(pattern, answer) == []
    moved = {**answer, "length_m": 95.37, "steps": [{"instruction": "go 6 m"}, answer["steps"][2]]}
    assert compare_json(pattern, moved) == [
        "$.length_m: the docs show 95.36, the server answered 95.37",
        '$.steps[0].instruction: the docs show "go 5 m", the server answered "go 6 m"',
    ]
    assert compare_json(parse_elided_json('{"a":1}'), {"a": 1, "b": 2}) == [
        "$: the answer has keys the docs do not show: ['b']"
    ]
    assert compare_json(parse_elided_json('{"n":399}'), {"n": 398}) != []
    assert compare_json(parse_elided_json('{"created_at":"2026"}'), {"created_at": "x"}) == []
    with pytest.raises(ElidedJsonError):
        parse_elided_json('{"a":1,"b"}')


def test_text_lines_compare_words_exactly_numbers_to_their_precision_not_durations():
    output = (
        "map: 8 tags, 191 detections used, error 347.7 → 3.839, 13.5 ms\n"
        "| dataset | poses | opt ms | shift opt |\n|---|---|---|---|\n"
        "| occam_room | 621 | 16.2 | 0.0052 |\n"
    )
    shown = [
        "map: 8 tags, 191 detections used, error 347.7 → 3.839, 10.8 ms …",
        "| dataset | poses | opt ms | shift opt |",
        "| occam_room | 621 | 11.1 | 0.0052 |",
    ]
    assert compare_text(shown, output) == []
    drifted = [shown[0].replace("3.839", "3.849"), shown[1], shown[2].replace("0.0052", "0.0115")]
    assert compare_text(drifted, output) == [
        f"{drifted[0]!r}: the docs show 3.849, the output has 3.839: {output.splitlines()[0]!r}",
        "row 'occam_room', column 'shift opt': the docs show 0.0115, output 0.0052",
    ]
    assert compare_text(["map: 9 tags …"], output) != []


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
    assert answer["jobs_by_state"]["succeeded"] >= DEMO_JOBS  # more on the second run
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
    # version 2: the demo rebuilt it with floor_2_straight's ground truth, to show the metric
    assert answer["current_version"]["number"] == 2
    assert answer["current_version"]["metrics"]["gt_metric_opt"] > 0
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
    assert answer["map_version"] == 2


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


def compare_answer(doc: Documented, stdout: str) -> list[str]:
    """Where the answer a command gave differs from the one its docs show (file:line first)."""
    if not doc.answer:
        return []
    shown = list(doc.answer)
    context = "localization" if re.search(r"/localizations\b", doc.command) else ""
    problems: list[str] = []
    if shown[0].startswith("HTTP/"):
        blank = shown.index("") if "" in shown else len(shown)
        head, _, stdout = stdout.replace("\r\n", "\n").partition("\n\n")
        problems += compare_headers(shown[:blank], head, context)
        shown = shown[blank + 1 :]
    text = "\n".join(shown)
    if text.lstrip().startswith(("{", "[")):
        try:
            actual = json.loads(stdout)
        except json.JSONDecodeError:
            problems.append(f"the docs show JSON, the command printed {stdout[:300]!r}")
        else:
            problems += compare_json(parse_elided_json(text), actual, context=context)
    elif shown:
        problems += compare_text(shown, stdout)
    return [f"{doc.where}: {problem}" for problem in problems]


def compare_headers(shown: list[str], head: str, context: str) -> list[str]:
    printed = head.splitlines()
    problems = []
    if shown[0].split()[1] != printed[0].split()[1]:
        problems.append(f"the docs show {shown[0]!r}, the server answered {printed[0]!r}")
    headers = {
        name.strip().lower(): value.strip()
        for name, _, value in (line.partition(":") for line in printed[1:])
    }
    for line in shown[1:]:
        name, _, value = (part.strip() for part in line.partition(":"))
        if name.lower() not in headers:
            problems.append(f"the answer has no {name} header")
        elif (
            name.lower() not in VARYING
            and f"{name.lower()}@{context}" not in VARYING
            and headers[name.lower()] != value
        ):
            problems.append(f"{name}: the docs show {value}, the server {headers[name.lower()]}")
    return problems


#: The README asks the reader to run the job's command again until the build is done; so does
#: the test (the job may still be queued when it is first asked).
RUN_AGAIN_UNTIL_DONE = r"\$HOST/v1/jobs/\$JOB "
#: What ``…`` stands for in a command of docs/api.md: the key and the JSON body's type.
ELIDED_HEADERS = " -H \"Authorization: Bearer $DEV\" -H 'Content-Type: application/json' "


def run_until_done(command: str, variables: dict[str, str], folder: Path) -> tuple[str, dict]:
    deadline = time.monotonic() + 60
    while True:
        stdout, after = run(command, variables, folder)
        if json.loads(stdout)["state"] in {"succeeded", "failed", "canceled"}:
            return stdout, after
        assert time.monotonic() < deadline, f"the job did not finish in 60 s: {stdout}"
        time.sleep(0.2)


def markdown_section(path: Path, heading: str) -> tuple[str, int]:
    """The text under ``heading`` (up to the next heading of its level) and its first line."""
    markdown = path.read_text()
    level = heading.split(" ", 1)[0]
    start = markdown.index(f"\n{heading}\n") + 1
    end = markdown.find(f"\n{level} ", start)
    return markdown[start : end if end != -1 else len(markdown)], markdown.count("\n", 0, start) + 1


def check_demo_output(demo: Demo) -> list[str]:
    """The demo's printed lines the README shows (Set up), with this server's port and key."""
    section, first_line = markdown_section(README, "## Set up")
    block = re.search(r"^```\n(Invisible Map server at .*?)^```", section, re.M | re.S)
    assert block is not None, "README.md's Set up no longer shows what scripts/demo prints"
    port = demo.url.rsplit(":", 1)[1]
    shown = [
        re.sub(r"im_admin_\S+", "…", line).replace(":8000", f":{port}")
        for line in block.group(1).splitlines()
        if line != "…"
    ]
    where = f"README.md:{first_line + section.count(chr(10), 0, block.start(1))}"
    return [f"{where}: {problem}" for problem in compare_text(shown, demo.log)]


def check_api_navigation(
    variables: dict[str, str], folder: Path
) -> tuple[list[str], dict[str, str]]:
    """Run docs/api.md's navigation examples (recorded on the demo's map 8) in the quick
    start's shell state; what differs from the answers shown."""
    section, first_line = markdown_section(
        API_DOC, "## Navigation: points of interest, routes, the path graph, live localization"
    )
    documented = console_commands(section, "docs/api.md", first_line)
    assert len(documented) >= 6, "docs/api.md's navigation examples are gone"
    problems: list[str] = []
    localization: str | None = None
    for doc in documented:
        command = doc.command.replace(" … ", ELIDED_HEADERS)
        if localization is not None:
            command = re.sub(r"/v1/localizations/\d+", f"/v1/localizations/{localization}", command)
        stdout, variables = run(command, variables, folder)
        problems += compare_answer(doc, stdout)
        if re.search(r"-si -X POST \$HOST/v1/maps/\d+/localizations", command):
            localization = str(json.loads(stdout.replace("\r\n", "\n").split("\n\n", 1)[1])["id"])
    return problems, variables


def check_python_client(demo: Demo, device_key: str) -> list[str]:
    """Run docs/api.md's Python client examples against the demo; compare what each print
    prints with the comment the docs write after it."""
    section, first_line = markdown_section(API_DOC, "## Python client")
    problems: list[str] = []
    for block in re.finditer(r"^```python\n(.*?)^```", section, re.MULTILINE | re.DOTALL):
        code = block.group(1)
        block_line = first_line + section.count("\n", 0, block.start(1))
        expected: list[tuple[str, str]] = []  # (where, line shown)
        waiting: int | None = None  # a print with its answer on the next comment line
        for offset, line in enumerate(code.splitlines()):
            comment = re.search(r"#\s(.*)$", line)
            if "print(" in line:
                if comment:
                    expected.append((f"docs/api.md:{block_line + offset}", comment.group(1)))
                else:
                    waiting = block_line + offset
            elif waiting is not None and line.strip().startswith("# "):
                assert comment is not None
                expected.append((f"docs/api.md:{waiting}", comment.group(1)))
                waiting = None
        assert waiting is None, f"docs/api.md:{waiting}: a print with no answer shown"
        keys = f"DEVICE_KEY = {device_key!r}\nADMIN_KEY = {demo.admin_key!r}\n"
        done = subprocess.run(
            [sys.executable, "-c", keys + code.replace("http://127.0.0.1:8000", demo.url)],
            cwd=REPO_ROOT,
            capture_output=True,
            text=True,
            timeout=120,
            check=False,
        )
        assert done.returncode == 0, f"docs/api.md:{block_line}: the example failed:\n{done.stderr}"
        printed = done.stdout.splitlines()
        if len(printed) != len(expected):
            problems.append(
                f"docs/api.md:{block_line}: {len(expected)} answers shown, {len(printed)} printed"
            )
        for (where, shown), line in zip(expected, printed, strict=False):
            problems += [f"{where}: {problem}" for problem in compare_text([shown], line)]
    return problems


def test_every_quick_start_command_runs_as_printed_and_answers_as_shown(
    demo: Demo, tmp_path: Path
) -> None:
    """The first run compares every answer the docs show with the demo's (the README's quick
    start, what scripts/demo prints, docs/api.md's navigation and Python client examples); the
    second, in a fresh shell, checks that the commands still work."""
    section, first_line = markdown_section(README, "## Quick start")
    documented = documented_commands(section, "README.md", first_line)
    commands = [doc.command for doc in documented]
    checks = [expectation(command) for command in commands]
    unused = [p for p, check in EXPECTATIONS if check is not no_check and check not in checks]
    assert not unused, f"no quick-start command matches {unused}: the README lost a step"

    # The demo data the quick start relies on: map 8 is the session with points of interest.
    assert re.search(r"^demo: floor_2_pois: session 8, map 8, job 8$", demo.log, re.MULTILINE)
    printed_host = next(c for c in commands if c.startswith("HOST="))
    assert printed_host == "HOST=http://127.0.0.1:8000", "scripts/demo serves on port 8000"
    assert re.fullmatch(r"ADMIN=im_admin_\S+", next(c for c in commands if c.startswith("ADMIN=")))
    assert not [c for c in commands if "8000" in c and not c.startswith("HOST=")]

    # Each request of the demo's polling is logged once, by the server (its access line), not a
    # second time by the HTTP client polling in the same process.
    polls = re.findall(r'"GET /v1/jobs/\d+ HTTP/1.1" 200', demo.log)
    assert polls, "the demo's polls are not in its log"
    assert "HTTP Request: GET" not in demo.log, "each poll of the demo is logged twice"

    problems = check_demo_output(demo)
    # Twice, in fresh shells: a reader may well run the quick start again.
    for attempt in ("first", "second"):
        folder = tmp_path / attempt
        folder.mkdir()
        (folder / "data").symlink_to(REPO_ROOT / "data")
        variables = {n: os.environ[n] for n in ("PATH", "HOME", "LANG") if n in os.environ}
        for doc, check in zip(documented, checks, strict=True):
            command = doc.command
            if command.startswith("HOST="):
                command = f"HOST={demo.url}"
            elif command.startswith("ADMIN="):
                command = f"ADMIN={demo.admin_key}"
            command = re.sub(r"^\.venv/bin/invisible-map ", f"{INVISIBLE_MAP} ", command)
            if re.search(RUN_AGAIN_UNTIL_DONE, command):
                stdout, variables = run_until_done(command, variables, folder)
            else:
                stdout, variables = run(command, variables, folder)
            if attempt == "first":
                problems += compare_answer(doc, stdout)
            try:
                check(Ran(command=command, stdout=stdout, variables=variables, folder=folder))
            except AssertionError as err:
                problems.append(f"{doc.where} ({attempt} run): {err}")
        if attempt == "first":
            navigation, _ = check_api_navigation(dict(variables), folder)
            problems += navigation + check_python_client(demo, variables["DEV"])
    assert not problems, (
        "the docs show answers the demo no longer gives; update these lines "
        "(or the code, if the docs are right):\n" + "\n".join(problems)
    )
