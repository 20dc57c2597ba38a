"""The ``invisible-map`` command: one module per command group (``program`` parses and dispatches).

main.py       process, evaluate, demo, plot: the mapping core, offline
server.py     serve, worker, migrate, keys
backup.py     export, import
tuning.py     sweep, simulate
common.py     what they share: the program's name and data, CommandError, settings, database
"""

from __future__ import annotations

from collections.abc import Sequence


def main(argv: Sequence[str] | None = None) -> int:
    """The console script's entry point (imports the command groups only when run)."""
    from app.cli.program import main as run

    return run(argv)
