"""Building maps made incremental (issue 38), with the real worker pipeline on SQLite and
PostgreSQL: a batch build of several walks stores, with its version and in its transaction, the
state that makes the next add incremental (``app.storage.isam_states``), made from the batch's
optimum; restored from the database, it is the batch map, and an add to it is the batch map of
one walk more. With ``Settings.incremental_builds`` the worker makes a change of one walk in the
stored state (restored from the database: a restarted worker too) and serves the engine's map
without a batch solve, within the bounds of the batch build that a rebuild of the same walks
makes; with ``Settings.incremental_check`` too it serves the batch build and logs how far the
engine's map is from it. A stale state leaves the change to the batch build alone."""

from __future__ import annotations

import json
from functools import cache

import numpy as np
import pytest

from app.config import Settings
from app.domain.evaluation.simulate import SimulationConfig
from app.domain.evaluation.simulate_building import simulate_building_sessions
from app.domain.mapping.incremental import IsamBuilding, Walk
from app.domain.mapping.joint import optimize_sessions
from app.domain.mapping.params import SlamParams
from app.domain.upload.session import decode_json_bytes, parse_session
from app.services.maps import add_session_to_map, enqueue_rebuild, remove_session_from_map
from app.storage import isam_states, maps, queue
from app.storage.db import Database
from tests.service.helpers import get_job, insert_session
from workers import pipeline
from workers.main import Worker
from workers.pipeline import BUILD_MAP_STAGES

pytestmark = pytest.mark.db

#: The issue's bounds on what is served, against the batch build of the same walks, m.
TAG_BOUND_M = 0.01
POSE_BOUND_M = 0.05
WALKS = 4


@cache
def building_uploads() -> tuple[bytes, ...]:
    """Four simulated walks of one building (300 poses each), each in its own world frame."""
    building = simulate_building_sessions(SimulationConfig(num_poses=300, seed=3), count=WALKS)
    return tuple(json.dumps(s.upload, separators=(",", ":")).encode() for s in building.sessions)


def walk(k: int, session_id: int) -> Walk:
    return Walk(
        walk_id=f"session {session_id}",
        session=parse_session(decode_json_bytes(building_uploads()[k])),
    )


def run_all(db: Database, *, mode: str = "off") -> None:
    """Run the worker until the queue is empty; ``mode``: incremental builds "off", "serve" or
    "check" (``workers.incremental_builds.mode_of``)."""
    settings = Settings(
        database_url=db.url.render_as_string(hide_password=False),
        lease_s=30.0,
        heartbeat_s=5.0,
        poll_s=0.05,
        retry_backoff_s=0.0,
        incremental_builds=mode != "off",
        incremental_check=mode == "check",
    )
    runner = Worker(db, settings, pipelines={"build_map": BUILD_MAP_STAGES})
    while runner.run_once():
        pass


def map_of(db: Database, walks: int, *, mode: str = "off") -> tuple[int, list[int]]:
    """A map of the first ``walks`` simulated walks, each added and built in turn (the other
    uploads' own maps are not built); its id and its sessions."""
    first = insert_session(db, building_uploads()[0])
    run_all(db, mode=mode)
    session_ids = [first.session_id]
    for k in range(1, walks):
        session_ids.append(add_walk(db, first.map_id, k, mode=mode)[0])
    return first.map_id, session_ids


def add_walk(db: Database, map_id: int, k: int, *, mode: str) -> tuple[int, str]:
    """Upload simulated walk ``k``, add it to map ``map_id`` and build; its session id and the
    build's log."""
    other = insert_session(db, building_uploads()[k])
    with db.transaction() as tx:
        queue.request_cancel(tx, other.job_id)
        job_id = add_session_to_map(tx, map_id, other.session_id, max_attempts=3).job_id
    run_all(db, mode=mode)
    return other.session_id, finished_log(db, job_id)


def finished_log(db: Database, job_id: int) -> str:
    job = get_job(db, job_id)
    assert job.state == "succeeded", job.error
    return job.log_tail


