"""Races on one map (issue 19, findings 7 and 8): a rebuild racing a delete is a 404, never a
foreign-key violation; two builds of one map storing at once both store, as versions 1 and 2.
Membership changes racing each other or a delete (issue 25, item 2): the second answers 404 or
409 with a reason, never 500 (a foreign-key or unique violation) or 503 (a deadlock), and a map
never loses its last session.
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
from app.services.maps import (
    add_session_to_map,
    delete_map_and_jobs,
    enqueue_rebuild,
    merge_maps,
    remove_session_from_map,
)
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


# --------------------------------------------------------------------------- membership (issue 25)


def race(db: Database, first: Callable[[Any], Any], second: Callable[[Any], Any]) -> Any:
    """Run ``first`` in a transaction that holds its writes while ``second`` starts in its own
    (in a thread, which waits for it); the second's outcome: {"value": …} or {"error": …}."""

    def run_second() -> Any:
        with db.transaction() as db_session:
            return second(db_session)

    with db.transaction() as db_session:
        first(db_session)
        thread, outcome = in_thread(run_second)
        thread.join(HOLD_S)  # the second waits for the first to commit
    thread.join(30)
    assert not thread.is_alive()
    return outcome


def answer(outcome: dict[str, Any]) -> tuple[int, str]:
    """The HTTP status and code the API answers for the second transaction's error."""
    assert "error" in outcome, outcome
    return status_and_code(outcome["error"])


def a_map_of(db: Database, count: int) -> tuple[int, list[int]]:
    """A map of ``count`` sessions (each uploaded with a map of its own first): its id and its
    sessions."""
    inserted = [insert_session(db, session_bytes("pgt_tester3")) for _ in range(count)]
    map_id = inserted[0].map_id
    with db.transaction() as db_session:
        for other in inserted[1:]:
            maps.add_session(db_session, map_id, other.session_id)
    return map_id, [i.session_id for i in inserted]


def sessions_of(db: Database, map_id: int) -> list[int]:
    with db.read() as db_session:
        return maps.map_session_ids(db_session, map_id)


def test_racing_changes_of_a_maps_sessions_answer_409_and_keep_the_last_session(
    db: Database,
) -> None:
    # two removes at once of a map's two sessions: the second finds the last session
    map_id, (first, second) = a_map_of(db, 2)
    outcome = race(
        db,
        lambda s: remove_session_from_map(s, map_id, first, max_attempts=3),
        lambda s: remove_session_from_map(s, map_id, second, max_attempts=3),
    )
    assert answer(outcome) == (409, "last_session")
    assert sessions_of(db, map_id) == [second]

    # the same session added twice at once: one add
    other = insert_session(db, session_bytes("pgt_tester3")).session_id
    outcome = race(
        db,
        lambda s: add_session_to_map(s, map_id, other, max_attempts=3),
        lambda s: add_session_to_map(s, map_id, other, max_attempts=3),
    )
    assert answer(outcome) == (409, "already_in_map")
    assert sessions_of(db, map_id) == [second, other]

    # a remove racing an add of another session: both changes made
    third = insert_session(db, session_bytes("pgt_tester3")).session_id
    outcome = race(
        db,
        lambda s: remove_session_from_map(s, map_id, second, max_attempts=3),
        lambda s: add_session_to_map(s, map_id, third, max_attempts=3),
    )
    assert "error" not in outcome, outcome
    assert sessions_of(db, map_id) == [other, third]


def test_merges_and_deletes_racing_changes_answer_404(db: Database) -> None:
    # merges both ways at once: one merge, then the other map is gone
    a, _ = a_map_of(db, 1)
    b, _ = a_map_of(db, 1)
    outcome = race(
        db,
        lambda s: merge_maps(s, a, b, max_attempts=3),
        lambda s: merge_maps(s, b, a, max_attempts=3),
    )
    assert answer(outcome) == (404, "not_found")
    assert len(sessions_of(db, a)) == 2
    with db.read() as db_session, pytest.raises(MapNotFound):
        maps.get_map(db_session, b)

    # a merge racing a delete of the map merged in
    c, _ = a_map_of(db, 1)
    outcome = race(
        db,
        lambda s: delete_map_and_jobs(s, c),
        lambda s: merge_maps(s, a, c, max_attempts=3),
    )
    assert answer(outcome) == (404, "not_found")
    assert len(sessions_of(db, a)) == 2

    # an add racing a delete of the map, either way round
    other = insert_session(db, session_bytes("pgt_tester3")).session_id
    outcome = race(
        db,
        lambda s: add_session_to_map(s, a, other, max_attempts=3),
        lambda s: delete_map_and_jobs(s, a),
    )
    assert outcome == {"value": None}
    with db.read() as db_session, pytest.raises(MapNotFound):
        maps.get_map(db_session, a)
    d, _ = a_map_of(db, 1)
    outcome = race(
        db,
        lambda s: delete_map_and_jobs(s, d),
        lambda s: add_session_to_map(s, d, other, max_attempts=3),
    )
    assert answer(outcome) == (404, "not_found")
