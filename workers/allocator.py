"""jemalloc for the processes that optimize maps (a sweep's pool, worker processes), where the
machine has it.

    with preloading_jemalloc():          # processes started in this block get LD_PRELOAD
        pool = ProcessPoolExecutor(2, mp_context=multiprocessing.get_context("spawn"))

gtsam allocates and frees many small matrices in every Levenberg–Marquardt iteration: with glibc's
malloc about a quarter of a sweep trial's CPU goes to ``malloc`` and ``free`` (``perf`` on
straight_209_occam). jemalloc (Debian's ``libjemalloc2``) runs the same trials about 20% faster,
with identical results. A library can only be preloaded into a process as it starts, so the
processes this project starts for optimization are given it in their environment
(``LD_PRELOAD``); the process that starts them keeps its allocator.

``INVISIBLE_MAP_JEMALLOC`` chooses:

    auto     (default) the first of JEMALLOC_PATHS that exists, else none
    off      never
    PATH     this library; a PATH that is not a file is an error (AllocatorError)
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path

from app.domain.errors import InvisibleMapError

#: The environment variable, and where Debian's and Alpine's packages put the library.
SETTING = "INVISIBLE_MAP_JEMALLOC"
JEMALLOC_PATHS = (
    "/usr/lib/x86_64-linux-gnu/libjemalloc.so.2",
    "/usr/lib/aarch64-linux-gnu/libjemalloc.so.2",
    "/usr/lib/libjemalloc.so.2",
    "/usr/local/lib/libjemalloc.so.2",
)


class AllocatorError(InvisibleMapError):
    """``INVISIBLE_MAP_JEMALLOC`` names no library (raised before any process starts)."""


def jemalloc_path(setting: str | None = None) -> str | None:
    """The library to preload, or None. ``setting``: the value of ``INVISIBLE_MAP_JEMALLOC``
    (default: read from the environment)."""
    value = (os.environ.get(SETTING, "auto") if setting is None else setting).strip()
    if value in ("", "auto"):
        return next((path for path in JEMALLOC_PATHS if Path(path).is_file()), None)
    if value == "off":
        return None
    if not Path(value).is_file():
        raise AllocatorError(f"{SETTING}={value}: no such file (give a path, 'auto' or 'off')")
    return value


@contextlib.contextmanager
def preloading_jemalloc(setting: str | None = None) -> Iterator[str | None]:
    """Within the block, processes started with exec (``spawn``, ``subprocess``) preload
    :func:`jemalloc_path`; yields it (None: nothing is preloaded). ``LD_PRELOAD`` is restored
    after the block; a library already in it is not added twice."""
    library = jemalloc_path(setting)
    before = os.environ.get("LD_PRELOAD")
    preloaded = (before or "").split()
    if library is not None and library not in preloaded:
        os.environ["LD_PRELOAD"] = " ".join([library, *preloaded])
    try:
        yield library
    finally:
        if before is None:
            os.environ.pop("LD_PRELOAD", None)
        else:
            os.environ["LD_PRELOAD"] = before
