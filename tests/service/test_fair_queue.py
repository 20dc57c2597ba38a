"""Fair turns across keys (issue 19, finding 2): one key's queued uploads do not make another
key's upload wait behind all of them; priority still comes first. On SQLite and PostgreSQL."""

from __future__ import annotations

import pytest
from sqlalchemy import update

from app.storage import queue
from app.storage.db import Database
from app.storage.orm import SessionRow
from tests.service.helpers import Inserted, insert_session, session_bytes

pytestmark = pytest.mark.db


def uploaded_by(db: Database, subject: str, *inserted: Inserted) -> None:
    with db.transaction() as tx:
        tx.execute(
            update(SessionRow)
            .where(SessionRow.id.in_([i.session_id for i in inserted]))
            .values(uploaded_by=subject)
        )


def claim_order(db: Database, count: int) -> list[int]:
    order = []
    for _ in range(count):
        lease = queue.claim(db, worker_id="w", lease_s=60)
        assert lease is not None
        order.append(lease.job_id)
    return order


def test_one_keys_queue_does_not_starve_anothers(db: Database) -> None:
    busy = [insert_session(db, session_bytes("onetag")) for _ in range(4)]
    other = insert_session(db, session_bytes("onetag"))
    late = insert_session(db, session_bytes("onetag"))
    uploaded_by(db, "key:1", *busy)
    uploaded_by(db, "key:2", other)
    uploaded_by(db, "key:3", late)
    assert claim_order(db, 6) == [
        busy[0].job_id,  # each key's first turn, oldest first
        other.job_id,
        late.job_id,
        busy[1].job_id,  # then key 1's second, third, fourth
        busy[2].job_id,
        busy[3].job_id,
    ]


def test_priority_comes_before_turns(db: Database) -> None:
    first = insert_session(db, session_bytes("onetag"))
    urgent = insert_session(db, session_bytes("onetag"), priority=5)
    uploaded_by(db, "key:1", first, urgent)
    assert claim_order(db, 2) == [urgent.job_id, first.job_id]
