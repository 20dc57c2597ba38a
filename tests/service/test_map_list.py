"""A page of maps is read in a fixed number of queries, and says of each map exactly what
reading that map alone says (issue 16: the list made three or four round trips per map)."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from api_support import ADMIN, OCCAM, ONETAG, Api, run_next_job, running_api
from sqlalchemy import event

from app.storage import maps


@pytest.fixture
def api(database_url: str) -> Iterator[Api]:
    with running_api(database_url) as running:
        yield running


def test_a_page_of_maps_is_each_map_as_read_alone_in_few_queries(api: Api) -> None:
    built = api.uploaded(ONETAG)
    assert run_next_job(api.db) == built["job_id"]
    rebuilt = api.client.post(built["map_url"] + "/rebuild", json={"params": {}}, headers=ADMIN)
    assert rebuilt.status_code == 202
    assert run_next_job(api.db) is not None  # two versions
    unbuilt = api.uploaded(OCCAM)  # no version yet
    jpeg = b"\xff\xd8\xff\xe0" + b"\x10" * 300 + b"\xff\xd9"
    put = api.client.put(
        f"/v1/sessions/{unbuilt['session_id']}/image",
        content=jpeg,
        headers={**ADMIN, "Content-Type": "image/jpeg"},
    )
    assert put.status_code == 200
    for k in range(3):
        api.uploaded(ONETAG, idempotency_key=f"again-{k}")

    statements: list[str] = []

    def record(*args: object) -> None:
        statements.append(str(args[2]))

    engines = {api.db.engine, getattr(api.db, "read_engine", api.db.engine)}
    for engine in engines:
        event.listen(engine, "before_cursor_execute", record)
    try:
        with api.db.read() as db_session:
            page, total = maps.list_maps(db_session, limit=50)
    finally:
        for engine in engines:
            event.remove(engine, "before_cursor_execute", record)
    queries = sum(1 for s in statements if s.lstrip().upper().startswith("SELECT"))
    assert total == len(page) == 5
    assert queries <= 6, statements  # count, page, versions, newest, pictures, sessions

    with api.db.read() as db_session:
        alone = [maps.get_map(db_session, info.id) for info in page]
    assert page == alone
    by_id = {info.id: info for info in page}
    assert by_id[built["map_id"]].version_count == 2
    assert by_id[built["map_id"]].current is not None
    assert by_id[built["map_id"]].current.number == 2
    assert by_id[unbuilt["map_id"]].current is None
    assert by_id[unbuilt["map_id"]].image_sha256 is not None
