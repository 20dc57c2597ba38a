"""The API's pools: on PostgreSQL shared out among `serve`'s API processes; on both databases,
every connection opened is kept (no overflow connections, opened and closed per request)."""

from __future__ import annotations

import pytest

from app.storage.db import Database

URL = "postgresql+psycopg://postgres@127.0.0.1:5432/postgres"  # no connection is made


@pytest.mark.parametrize(("share", "kept"), [(1, 30), (2, 15), (4, 7), (8, 4), (16, 4)])
def test_each_process_pools_its_share_of_the_connections(share, kept):
    db = Database(URL, pool_share=share)
    try:
        assert db.engine.pool.size() == kept
        assert db.engine.pool._max_overflow == 0  # type: ignore[attr-defined]
        fast = db._async_commits()
        assert fast.pool.size() == max(4, 15 // share)
        assert fast.pool._max_overflow == 0  # type: ignore[attr-defined]
    finally:
        db.dispose()


def test_n_processes_hold_about_what_one_did():
    one = Database(URL)
    try:
        one_total = one.engine.pool.size() + one._async_commits().pool.size()
    finally:
        one.dispose()
    for share in (2, 3, 4):
        db = Database(URL, pool_share=share)
        try:
            total = db.engine.pool.size() + db._async_commits().pool.size()
        finally:
            db.dispose()
        assert share * total <= one_total + 4 * share


def test_sqlite_keeps_the_connections_it_opens(tmp_path):
    db = Database(f"sqlite:///{tmp_path / 'pools.sqlite3'}")
    try:
        for engine in (db.engine, db.read_engine):
            assert engine.pool._max_overflow == 0  # type: ignore[attr-defined]
            connections = [engine.connect() for _ in range(12)]
            for connection in connections:
                connection.close()
            assert engine.pool.checkedin() == 12  # all 12 kept for the next requests
    finally:
        db.dispose()
