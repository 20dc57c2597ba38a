"""prometheus-client's multiprocess mode for ``serve``'s API processes.

    with multiprocess_metrics():      # before the API processes start, until they have stopped
        api.start()
        …

Each API process counts its own requests; in multiprocess mode each writes its counts to files
in one folder (``PROMETHEUS_MULTIPROC_DIR``), and the one that answers a scrape adds them all up,
those of processes that died and were replaced included. The variable must be in a process's
environment before it imports prometheus-client, so ``serve`` sets it before it starts them (they
are spawned, and inherit it). This module does not import prometheus-client itself.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from collections.abc import Iterator

#: prometheus-client's variable naming the folder.
MULTIPROCESS_DIR_VARIABLE = "PROMETHEUS_MULTIPROC_DIR"


@contextlib.contextmanager
def multiprocess_metrics() -> Iterator[str]:
    """A new, empty folder in ``PROMETHEUS_MULTIPROC_DIR`` for the processes started inside the
    block, removed (and the variable with it) at its end; yields the folder. A folder the
    operator set in the variable is used as it is and kept (it must be emptied before each
    start: prometheus-client's rule)."""
    chosen = os.environ.get(MULTIPROCESS_DIR_VARIABLE)
    if chosen:
        yield chosen
        return
    folder = tempfile.mkdtemp(prefix="invisible-map-metrics-")
    os.environ[MULTIPROCESS_DIR_VARIABLE] = folder
    try:
        yield folder
    finally:
        if os.environ.get(MULTIPROCESS_DIR_VARIABLE) == folder:
            del os.environ[MULTIPROCESS_DIR_VARIABLE]
        shutil.rmtree(folder, ignore_errors=True)
