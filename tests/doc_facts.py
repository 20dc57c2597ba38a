"""The docs' facts that the code decides, computed from the code, and written into the docs.

Each fact lives in the docs between markers that a reader of the rendered page does not see::

    the OpenAPI document (<!-- generated: operation-count -->49<!-- /generated --> operations)

    <!-- generated: permissions -->
    | operation | key | … |
    <!-- /generated -->

and the Alembic head in every ``"schema_revision":"…"`` a page shows (inside code blocks, where a
marker would be printed). ``scripts/gen_docs`` rewrites them all (``--check``: says which are
stale and exits 1); ``tests/unit/test_docs_drift.py`` fails while any is stale, so a new endpoint,
migration or change of the path graph cannot leave the docs behind.

What is computed, and from what:

- ``operation-count``: the operations of the app's OpenAPI document (``app.openapi()``).
- ``permissions``: every operation the API serves (the OpenAPI document's and the ones left out
  of it, such as ``/metrics``; not the dashboard's pages, which log in with a form), each with the
  key it needs, read from the route's dependencies: ``admin_principal`` (an admin key; a device
  key gets 403), ``current_principal`` (any valid key) or neither (no key). Where a device key
  sees only what it made, :data:`OWN_ONLY` says so (the tests of each route check it).
- ``geojson-floor_2_straight``: the path graph that a build of ``data/sessions/floor_2_straight
  .json`` with the default parameters makes (the pipeline's own steps: optimize, corridor
  skeleton, GeoJSON), counted.
- the schema revision: the Alembic head of ``migrations/``.

    .venv/bin/python -m tests.doc_facts            # rewrite the docs (scripts/gen_docs)
    .venv/bin/python -m tests.doc_facts --check    # exit 1 if any block is stale
"""

from __future__ import annotations

import argparse
import re
import sys
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any

REPO_ROOT = Path(__file__).resolve().parents[1]
#: The pages: the README and docs/.
PAGES = [REPO_ROOT / "README.md", *sorted((REPO_ROOT / "docs").glob("*.md"))]
HTTP_METHODS = ("get", "put", "post", "delete", "patch", "head", "options")

BLOCK = re.compile(
    r"(<!-- generated: (?P<name>[\w.-]+) -->)(?P<body>.*?)(<!-- /generated -->)", re.DOTALL
)
SCHEMA_REVISION = re.compile(r'("schema_revision":\s*")([0-9a-f]+)(")')

#: Operations a device key may call on what it made only: another key's session, job or
#: navigation session answers 404, as if it did not exist (docs/api.md, "Authentication").
OWN_ONLY: dict[tuple[str, str], str] = {
    ("GET", "/v1/sessions"): "lists its own only",
    ("GET", "/v1/sessions/{session_id}"): "its own only (another key's: 404)",
    ("GET", "/v1/sessions/{session_id}/raw"): "its own only (another key's: 404)",
    ("PUT", "/v1/sessions/{session_id}/image"): "its own only (another key's: 404)",
    ("GET", "/v1/jobs/{job_id}"): "its own sessions' only (another key's: 404)",
    ("GET", "/v1/localizations/{localization_id}"): "its own only (another key's: 404)",
    ("POST", "/v1/localizations/{localization_id}/updates"): "its own only (another key's: 404)",
}
#: Paths that are not the API's operations: the dashboard (a login form and a cookie) and the
#: pages of the API's own documentation (no key).
NOT_OPERATIONS = re.compile(r"^/(admin|docs|redoc|docs-assets)(/|$)")


# --------------------------------------------------------------------------- the app


@cache
def app() -> Any:
    """The API as ``serve`` makes it (no database is opened: that is the lifespan's)."""
    from app.config import Settings
    from app.main import create_app

    return create_app(Settings(database_url="sqlite:////nonexistent/doc-facts.sqlite3"))


def openapi_operations() -> list[tuple[str, str]]:
    """(METHOD, path) of each operation of the OpenAPI document."""
    return [
        (method.upper(), path)
        for path, item in app().openapi()["paths"].items()
        for method in item
        if method in HTTP_METHODS
    ]


@dataclass(frozen=True, slots=True)
class Operation:
    method: str
    path: str
    #: "none", "any" (a valid key of either role) or "admin"
    key: str
    in_openapi: bool


def operations() -> list[Operation]:
    """Every operation the API serves, with the key its dependencies ask for, in path order."""
    from fastapi.routing import iter_route_contexts

    from app.web.deps import admin_principal, current_principal

    def calls(dependant: Any) -> Iterator[Callable[..., Any]]:
        for sub in dependant.dependencies:
            yield sub.call
            yield from calls(sub)

    found = []
    for route in iter_route_contexts(app().routes):
        dependant = getattr(route, "dependant", None)
        if dependant is None or route.path is None or NOT_OPERATIONS.match(route.path):
            continue
        needs = set(calls(dependant))
        key = (
            "admin" if admin_principal in needs else "any" if current_principal in needs else "none"
        )
        for method in sorted(route.methods or ()):
            if method != "HEAD":
                found.append(Operation(method, route.path, key, bool(route.include_in_schema)))
    return sorted(found, key=lambda op: (op.path, HTTP_METHODS.index(op.method.lower())))


