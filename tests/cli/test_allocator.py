"""jemalloc for the processes that optimize (``workers/allocator.py``): the setting, the environment
of the processes started inside ``preloading_jemalloc``, and the two places that start them (a
sweep's pool, the worker supervisor). Where the machine has no jemalloc, the tests that need one
skip, saying so, unless ``INVISIBLE_MAP_REQUIRE_JEMALLOC=1`` (CI sets it), which makes that a
failure."""

from __future__ import annotations

import multiprocessing
import os
import time
from pathlib import Path

import pytest
from cli_support import assert_one_line_error

from app import cli
from app.config import Settings
from app.domain.mapping.params import SlamParams
from app.domain.upload.session import load_session
from workers import allocator
from workers.allocator import AllocatorError, jemalloc_path, preloading_jemalloc
from workers.main import start_worker_processes, stop_worker_processes
from workers.sweep_pool import trial_pool

ONETAG = Path(__file__).resolve().parents[2] / "data" / "sessions" / "onetag.json"
MACHINE_JEMALLOC = jemalloc_path("auto")
NO_JEMALLOC = (
    f"no jemalloc on this machine (looked for {', '.join(allocator.JEMALLOC_PATHS)}; "
    "Debian: apt-get install libjemalloc2)"
)


@pytest.fixture
def needs_jemalloc() -> None:
    if MACHINE_JEMALLOC is None:
        if os.environ.get("INVISIBLE_MAP_REQUIRE_JEMALLOC") == "1":
            pytest.fail(f"INVISIBLE_MAP_REQUIRE_JEMALLOC=1 but {NO_JEMALLOC}")
        pytest.skip(NO_JEMALLOC)


def test_the_setting_chooses_the_library(tmp_path, monkeypatch) -> None:
    library = tmp_path / "libjemalloc.so.2"
    library.write_bytes(b"")
    monkeypatch.setattr(allocator, "JEMALLOC_PATHS", (str(tmp_path / "none.so.2"), str(library)))
    assert jemalloc_path("auto") == str(library)
    assert jemalloc_path("") == str(library)
    assert jemalloc_path("off") is None
    assert jemalloc_path(str(library)) == str(library)
    monkeypatch.setenv("INVISIBLE_MAP_JEMALLOC", "off")
    assert jemalloc_path() is None
    monkeypatch.setattr(allocator, "JEMALLOC_PATHS", (str(tmp_path / "none.so.2"),))
    assert jemalloc_path("auto") is None


def test_a_setting_that_names_no_file_is_an_error_naming_it(tmp_path) -> None:
    missing = tmp_path / "nope.so"
    with pytest.raises(AllocatorError, match=f"INVISIBLE_MAP_JEMALLOC={missing}: no such file"):
        jemalloc_path(str(missing))
    with pytest.raises(AllocatorError), preloading_jemalloc(str(missing)):
        pass


def test_the_preload_is_set_inside_the_block_only(tmp_path, monkeypatch) -> None:
    library = tmp_path / "libjemalloc.so.2"
    library.write_bytes(b"")
    monkeypatch.delenv("LD_PRELOAD", raising=False)
    with preloading_jemalloc(str(library)) as chosen:
        assert chosen == str(library)
        assert os.environ["LD_PRELOAD"] == str(library)
    assert "LD_PRELOAD" not in os.environ

    monkeypatch.setenv("LD_PRELOAD", "/opt/other.so")
    with preloading_jemalloc(str(library)):
        assert os.environ["LD_PRELOAD"] == f"{library} /opt/other.so"
    assert os.environ["LD_PRELOAD"] == "/opt/other.so"

    monkeypatch.setenv("LD_PRELOAD", str(library))  # already there: not twice
    with preloading_jemalloc(str(library)):
        assert os.environ["LD_PRELOAD"] == str(library)
    with preloading_jemalloc("off") as chosen:
        assert chosen is None
        assert os.environ["LD_PRELOAD"] == str(library)


def loaded_libraries(pid: int) -> set[str]:
    """The paths of the shared libraries mapped into process ``pid`` (Linux ``/proc``; empty
    where it cannot be read)."""
    try:
        maps = Path(f"/proc/{pid}/maps").read_text()
    except OSError:
        return set()
    paths = (line.split()[-1] for line in maps.splitlines() if len(line.split()) >= 6)
    return {path for path in paths if ".so" in Path(path).name}


def libraries_once_started(pid: int, timeout_s: float = 20.0) -> set[str]:
    """The libraries of process ``pid`` once the dynamic loader has mapped the C library, which
    comes after any preloaded one (just after the start only the loader itself is mapped)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        libraries = loaded_libraries(pid)
        if any(Path(path).name.startswith("libc.so") for path in libraries):
            return libraries
        time.sleep(0.05)
    return loaded_libraries(pid)


def _libraries_of_this_process() -> set[str]:
    return loaded_libraries(os.getpid())


@pytest.mark.usefixtures("needs_jemalloc")
def test_a_process_started_inside_the_block_runs_on_jemalloc() -> None:
    context = multiprocessing.get_context("spawn")
    with preloading_jemalloc("auto"):
        inside = context.Pool(1)
    outside = context.Pool(1)
    with inside, outside:
        assert MACHINE_JEMALLOC in inside.apply(_libraries_of_this_process)
        assert MACHINE_JEMALLOC not in outside.apply(_libraries_of_this_process)


@pytest.mark.usefixtures("needs_jemalloc")
def test_a_sweeps_pool_runs_on_jemalloc_unless_it_is_off(monkeypatch) -> None:
    session = load_session(ONETAG)
    with trial_pool(1, session, SlamParams(), None) as pool:
        pid = pool.submit(os.getpid).result()
        assert MACHINE_JEMALLOC in loaded_libraries(pid)
    monkeypatch.setenv("INVISIBLE_MAP_JEMALLOC", "off")
    with trial_pool(1, session, SlamParams(), None) as pool:
        pid = pool.submit(os.getpid).result()
        assert MACHINE_JEMALLOC not in loaded_libraries(pid)


@pytest.mark.usefixtures("needs_jemalloc")
def test_worker_processes_run_on_jemalloc(tmp_path) -> None:
    settings = Settings(database_url=f"sqlite:///{tmp_path / 'w.sqlite3'}", poll_s=0.05)
    processes = start_worker_processes(settings, 2)
    try:
        for process in processes:
            assert MACHINE_JEMALLOC in libraries_once_started(int(process.pid or 0))
    finally:
        stop_worker_processes(processes, timeout_s=10)


def test_sweep_with_a_setting_that_names_no_file_fails_in_one_line(
    capsys, tmp_path, monkeypatch
) -> None:
    missing = tmp_path / "nope.so"
    monkeypatch.setenv("INVISIBLE_MAP_JEMALLOC", str(missing))
    status = cli.main(["sweep", str(ONETAG), "--trials", "2", "--processes", "1"])
    assert_one_line_error(status, capsys.readouterr().err, f"INVISIBLE_MAP_JEMALLOC={missing}")
