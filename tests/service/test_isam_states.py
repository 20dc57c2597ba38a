"""A building map's incremental state in the database (app/storage/isam_states.py, issue 38): rows
as data that read back as the state saved, one state per map (its current version's), gone with
its version or its map, and not in backups."""

from __future__ import annotations

from functools import cache

import numpy as np
import pytest
from sqlalchemy import func, select

from app.domain.evaluation.table import evaluate_map
from app.domain.frames import make_pose
from app.domain.mapping.incremental import IsamState, IsamWalkState, StaleStateError
from app.domain.mapping.map_result import MapResult
from app.domain.mapping.params import SlamParams
from app.domain.mapping.slam import optimize_session
from app.domain.upload.session import decode_json_bytes, parse_session
from app.storage import isam_states, maps
from app.storage.backup.archive import TABLES_BY_NAME
from app.storage.db import Database
from app.storage.orm import IsamStateRow, IsamWalkStateRow
from tests.service.helpers import insert_session, session_bytes

pytestmark = pytest.mark.db


def a_state(walk_ids: tuple[str, ...] = ("session 1", "session 2")) -> IsamState:
    """A state of made-up numbers (what it holds is not checked here, only kept)."""
    rng = np.random.default_rng(len(walk_ids))

    def pose(k: float) -> np.ndarray:
        return make_pose(np.eye(3), np.array([k, 0.5 * k, -k]))

    walks = tuple(
        IsamWalkState(
            walk_id=walk_id,
            fingerprint=f"{k:064x}",
            depth_scale=1.0 + 0.01 * k,
            noise_scales=rng.uniform(0.5, 2.0, 4),
            cost_alone=10.0 * k,
            key_offset=400 * k,
            map_T_world=pose(k),
            keyframes=np.arange(0, 400, 7, dtype=np.int64),
            map_T_keyframe=np.stack([pose(k + 0.01 * i) for i in range(0, 400, 7)]),
            alone_tag_ids=np.array([0, 3], dtype=np.int64),
            world_T_tag_alone=np.stack([pose(k + 0.5), pose(k + 1.5)]),
        )
        for k, walk_id in enumerate(walk_ids)
    )
    return IsamState(
        walks=walks,
        tag_ids=np.array([0, 3, 9], dtype=np.int64),
        map_T_tag=np.stack([pose(t) for t in (0.0, 3.0, 9.0)]),
        params=SlamParams().to_dict(),
        next_key=400 * len(walk_ids),
    )


@cache
def a_result() -> tuple[MapResult, float]:
    parsed = parse_session(decode_json_bytes(session_bytes("onetag")))
    return optimize_session(parsed, SlamParams()), parsed.path_length_m()


def store_a_version(db: Database, map_id: int, state: IsamState | None) -> int:
    result, length_m = a_result()
    with db.transaction() as tx:
        version = maps.store_version(
            tx,
            map_id=map_id,
            job_id=None,
            result=result,
            evaluation=evaluate_map(result_session(), result),
            path_length_m=length_m,
        )
        if state is not None:
            isam_states.save_state(tx, map_id=map_id, map_version_id=version.id, state=state)
    return version.id


@cache
def result_session():  # type: ignore[no-untyped-def]
    return parse_session(decode_json_bytes(session_bytes("onetag")))


def rows(db: Database) -> tuple[int, int]:
    with db.read() as tx:
        return (
            tx.scalar(select(func.count()).select_from(IsamStateRow)) or 0,
            tx.scalar(select(func.count()).select_from(IsamWalkStateRow)) or 0,
        )


def assert_same(a: IsamState, b: IsamState) -> None:
    assert a.walk_ids == b.walk_ids
    assert a.fingerprint == b.fingerprint
    assert a.next_key == b.next_key
    np.testing.assert_array_equal(a.tag_ids, b.tag_ids)
    np.testing.assert_allclose(a.map_T_tag, b.map_T_tag, atol=0.0)
    for wa, wb in zip(a.walks, b.walks, strict=True):
        assert (wa.walk_id, wa.fingerprint, wa.key_offset) == (
            wb.walk_id,
            wb.fingerprint,
            wb.key_offset,
        )
        assert (wa.depth_scale, wa.cost_alone) == (wb.depth_scale, wb.cost_alone)
        np.testing.assert_array_equal(wa.keyframes, wb.keyframes)
        np.testing.assert_allclose(wa.noise_scales, wb.noise_scales, atol=0.0)
        np.testing.assert_allclose(wa.map_T_keyframe, wb.map_T_keyframe, atol=0.0)
        np.testing.assert_allclose(wa.map_T_world, wb.map_T_world, atol=0.0)
        np.testing.assert_array_equal(wa.alone_tag_ids, wb.alone_tag_ids)
        np.testing.assert_allclose(wa.world_T_tag_alone, wb.world_T_tag_alone, atol=0.0)


def test_a_state_reads_back_as_saved_and_only_the_current_versions(db: Database) -> None:
    map_id = insert_session(db, session_bytes("onetag")).map_id
    with db.read() as tx:
        assert isam_states.current_state(tx, map_id) is None  # no version yet
    first = a_state()
    v1 = store_a_version(db, map_id, first)
    with db.read() as tx:
        stored = isam_states.current_state(tx, map_id)
    assert stored is not None
    assert (stored.map_version_id, stored.version_number) == (v1, 1)
    assert_same(stored.state, first)
    assert rows(db) == (1, 2)

    second = a_state(("session 1", "session 2", "session 5"))
    v2 = store_a_version(db, map_id, second)
    with db.read() as tx:
        stored = isam_states.current_state(tx, map_id)
    assert stored is not None
    assert stored.map_version_id == v2
    assert_same(stored.state, second)
    assert rows(db) == (1, 3)  # the map keeps one state: version 1's is gone

    store_a_version(db, map_id, None)  # a version made without a state (a batch build's)
    with db.read() as tx:
        assert isam_states.current_state(tx, map_id) is None  # never an older version's


def test_a_walk_row_that_is_not_the_states_is_refused(db: Database) -> None:
    map_id = insert_session(db, session_bytes("onetag")).map_id
    v1 = store_a_version(db, map_id, a_state())
    with db.transaction() as tx:
        row = tx.get(IsamWalkStateRow, (v1, 1))
        assert row is not None
        row.fingerprint = "f" * 64  # another walk's data behind the state's back
    with db.read() as tx, pytest.raises(StaleStateError):
        isam_states.current_state(tx, map_id)


def test_deleting_the_map_deletes_its_state(db: Database) -> None:
    kept = insert_session(db, session_bytes("onetag")).map_id
    gone = insert_session(db, session_bytes("onetag")).map_id
    store_a_version(db, kept, a_state())
    store_a_version(db, gone, a_state(("session 7", "session 8", "session 9")))
    assert rows(db) == (2, 5)
    with db.transaction() as tx:
        maps.delete_map(tx, gone)
    assert rows(db) == (1, 2)
    with db.read() as tx:
        assert isam_states.state_count(tx, kept) == 1
        assert isam_states.state_count(tx, gone) == 0


def test_backups_skip_the_state() -> None:
    # derivable: a batch build of the version's walks makes it again (isam_states' docstring)
    assert "isam_state" not in TABLES_BY_NAME
    assert "isam_walk_state" not in TABLES_BY_NAME
