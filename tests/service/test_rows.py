"""Rows to the storage layer's dataclasses by field name (``app.storage.rows``)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import pytest

from app.storage.keys import KeyInfo, create_key
from app.storage.orm import JobState, Role
from app.storage.rows import info_from_row


@dataclass(frozen=True, slots=True, kw_only=True)
class _Info:
    id: int
    state: JobState
    role: Role | None
    params: dict[str, Any]
    names: list[str] = field(default_factory=list)
    extra: str = ""


class _Row:
    def __init__(self, **values: Any) -> None:
        self.__dict__.update(values)


def test_fields_come_by_name_converted_to_their_types():
    params = {"a": 1}
    row = _Row(id=3, state="running", role="admin", params=params, names=("x",), extra="e")
    info = info_from_row(_Info, row)
    assert info == _Info(
        id=3, state=JobState.RUNNING, role=Role.ADMIN, params={"a": 1}, names=["x"], extra="e"
    )
    assert info.params is not params  # a copy: the row's JSON value is not shared


def test_none_stays_none_and_given_values_win():
    row = _Row(id=3, state="queued", role=None, params={}, names=[], extra="row's")
    info = info_from_row(_Info, row, extra="given")
    assert info.role is None
    assert info.extra == "given"


def test_a_field_the_row_lacks_is_an_error_naming_it():
    with pytest.raises(AttributeError, match="names"):
        info_from_row(_Info, _Row(id=1, state="queued", role=None, params={}, extra=""))


@pytest.mark.db
def test_real_rows_of_both_databases(db):
    with db.transaction() as db_session:
        info, _secret = create_key(db_session, name="phone", role=Role.DEVICE)
    assert isinstance(info, KeyInfo)
    assert info.role is Role.DEVICE
    assert info.name == "phone"
