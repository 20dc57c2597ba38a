"""Races on one map (issue 19, findings 7 and 8): a rebuild racing a delete is a 404, never a
foreign-key violation; two builds of one map storing at once both store, as versions 1 and 2.
Each race is made deterministic: one transaction holds its write while the other runs in a
thread. On SQLite (writers run one at a time: the second waits for the first) and PostgreSQL
(where both used to fail)."""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

import pytest

from app.domain.evaluation.table import evaluate_map
from app.domain.mapping.params import SlamParams
from app.domain.mapping.slam import optimize_session
from app.domain.upload.session import decode_json_bytes, parse_session
from app.services.errors import status_and_code
from app.services.maps import delete_map_and_jobs, enqueue_rebuild
from app.storage import maps
from app.storage.db import Database
from app.storage.maps import MapNotFound
from tests.service.helpers import insert_session, session_bytes

pytestmark = pytest.mark.db

#: How long the first transaction holds its write while the second waits, s.
HOLD_S = 0.5


def in_thread(call: Callable[[], Any]) -> tuple[threading.Thread, dict[str, Any]]:
    outcome: dict[str, Any] = {}

    def run() -> None:
        try:
            outcome["value"] = call()
        except BaseException as err:
            outcome["error"] = err

    thread = threading.Thread(target=run)
    thread.start()
    return thread, outcome


def test_a_rebuild_racing_a_delete_is_map_not_found(db: Database) -> None:
    map_id = insert_session(db, session_bytes("onetag")).map_id

    def rebuild() -> Any:
        with db.transaction() as db_session:
            return enqueue_rebuild(db_session, map_id, {}, max_attempts=3)

    with db.transaction() as db_session:
        delete_map_and_jobs(db_session, map_id)
        thread, outcome = in_thread(rebuild)
        thread.join(HOLD_S)  # the rebuild waits for the delete
    thread.join(30)
    assert isinstance(outcome.get("error"), MapNotFound), outcome
    assert status_and_code(outcome["error"]) == (404, "not_found")
    with db.read() as db_session, pytest.raises(MapNotFound):
        maps.get_map(db_session, map_id)


def test_a_delete_racing_a_rebuild_deletes_the_new_job_too(db: Database) -> None:
    map_id = insert_session(db, session_bytes("onetag")).map_id

    def delete() -> None:
        with db.transaction() as db_session:
            delete_map_and_jobs(db_session, map_id)

    with db.transaction() as db_session:
        enqueue_rebuild(db_session, map_id, {}, max_attempts=3)
        thread, outcome = in_thread(delete)
        thread.join(HOLD_S)
    thread.join(30)
    assert outcome == {"value": None}


def test_two_builds_of_one_map_storing_at_once_both_store(db: Database) -> None:
    inserted = insert_session(db, session_bytes("onetag"))
    parsed = parse_session(decode_json_bytes(session_bytes("onetag")))
    result = optimize_session(parsed, SlamParams())
    evaluation = evaluate_map(parsed, result)

    def store() -> int:
        with db.transaction() as db_session:
            return maps.store_version(
                db_session,
                map_id=inserted.map_id,
                job_id=None,
                result=result,
                evaluation=evaluation,
                path_length_m=parsed.path_length_m(),
                plot_png=None,
            ).number

    with db.transaction() as db_session:
        first = maps.store_version(
            db_session,
            map_id=inserted.map_id,
            job_id=None,
            result=result,
            evaluation=evaluation,
            path_length_m=parsed.path_length_m(),
            plot_png=None,
        ).number
        thread, outcome = in_thread(store)
        thread.join(HOLD_S)  # the second store waits for the first to commit
    thread.join(30)
    assert "error" not in outcome, outcome
    assert (first, outcome["value"]) == (1, 2)