def current_session_ids(db: Database, map_id: int) -> list[int] | None:
    with db.read() as tx:
        current = maps.get_map(tx, map_id).current
    assert current is not None
    return current.session_ids


def incremental_lines(log: str) -> list[str]:
    return [line for line in log.splitlines() if "incremental:" in line]


def test_a_batch_build_stores_the_state_that_restores_its_map(db: Database) -> None:
    map_id, session_ids = map_of(db, 3)
    with db.read() as tx:
        current = maps.get_map(tx, map_id).current
        stored = isam_states.current_state(tx, map_id)
        assert isam_states.state_count(tx) == 1  # version 2's state was replaced by version 3's
    assert current is not None
    assert current.session_ids == session_ids
    assert stored is not None
    assert stored.version_number == current.number == 3
    walks = [walk(k, s) for k, s in enumerate(session_ids)]
    assert stored.state.walk_ids == tuple(w.walk_id for w in walks)
    stored.state.require_current(walks, SlamParams())

    # restored from the rows, the tree is the stored map; one walk more, the batch map of all
    joint = optimize_sessions(
        [w.session for w in walks], SlamParams(), names=[w.walk_id for w in walks]
    )
    building, restored = IsamBuilding.restore(stored.state, walks, SlamParams())
    np.testing.assert_allclose(restored.map_T_tag, joint.map.world_T_tag, atol=TAG_BOUND_M / 10)
    fourth = walk(3, 99)
    added = building.add(fourth)
    everyone = [*walks, fourth]
    batch = optimize_sessions(
        [w.session for w in everyone], SlamParams(), names=[w.walk_id for w in everyone]
    )
    np.testing.assert_array_equal(added.tag_ids, batch.map.tag_ids)
    tag_m = np.max(
        np.linalg.norm(added.map_T_tag[:, :3, 3] - batch.map.world_T_tag[:, :3, 3], axis=1)
    )
    assert tag_m <= TAG_BOUND_M
    for part, poses in zip(batch.parts, added.world_T_phone, strict=True):
        pose_m = np.max(
            np.linalg.norm(batch.map.world_T_phone[part.pose_rows, :3, 3] - poses[:, :3, 3], axis=1)
        )
        assert pose_m <= POSE_BOUND_M


def test_a_map_of_one_walk_has_no_state_and_deleting_a_map_deletes_its_state(
    db: Database,
) -> None:
    map_id, _ = map_of(db, 2)
    with db.read() as tx:
        assert isam_states.state_count(tx, map_id) == 1
    lone = insert_session(db, building_uploads()[3])
    run_all(db)
    with db.read() as tx:
        assert isam_states.state_count(tx, lone.map_id) == 0
    with db.transaction() as tx:
        maps.delete_map(tx, map_id)
    with db.read() as tx:
        assert isam_states.state_count(tx) == 0


def test_one_walk_added_is_checked_against_the_batch_build_after_a_restart(
    db: Database,
) -> None:
    map_id, session_ids = map_of(db, 3, mode="check")
    pipeline.LAST_JOINT_MAPS.clear()  # a restarted worker: nothing of the map in memory
    added, log = add_walk(db, map_id, 3, mode="check")
    lines = incremental_lines(log)
    assert len(lines) == 1, lines
    assert f"session {added} added in version 3's state" in lines[0]
    assert "from the batch map, within 10 / 50 mm" in lines[0]
    assert current_session_ids(db, map_id) == [*session_ids, added]
    with db.read() as tx:
        stored = isam_states.current_state(tx, map_id)
    assert stored is not None
    assert stored.state.walk_ids == tuple(f"session {s}" for s in [*session_ids, added])


def test_one_walk_taken_out_is_checked_against_the_batch_build(db: Database) -> None:
    map_id, session_ids = map_of(db, 3, mode="check")
    with db.transaction() as tx:
        job_id = remove_session_from_map(tx, map_id, session_ids[1], max_attempts=3).job_id
    run_all(db, mode="check")
    lines = incremental_lines(finished_log(db, job_id))
    assert len(lines) == 1, lines
    assert f"session {session_ids[1]} taken out in version 3's state" in lines[0]
    assert "from the batch map, within 10 / 50 mm" in lines[0]
    assert current_session_ids(db, map_id) == [session_ids[0], session_ids[2]]


