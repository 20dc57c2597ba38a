"""The API's PostgreSQL pools are shared out among `serve`'s API processes."""

from __future__ import annotations

import pytest

from app.storage.db import Database

URL = "postgresql+psycopg://postgres@127.0.0.1:5432/postgres"  # no connection is made


@pytest.mark.parametrize(
    ("share", "kept", "overflow"), [(1, 10, 20), (2, 5, 10), (4, 2, 5), (8, 2, 2)]
)
def test_each_process_pools_its_share_of_the_connections(share, kept, overflow):
    db = Database(URL, pool_share=share)
    try:
        assert db.engine.pool.size() == kept
        assert db.engine.pool._max_overflow == overflow  # type: ignore[attr-defined]
    finally:
        db.dispose()


def test_n_processes_hold_about_what_one_did():
    one = Database(URL)
    try:
        one_total = one.engine.pool.size() + one.engine.pool._max_overflow  # type: ignore[attr-defined]
    finally:
        one.dispose()
    for share in (2, 3, 4):
        db = Database(URL, pool_share=share)
        try:
            total = db.engine.pool.size() + db.engine.pool._max_overflow  # type: ignore[attr-defined]
        finally:
            db.dispose()
        assert share * total <= one_total + 4 * share
