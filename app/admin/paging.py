"""Paging of the dashboard's lists: ``?page=N`` (from 1) with a fixed page size.

page = Page.of(number=2, size=25, total=60, url="/admin/sessions", query={"q": "occam"})
page.offset, page.first, page.last            # 25, 26, 50
page.previous_url, page.next_url              # "/admin/sessions?q=occam&page=1", "…page=3"
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated
from urllib.parse import urlencode

from fastapi import Query

PAGE_SIZE = 25
#: The largest page number accepted (far beyond any list; keeps offsets small integers).
MAX_PAGE = 100_000

PageNumber = Annotated[int, Query(ge=1, le=MAX_PAGE, description="page number, from 1")]


@dataclass(frozen=True, slots=True, kw_only=True)
class Page:
    number: int
    size: int
    total: int
    previous_url: str | None
    next_url: str | None

    @property
    def offset(self) -> int:
        return (self.number - 1) * self.size

    @property
    def first(self) -> int:
        return min(self.offset + 1, self.total)

    @property
    def last(self) -> int:
        return min(self.offset + self.size, self.total)

    @classmethod
    def of(
        cls, *, number: int, size: int, total: int, url: str, query: dict[str, str] | None = None
    ) -> Page:
        kept = {name: value for name, value in (query or {}).items() if value}

        def link(to: int) -> str:
            return f"{url}?{urlencode({**kept, 'page': str(to)})}"

        return cls(
            number=number,
            size=size,
            total=total,
            previous_url=link(number - 1) if number > 1 else None,
            next_url=link(number + 1) if number * size < total else None,
        )


def offset_of(number: int, size: int = PAGE_SIZE) -> int:
    return (number - 1) * size
