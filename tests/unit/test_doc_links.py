"""The docs' links between themselves: each relative link leads to a file that exists, and no
page links to itself as if it were another (``[docs/x.md](docs/x.md)`` inside docs/x.md)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[2]
PAGES = [REPO_ROOT / "README.md", *sorted((REPO_ROOT / "docs").glob("*.md"))]
#: ``[text](target)``, not inside backticks' code (targets with a scheme are left alone).
LINK = re.compile(r"\[[^\]\n]*\]\(([^)\s]+)\)")


def relative_links(page: Path) -> list[tuple[int, str]]:
    links = []
    in_code = False
    for number, line in enumerate(page.read_text().splitlines(), start=1):
        if line.lstrip().startswith("```"):
            in_code = not in_code
            continue
        if in_code:
            continue
        for target in LINK.findall(re.sub(r"`[^`]*`", "", line)):
            if not re.match(r"[a-z]+:", target) and not target.startswith("#"):
                links.append((number, target))
    return links


@pytest.mark.parametrize("page", PAGES, ids=lambda page: page.name)
def test_every_relative_link_leads_to_another_existing_file(page: Path) -> None:
    problems = []
    for number, target in relative_links(page):
        path = (page.parent / target.split("#", 1)[0]).resolve()
        if not path.exists():
            problems.append(f"{page.name}:{number}: {target} leads nowhere ({path})")
        elif path == page.resolve():
            problems.append(f"{page.name}:{number}: {target} is this page itself")
    assert not problems, "\n".join(problems)


def test_the_link_reader_finds_links_outside_code_only() -> None:
    page = REPO_ROOT / "README.md"
    assert (
        page.parent / "docs/api.md",
        "docs/api.md",
    ) in [(page.parent / target, target) for _, target in relative_links(page)]
