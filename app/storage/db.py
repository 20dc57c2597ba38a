"""Engines and transactions.

``Database.transaction()`` is one read-write transaction (commit on success, rollback on an
exception); ``Database.read()`` one read-only transaction. On SQLite, writers start with
``BEGIN IMMEDIATE`` so that two processes never both read and then fail to upgrade to a write, and
the file is in WAL mode so readers never wait for a writer. On PostgreSQL both are ordinary
``READ COMMITTED`` transactions; the job queue claims rows with ``FOR UPDATE SKIP LOCKED``.
"""

from __future__ import annotations

import enum
import os
import sqlite3
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from sqlalchemy import Connection, Engine, create_engine, event, make_url, text
from sqlalchemy import exc as sqlalchemy_exc
from sqlalchemy.orm import Session, sessionmaker

if TYPE_CHECKING:
    from app.config import Settings

SQLITE_BUSY_TIMEOUT_MS = 30_000
#: Execution option of the connections :meth:`Database.autocommit` gives: no BEGIN on SQLite.
AUTOCOMMIT = "invisible_map_autocommit"
#: ``Session.info`` key of the sessions :meth:`Database.transaction` made (they may write).
WRITES = "invisible_map_writes"


@dataclass(frozen=True, slots=True, kw_only=True)
class ServerTimeouts:
    """PostgreSQL's limits on a server process's connections (``Settings.db_timeouts``; SQLite
    has its busy timeout, :data:`SQLITE_BUSY_TIMEOUT_MS`). A limit that runs out is a database
    fault (503 ``database_unavailable`` to a request, a wait-and-retry to a worker).

    lock_s: the longest a statement waits for a lock (a row another transaction holds).
    statement_s: the longest a statement runs.
    idle_in_transaction_s: a session idle this long inside a transaction (its process stalled,
        e.g. stopped with SIGSTOP) is ended by the server, and its locks with it.
    """

    lock_s: float
    statement_s: float
    idle_in_transaction_s: float

    @classmethod
    def of(cls, settings: Settings) -> ServerTimeouts:
        """``INVISIBLE_MAP_DB_LOCK_TIMEOUT_S`` and the others."""
        return cls(
            lock_s=settings.db_lock_timeout_s,
            statement_s=settings.db_statement_timeout_s,
            idle_in_transaction_s=settings.db_idle_in_transaction_timeout_s,
        )

    def options(self) -> str:
        """libpq's ``options``: ``-c lock_timeout=5000 …`` (ms)."""
        return " ".join(
            f"-c {name}={round(seconds * 1000)}"
            for name, seconds in (
                ("lock_timeout", self.lock_s),
                ("statement_timeout", self.statement_s),
                ("idle_in_transaction_session_timeout", self.idle_in_transaction_s),
            )
        )


#: PostgreSQL connections one API process may hold (opened as needed, then kept).
POOL_CONNECTIONS = 30
#: The same for the localization updates' pool (``Database.autocommit(durable=False)``).
ASYNC_COMMIT_CONNECTIONS = 15
#: SQLite connections each of a process's two engines (writes, reads) may hold, opened as needed
#: and kept. A connection is cheap to keep, dear to open: its PRAGMAs, then the schema parsed on
#: its first statement.
SQLITE_POOL_CONNECTIONS = 30


