"""Shared test fixtures: where the repository and its data are, and fresh databases.

Database fixtures: every database test runs on SQLite and on the local PostgreSQL.

Each test gets a fresh, migrated database: on SQLite a copy of a template file migrated once per
run; on PostgreSQL ``CREATE DATABASE … TEMPLATE`` of a template database migrated once per run,
dropped at the end. PostgreSQL is found at ``TEST_POSTGRES_URL`` (default
``postgresql+psycopg://postgres@127.0.0.1:5432/postgres``). Where it is unreachable the PostgreSQL
half is skipped, with the reason, unless ``INVISIBLE_MAP_REQUIRE_POSTGRES=1`` (CI sets it), which
makes it an error.
"""

from __future__ import annotations

import gc
import os
import shutil
import uuid
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

import pytest
from sqlalchemy import create_engine, make_url, text
from sqlalchemy.engine import URL, Engine

from app.storage.db import Database
from app.storage.migrate import upgrade_to_head
from tests.demo_support import Demo, running_demo
from tests.fastapi_caches import forget_fastapi_caches

POSTGRES_ADMIN_URL = os.environ.get(
    "TEST_POSTGRES_URL", "postgresql+psycopg://postgres@127.0.0.1:5432/postgres"
)
REQUIRE_POSTGRES = os.environ.get("INVISIBLE_MAP_REQUIRE_POSTGRES") == "1"
RUN_ID = uuid.uuid4().hex[:8]


def _admin_engine():  # type: ignore[no-untyped-def]
    return create_engine(POSTGRES_ADMIN_URL, isolation_level="AUTOCOMMIT", pool_pre_ping=True)


def postgres_unavailable_reason() -> str | None:
    """None if the local PostgreSQL answers, else why not."""
    try:
        engine = _admin_engine()
        with engine.connect() as connection:
            connection.execute(text("SELECT 1"))
        engine.dispose()
    except Exception as err:
        return (
            f"PostgreSQL at {make_url(POSTGRES_ADMIN_URL).render_as_string()} unreachable: "
            + (str(err).splitlines()[0])
        )
    return None


# The garbage collector, tuned for a test process (not for the servers, which keep their own). A
# test process holds ~0.3 M long-lived objects once its tests are collected (modules, gtsam,
# pydantic models, the items) and makes and drops whole apps test after test; with Python's
# default thresholds (700, 10, 10) a full collection walked all of them every few tests: 13.5 s
# of tests/unit's 96 s and 109 s of tests/service's 480 s (one process, 2026-12-02). What is
# there when collection ends is frozen (never freed anyway), and young objects are collected
# less often: tests/unit 96 → 86 s, 2.8 s of it collecting.
GC_THRESHOLDS = (10_000, 20, 20)


def pytest_collection_finish() -> None:
    gc.collect()
    gc.freeze()
    gc.set_threshold(*GC_THRESHOLDS)


def pytest_report_header() -> list[str]:
    """What will be skipped on this machine, said first (``tests/skip_report.py``; ``-q`` hides
    it, so ``scripts/test`` says it before pytest starts)."""
    from tests.skip_report import report

    return report()


_UNGROUPED = pytest.StashKey[str]()


@pytest.hookimpl(trylast=True)
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Under ``--dist loadgroup`` (``scripts/test``), a test marked ``xdist_group`` must carry its
    group in its id, which is how pytest-xdist sends a group to one process. pytest 9.2 with
    pytest-xdist 3.8 drops it silently, and every process then builds the shared demo itself:
    such a test fails and says why (pyproject.toml bounds pytest below 9.2 for this)."""
    if not getattr(config.option, "loadgroup", False):
        return
    for item in items:
        if item.get_closest_marker("xdist_group") is not None and "@" not in item.nodeid:
            item.stash[_UNGROUPED] = (
                f"--dist loadgroup did not group this xdist_group test: pytest "
                f"{pytest.__version__} and this pytest-xdist disagree (see pyproject.toml)"
            )


def pytest_runtest_setup(item: pytest.Item) -> None:
    if _UNGROUPED in item.stash:
        pytest.fail(item.stash[_UNGROUPED], pytrace=False)


@pytest.fixture(autouse=True)
def _forget_the_apps_fastapi_cached() -> Iterator[None]:
    """Each test's apps freed after it (``tests/fastapi_caches.py`` says why)."""
    yield
    forget_fastapi_caches()


