"""What the test suite will skip on this machine, and how to install what it lacks.

Tests that need something outside Python skip themselves with the reason where it is missing
(unless CI's ``INVISIBLE_MAP_REQUIRE_*`` makes that an error): the PostgreSQL half of every
database test, the browser tests (Debian's Chromium), the jemalloc tests and the fault tests (a
private PostgreSQL server, a tmpfs). A skip is easy to miss at the end of a ten-minute run, so
``scripts/test`` says up front what will be skipped (``python -m tests.skip_report``), and so
does pytest's header (``tests/conftest.py``) when the run is not ``-q``.

    $ python -m tests.skip_report
    will be skipped on this machine (see the end of the run for each test):
      - browser tests: /usr/bin/chromium is missing (apt-get install chromium)
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

CHROMIUM = Path("/usr/bin/chromium")


def browser_unavailable_reason() -> str | None:
    """None if the browser tests can run, else why not."""
    if not CHROMIUM.is_file():
        return f"{CHROMIUM} is missing (apt-get install chromium)"
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError as err:
        return f"playwright is not installed ({err})"
    return None


def jemalloc_unavailable_reason() -> str | None:
    from workers import allocator

    if allocator.jemalloc_path("auto") is None:
        return "no jemalloc (apt-get install libjemalloc2)"
    return None


def fault_tests_unavailable_reason() -> str | None:
    """Why the fault tests (tests/e2e/test_faults.py) cannot run all, if they cannot: a private
    PostgreSQL server needs its binaries, the full-disk test mounts a tmpfs (root)."""
    binaries = shutil.which("pg_ctl") or sorted(Path("/usr/lib/postgresql").glob("*/bin/pg_ctl"))
    if not binaries:
        return "PostgreSQL's server binaries are not installed (apt-get install postgresql)"
    if os.geteuid() != 0:
        return "the full-disk test mounts a tmpfs, which needs root"
    return None


def postgres_unavailable_reason() -> str | None:
    from tests.conftest import postgres_unavailable_reason as reason

    found = reason()
    if found is None:
        return None
    return (
        f"{found} (apt-get install postgresql, then pg_ctlcluster <version> main start; "
        "or set TEST_POSTGRES_URL)"
    )


def skipped_parts() -> list[str]:
    """One line per part of the suite that will be skipped here, with how to install it."""
    reasons = {
        "the PostgreSQL half of every database test": postgres_unavailable_reason(),
        "browser tests": browser_unavailable_reason(),
        "jemalloc tests": jemalloc_unavailable_reason(),
        "fault tests (some)": fault_tests_unavailable_reason(),
    }
    return [f"{part}: {reason}" for part, reason in reasons.items() if reason is not None]


def report() -> list[str]:
    parts = skipped_parts()
    if not parts:
        return ["nothing will be skipped: PostgreSQL, Chromium, jemalloc and pg_ctl found"]
    return [
        "will be skipped on this machine (see the end of the run for each test):",
        *(f"  - {part}" for part in parts),
    ]


if __name__ == "__main__":
    print("\n".join(report()), flush=True)
