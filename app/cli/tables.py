"""Plain-text tables: Markdown that also reads well in a terminal.

render_markdown_table([["case", "ms"], ["a", "1.0"]])              # cells left-justified
render_markdown_table(lines, justify="right")                      # numbers line up
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal


def render_markdown_table(
    lines: Sequence[Sequence[str]], *, justify: Literal["left", "right"] = "left"
) -> str:
    """A Markdown table from rows of cells; the first row is the header."""
    widths = [max(len(line[c]) for line in lines) for c in range(len(lines[0]))]

    def pad(cell: str, width: int) -> str:
        return cell.rjust(width) if justify == "right" else cell.ljust(width)

    rendered = [
        "| " + " | ".join(pad(cell, w) for cell, w in zip(line, widths, strict=True)) + " |"
        for line in lines
    ]
    rendered.insert(1, "|" + "|".join("-" * (w + 2) for w in widths) + "|")
    return "\n".join(rendered)
