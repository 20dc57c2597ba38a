"""Issue 40 (hardening round 4): what an outside probe broke, on SQLite and PostgreSQL.

1. A malformed ``If-Match`` (5,000 digits, a digit that is not ASCII) was a 500.
2. An id between 2^31 and 2^63 - 1 was a 500 on PostgreSQL (its columns are 32-bit) and a 404 on
   SQLite. The rule now: an id is 1…2147483647; any other number names nothing, and gets the
   answer of an id that does not exist, on every route, wherever the id is (path, query, body).
   :func:`id_cases` walks the app's OpenAPI, so a new route is covered without a line here.
3. An upload into an existing map (``into_map``) retried with its ``Idempotency-Key`` answered
   another job than the first time.
4. An error echoed 1e308 as 309 digits; some endpoints answered malformed JSON with no JSON.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import pytest

from app.config import Settings
from app.main import create_app
from app.web.errors import MAX_DIGITS_SHOWN, MAX_ERROR_TEXT, error_response
from tests.conftest import fresh_database_url
from tests.service.api_support import (
    ADMIN,
    JSON,
    ONETAG,
    Api,
    run_next_job,
    running_api,
    session_variant,
)

pytestmark = pytest.mark.db

#: The largest id (the columns are 32-bit INTEGER), never used by a fresh database.
MAX_ID = 2**31 - 1
#: Ids beyond it: the first that overflows, the largest 64-bit one, and one beyond any integer
#: type a driver has.
OUT_OF_RANGE = [2**31, 2**63 - 1, 10**30]

#: Query parameters that name a row by its id or number (besides every ``*_id``).
ID_QUERY_PARAMETERS = {"into_map", "version", "after", "before", "cursor"}
#: ``*_id`` parameters that name no row: an AprilTag's number (an upload refuses one beyond
#: 2^31 - 1, so a filter by a larger one finds nothing, the same as any unknown tag).
NOT_ROW_IDS = {"tag_id"}


def _openapi() -> dict[str, Any]:
    app = create_app(Settings(database_url="sqlite://", admin_key="x" * 32))
    spec: dict[str, Any] = app.openapi()
    return spec


def _schema_of(spec: dict[str, Any], schema: dict[str, Any]) -> dict[str, Any]:
    """``schema`` with a reference resolved (an optional body's ``anyOf: [ref, null]`` too)."""
    for option in schema.get("anyOf", []):
        if "$ref" in option:
            return _schema_of(spec, option)
    if "$ref" in schema:
        resolved: dict[str, Any] = spec["components"]["schemas"][schema["$ref"].split("/")[-1]]
        return resolved
    return schema


def _is_integer(schema: dict[str, Any]) -> bool:
    options = schema.get("anyOf", [schema])
    return any(option.get("type") == "integer" for option in options)


def _is_id_list(schema: dict[str, Any]) -> bool:
    options = schema.get("anyOf", [schema])
    return any(
        option.get("type") == "array" and option.get("items", {}).get("type") == "integer"
        for option in options
    )


@dataclass(frozen=True)
class IdCase:
    """One id parameter of one route: ``where`` is path, query, body or body-list."""

    method: str
    path: str
    where: str
    name: str
    body: Any

    def __str__(self) -> str:
        return f"{self.method} {self.path} {self.where}:{self.name}"


def _example_body(operation: dict[str, Any]) -> Any:
    content = operation.get("requestBody", {}).get("content", {}).get("application/json")
    if content is None:
        return None
    if "example" in content:
        return content["example"]
    for example in content.get("examples", {}).values():
        if "value" in example:
            return example["value"]
    return {}


def id_cases() -> list[IdCase]:
    """Every id parameter of every route of the OpenAPI: integer path parameters, integer query
    parameters that name a row, and integer (or integer list) fields of a JSON body named
    ``*_id`` or ``*_ids``."""
    spec = _openapi()
    cases = []
    for path, operations in spec["paths"].items():
        for method, operation in operations.items():
            body = _example_body(operation)
            for parameter in operation.get("parameters", []):
                name, where = parameter["name"], parameter["in"]
                if not _is_integer(parameter["schema"]):
                    continue
                if where == "path" or (
                    where == "query"
                    and (name.endswith("_id") or name in ID_QUERY_PARAMETERS)
                    and name not in NOT_ROW_IDS
                ):
                    cases.append(IdCase(method.upper(), path, where, name, body))
            content = operation.get("requestBody", {}).get("content", {}).get("application/json")
            if content is None:
                continue
            schema = _schema_of(spec, content.get("schema", {}))
            for name, field in schema.get("properties", {}).items():
                if name.endswith("_id") and _is_integer(field):
                    cases.append(IdCase(method.upper(), path, "body", name, body))
                elif name.endswith("_ids") and _is_id_list(field):
                    cases.append(IdCase(method.upper(), path, "body-list", name, body))
    return cases


ID_CASES = id_cases()


@dataclass
class Built:
    """An app with one built map (of the onetag session) and the ids of what it holds."""

    api: Api
    ids: dict[str, int]


@pytest.fixture(
    scope="module",
    params=[pytest.param(b, marks=pytest.mark.db) for b in ("sqlite", "postgresql")],
)
def built(
    request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory
) -> Iterator[Built]:
    urls = fresh_database_url(request.param, request, tmp_path_factory.mktemp("round4"))
    url = next(urls)
    try:
        with running_api(url) as api:
            created = api.uploaded(ONETAG)
            assert run_next_job(api.db, path_graph=True) == created["job_id"]
            key = api.client.post(
                "/v1/keys", json={"name": "probe", "role": "device"}, headers=ADMIN
            )
            assert key.status_code == 201, key.text
            yield Built(
                api=api,
                ids={
                    "map_id": created["map_id"],
                    "session_id": created["session_id"],
                    "job_id": created["job_id"],
                    "key_id": key.json()["id"],
                    "number": 1,
                },
            )
    finally:
        for _ in urls:
            pass


def _request(built: Built, case: IdCase, value: int) -> Any:
    """``case``'s route with ``value`` as its id and the fixture's real rows as its other ids
    (an id the database has not got, for kinds it has none of)."""
    ids = {**built.ids, case.name: value} if case.where == "path" else dict(built.ids)
    path = case.path
    for name in [part[1:-1] for part in path.split("/") if part.startswith("{")]:
        path = path.replace("{" + name + "}", str(ids.get(name, MAX_ID)))
    params: dict[str, Any] = {}
    body = case.body
    content: bytes | None = None
    headers = dict(ADMIN)
    if case.where == "query":
        params[case.name] = value
    if case.path == "/v1/sessions" and case.method == "POST":
        content = ONETAG.read_bytes()  # an upload the id alone refuses
        headers.update(JSON)
    elif body is not None:
        body = dict(body) if isinstance(body, dict) else body
        if case.where == "body":
            body[case.name] = value
        elif case.where == "body-list":
            body[case.name] = [value]
        content = json.dumps(body).encode()
        headers.update(JSON)
    return built.api.client.request(
        case.method, path, params=params, content=content, headers=headers
    )


def _answer(response: Any) -> Any:
    """What must be the same for an id out of range and one that does not exist: the status,
    and the error's code and field (its detail names the number), or the whole 2xx body."""
    assert response.headers["content-type"].startswith("application/json"), response.text
    document = response.json()
    if response.status_code >= 300:
        return response.status_code, document["code"], document["field"]
    return response.status_code, document


@pytest.mark.parametrize("value", OUT_OF_RANGE, ids=["2^31", "2^63-1", "10^30"])
@pytest.mark.parametrize("case", ID_CASES, ids=str)
def test_an_id_out_of_range_is_answered_as_one_that_does_not_exist(
    built: Built, case: IdCase, value: int
) -> None:
    out_of_range = _request(built, case, value)
    assert out_of_range.status_code < 500, out_of_range.text
    assert _answer(out_of_range) == _answer(_request(built, case, MAX_ID))
    if case.where == "path" and case.method == "GET":
        assert out_of_range.status_code == 404, out_of_range.text


def test_the_walk_finds_the_ids_of_every_kind() -> None:
    found = {(case.where, case.name) for case in ID_CASES}
    assert {
        ("path", "map_id"),
        ("path", "session_id"),
        ("path", "job_id"),
        ("path", "key_id"),
        ("path", "sweep_id"),
        ("path", "edit_id"),
        ("path", "localization_id"),
        ("path", "number"),
        ("query", "map_id"),
        ("query", "into_map"),
        ("body", "map_id"),
        ("body", "session_id"),
        ("body-list", "session_ids"),
    } <= found
    assert len({(case.method, case.path) for case in ID_CASES}) >= 35


def test_every_id_parameter_documents_the_rule() -> None:
    spec = _openapi()
    documented = {IdCase(c.method, c.path, c.where, c.name, None) for c in ID_CASES}
    undocumented = []
    for path, operations in spec["paths"].items():
        for method, operation in operations.items():
            for parameter in operation.get("parameters", []):
                case = IdCase(method.upper(), path, parameter["in"], parameter["name"], None)
                if case in documented and "2147483647" not in parameter.get("description", ""):
                    undocumented.append(str(case))
    assert undocumented == []


# --------------------------------------------------------------------------- malformed JSON

#: Bodies that are no JSON document (or not whole): cut short, a stray comma, a bare word,
#: bytes that are not UTF-8, and nothing at all.
MALFORMED_JSON = [b'{"op": "quiet", "at": [1, 2', b'{"a": 1,}', b"quiet", b"\xff\xfe{", b""]


def json_body_routes() -> list[tuple[str, str]]:
    """Every (method, path) of the OpenAPI whose body is JSON (POST, PUT, PATCH)."""
    spec = _openapi()
    routes = []
    for path, operations in spec["paths"].items():
        for method, operation in operations.items():
            if method not in {"post", "put", "patch"}:
                continue
            content = operation.get("requestBody", {}).get("content", {})
            if "application/json" in content:
                routes.append((method.upper(), path))
    return routes


JSON_BODY_ROUTES = json_body_routes()


@pytest.mark.parametrize("body", MALFORMED_JSON, ids=["cut", "comma", "word", "not-utf8", "empty"])
@pytest.mark.parametrize(
    ("method", "path"), JSON_BODY_ROUTES, ids=[" ".join(r) for r in JSON_BODY_ROUTES]
)
def test_malformed_json_is_a_json_4xx_naming_the_problem(
    built: Built, method: str, path: str, body: bytes
) -> None:
    for name in [part[1:-1] for part in path.split("/") if part.startswith("{")]:
        path = path.replace("{" + name + "}", str(built.ids.get(name, MAX_ID)))
    if path.startswith("/v1/localizations/"):  # a navigation session that exists
        started = built.api.client.post(
            f"/v1/maps/{built.ids['map_id']}/localizations", headers=ADMIN
        )
        path = path.replace(str(MAX_ID), str(started.json()["id"]))
    response = built.api.client.request(method, path, content=body, headers={**ADMIN, **JSON})
    if not body and path.endswith("/rebuild"):  # its body is optional: none is a rebuild
        assert response.status_code == 202, response.text
        return
    assert 400 <= response.status_code < 500, response.text
    assert response.headers["content-type"] == "application/json", response.text
    document = response.json()
    assert set(document) == {"detail", "code", "field"}
    if path == "/v1/sessions":  # the upload reads its own body: the session format's errors
        assert document["code"] in {"invalid_session", "invalid_json"}, document
        assert document["detail"].startswith(("upload", "the body")), document
    elif not body:
        assert (response.status_code, document["field"]) == (422, "body"), document
        assert "body is missing" in document["detail"]
    else:
        assert (response.status_code, document["code"]) == (400, "invalid_json"), document
        assert document["detail"].startswith("the body is not valid JSON: "), document
        assert document["field"] == "body"


def test_the_malformed_json_walk_covers_the_json_routes() -> None:
    assert ("POST", "/v1/maps/{map_id}/corridor-edits") in JSON_BODY_ROUTES
    assert ("POST", "/v1/sessions") in JSON_BODY_ROUTES
    assert ("PATCH", "/v1/maps/{map_id}") in JSON_BODY_ROUTES
    assert len(JSON_BODY_ROUTES) >= 10


# --------------------------------------------------------------------------- If-Match


@pytest.mark.parametrize(
    "if_match",
    [
        b'"edits-' + b"9" * 5000 + b'"',  # int() refuses more than 4,300 digits
        b'"edits-\xb2"',  # "²" (Latin-1, as Starlette reads a header): isdigit() but no int
        '"edits-١٢"'.encode(),  # Arabic-Indic digits, sent as UTF-8
        b'"edits-0000000000000000000000001"',
        b'"edits-"',
        b"edits-4, edits-5",
    ],
    ids=["5000-digits", "superscript-two", "arabic-indic", "too-long", "no-number", "a-list"],
)
def test_a_malformed_if_match_is_refused_naming_the_header(built: Built, if_match: bytes) -> None:
    map_id = built.ids["map_id"]
    headers: dict[str, Any] = {**ADMIN, **JSON, "If-Match": if_match}
    before = built.api.client.get(f"/v1/maps/{map_id}/corridor-edits", headers=ADMIN)
    assert before.status_code == 200, before.text
    add = built.api.client.post(
        f"/v1/maps/{map_id}/corridor-edits", json={"op": "quiet", "at": [0, 0, 0]}, headers=headers
    )
    delete = built.api.client.delete(f"/v1/maps/{map_id}/corridor-edits/1", headers=headers)
    for response in (add, delete):
        assert response.status_code == 400, response.text
        assert response.json()["code"] == "invalid_if_match"
        assert response.json()["field"] == "If-Match"
        assert len(response.json()["detail"]) < 200
    after = built.api.client.get(f"/v1/maps/{map_id}/corridor-edits", headers=ADMIN)
    assert after.headers["ETag"] == before.headers["ETag"]  # nothing changed


def test_a_well_formed_if_match_still_works(built: Built) -> None:
    map_id = built.ids["map_id"]
    etag = built.api.client.get(f"/v1/maps/{map_id}/corridor-edits", headers=ADMIN).headers["ETag"]
    revision = int(etag.strip('"').removeprefix("edits-"))
    stale = f'"edits-{revision + 10**17}"'  # 18 digits: well formed, not the edits' revision
    response = built.api.client.delete(
        f"/v1/maps/{map_id}/corridor-edits/1", headers={**ADMIN, "If-Match": stale}
    )
    assert response.status_code == 412, response.text
    assert response.json()["code"] == "edits_changed"
    for weak_or_bare in (f"W/{etag}", etag.strip('"')):
        response = built.api.client.delete(
            f"/v1/maps/{map_id}/corridor-edits/{MAX_ID}",
            headers={**ADMIN, "If-Match": weak_or_bare},
        )
        assert response.status_code == 404, response.text  # past If-Match: no such edit


# --------------------------------------------------------------------------- numbers echoed


@pytest.mark.parametrize(
    ("method", "path", "body"),
    [
        ("POST", "/v1/maps/{map_id}/corridor-edits", {"op": "quiet", "at": [1e308, 0, 0]}),
        ("POST", "/v1/maps/{map_id}/merge", {"map_id": 1e308}),
        ("GET", "/v1/maps/" + "9" * 400, None),
        ("GET", "/v1/maps/{map_id}/app-map?version=" + "9" * 400, None),
    ],
    ids=["edit-point", "merge-id", "path-id", "version"],
)
def test_an_error_shows_a_huge_number_compactly(
    built: Built, method: str, path: str, body: Any
) -> None:
    path = path.replace("{map_id}", str(built.ids["map_id"]))
    response = built.api.client.request(method, path, json=body, headers=ADMIN)
    assert 400 <= response.status_code < 500, response.text
    detail = response.json()["detail"]
    assert "e+308" in detail or "e+399" in detail or "e+400" in detail, detail
    digit_runs = "".join(c if c.isdigit() else " " for c in detail).split()
    assert max(len(run) for run in digit_runs) <= MAX_DIGITS_SHOWN
    assert len(detail) < 400


def test_an_error_keeps_a_64_bit_number_whole_and_its_text_bounded() -> None:
    for whole in (2**64, 2**70, 10**29):
        response = error_response(404, "not_found", f"map {whole} not found")
        assert json.loads(response.body)["detail"] == f"map {whole} not found"
    response = error_response(404, "not_found", f"map {10**30} not found")
    assert json.loads(response.body)["detail"] == "map 1e+30 not found"
    response = error_response(422, "validation_error", "x" * 10_000, field="y" * 10_000)
    document = json.loads(response.body)
    assert len(document["detail"]) == len(document["field"]) == MAX_ERROR_TEXT


# --------------------------------------------------------------------------- idempotent into_map


def _into(api: Api, map_id: int, body: bytes, key: str) -> Any:
    return api.client.post(
        f"/v1/sessions?into_map={map_id}",
        content=body,
        headers={**ADMIN, **JSON, "Idempotency-Key": key},
    )


def _ids(response: Any) -> tuple[int, int, int]:
    assert response.status_code == 202, response.text
    document = response.json()
    return document["session_id"], document["map_id"], document["job_id"]


def test_an_upload_into_a_map_replays_its_first_answer(database_url: str) -> None:
    """The map's build is a new job (the map's first build had finished), then later changes
    queue builds listing the session too: the replay answers the first build, every time."""
    with running_api(database_url) as api:
        first = api.uploaded(ONETAG)
        assert run_next_job(api.db) == first["job_id"]
        body = session_variant(ONETAG, map_id="second walk")
        answer = _into(api, first["map_id"], body, "walk-2")
        session_id, map_id, job_id = _ids(answer)
        assert map_id == first["map_id"]
        assert answer.headers["Location"] == f"/v1/jobs/{job_id}"

        replay = _into(api, first["map_id"], body, "walk-2")
        assert _ids(replay) == (session_id, map_id, job_id)
        assert replay.headers["Idempotent-Replayed"] == "true"
        assert replay.headers["Location"] == f"/v1/jobs/{job_id}"
        assert replay.json() == answer.json()

        # later builds of the map list the session too; the replay still answers the first
        rebuild = api.client.post(f"/v1/maps/{map_id}/rebuild", headers=ADMIN)
        assert rebuild.status_code == 202, rebuild.text
        assert rebuild.json()["job_id"] == job_id  # still queued: it absorbed the rebuild
        canceled = api.client.post(f"/v1/jobs/{job_id}/cancel", headers=ADMIN)
        assert canceled.status_code == 200, canceled.text
        rebuild = api.client.post(f"/v1/maps/{map_id}/rebuild", headers=ADMIN)
        assert rebuild.json()["job_id"] > job_id
        third = _into(api, map_id, session_variant(ONETAG, map_id="third walk"), "walk-3")
        assert _ids(third)[2] == rebuild.json()["job_id"]  # absorbed by the queued rebuild
        assert _ids(_into(api, first["map_id"], body, "walk-2")) == (session_id, map_id, job_id)

        # the same key with another body is refused, as a plain upload's replay is
        sessions_before = api.client.get("/v1/sessions", headers=ADMIN).json()["count"]
        other = _into(api, first["map_id"], session_variant(ONETAG, map_id="other"), "walk-2")
        assert other.status_code == 409, other.text
        assert other.json()["code"] == "idempotency_conflict"
        plain = api.upload(session_variant(ONETAG, map_id="other"), idempotency_key="walk-2")
        assert (plain.status_code, plain.json()["code"]) == (409, "idempotency_conflict")
        assert api.client.get("/v1/sessions", headers=ADMIN).json()["count"] == sessions_before


def test_an_upload_absorbed_by_a_queued_build_replays_that_build(database_url: str) -> None:
    """The map's first build is still queued when the walk is uploaded into it: that build
    absorbs the upload, and the replay answers it (not the walk's own, canceled build)."""
    with running_api(database_url) as api:
        first = api.uploaded(ONETAG)  # its build stays queued
        body = session_variant(ONETAG, map_id="second walk")
        session_id, map_id, job_id = _ids(_into(api, first["map_id"], body, "walk-2"))
        assert (map_id, job_id) == (first["map_id"], first["job_id"])
        assert _ids(_into(api, first["map_id"], body, "walk-2")) == (session_id, map_id, job_id)
        # a replay without into_map is the same upload by the same key: the same answer
        replay = api.upload(body, idempotency_key="walk-2")
        assert _ids(replay) == (session_id, map_id, job_id)


def test_the_corridor_editor_answers_malformed_json_with_json(database_url: str) -> None:
    """The dashboard's corridor editor talks JSON to its script: a malformed body is a JSON 400
    there too, not an error page."""
    from tests.service.admin_support import csrf_token, logged_in

    with running_api(database_url) as api:
        created = api.uploaded(ONETAG)
        run_next_job(api.db, path_graph=True)
        logged_in(api.client)
        token = csrf_token(api.client)
        for body in MALFORMED_JSON[:4]:
            response = api.client.post(
                f"/admin/maps/{created['map_id']}/editor/edits",
                content=body,
                headers={**JSON, "X-CSRF-Token": token},
            )
            assert response.status_code == 400, response.text
            assert response.headers["content-type"] == "application/json", response.text
            assert response.json()["code"] == "invalid_json"
        refused = api.client.post(
            f"/admin/maps/{created['map_id']}/editor/edits",
            json={"op": "quiet", "at": [0, 0, 0]},
            headers={"X-CSRF-Token": "wrong"},
        )
        assert refused.status_code == 403, refused.text
        assert refused.json()["code"] == "forbidden"


# --------------------------------------------------------------------------- Content-Length


def _asgi_post(app: Any, path: str, content_length: bytes, body: bytes) -> tuple[int, Any]:
    """POST ``body`` to ``app`` with this raw Content-Length (an HTTP client always sends a
    true one, so straight to the ASGI app, as a server that passed the header on would)."""
    import asyncio

    scope = {
        "type": "http",
        "asgi": {"version": "3.0"},
        "http_version": "1.1",
        "method": "POST",
        "scheme": "http",
        "path": path,
        "raw_path": path.encode(),
        "query_string": b"",
        "root_path": "",
        "headers": [
            (b"host", b"testserver"),
            (b"content-type", b"application/json"),
            (b"authorization", ADMIN["Authorization"].encode()),
            (b"content-length", content_length),
        ],
        "client": ("127.0.0.1", 1234),
        "server": ("testserver", 80),
    }
    sent = [{"type": "http.request", "body": body, "more_body": False}]
    answer: dict[str, Any] = {"body": b""}

    async def receive() -> dict[str, Any]:
        return sent.pop(0) if sent else {"type": "http.disconnect"}

    async def send(message: dict[str, Any]) -> None:
        if message["type"] == "http.response.start":
            answer["status"] = message["status"]
        elif message["type"] == "http.response.body":
            answer["body"] += message.get("body", b"")

    asyncio.run(app(scope, receive, send))
    return answer["status"], json.loads(answer["body"])


@pytest.mark.parametrize(
    "content_length",
    [b"9" * 5000, b"\xb2", "١٢".encode(), b"12abc"],
    ids=["5000-digits", "superscript-two", "arabic-indic", "not-a-number"],
)
def test_a_malformed_content_length_is_no_500(built: Built, content_length: bytes) -> None:
    body = b'{"name": "probe"}'
    for path in ("/v1/sessions", "/v1/keys"):
        status, document = _asgi_post(built.api.app, path, content_length, body)
        assert status in {400, 413, 422}, (path, document)
        assert set(document) == {"detail", "code", "field"}
        assert len(document["detail"]) < 200


# --------------------------------------------------------------------------- cursors


@pytest.mark.parametrize("after_id", [*OUT_OF_RANGE[:2], 10**17], ids=["2^31", "2^63-1", "10^17"])
def test_a_cursor_past_any_id_is_answered_as_one_past_the_last_edit(
    built: Built, after_id: int
) -> None:
    """A cursor (opaque, but it carries an id) naming an id out of range gets the answer of
    one naming an id that does not exist, or the 422 invalid_cursor of a cursor the API did not
    give: never a 500 on PostgreSQL."""
    from app.api.schemas.corridor_edits import edits_cursor

    url = f"/v1/maps/{built.ids['map_id']}/corridor-edits"
    out_of_range = built.api.client.get(
        url, params={"cursor": edits_cursor(after_id)}, headers=ADMIN
    )
    past_the_last = built.api.client.get(
        url, params={"cursor": edits_cursor(MAX_ID)}, headers=ADMIN
    )
    assert past_the_last.status_code == 200, past_the_last.text
    if out_of_range.status_code == 200:
        assert out_of_range.json() == past_the_last.json()
    else:
        assert out_of_range.status_code == 422, out_of_range.text
        assert (out_of_range.json()["code"], out_of_range.json()["field"]) == (
            "invalid_cursor",
            "cursor",
        )
