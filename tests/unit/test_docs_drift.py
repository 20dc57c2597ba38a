"""The docs cannot drift from the code (issue 40, item 2).

What the code decides is generated into the docs (``tests/doc_facts.py``, ``scripts/gen_docs``)
and checked here: the operation count, the permissions table (every operation the API serves,
with the key its dependencies ask for), the path graph's counts, the schema revision each page
shows. The table is also held to the lists by which ``tests/service/test_api_jobs_keys.py`` calls
every operation with a device key. And every command a page prints runs after the README's own
install: no bare ``invisible-map`` (not on the PATH after ``scripts/demo`` or ``scripts/test``)
unless the page said ``source .venv/bin/activate`` first.

The answers the README and api.md show are compared with a live demo's in
``tests/e2e/test_quickstart.py`` (@slow); the links between pages in ``test_doc_links.py``.
"""

from __future__ import annotations

import importlib
import re
from pathlib import Path

import pytest

from tests import doc_facts
from tests.doc_facts import PAGES, REPO_ROOT

API_DOC = REPO_ROOT / "docs" / "api.md"


def test_every_generated_fact_in_the_docs_is_current() -> None:
    stale = doc_facts.stale_facts()
    assert not stale, "run scripts/gen_docs:\n" + "\n".join(map(str, stale))


def test_the_generated_blocks_are_where_the_docs_need_them() -> None:
    names = doc_facts.block_names()
    assert names["permissions"] == 1
    assert names["operation-count"] >= 1
    assert names["geojson-floor_2_straight"] == 1
    assert set(names) <= set(doc_facts.BLOCKS)
    revisions = {page.name: doc_facts.SCHEMA_REVISION.findall(page.read_text()) for page in PAGES}
    assert revisions["README.md"]
    assert revisions["api.md"]


def test_a_stale_fact_is_found_and_rewritten(tmp_path: Path) -> None:
    """The check can fail: a page with an old count, an old table and an old revision."""
    page = tmp_path / "page.md"
    text = (
        "(<!-- generated: operation-count -->36<!-- /generated --> operations)\n"
        "<!-- generated: permissions -->\n| old | table |\n<!-- /generated -->\n"
        '```\n{"status":"ready","schema_revision":"255ed7c85f58"}\n```\n'
    )
    page.write_text(text)

    stale = doc_facts.stale_facts([page], write=True)

    assert [fact.what for fact in stale] == [
        "block 'operation-count'",
        "block 'permissions'",
        "schema_revision",
    ]
    assert [fact.line for fact in stale] == [1, 2, 6]
    rewritten = page.read_text()
    assert f"{len(doc_facts.openapi_operations())}<!-- /generated --> operations" in rewritten
    assert f'"schema_revision":"{doc_facts.head_revision()}"' in rewritten
    assert "| old | table |" not in rewritten
    assert doc_facts.stale_facts([page]) == []


def test_the_schema_revision_is_the_alembic_head_of_migrations() -> None:
    """The head as Alembic finds it in migrations/ (not the app's own answer to /readyz)."""
    from alembic.script import ScriptDirectory

    heads = ScriptDirectory(str(REPO_ROOT / "migrations")).get_heads()
    assert heads == [doc_facts.head_revision()]


# --------------------------------------------------------------------------- permissions


def documented_permissions() -> dict[tuple[str, str], tuple[str, str]]:
    """The api.md table: (METHOD, path) → (key it needs, what a device key gets)."""
    text = API_DOC.read_text()
    start = text.index("<!-- generated: permissions -->")
    block = text[start : text.index("<!-- /generated -->", start)]
    table: dict[tuple[str, str], tuple[str, str]] = {}
    for line in block.splitlines():
        match = re.match(r"\| `(\w+) (\S+)`[^|]*\| (\w+) \| ([^|]+) \|", line)
        if match:
            method, path, key, device = match.groups()
            assert (method, path) not in table, f"{method} {path} twice in the table"
            table[method, path] = (key, device.strip())
    return table


def test_every_operation_is_in_the_permissions_table() -> None:
    table = documented_permissions()
    served = {(op.method, op.path) for op in doc_facts.operations()}
    assert set(table) == served
    # every operation of the OpenAPI document is served, so in the table
    assert set(doc_facts.openapi_operations()) <= served
    assert len(table) > len(doc_facts.openapi_operations())  # /metrics is not in the document


