"""The domain core imports no web, database or plotting code (DESIGN §1)."""

from __future__ import annotations

import ast
from pathlib import Path

DOMAIN = Path(__file__).parents[2] / "app" / "domain"
FORBIDDEN = {"fastapi", "sqlalchemy", "pydantic", "starlette", "matplotlib", "httpx", "alembic"}


def imported_top_level_modules(path: Path) -> set[str]:
    modules = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            modules.update(alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            modules.add(node.module.split(".")[0])
    return modules


def test_domain_core_imports_no_web_database_or_plotting_code():
    offenders = {
        path.name: sorted(imported_top_level_modules(path) & FORBIDDEN)
        for path in DOMAIN.glob("*.py")
    }
    assert {name: bad for name, bad in offenders.items() if bad} == {}
    assert len(offenders) >= 10  # the check really looked at the modules