def _database_url(name: str) -> URL:
    return make_url(POSTGRES_ADMIN_URL).set(database=name)


@pytest.fixture(scope="session")
def sqlite_template(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("sqlite-template") / "template.sqlite3"
    database = Database(f"sqlite:///{path}")
    upgrade_to_head(database)
    database.dispose()
    return path


@pytest.fixture(scope="session")
def postgres_template() -> Iterator[str]:
    reason = postgres_unavailable_reason()
    if reason is not None:
        if REQUIRE_POSTGRES:
            pytest.fail(f"INVISIBLE_MAP_REQUIRE_POSTGRES=1 but {reason}")
        pytest.skip(f"PostgreSQL half skipped: {reason}")
    name = f"im_test_tpl_{RUN_ID}"
    admin = _admin_engine()
    with admin.connect() as connection:
        connection.execute(text(f'CREATE DATABASE "{name}"'))
    database = Database(_database_url(name).render_as_string(hide_password=False))
    upgrade_to_head(database)
    database.dispose()
    yield name
    with admin.connect() as connection:
        connection.execute(text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))
    admin.dispose()


def fresh_database_url(
    backend: str, request: pytest.FixtureRequest, tmp_path: Path
) -> Iterator[str]:
    """A migrated, empty database of ``backend``; dropped (PostgreSQL) after the test."""
    if backend == "sqlite":
        template: Path = request.getfixturevalue("sqlite_template")
        path = tmp_path / "test.sqlite3"
        shutil.copyfile(template, path)
        yield f"sqlite:///{path}"
        return
    databases: PostgresDatabases = request.getfixturevalue("postgres_databases")
    name = databases.take()
    try:
        yield _database_url(name).render_as_string(hide_password=False)
    finally:
        databases.give_back(name)


class PostgresDatabases:
    """Fresh copies of the template database for this test process, made and dropped off the
    tests' path: while a test runs, the next test's copy is made, and finished tests' copies are
    dropped in batches. ``CREATE DATABASE … TEMPLATE`` takes ~0.3–0.5 s here; a ``DROP
    DATABASE`` waits for a checkpoint of its own, ~0.1–1.4 s one after another, but several
    dropped at once share one (6 in 0.8 s, one after another 7.5 s). One thread makes copies,
    another drops them, ``DROP_BATCH`` at a time, concurrently, so a drop never delays the next
    test's copy. A copy that cannot be made fails the test that takes it; a drop that fails fails
    the run at its end."""

    #: finished tests' databases dropped together, at once (those left over at the end of the run)
    DROP_BATCH = 8

    def __init__(self, template: str) -> None:
        self.template = template
        self.admin = _admin_engine()
        self.maker = ThreadPoolExecutor(max_workers=1, thread_name_prefix="test-databases")
        self.dropper = ThreadPoolExecutor(max_workers=1, thread_name_prefix="test-drops")
        self.ahead: Future[str] | None = None
        self.finished: list[str] = []
        self.failed_drops: list[str] = []

    def _create(self) -> str:
        name = f"im_test_{RUN_ID}_{uuid.uuid4().hex[:8]}"
        with self.admin.connect() as connection:
            connection.execute(text(f'CREATE DATABASE "{name}" TEMPLATE "{self.template}"'))
        return name

    def _drop(self, name: str) -> None:
        try:
            with self.admin.connect() as connection:
                connection.execute(text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))
        except Exception as err:  # reported at the end of the run
            self.failed_drops.append(f"{name}: {err}")

    def _drop_all(self, names: list[str]) -> None:
        with ThreadPoolExecutor(max_workers=len(names)) as drops:
            list(drops.map(self._drop, names))

    def take(self) -> str:
        """A fresh database's name (the one made ahead, if any); starts making the next."""
        name = self.ahead.result() if self.ahead is not None else self._create()
        self.ahead = self.maker.submit(self._create)
        return name

    def give_back(self, name: str) -> None:
        self.finished.append(name)
        if len(self.finished) >= self.DROP_BATCH:
            self.dropper.submit(self._drop_all, self.finished)
            self.finished = []

    def close(self) -> None:
        if self.ahead is not None:
            try:
                self.finished.append(self.ahead.result())
            except Exception as err:
                self.failed_drops.append(f"the copy made ahead: {err}")
        if self.finished:
            self.dropper.submit(self._drop_all, self.finished)
        self.maker.shutdown(wait=True)
        self.dropper.shutdown(wait=True)
        self.admin.dispose()
        assert not self.failed_drops, f"test databases not dropped: {self.failed_drops}"


