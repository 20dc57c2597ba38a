"""Hypothesis on the live-localization update (``parse_update`` then ``update``): arbitrary JSON
and arbitrary numbers anywhere in a real update never raise anything but
:class:`LocalizationUpdateError`, never change the state they were given, and never produce a
non-finite pose.

(The same for the upload parser is in test_session.py.)
"""

from __future__ import annotations

import json
from typing import Any

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from app.domain.evaluation.simulate import SimulationConfig, simulate_session
from app.domain.localize import (
    LocalizationUpdateError,
    LocalizerState,
    parse_update,
    session_update_documents,
    update,
)
from app.domain.upload.session import parse_session
from tests.unit.test_session import json_values, node_paths, replaced

# A short simulated walk: its tags are the map, and its updates of 10 poses are real documents.
_SIM = simulate_session(SimulationConfig(num_poses=400, seed=3))
MAP_TAGS = dict(_SIM.world_T_tag_true)
DOCUMENTS = session_update_documents(parse_session(_SIM.upload), 10)


def _localized_state() -> tuple[LocalizerState, int]:
    """The state after the updates up to the first one that localized, and the index of the
    next document (one with a detection, which exercises the optimization)."""
    state = LocalizerState.initial()
    for k, document in enumerate(DOCUMENTS):
        state, result = update(state, parse_update(document), MAP_TAGS)
        if result.status == "localized":
            later = next(j for j in range(k + 1, len(DOCUMENTS)) if DOCUMENTS[j].get("tag_data"))
            for document_between in DOCUMENTS[k + 1 : later]:
                state, _ = update(state, parse_update(document_between), MAP_TAGS)
            return state, later
    raise AssertionError("the simulated walk never localized")


STATE, NEXT = _localized_state()
NEXT_DOCUMENT = DOCUMENTS[NEXT]
STATE_JSON = json.dumps(STATE.to_json(), sort_keys=True)

PATHS = sorted(node_paths(NEXT_DOCUMENT), key=repr)


def accepts_or_refuses_cleanly(document: Any) -> None:
    """Parse and apply ``document`` to :data:`STATE`: a :class:`LocalizationUpdateError` or a
    result with finite numbers, and :data:`STATE` as it was either way."""
    try:
        new_state, result = update(STATE, parse_update(document), MAP_TAGS)
    except LocalizationUpdateError as err:
        refusal = str(err)
        assert refusal, "a refusal must say why"
    else:
        for pose in (result.map_T_phone, result.map_T_session):
            assert pose is None or np.isfinite(pose).all()
        assert new_state.to_json() is not None
    assert json.dumps(STATE.to_json(), sort_keys=True) == STATE_JSON


def test_the_unchanged_document_localizes() -> None:
    _, result = update(STATE, parse_update(NEXT_DOCUMENT), MAP_TAGS)
    assert result.status == "localized"
    assert len(PATHS) > 50


@settings(max_examples=200, deadline=None)
@given(json_values)
def test_arbitrary_json_raises_only_update_errors(value: Any) -> None:
    accepts_or_refuses_cleanly(value)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.sampled_from(PATHS), json_values)
def test_any_value_replaced_by_any_json_raises_only_update_errors(
    path: tuple[Any, ...], value: Any
) -> None:
    accepts_or_refuses_cleanly(replaced(NEXT_DOCUMENT, path, value))


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.sampled_from(PATHS), st.floats() | st.integers())
def test_any_value_replaced_by_any_number_raises_only_update_errors(
    path: tuple[Any, ...], value: float
) -> None:
    accepts_or_refuses_cleanly(replaced(NEXT_DOCUMENT, path, value))
