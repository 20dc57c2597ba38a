"""Plain-text tables: Markdown that also reads well in a terminal.

render_markdown_table([["case", "ms"], ["a", "1.0"]])              # cells left-justified
render_markdown_table(lines, justify="right")                      # numbers line up
fixed_cell(0.04321), change_cell(0.62, 0.60)                       # "0.0432", "+3.3%"
before_after_cell(0.615, 0.624, 3)                                 # "0.615 → 0.624"
"""

from __future__ import annotations

import math
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


def fixed_cell(value: float, digits: int = 4) -> str:
    """A number with ``digits`` decimals, "—" for NaN (not measured)."""
    return "—" if math.isnan(value) else f"{value:.{digits}f}"


def before_after_cell(before: float, after: float, digits: int = 4) -> str:
    """ "0.615 → 0.624": two numbers as :func:`fixed_cell` writes them."""
    return f"{fixed_cell(before, digits)} → {fixed_cell(after, digits)}"


def change_cell(new: float, old: float) -> str:
    """The relative change from ``old`` to ``new`` ("+3.3%"), "—" where it is undefined."""
    return "—" if math.isnan(new) or math.isnan(old) or old == 0 else f"{new / old - 1:+.1%}"