def head_revision() -> str:
    from app.storage.migrate import head_revision as alembic_head

    return str(alembic_head())


# --------------------------------------------------------------------------- the blocks


def operation_count() -> str:
    return str(len(openapi_operations()))


def permissions_table() -> str:
    rows = [
        "| operation | key it needs | a device key | an admin key |",
        "|---|---|---|---|",
    ]
    for op in operations():
        name = f"`{op.method} {op.path}`" + ("" if op.in_openapi else " (not in `/openapi.json`)")
        if op.key == "none":
            device, admin = "yes (no key needed)", "yes"
        elif op.key == "admin":
            device, admin = "403 `forbidden`", "yes"
        elif (op.method, op.path) in OWN_ONLY:
            device, admin = OWN_ONLY[op.method, op.path], "all"
        else:
            device, admin = "yes", "yes"
        rows.append(f"| {name} | {op.key} | {device} | {admin} |")
    return "\n" + "\n".join(rows) + "\n"


@cache
def floor_2_straight_graph() -> str:
    """The counts of the path graph the demo's floor_2_straight map serves as GeoJSON."""
    from app.domain.mapping.slam import optimize_session
    from app.domain.navigation.path_graph.geojson import path_graph_to_geojson
    from app.domain.navigation.skeleton import build_skeleton
    from app.domain.upload.session import load_session

    result = optimize_session(load_session(REPO_ROOT / "data/sessions/floor_2_straight.json"))
    document = path_graph_to_geojson(build_skeleton(result, walk_starts=[0]))
    kinds = Counter(
        (feature["geometry"]["type"], feature["properties"]["kind"])
        for feature in document["features"]
    )
    nodes = kinds["Point", "node"] + kinds["Point", "junction"]
    edges = sum(count for (shape, _), count in kinds.items() if shape == "LineString")
    return (
        f"{kinds['Point', 'tag']} tags and {kinds['Point', 'poi']} points of interest attached, "
        f"{nodes} nodes ({kinds['Point', 'junction']} of them junctions) and {edges} edges"
    )


#: Each block's content, by name.
BLOCKS: dict[str, Callable[[], str]] = {
    "operation-count": operation_count,
    "permissions": permissions_table,
    "geojson-floor_2_straight": floor_2_straight_graph,
}


# --------------------------------------------------------------------------- the pages


@dataclass(frozen=True, slots=True)
class Stale:
    page: Path
    line: int
    what: str
    shown: str
    current: str

    def __str__(self) -> str:
        return (
            f"{self.page.relative_to(REPO_ROOT)}:{self.line}: {self.what} is stale: the docs "
            f"show {_short(self.shown)}, the code gives {_short(self.current)}"
        )


def _short(text: str) -> str:
    text = text.strip()
    return repr(text) if len(text) <= 80 else f"{text[:80]!r}… ({len(text)} characters)"


def rewrite(text: str, page: Path, stale: list[Stale]) -> str:
    """``text`` with every block and schema revision current; what was stale added to
    ``stale``. A block whose name is unknown is an error."""

    def block(match: re.Match[str]) -> str:
        name = match.group("name")
        if name not in BLOCKS:
            raise ValueError(f"{page.name}: unknown generated block {name!r}")
        current = BLOCKS[name]()
        if match.group("body") != current:
            line = text.count("\n", 0, match.start()) + 1
            stale.append(Stale(page, line, f"block {name!r}", match.group("body"), current))
        return match.group(1) + current + match.group(4)

    def revision(match: re.Match[str]) -> str:
        return match.group(1) + head_revision() + match.group(3)

    rewritten = BLOCK.sub(block, text)
    for match in SCHEMA_REVISION.finditer(text):  # numbered in the page as it is
        if match.group(2) != head_revision():
            line = text.count("\n", 0, match.start()) + 1
            stale.append(Stale(page, line, "schema_revision", match.group(2), head_revision()))
    return SCHEMA_REVISION.sub(revision, rewritten)


def stale_facts(pages: list[Path] = PAGES, *, write: bool = False) -> list[Stale]:
    """Every stale fact of ``pages``; with ``write``, the pages rewritten with current ones."""
    stale: list[Stale] = []
    for page in pages:
        text = page.read_text()
        current = rewrite(text, page, stale)
        if write and current != text:
            page.write_text(current)
    return stale


def block_names(pages: list[Path] = PAGES) -> Counter[str]:
    """How often each generated block appears in ``pages``."""
    return Counter(m.group("name") for page in pages for m in BLOCK.finditer(page.read_text()))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="scripts/gen_docs", description=__doc__.split("\n")[0])
    parser.add_argument("--check", action="store_true", help="only say what is stale; exit 1")
    args = parser.parse_args(argv)
    stale = stale_facts(write=not args.check)
    for fact in stale:
        print(fact)
    if args.check:
        return 1 if stale else 0
    print(f"gen_docs: {len(stale)} stale fact(s) rewritten" if stale else "gen_docs: all current")
    return 0


if __name__ == "__main__":
    sys.exit(main())