@pytest.fixture(scope="session")
def postgres_databases(postgres_template: str) -> Iterator[PostgresDatabases]:
    databases = PostgresDatabases(postgres_template)
    yield databases
    databases.close()


class PreparedDatabases:
    """Databases with data in them, made once per test process and copied into a test's fresh
    database: a fixture that uploads and builds the same map for every test of a module pays for
    the build once per database kind (``CREATE DATABASE … TEMPLATE`` of the prepared one on
    PostgreSQL, a file copy on SQLite). ``prepare(url)`` must close every connection it opens
    (PostgreSQL copies a database only while nobody is connected to it)."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        self.prepared: dict[tuple[str, str], str] = {}  # (backend, key) → file or database
        self.admin: Engine | None = None

    def copy_into(self, database_url: str, key: str, prepare: Callable[[str], None]) -> None:
        """Make ``database_url`` (a test's fresh database, not yet connected to) a copy of the
        database ``prepare`` makes from a fresh one."""
        url = make_url(database_url)
        backend = "sqlite" if url.get_backend_name() == "sqlite" else "postgresql"
        if backend == "sqlite":
            prepared = self.prepared.get((backend, key))
            if prepared is None:
                prepared = str(self.folder / f"{key}.sqlite3")
                shutil.copyfile(str(url.database), prepared)
                prepare(f"sqlite:///{prepared}")
                self.prepared[(backend, key)] = prepared
            shutil.copyfile(prepared, str(url.database))
            return
        if self.admin is None:
            self.admin = _admin_engine()
        prepared = self.prepared.get((backend, key))
        with self.admin.connect() as connection:
            if prepared is None:
                prepared = f"im_test_prep_{RUN_ID}_{key}"
                connection.execute(text(f'CREATE DATABASE "{prepared}" TEMPLATE "{url.database}"'))
                try:
                    prepare(_database_url(prepared).render_as_string(hide_password=False))
                except BaseException:  # not left behind half made, nor copied
                    connection.execute(text(f'DROP DATABASE "{prepared}" WITH (FORCE)'))
                    raise
                self.prepared[(backend, key)] = prepared
            connection.execute(text(f'DROP DATABASE "{url.database}" WITH (FORCE)'))
            connection.execute(text(f'CREATE DATABASE "{url.database}" TEMPLATE "{prepared}"'))

    def close(self) -> None:
        if self.admin is None:
            return
        with self.admin.connect() as connection:
            for (backend, _), name in self.prepared.items():
                if backend == "postgresql":
                    connection.execute(text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))
        self.admin.dispose()


@pytest.fixture(scope="session")
def prepared_databases(tmp_path_factory: pytest.TempPathFactory) -> Iterator[PreparedDatabases]:
    databases = PreparedDatabases(tmp_path_factory.mktemp("prepared-databases"))
    yield databases
    databases.close()


@pytest.fixture(params=[pytest.param(b, marks=pytest.mark.db) for b in ("sqlite", "postgresql")])
def database_url(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[str]:
    """A fresh migrated database, once on SQLite and once on PostgreSQL."""
    yield from fresh_database_url(request.param, request, tmp_path)


@pytest.fixture
def postgres_url(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[str]:
    """A fresh migrated PostgreSQL database (for tests that are about PostgreSQL only)."""
    yield from fresh_database_url("postgresql", request, tmp_path)


@pytest.fixture
def db(database_url: str) -> Iterator[Database]:
    database = Database(database_url)
    yield database
    database.dispose()


REPO_ROOT = Path(__file__).resolve().parents[1]
DATA_DIR = REPO_ROOT / "data"


@pytest.fixture(scope="session")
def repo_root() -> Path:
    """The project root (where ``pyproject.toml`` and ``data/`` are)."""
    return REPO_ROOT


@pytest.fixture(scope="session")
def data_dir() -> Path:
    """``data/``: the real sessions and ground truth shipped with the project."""
    return DATA_DIR


@pytest.fixture(scope="session")
def demo(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Demo]:
    """``invisible-map serve --demo`` as ``scripts/demo`` runs it, once per test process
    (``tests/demo_support.py``: its users are marked ``xdist_group("demo")``)."""
    with running_demo(tmp_path_factory.mktemp("demo")) as running:
        yield running
