"""A worker keeps the walks it parsed for the next build of the same building map
(``workers.pipeline.loading.PARSED_SESSIONS``, issue 38: parsing every walk again was most of a
big map's ``load`` stage), by database, session id and the upload's SHA-256, read-only, and
within a bound on the poses it holds."""

from __future__ import annotations

import numpy as np
import pytest

from app.storage import sessions
from app.storage.db import Database
from tests.service.test_worker_incremental import add_walk, map_of
from workers.pipeline import loading

pytestmark = pytest.mark.db


@pytest.fixture(autouse=True)
def no_parsed_sessions():
    loading.PARSED_SESSIONS.clear()
    yield
    loading.PARSED_SESSIONS.clear()


def parsed_lines(log: str) -> list[str]:
    return [line for line in log.splitlines() if "load: session " in line]


def test_a_walk_parsed_for_one_build_is_not_parsed_again_for_the_next(db: Database) -> None:
    map_id, session_ids = map_of(db, 2)
    added, log = add_walk(db, map_id, 2, mode="off")
    lines = parsed_lines(log)
    assert len(lines) == 1, lines  # only the walk added was read and parsed
    assert f"load: session {added}: " in lines[0]
    assert "load: 2 of 3 sessions as this worker parsed them before" in log
    with db.read() as tx:
        digests = sessions.raw_sha256s(tx, [*session_ids, added, 10**6])
    assert set(digests) == {*session_ids, added}  # an id not stored is left out
    url = db.url.render_as_string(hide_password=True)
    assert set(loading.PARSED_SESSIONS) == {(url, s, digests[s]) for s in [*session_ids, added]}
    for walk in loading.PARSED_SESSIONS.values():  # no stage can change what the next reads
        assert not walk.world_T_phone.flags.writeable
        assert not walk.detections.camera_T_tag.flags.writeable
        with pytest.raises(ValueError, match="read-only"):
            walk.world_T_phone[0, 0, 3] = np.nan


def test_the_walks_kept_are_bounded_by_their_poses(
    db: Database, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Over the bound, the least recently used walks go first."""
    monkeypatch.setattr(loading, "PARSED_SESSIONS_MAX_POSES", 700)  # two walks of 300 poses
    map_id, session_ids = map_of(db, 2)
    added, log = add_walk(db, map_id, 2, mode="off")
    assert len(parsed_lines(log)) == 1
    kept = [key[1] for key in loading.PARSED_SESSIONS]
    assert kept == [session_ids[1], added]
    assert sum(w.num_poses for w in loading.PARSED_SESSIONS.values()) == 600
