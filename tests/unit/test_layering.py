"""The layers of docs/architecture.md §1, checked on the source: who may import whom, and no cycles.

app/domain     pure: numpy, gtsam, networkx; imports nothing else of the project
app/storage    the database: imports the domain only
app/services   what the API and the dashboard both do: storage and the domain, no web framework
app/api        routers: services, storage, domain (never the dashboard, the CLI or workers)
app/admin      dashboard pages: services and the API's plumbing, never its routers
app/render     PNG plots: the domain only
workers/       the job loop: storage, domain, render, config (never the API or dashboard)
app/cli        the command: anything
"""

from __future__ import annotations

import ast
from collections.abc import Iterator
from pathlib import Path

import networkx as nx
import pytest

ROOT = Path(__file__).parents[2]
DOMAIN = ROOT / "app" / "domain"
FORBIDDEN = {"fastapi", "sqlalchemy", "pydantic", "starlette", "matplotlib", "httpx", "alembic"}

#: layer → the project modules (by prefix) it must not import.
FORBIDDEN_PROJECT_IMPORTS = {
    "app.domain": ("app.storage", "app.services", "app.api", "app.admin", "app.render",
                   "app.cli", "app.config", "app.main", "app.client", "workers"),
    "app.storage": ("app.services", "app.api", "app.admin", "app.render", "app.cli",
                    "app.main", "workers"),
    "app.services": ("app.api", "app.admin", "app.cli", "app.main", "workers"),
    "app.api": ("app.admin", "app.cli", "app.main", "workers"),
    "app.admin": ("app.api.routes", "app.cli", "app.main", "workers"),
    "app.render": ("app.storage", "app.services", "app.api", "app.admin", "app.cli", "workers"),
    "workers": ("app.api", "app.admin", "app.services", "app.cli", "app.main"),
}  # fmt: skip
#: third-party packages a layer must not import.
FORBIDDEN_PACKAGES = {
    "app.domain": FORBIDDEN,
    "app.services": {"fastapi", "starlette"},
    "app.storage": {"fastapi", "starlette", "matplotlib"},
}


def module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def project_modules() -> dict[str, Path]:
    paths = [*(ROOT / "app").rglob("*.py"), *(ROOT / "workers").rglob("*.py")]
    return {module_name(path): path for path in paths}


def imports(path: Path) -> Iterator[str]:
    """Every module ``path`` imports (at the top or inside functions), absolute names."""
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            yield from (alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            yield node.module
            yield from (f"{node.module}.{alias.name}" for alias in node.names)


def layer_of(module: str) -> str | None:
    return next((layer for layer in FORBIDDEN_PROJECT_IMPORTS if _within(module, layer)), None)


def _within(module: str, prefix: str) -> bool:
    return module == prefix or module.startswith(prefix + ".")


def test_domain_core_imports_no_web_database_or_plotting_code():
    offenders = {
        path.name: sorted({name.split(".")[0] for name in imports(path)} & FORBIDDEN)
        for path in DOMAIN.rglob("*.py")
    }
    assert {name: bad for name, bad in offenders.items() if bad} == {}
    assert len(offenders) >= 10  # the check really looked at the modules


def test_each_layer_imports_only_the_layers_below_it():
    modules = project_modules()
    offences = []
    for module, path in modules.items():
        layer = layer_of(module)
        if layer is None:
            continue
        for imported in set(imports(path)):
            banned = FORBIDDEN_PROJECT_IMPORTS[layer]
            if any(_within(imported, prefix) for prefix in banned):
                offences.append(f"{module} imports {imported}")
            if imported.split(".")[0] in FORBIDDEN_PACKAGES.get(layer, set()):
                offences.append(f"{module} imports {imported}")
    assert sorted(offences) == []
    assert {layer_of(m) for m in modules} >= set(FORBIDDEN_PROJECT_IMPORTS)  # every layer seen


def test_no_module_imports_itself_through_others():
    modules = project_modules()
    graph: nx.DiGraph[str] = nx.DiGraph()
    for module, path in modules.items():
        for imported in imports(path):
            if imported in modules and imported != module:
                graph.add_edge(module, imported)
    assert graph.number_of_edges() > 100
    assert list(nx.simple_cycles(graph)) == []


@pytest.mark.parametrize(
    ("module", "imported", "allowed"),
    [
        ("app.domain.slam", "app.storage.maps", False),
        ("app.admin.pages.maps", "app.api.routes.maps", False),
        ("app.admin.pages.maps", "app.services.maps", True),
        ("app.storage.maps", "app.api.deps", False),
        ("workers.pipeline", "app.render.map_plot", True),
        ("app.cli.server", "workers.main", True),
    ],
)
def test_the_rules_say_what_the_layers_mean(module: str, imported: str, allowed: bool):
    layer = layer_of(module)
    banned = FORBIDDEN_PROJECT_IMPORTS.get(layer, ()) if layer else ()
    assert (not any(_within(imported, prefix) for prefix in banned)) == allowed


def test_no_module_takes_another_modules_private_names():
    """A name with a leading underscore is its module's own: sharing it means making it public
    (or moving it where both can reach it)."""
    taken = []
    for module, path in project_modules().items():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                if node.module.split(".")[0] not in {"app", "workers"}:
                    continue
                taken += [
                    f"{module}: {node.module}.{a.name}" for a in node.names if a.name[0] == "_"
                ]
    assert taken == []