def _shared(connections: int, share: int) -> int:
    """``connections`` over ``share`` processes, at least 4 each."""
    return max(4, connections // max(1, share))


class Database:
    """The engines for one database URL; create one per process (after any fork).
    ``timeouts``: :class:`ServerTimeouts` for PostgreSQL's sessions (the API and the workers pass
    them; the CLI's commands, such as ``migrate`` and ``export``, run without). ``pool_share``:
    how many processes of the same kind share the database's connections (``serve
    --api-processes N``): each pools :data:`POOL_CONNECTIONS` over N, so that N processes hold
    what one did (PostgreSQL's ``max_connections`` is 100 by default)."""

    def __init__(
        self,
        url: str,
        *,
        echo: bool = False,
        timeouts: ServerTimeouts | None = None,
        pool_share: int = 1,
    ) -> None:
        self.url = make_url(url)
        self.is_sqlite = self.url.get_backend_name() == "sqlite"
        self._connect_args: dict[str, str] = {}
        if self.is_sqlite:
            _ensure_sqlite_folder(self.url.database)
            self.engine = _sqlite_engine(url, echo=echo, begin="BEGIN IMMEDIATE")
            self.read_engine = _sqlite_engine(url, echo=echo, begin="BEGIN")
        else:
            connect_args = {} if timeouts is None else {"options": timeouts.options()}
            self._connect_args = connect_args
            self.engine = create_engine(
                url,
                echo=echo,
                pool_pre_ping=True,
                # Every connection opened is kept (no overflow): under load a pool that closes
                # what it opened beyond its size opens a new server process per request.
                pool_size=_shared(POOL_CONNECTIONS, pool_share),
                max_overflow=0,
                connect_args=connect_args,
            )
            self.read_engine = self.engine
        self._pool_share = pool_share
        self._async_commit_engine: Engine | None = None
        self._engine_lock = threading.Lock()
        self._sessions = sessionmaker(self.engine, expire_on_commit=False)
        self._read_sessions = sessionmaker(self.read_engine, expire_on_commit=False)

    @property
    def backend(self) -> str:
        """``sqlite`` or ``postgresql``."""
        return self.url.get_backend_name()

    @contextmanager
    def transaction(self) -> Iterator[Session]:
        """One read-write transaction: commits if the block ends normally, else rolls back.
        (:func:`end_transaction` may commit it earlier.)"""
        with self._sessions.begin() as db_session:
            db_session.info[WRITES] = True
            yield db_session

    @contextmanager
    def autocommit(self, *, durable: bool = True) -> Iterator[Connection]:
        """A connection on which every statement is its own transaction, committed as it ends
        (no ``BEGIN`` or ``COMMIT`` round trips): for the hot path's single statements, such as a
        compare-and-set ``UPDATE … WHERE revision = ?``, which need no transaction around them.
        On SQLite a writing statement takes the write lock as it starts (waiting up to the busy
        timeout), as ``BEGIN IMMEDIATE`` would.

        ``durable=False``, on PostgreSQL: the commits do not wait for the WAL to reach the disk
        (``synchronous_commit=off``, a pool of its own): a crash of the database server (not of
        an API process) may lose the last fraction of a second of such writes, never corrupt
        anything. For state a client sends again anyway (localization updates). SQLite's
        commits never wait for the disk here (``synchronous=NORMAL`` in WAL mode)."""
        if self.is_sqlite:
            # The connections already run pysqlite in autocommit mode (isolation_level None);
            # the "begin" listener leaves out its BEGIN for this option, so nothing opens one.
            options: dict[str, Any] = {AUTOCOMMIT: True}
            engine = self.engine
        else:
            options = {"isolation_level": "AUTOCOMMIT"}
            engine = self.engine if durable else self._async_commits()
        with engine.connect().execution_options(**options) as connection:
            yield connection

    def _async_commits(self) -> Engine:
        """The PostgreSQL engine of :meth:`autocommit` ``(durable=False)``, made on first use."""
        with self._engine_lock:
            if self._async_commit_engine is None:
                options = self._connect_args.get("options", "")
                self._async_commit_engine = create_engine(
                    self.url,
                    pool_pre_ping=True,
                    pool_size=_shared(ASYNC_COMMIT_CONNECTIONS, self._pool_share),
                    max_overflow=0,
                    connect_args={"options": f"{options} -c synchronous_commit=off".strip()},
                )
            return self._async_commit_engine

    @contextmanager
    def read(self) -> Iterator[Session]:
        """One read-only transaction (rolled back at the end)."""
        with self._read_sessions() as session:
            yield session
            session.rollback()

    def ping(self) -> None:
        """Raise if the database cannot be reached."""
        with self.read_engine.connect() as connection:
            connection.execute(text("SELECT 1"))

    def dispose(self) -> None:
        self.engine.dispose()
        if self._async_commit_engine is not None:
            self._async_commit_engine.dispose()
        if self.read_engine is not self.engine:
            self.read_engine.dispose()


class DatabaseFault(enum.StrEnum):
    """Why the database could not do what was asked, when it is the database's fault and not
    the request's; the same request may succeed later (a 503 in the API, a wait in the worker)."""

    #: unreachable, restarting, a dropped connection, busy or locked past its timeout
    UNAVAILABLE = "database_unavailable"
    #: the disk holding the database is full (SQLITE_FULL; PostgreSQL SQLSTATE 53100)
    STORAGE_FULL = "storage_full"
    #: the database refuses writes (a read-only file or file system; a read-only server)
    READ_ONLY = "storage_read_only"
    #: the SQLite file cannot be opened (its disk is read-only, unmounted or gone)
    CANNOT_OPEN = "storage_unavailable"


#: PostgreSQL SQLSTATEs that name the fault (other connection and shutdown errors are
#: OperationalErrors: unavailable).
_PG_READ_ONLY_SQLSTATES = frozenset({"25006"})
_PG_FULL_SQLSTATES = frozenset({"53100"})


#: SQLite's primary result codes that are faults of the database's state, not of the request.
_SQLITE_FAULTS = {
    sqlite3.SQLITE_FULL: DatabaseFault.STORAGE_FULL,
    sqlite3.SQLITE_READONLY: DatabaseFault.READ_ONLY,
    sqlite3.SQLITE_CANTOPEN: DatabaseFault.CANNOT_OPEN,
    sqlite3.SQLITE_BUSY: DatabaseFault.UNAVAILABLE,
    sqlite3.SQLITE_LOCKED: DatabaseFault.UNAVAILABLE,
    sqlite3.SQLITE_IOERR: DatabaseFault.UNAVAILABLE,
    sqlite3.SQLITE_PROTOCOL: DatabaseFault.UNAVAILABLE,
}


def database_fault(err: BaseException) -> DatabaseFault | None:
    """What kind of database fault ``err`` is, or None if it is not one (a bug, a constraint
    violation, a bad statement: those are not made better by waiting)."""
    if isinstance(err, sqlalchemy_exc.DBAPIError):
        original = err.orig
        sqlite_code = getattr(original, "sqlite_errorcode", None)
        if isinstance(sqlite_code, int):
            # (pysqlite raises OperationalError for syntax errors too: the code tells them apart;
            # extended result codes carry the primary one in their low byte)
            return _SQLITE_FAULTS.get(sqlite_code & 0xFF)
        sqlstate = getattr(original, "sqlstate", None)
        if sqlstate in _PG_FULL_SQLSTATES:
            return DatabaseFault.STORAGE_FULL
        if sqlstate in _PG_READ_ONLY_SQLSTATES:
            return DatabaseFault.READ_ONLY
        if isinstance(err, sqlalchemy_exc.OperationalError | sqlalchemy_exc.InterfaceError):
            return DatabaseFault.UNAVAILABLE
        if err.connection_invalidated:
            return DatabaseFault.UNAVAILABLE
        return None
    if isinstance(err, sqlalchemy_exc.TimeoutError):  # no pooled connection came free in time
        return DatabaseFault.UNAVAILABLE
    return None


def end_transaction(db_session: Session) -> None:
    """End ``session``'s transaction now and give its connection back to the pool: commit it if
    it came from :meth:`Database.transaction`, roll it back if from :meth:`Database.read`. The
    ``with`` block that made the session then has nothing left to do."""
    if not db_session.in_transaction():
        return
    if db_session.info.get(WRITES):
        db_session.commit()
    else:
        db_session.rollback()


def first_line(err: BaseException) -> str:
    """The first line of ``err``'s message (of the driver's own error, if SQLAlchemy wrapped
    one: its message goes on with the SQL), or its type's name if it has none."""
    text = str(getattr(err, "orig", None) or err).strip()
    return text.splitlines()[0] if text else type(err).__name__


def _ensure_sqlite_folder(database: str | None) -> None:
    """Make the SQLite file's folder, and the file itself readable by its owner only (0600:
    it holds every upload and the keys' digests; SQLite gives its ``-wal`` and ``-shm`` files
    the database file's mode). An existing file of ours that others may read is made 0600."""
    if database and database != ":memory:" and not database.startswith("file:"):
        path = Path(database).expanduser().resolve()
        path.parent.mkdir(parents=True, exist_ok=True)
        try:
            os.close(os.open(path, os.O_WRONLY | os.O_CREAT, 0o600))
            for file in (
                path,
                path.with_name(path.name + "-wal"),
                path.with_name(path.name + "-shm"),
            ):
                if (
                    file.exists()
                    and file.stat().st_mode & 0o077
                    and file.stat().st_uid == os.getuid()
                ):
                    file.chmod(0o600)
        except OSError:
            pass  # a read-only folder or file: opening it says so, naming the file


def _sqlite_engine(url: str, *, echo: bool, begin: str) -> Engine:
    engine = create_engine(
        url,
        echo=echo,
        pool_size=SQLITE_POOL_CONNECTIONS,
        max_overflow=0,
        connect_args={"timeout": SQLITE_BUSY_TIMEOUT_MS / 1000},
    )

    @event.listens_for(engine, "connect")
    def _on_connect(dbapi_connection: Any, _record: Any) -> None:
        # Let SQLAlchemy's "begin" event issue BEGIN (pysqlite's own would be deferred and late).
        dbapi_connection.isolation_level = None
        cursor = dbapi_connection.cursor()
        cursor.execute("PRAGMA journal_mode=WAL")
        cursor.execute("PRAGMA synchronous=NORMAL")
        cursor.execute("PRAGMA foreign_keys=ON")
        cursor.execute(f"PRAGMA busy_timeout={SQLITE_BUSY_TIMEOUT_MS}")
        cursor.close()

    @event.listens_for(engine, "begin")
    def _on_begin(connection: Connection) -> None:
        if not connection.get_execution_options().get(AUTOCOMMIT):
            connection.exec_driver_sql(begin)

    return engine