@pytest.mark.parametrize(
    ("operation", "key"),
    [
        (("GET", "/healthz"), "none"),
        (("GET", "/readyz"), "none"),
        (("GET", "/metrics"), "admin"),
        (("GET", "/v1/maps/{map_id}"), "any"),
        (("POST", "/v1/maps/{map_id}/merge"), "admin"),
        (("GET", "/v1/maps/{map_id}/sessions"), "any"),
        (("POST", "/v1/maps/{map_id}/sessions"), "admin"),
        (("GET", "/v1/maps/{map_id}/corridor-edits"), "admin"),
        (("GET", "/v1/jobs"), "admin"),
        (("GET", "/v1/jobs/{job_id}"), "any"),
    ],
)
def test_the_table_reads_each_key_from_the_routes_dependencies(
    operation: tuple[str, str], key: str
) -> None:
    """Spot checks of the reading itself, among them the rows the hand-written table had wrong
    or missing (issue 40: a device key gets 403 on GET corridor-edits; /merge and the map's
    /sessions were missing)."""
    assert documented_permissions()[operation][0] == key


def test_the_table_agrees_with_the_operations_called_with_a_device_key(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """``tests/service/test_api_jobs_keys.py`` calls each of its ADMIN_ONLY operations with a
    device key (403) and the others (never 401/403); the table says the same of each."""
    monkeypatch.syspath_prepend(str(REPO_ROOT / "tests" / "service"))  # as pytest imports it
    calls = importlib.import_module("test_api_jobs_keys")
    ADMIN_ONLY, DEVICE_ALLOWED = calls.ADMIN_ONLY, calls.DEVICE_ALLOWED

    def called_as(path: str) -> str:
        return re.sub(r"\{\w+\}", "1", path)

    table = documented_permissions()
    admin = {(m, called_as(p)) for (m, p), (key, _) in table.items() if key == "admin"}
    device = {(m, called_as(p)) for (m, p), (key, _) in table.items() if key == "any"}
    assert admin - {("GET", "/metrics")} == set(ADMIN_ONLY)
    assert device == set(DEVICE_ALLOWED)
    for (method, path), (key, device_gets) in table.items():
        assert (device_gets == "403 `forbidden`") == (key == "admin"), (method, path)
        assert (device_gets.startswith(("its own", "lists its own"))) == (
            (method, path) in doc_facts.OWN_ONLY
        )


# --------------------------------------------------------------------------- commands


#: A command line in a code block that runs ``invisible-map`` by its bare name (after an
#: optional ``$`` prompt and ``NAME=value`` settings).
BARE_COMMAND = re.compile(r"^\s*(?:\$ )?(?:[A-Z_][A-Z0-9_]*=\S* )*invisible-map(?:\s|$)")
ACTIVATE = re.compile(r"^\s*(?:\$ )?(?:source|\.) \.venv/bin/activate\s*$")


def bare_commands(text: str) -> list[tuple[int, str]]:
    """(line number, line) of each code-block line that runs a bare ``invisible-map`` before any
    ``source .venv/bin/activate`` in the page."""
    found = []
    in_code = activated = False
    for number, line in enumerate(text.splitlines(), start=1):
        if line.lstrip().startswith("```"):
            in_code = not in_code
            continue
        if not in_code:
            continue
        if ACTIVATE.match(line):
            activated = True
        elif not activated and BARE_COMMAND.match(line):
            found.append((number, line))
    return found


@pytest.mark.parametrize("page", PAGES, ids=lambda page: page.name)
def test_every_printed_command_runs_after_the_readmes_install(page: Path) -> None:
    """The README installs into .venv (scripts/demo, scripts/test) and puts nothing on the PATH:
    a page runs ``.venv/bin/invisible-map …``, or says ``source .venv/bin/activate`` first."""
    found = bare_commands(page.read_text())
    assert not found, "\n".join(f"{page.name}:{n}: {line.strip()}" for n, line in found)


def test_the_command_check_finds_bare_commands_only_before_activation() -> None:
    text = (
        "```bash\n$ invisible-map keys list\nFOO=1 invisible-map serve\n"
        ".venv/bin/invisible-map serve\ninvisible-maps\n```\n"
        "`invisible-map serve` in prose\n"
        "```bash\nsource .venv/bin/activate\ninvisible-map serve\n```\n"
    )
    assert bare_commands(text) == [
        (2, "$ invisible-map keys list"),
        (3, "FOO=1 invisible-map serve"),
    ]