def test_a_stale_state_leaves_the_change_to_the_batch_build(db: Database) -> None:
    map_id, session_ids = map_of(db, 2)
    with db.read() as tx:
        old = isam_states.current_state(tx, map_id)
    assert old is not None
    third, _ = add_walk(db, map_id, 2, mode="off")
    # version 3 with version 2's state: a walk was added behind the state's back
    with db.transaction() as tx:
        version = maps.get_map(tx, map_id).current
        assert version is not None
        isam_states.save_state(tx, map_id=map_id, map_version_id=version.id, state=old.state)
    fourth, log = add_walk(db, map_id, 3, mode="serve")
    lines = incremental_lines(log)
    assert len(lines) == 1, lines
    assert "a batch build (not one walk added to or taken out of" in lines[0]
    assert "optimize: 4 sessions, " in log  # the batch build's line
    assert current_session_ids(db, map_id) == [*session_ids, third, fourth]
    with db.read() as tx:
        stored = isam_states.current_state(tx, map_id)
    assert stored is not None  # the batch build's state: the next add is incremental again
    assert len(stored.state.walk_ids) == 4


def served_tags(db: Database, map_id: int, number: int) -> dict[int, np.ndarray]:
    """Version ``number``'s tag positions as the store keeps them, m."""
    with db.read() as tx:
        version = maps.get_version(tx, map_id, number)
        return {t.tag_id: np.array(t.position_m) for t in maps.tag_poses(tx, version.id)}


def test_one_walk_added_and_one_taken_out_are_served_by_the_engine(db: Database) -> None:
    """No batch solve: the engine's map is stored as the version (its tags within 1 cm of the
    batch build a rebuild of the same walks then makes), the engine's state with it, so that
    the next change, after a restart, is the engine's again."""
    map_id, session_ids = map_of(db, 3)
    pipeline.LAST_JOINT_MAPS.clear()  # a restarted worker: nothing of the map in memory
    added, log = add_walk(db, map_id, 3, mode="serve")
    lines = incremental_lines(log)
    assert len(lines) == 1, lines
    assert f"session {added} added in version 3's state" in lines[0]
    assert "; served (" in lines[0]
    assert "warm start" not in log
    assert "incremental state made" not in log
    assert "optimize: 4 sessions, 1 rounds" in log
    assert "optimize: incremental state of the engine kept" in log
    everyone = [*session_ids, added]
    assert current_session_ids(db, map_id) == everyone
    with db.read() as tx:
        stored = isam_states.current_state(tx, map_id)
    assert stored is not None
    assert stored.version_number == 4
    assert stored.state.walk_ids == tuple(f"session {s}" for s in everyone)

    pipeline.LAST_JOINT_MAPS.clear()
    with db.transaction() as tx:
        job_id = remove_session_from_map(tx, map_id, added, max_attempts=3).job_id
    run_all(db, mode="serve")
    lines = incremental_lines(finished_log(db, job_id))
    assert len(lines) == 1, lines
    assert f"session {added} taken out in version 4's state" in lines[0]
    assert "; served (" in lines[0]
    left = session_ids
    assert current_session_ids(db, map_id) == left

    # the batch build of the same walks, on demand: the served tags within the bound
    with db.transaction() as tx:
        _, job_id = enqueue_rebuild(tx, map_id, {}, max_attempts=3)
    run_all(db, mode="serve")
    log = finished_log(db, job_id)
    assert "a batch build (the same walks (a rebuild))" in incremental_lines(log)[0]
    engine, batch = served_tags(db, map_id, 5), served_tags(db, map_id, 6)
    assert engine.keys() == batch.keys()
    assert max(np.linalg.norm(engine[t] - batch[t]) for t in batch) <= TAG_BOUND_M
