"""The worker's warm start of a building map (``workers.pipeline.warm_start``): the next build of
a map starts from the last joint map this process built of it only where that map's walks are
these walks' data with these parameters."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import pytest

from app.domain.mapping.params import SlamParams
from workers import pipeline
from workers.pipeline import WARM_START_MAPS, remember_joint_map, warm_start

PARAMS = SlamParams()


def joint_of(*names: str, params: SlamParams = PARAMS) -> Any:
    """A stand-in for a JointMap: its parts' names and their fits' parameters are all that the
    choice reads."""
    return SimpleNamespace(
        parts=[
            SimpleNamespace(dataset=name, fit=SimpleNamespace(alone=SimpleNamespace(params=params)))
            for name in names
        ]
    )


@pytest.fixture(autouse=True)
def empty_cache(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(pipeline.joint, "LAST_JOINT_MAPS", {})


def test_the_same_walks_start_from_the_last_build_and_a_new_walk_joins_it() -> None:
    last = joint_of("session 1", "session 2")
    remember_joint_map(7, {"session 1": "a", "session 2": "b"}, last)
    previous, reused = warm_start(7, {"session 1": "a", "session 2": "b", "session 3": "c"}, PARAMS)
    assert previous is last
    assert reused == ["session 1", "session 2"]
    # taken out: a build that fails leaves nothing stale behind
    assert warm_start(7, {"session 1": "a", "session 2": "b"}, PARAMS) == (None, [])


def test_another_map_or_other_data_under_the_same_name_start_cold() -> None:
    remember_joint_map(7, {"session 1": "a", "session 2": "b"}, joint_of("session 1", "session 2"))
    assert warm_start(8, {"session 1": "a", "session 2": "b"}, PARAMS) == (None, [])
    # another database's session 2 (same name, other data): none of the map is reused
    assert warm_start(7, {"session 1": "a", "session 2": "X"}, PARAMS) == (None, [])


def test_other_parameters_start_cold() -> None:
    remember_joint_map(7, {"session 1": "a"}, joint_of("session 1"))
    other = PARAMS.with_overrides({"max_reprojection_px": 7.0})
    assert warm_start(7, {"session 1": "a"}, other) == (None, [])


def test_a_walk_taken_out_is_not_reused() -> None:
    remember_joint_map(7, {"session 1": "a", "session 2": "b"}, joint_of("session 1", "session 2"))
    previous, reused = warm_start(7, {"session 1": "a"}, PARAMS)
    assert previous is not None
    assert reused == ["session 1"]


def test_only_the_last_few_maps_are_kept() -> None:
    for map_id in range(WARM_START_MAPS + 1):
        remember_joint_map(map_id, {"session 1": "a"}, joint_of("session 1"))
    assert warm_start(0, {"session 1": "a"}, PARAMS) == (None, [])  # the oldest went
    assert warm_start(WARM_START_MAPS, {"session 1": "a"}, PARAMS)[0] is not None
