"""The layers of docs/architecture.md §1, checked on the source: who may import whom, and no cycles.

app/domain     pure: numpy, gtsam, networkx; imports nothing else of the project; inside it, the
               paper's stages in order (upload, mapping, navigation, localize | evaluation,
               formats), none importing a later one
app/storage    the database: imports the domain only
app/services   what the API and the dashboard both do: storage and the domain, no web framework
app/web        the HTTP plumbing both use (dependencies, errors, headers, the route class):
               services, storage, domain
app/api        routers: web, services, storage, domain (never the dashboard, the CLI or workers)
app/admin      dashboard pages: web, services, storage, domain (never the API)
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
    "app.domain": ("app.storage", "app.services", "app.web", "app.api", "app.admin", "app.render",
                   "app.cli", "app.config", "app.main", "app.client", "workers"),
    "app.storage": ("app.services", "app.web", "app.api", "app.admin", "app.render", "app.cli",
                    "app.main", "workers"),
    "app.services": ("app.web", "app.api", "app.admin", "app.cli", "app.main", "workers"),
    "app.web": ("app.api", "app.admin", "app.cli", "app.main", "workers"),
    "app.api": ("app.admin", "app.cli", "app.main", "workers"),
    "app.admin": ("app.api", "app.cli", "app.main", "workers"),
    "app.render": ("app.storage", "app.services", "app.web", "app.api", "app.admin", "app.cli",
                   "workers"),
    "workers": ("app.web", "app.api", "app.admin", "app.services", "app.cli", "app.main"),
}  # fmt: skip
#: the domain's stages (app/domain/__init__.py) → the stages they must not import: each may import
#: only the shared modules (errors, frames, json_values) and the stages before it.
DOMAIN_STAGES = ("upload", "mapping", "navigation", "localize", "evaluation", "formats")
SIBLINGS = {"localize": {"evaluation"}, "evaluation": {"localize"}}
FORBIDDEN_STAGE_IMPORTS = {
    stage: set(DOMAIN_STAGES[i + 1 :]) | SIBLINGS.get(stage, set())
    for i, stage in enumerate(DOMAIN_STAGES)
}
SHARED_DOMAIN_MODULES = {"errors", "frames", "json_values"}
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


def stage_of(module: str) -> str | None:
    """The domain stage a module belongs to (``app.domain.mapping.slam`` → ``mapping``), None for
    the shared modules and anything outside the domain."""
    parts = module.split(".")
    if parts[:2] != ["app", "domain"] or len(parts) < 3 or parts[2] in SHARED_DOMAIN_MODULES:
        return None
    return parts[2]


def test_the_domain_holds_only_its_stages_and_shared_modules():
    top = {path.stem if path.is_file() else path.name for path in DOMAIN.iterdir()}
    top -= {"__init__", "__pycache__"}
    assert top == set(DOMAIN_STAGES) | SHARED_DOMAIN_MODULES
    for stage in DOMAIN_STAGES:
        init = DOMAIN / stage / "__init__.py"
        assert ast.get_docstring(ast.parse(init.read_text())), f"{init} says what it is for"


def test_each_domain_stage_imports_only_earlier_stages():
    offences = []
    for module, path in project_modules().items():
        stage = stage_of(module)
        if stage is None:
            shared = (
                module.startswith("app.domain.") and module.split(".")[2] in SHARED_DOMAIN_MODULES
            )
            if shared:  # the shared modules import no stage at all
                offences += [f"{module} imports {i}" for i in imports(path) if stage_of(i)]
            continue
        for imported in set(imports(path)):
            if stage_of(imported) in FORBIDDEN_STAGE_IMPORTS[stage]:
                offences.append(f"{module} imports {imported}")
    assert sorted(offences) == []


@pytest.mark.parametrize(
    ("module", "imported", "allowed"),
    [
        ("app.domain.mapping.slam", "app.domain.upload.session", True),
        ("app.domain.upload.session", "app.domain.mapping.slam", False),
        ("app.domain.mapping.joint", "app.domain.evaluation.metrics", False),
        ("app.domain.localize.smoother", "app.domain.evaluation.simulate", False),
        ("app.domain.evaluation.simulate", "app.domain.localize.state", False),
        ("app.domain.formats.map_io", "app.domain.navigation.path_graph", True),
        ("app.domain.navigation.routing", "app.domain.frames", True),
    ],
)
def test_the_stage_rules_say_what_the_stages_mean(module: str, imported: str, allowed: bool):
    stage = stage_of(module)
    assert stage is not None
    assert (stage_of(imported) not in FORBIDDEN_STAGE_IMPORTS[stage]) == allowed


@pytest.mark.parametrize(
    ("module", "imported", "allowed"),
    [
        ("app.domain.mapping.slam", "app.storage.maps", False),
        ("app.admin.pages.maps", "app.api.routes.maps", False),
        ("app.admin.pages.maps", "app.services.maps", True),
        ("app.storage.maps", "app.web.deps", False),
        ("workers.pipeline", "app.render.map_plot", True),
        ("app.cli.server", "workers.main", True),
    ],
)
def test_the_rules_say_what_the_layers_mean(module: str, imported: str, allowed: bool):
    layer = layer_of(module)
    banned = FORBIDDEN_PROJECT_IMPORTS.get(layer, ()) if layer else ()
    assert (not any(_within(imported, prefix) for prefix in banned)) == allowed


def imported_from(node: ast.ImportFrom, module: str, path: Path) -> str:
    """The absolute name of the module ``from … import`` reads in ``module`` (at ``path``): a
    relative import (``from .updates import x``) resolved against the importer's package."""
    if node.level == 0:
        return node.module or ""
    package = module.split(".") if path.name == "__init__.py" else module.split(".")[:-1]
    base = package[: len(package) - (node.level - 1)]
    return ".".join([*base, node.module] if node.module else base)


@pytest.mark.parametrize(
    ("source", "module", "filename", "expected"),
    [
        ("from app.domain import frames", "app.cli.main", "main.py", "app.domain"),
        ("from .updates import x", "app.domain.mapping.incremental", "__init__.py",
         "app.domain.mapping.incremental.updates"),
        ("from .updates import x", "app.domain.mapping.incremental.graph", "graph.py",
         "app.domain.mapping.incremental.updates"),
        ("from ..frames import x", "app.domain.mapping.joint", "joint.py", "app.domain.frames"),
        ("from . import x", "app.domain.mapping.slam.trial", "trial.py", "app.domain.mapping.slam"),
    ],
)  # fmt: skip
def test_relative_imports_are_read_against_the_importers_package(
    source: str, module: str, filename: str, expected: str
):
    node = ast.parse(source).body[0]
    assert isinstance(node, ast.ImportFrom)
    assert imported_from(node, module, Path(filename)) == expected


def test_no_module_takes_another_modules_private_names():
    """A name with a leading underscore is its module's own: sharing it means making it public
    (or moving it where both can reach it). Relative imports count as much as absolute ones."""
    taken = []
    for module, path in project_modules().items():
        for node in ast.walk(ast.parse(path.read_text())):
            if not isinstance(node, ast.ImportFrom):
                continue
            source = imported_from(node, module, path)
            if source.split(".")[0] not in {"app", "workers"}:
                continue
            taken += [f"{module}: {source}.{a.name}" for a in node.names if a.name[0] == "_"]
    assert taken == []
