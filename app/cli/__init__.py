"""The ``invisible-map`` command: one module per command group (``program`` parses and dispatches).

program.py    the parser; process, evaluate, evaluate-samples: the mapping core, offline
server.py     serve, worker, migrate, keys
backup.py     export, import
firebase.py   import-firebase
tuning.py     sweep, simulate
common.py     what they share: the program's name and data, CommandError, settings, database

Building the parser imports no heavy library; each command's handler imports what it needs.
"""

from __future__ import annotations

from collections.abc import Sequence


def main(argv: Sequence[str] | None = None) -> int:
    """The console script's entry point (imports the command groups only when run)."""
    from app.cli.program import main as run

    return run(argv)
