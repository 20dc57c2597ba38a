"""The admin dashboard's pages and forms through the app (TestClient): what each page shows, what
each form changes, and the pages for bad input (4xx with a readable message, never a 500).
SQLite and PostgreSQL."""

from __future__ import annotations

import json
import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from admin_support import assert_error_pages, csrf_token, logged_in
from api_support import (
    ADMIN,
    OCCAM,
    ONETAG,
    SESSIONS_DIR,
    Api,
    bearer,
    run_next_job,
    running_api,
    session_variant,
)

from app.admin.paging import Page
from app.config import Settings
from app.domain.mapping.params import HUBER_K
from app.storage import queue
from app.storage.orm import JobState, Role

pytestmark = pytest.mark.db


@pytest.fixture
def api(database_url: str, tmp_path: Path) -> Iterator[Api]:
    with running_api(database_url, data_dir=tmp_path) as running:
        logged_in(running.client)
        yield running


@pytest.fixture
def upload(api: Api) -> dict[str, Any]:
    return api.uploaded(ONETAG)


#: A small real session (132 poses, tags 302–305): quick to build.
SMALL = SESSIONS_DIR / "pgt_tester3.json"


@pytest.fixture
def built(api: Api) -> dict[str, Any]:
    """A small real session uploaded and built, with its path graph."""
    accepted = api.uploaded(SMALL)
    assert run_next_job(api.db, path_graph=True) == accepted["job_id"]
    return accepted


def post(api: Api, path: str, data: dict[str, str] | None = None, *, token_from: str = "/admin"):  # type: ignore[no-untyped-def]
    """A form post with the CSRF token, not followed."""
    form = {"csrf_token": csrf_token(api.client, token_from), **(data or {})}
    return api.client.post(path, data=form, follow_redirects=False)


def figure_of(page_html: str) -> dict[str, Any]:
    match = re.search(r'<script type="application/json" id="map-figure">(.*?)</script>', page_html)
    assert match is not None
    figure: dict[str, Any] = json.loads(match.group(1))
    return figure


# --------------------------------------------------------------------------- overview


def test_overview_shows_the_queue_workers_recent_jobs_and_failures(
    api: Api, upload: dict[str, Any]
) -> None:
    lease = queue.claim(api.db, worker_id="w-1", lease_s=60)
    assert lease is not None
    queue.fail(api.db, lease, error="boom: no tags", permanent=True, backoff_s=0, log_tail="")
    api.uploaded(session_variant(ONETAG, map_id="second"))
    queue.register_worker(api.db, worker_id="w-2", hostname="host-a", pid=42)

    page = api.client.get("/admin")
    assert page.status_code == 200
    assert re.search(r'id="queue-depth">1<', page.text)
    assert 'data-job-state="failed"' in page.text
    assert "boom: no tags" in page.text
    assert "host-a (pid 42)" in page.text
    assert 'data-live-url="/admin/live/overview"' in page.text
    live = api.client.get("/admin/live/overview")
    assert live.status_code == 200
    assert "<html" not in live.text
    assert f'data-job-id="{upload["job_id"]}"' in live.text


# --------------------------------------------------------------------------- sessions


def test_sessions_are_searched_by_map_name(api: Api) -> None:
    api.uploaded(session_variant(ONETAG, map_id="Lobby east"))
    api.uploaded(session_variant(ONETAG, map_id="lab_100%"))
    page = api.client.get("/admin/sessions", params={"q": "LOBBY"})
    assert page.status_code == 200
    assert "Lobby east" in page.text
    assert "lab_100%" not in page.text
    literal = api.client.get("/admin/sessions", params={"q": "_100%"})
    assert "lab_100%" in literal.text
    assert "Lobby east" not in literal.text
    assert "No session matches" in api.client.get("/admin/sessions?q=zzz").text


def test_sessions_name_their_uploader_by_the_keys_name(api: Api) -> None:
    """Not "key:1": the key's name and id, the environment's admin key as such, an imported
    owner as stored; a key's name is text of the operator's, shown escaped."""
    key_id, secret = api.create_key(Role.DEVICE, name="lab iPhone <12>")
    by_device = api.uploaded(session_variant(ONETAG, map_id="by device"), auth=bearer(secret))
    by_admin = api.uploaded(session_variant(ONETAG, map_id="by admin"))
    page = api.client.get("/admin/sessions")
    assert page.status_code == 200
    assert f"key:{key_id}" not in page.text
    assert f"lab iPhone &lt;12&gt; (key {key_id})" in page.text
    assert "env-admin" not in page.text
    assert "the admin key from INVISIBLE_MAP_ADMIN_KEY" in page.text
    detail = api.client.get(f"/admin/sessions/{by_device['session_id']}")
    assert f"by lab iPhone &lt;12&gt; (key {key_id})" in detail.text
    admin_detail = api.client.get(f"/admin/sessions/{by_admin['session_id']}")
    assert "by the admin key from INVISIBLE_MAP_ADMIN_KEY" in admin_detail.text


def test_pages_link_to_their_neighbours() -> None:
    page = Page.of(number=2, size=25, total=60, url="/admin/sessions", query={"q": "lab"})
    assert (page.offset, page.first, page.last) == (25, 26, 50)
    assert page.previous_url == "/admin/sessions?q=lab&page=1"
    assert page.next_url == "/admin/sessions?q=lab&page=3"
    last = Page.of(number=3, size=25, total=60, url="/admin/maps")
    assert last.next_url is None
    assert (last.first, last.last) == (51, 60)


def test_session_page_shows_statistics_detections_per_tag_and_jobs(
    api: Api, upload: dict[str, Any]
) -> None:
    page = api.client.get(f"/admin/sessions/{upload['session_id']}")
    assert page.status_code == 200
    for text in ("Poses", "Distance walked", "Duration", "Detections per tag"):
        assert text in page.text
    detail = api.client.get(f"/v1/sessions/{upload['session_id']}", headers=ADMIN).json()
    rows = re.findall(
        r'<tr><th scope="row">(\d+)</th><td>(\d+)</td></tr>',
        page.text.split('id="detections-per-tag"')[1],
    )
    assert sum(int(count) for _, count in rows) == detail["statistics"]["detection_count"]
    assert f'href="/admin/jobs/{upload["job_id"]}"' in page.text


def test_the_raw_upload_downloads_byte_for_byte(api: Api, upload: dict[str, Any]) -> None:
    response = api.client.get(f"/admin/sessions/{upload['session_id']}/raw")
    assert response.status_code == 200
    assert response.content == ONETAG.read_bytes()
    assert "attachment" in response.headers["content-disposition"]


# --------------------------------------------------------------------------- jobs


def test_cancel_then_retry_a_job_from_its_page(api: Api, upload: dict[str, Any]) -> None:
    job_id = upload["job_id"]
    assert f"Cancel job {job_id}" in api.client.get(f"/admin/jobs/{job_id}").text
    canceled = post(api, f"/admin/jobs/{job_id}/cancel")
    assert canceled.status_code == 303
    assert canceled.headers["location"] == f"/admin/jobs/{job_id}"
    page = api.client.get(f"/admin/jobs/{job_id}")
    assert f"Job {job_id} canceled." in page.text  # the flash message
    assert f"Retry job {job_id}" in page.text

    again = post(api, f"/admin/jobs/{job_id}/cancel")
    assert again.status_code == 409
    assert f"Job {job_id} is canceled: cannot cancel it." in again.text

    assert post(api, f"/admin/jobs/{job_id}/retry").status_code == 303
    with api.db.read() as db_session:
        assert queue.get_job(db_session, job_id).state is JobState.QUEUED


def test_a_jobs_page_survives_its_maps_deletion_and_says_so(
    api: Api, upload: dict[str, Any]
) -> None:
    assert api.client.delete(f"/v1/maps/{upload['map_id']}", headers=ADMIN).status_code == 204
    page = api.client.get(f"/admin/jobs/{upload['job_id']}")
    assert page.status_code == 200
    assert re.search(r'id="job-map">deleted \(the log says which\)<', page.text)
    assert f"map {upload['map_id']} deleted; this job is kept" in page.text
    assert 'data-job-state="canceled"' in page.text  # it was queued: the delete canceled it
    assert f"Retry job {upload['job_id']}" not in page.text  # no map to build any more
    live = api.client.get(f"/admin/live/jobs/{upload['job_id']}")
    assert live.status_code == 200
    assert "deleted (the log says which)" in live.text
    listed = api.client.get("/admin/jobs")
    assert f'href="/admin/jobs/{upload["job_id"]}"' in listed.text


def test_jobs_are_listed_by_state(api: Api, upload: dict[str, Any]) -> None:
    assert f'data-job-id="{upload["job_id"]}"' in api.client.get("/admin/jobs?state=queued").text
    assert (
        f'data-job-id="{upload["job_id"]}"' not in api.client.get("/admin/jobs?state=failed").text
    )
    bad = api.client.get("/admin/jobs?state=exploded")
    assert bad.status_code == 422
    assert "Invalid state: input should be" in bad.text


def test_the_job_fragment_shows_progress_and_log(api: Api, upload: dict[str, Any]) -> None:
    lease = queue.claim(api.db, worker_id="w-1", lease_s=60)
    assert lease is not None
    queue.report_progress(api.db, lease, progress=0.5, stage="optimize", log_tail="line one\n")
    live = api.client.get(f"/admin/live/jobs/{upload['job_id']}")
    assert 'value="0.5"' in live.text
    assert "optimize" in live.text
    assert "line one" in live.text


# --------------------------------------------------------------------------- maps


def test_a_map_without_a_version_says_so(api: Api, upload: dict[str, Any]) -> None:
    page = api.client.get(f"/admin/maps/{upload['map_id']}")
    assert page.status_code == 200
    assert "This map has no version yet" in page.text
    assert "map-figure" not in page.text


def test_the_map_page_has_the_plot_data_tables_versions_and_downloads(
    api: Api, built: dict[str, Any]
) -> None:
    map_id = built["map_id"]
    page = api.client.get(f"/admin/maps/{map_id}")
    assert page.status_code == 200
    figure = figure_of(page.text)
    current = api.client.get(f"/v1/maps/{map_id}", headers=ADMIN).json()["current_version"]
    assert figure["tag_count"] == current["tag_count"] == len(current["tags"])
    plotted = [tag["id"] for floor in figure["floors"] for tag in floor["tags"]]
    assert sorted(plotted) == sorted(tag["tag_id"] for tag in current["tags"])
    floor = figure["floors"][0]
    for layer in ("raw", "optimized", "walk"):
        assert floor[layer]["x"], layer
    assert page.text.count('class="tag-table"') == len(figure["floors"])
    assert "Version 1" in page.text
    # Where the shift metric is shown, which way optimizing usually moves it is said.
    assert 'id="shift-explained"' in page.text
    assert "usually lower" in page.text
    assert 'id="shift-explained"' in api.client.get("/admin/maps").text

    app_map = api.client.get(f"/admin/maps/{map_id}/app-map")
    assert app_map.json() == api.client.get(f"/v1/maps/{map_id}/app-map", headers=ADMIN).json()
    geojson = api.client.get(f"/admin/maps/{map_id}/geojson")
    assert geojson.json() == api.client.get(f"/v1/maps/{map_id}/geojson", headers=ADMIN).json()
    assert "attachment" in geojson.headers["content-disposition"]


def test_the_map_page_shows_the_ground_truth_metric_of_a_version_built_with_it(
    api: Api, data_dir: Path
) -> None:
    accepted = api.uploaded(OCCAM)
    truth = json.loads((data_dir / "ground_truth" / "occam_room_tape.json").read_text())
    rebuild = api.client.post(
        f"/v1/maps/{accepted['map_id']}/rebuild", headers=ADMIN, json={"ground_truth": truth}
    )
    assert rebuild.status_code == 202
    from workers.main import Worker

    worker = Worker(api.db, Settings(database_url="sqlite://", lease_s=60, heartbeat_s=5))
    while worker.run_once():
        pass
    page = api.client.get(f"/admin/maps/{accepted['map_id']}")
    assert page.status_code == 200
    metrics = api.client.get(f"/v1/maps/{accepted['map_id']}", headers=ADMIN).json()[
        "current_version"
    ]["metrics"]
    assert re.search(rf'id="gt-metric">{metrics["gt_metric_opt"]:.3g}<', page.text)
    assert f"Ground-truth metric, pre-optimized</dt><dd>{metrics['gt_metric_pre']:.3g}<" in (
        page.text
    )
    assert "8 tags; pre-optimized" in page.text


def test_rebuild_queues_a_job_with_the_changed_parameters_only(
    api: Api, built: dict[str, Any]
) -> None:
    map_id = built["map_id"]
    form = {"tag_position_var_m2": "1e-3", "huber_k": str(HUBER_K), "tag_sizes_m": ""}
    response = post(api, f"/admin/maps/{map_id}/rebuild", form)
    assert response.status_code == 303
    jobs = api.client.get(f"/v1/jobs?map_id={map_id}", headers=ADMIN).json()["data"]
    assert jobs[0]["params"] == {"tag_position_var_m2": 0.001}
    assert "queued as job" in api.client.get(f"/admin/maps/{map_id}").text


BAD_REBUILDS = [
    ("tag_position_var_m2", "-1", "tag_position_var_m2 must be &gt; 0"),
    ("max_iterations", "many", "parameter max_iterations: cannot use &#39;many&#39;"),
    ("max_view_angle_deg", "120", "max_view_angle_deg must be in (0, 90]"),
    ("compute_marginals", "perhaps", "not a boolean"),
]


def test_rebuild_with_bad_parameters_is_refused_on_the_page(
    api: Api, built: dict[str, Any]
) -> None:
    map_id = built["map_id"]
    for field, value, message in BAD_REBUILDS:
        response = post(api, f"/admin/maps/{map_id}/rebuild", {field: value})
        assert response.status_code == 422, field
        assert message in response.text
        assert re.search(rf'id="param-{field}"[^>]*value="{re.escape(value)}"', response.text)
        assert re.search(rf'id="param-{field}"[^>]*aria-invalid="true"', response.text, re.S)
    jobs = api.client.get(f"/v1/jobs?map_id={map_id}", headers=ADMIN).json()
    assert jobs["count"] == 1  # nothing queued


def test_delete_a_map(api: Api, built: dict[str, Any]) -> None:
    response = post(api, f"/admin/maps/{built['map_id']}/delete")
    assert response.status_code == 303
    assert api.client.get(f"/v1/maps/{built['map_id']}", headers=ADMIN).status_code == 404
    assert api.client.get(f"/admin/maps/{built['map_id']}").status_code == 404


# --------------------------------------------------------------------------- route tester


def test_the_route_tester_plans_and_draws_a_route(api: Api, built: dict[str, Any]) -> None:
    map_id = built["map_id"]
    empty = api.client.get(f"/admin/maps/{map_id}/route")
    assert empty.status_code == 200
    assert '<option value="tag:305"' in empty.text
    page = api.client.get(f"/admin/maps/{map_id}/route?from=tag:302&to=tag:305")
    assert page.status_code == 200
    assert "arrive at tag 305" in page.text
    assert any(floor["route"] for floor in figure_of(page.text)["floors"])
    clicked = api.client.get(f"/admin/maps/{map_id}/route?from=pos:1.0,0.15,2.0&to=tag:305")
    assert clicked.status_code == 200
    assert "The place clicked on the map (1.0,0.15,2.0)" in clicked.text


REFUSED_ROUTES = [
    ("from=tag:302&to=tag:999", 404, "tag 999"),
    ("from=tag:302&to=elsewhere", 422, "To: choose a tag, a point of interest"),
    ("from=pos:1,nan,2&to=tag:303", 422, "From: choose a tag"),
    ("from=poi:Nowhere&to=tag:303", 404, "Nowhere"),
]


def test_the_route_tester_explains_a_refused_route(api: Api, built: dict[str, Any]) -> None:
    for query, status, message in REFUSED_ROUTES:
        page = api.client.get(f"/admin/maps/{built['map_id']}/route?{query}")
        assert page.status_code == status, query
        assert message in page.text
        assert 'role="alert"' in page.text


def test_a_map_without_a_path_graph_cannot_route(api: Api, upload: dict[str, Any]) -> None:
    run_next_job(api.db)  # a version without a path graph
    page = api.client.get(f"/admin/maps/{upload['map_id']}/route")
    assert page.status_code == 409
    assert "has no path graph" in page.text


# --------------------------------------------------------------------------- keys


def test_a_created_key_is_shown_once_and_works(api: Api) -> None:
    response = post(
        api, "/admin/keys", {"name": "lab phone", "role": "device"}, token_from="/admin/keys"
    )
    assert response.status_code == 201
    secret = re.search(r'id="new-key" type="text" readonly value="([^"]+)"', response.text)
    assert secret is not None
    headers = {"Authorization": f"Bearer {secret.group(1)}"}
    assert api.client.get("/v1/info", headers=headers).json()["principal"]["role"] == "device"
    assert secret.group(1) not in api.client.get("/admin/keys").text


BAD_KEY_FORMS = [
    ({"name": "", "role": "device"}, "name: String should have at least 1 character"),
    ({"name": "x", "role": "root"}, "role: Input should be &#39;device&#39; or &#39;admin&#39;"),
    ({"name": "x", "role": "device", "expires_on": "2001-01-01"}, "expires_at is in the past"),
    ({"name": "x", "role": "device", "expires_on": "soon"}, "Expires on: not a date"),
]


def test_a_bad_key_form_is_refused_with_a_reason(api: Api) -> None:
    for form, message in BAD_KEY_FORMS:
        response = post(api, "/admin/keys", form, token_from="/admin/keys")
        assert response.status_code == 422, form
        assert message in response.text
    assert api.client.get("/v1/keys", headers=ADMIN).json()["count"] == 0


def test_revoke_a_key(api: Api) -> None:
    key_id, secret = api.create_key(name="old phone")
    response = post(api, f"/admin/keys/{key_id}/revoke", token_from="/admin/keys")
    assert response.status_code == 303
    assert "is revoked" in api.client.get("/admin/keys").text
    assert (
        api.client.get("/v1/info", headers={"Authorization": f"Bearer {secret}"}).status_code == 401
    )


# --------------------------------------------------------------------------- not found, bad ids


BAD_PATHS = [
    ("/admin/sessions/999", 404, "Session 999 not found."),
    ("/admin/sessions/999/raw", 404, "Session 999 not found."),
    ("/admin/jobs/999", 404, "Job 999 not found."),
    ("/admin/live/jobs/999", 404, "Job 999 not found."),
    ("/admin/maps/999", 404, "Map 999 not found."),
    ("/admin/maps/999/route", 404, "Map 999 not found."),
    ("/admin/maps/999/app-map", 404, "Map 999 not found."),
    ("/admin/maps/0", 404, "Map 0 not found."),
    (f"/admin/maps/{2**70}", 404, f"Map {2**70} not found."),
    ("/admin/maps/abc", 422, "Invalid map_id: input should be a valid integer"),
    ("/admin/sessions?page=0", 422, "Invalid page: input should be greater than"),
    ("/admin/nothing-here", 404, "Page /admin/nothing-here not found."),
    ("/admin/static/secrets.txt", 404, "File secrets.txt not found."),
]


def test_unknown_ids_and_bad_paths_are_pages_not_errors(api: Api) -> None:
    assert_error_pages(api.client, BAD_PATHS)


def test_forms_on_unknown_ids_are_404_pages(api: Api) -> None:
    for action in ("/admin/jobs/999/cancel", "/admin/maps/999/rebuild", "/admin/keys/999/revoke"):
        response = post(api, action)
        assert response.status_code == 404, action
        assert "not found" in response.text


def test_the_version_of_a_map_page_must_exist(api: Api, built: dict[str, Any]) -> None:
    response = api.client.get(f"/admin/maps/{built['map_id']}?version=7")
    assert response.status_code == 404
    assert f"Version 7 of map {built['map_id']} not found." in response.text


def test_static_files_are_served_from_the_app(api: Api) -> None:
    plotly = api.client.get("/admin/static/plotly.min.js")
    assert plotly.status_code == 200
    assert plotly.headers["content-type"].startswith("text/javascript")
    assert b"plotly.js" in plotly.content[:200]
    assert api.client.get("/admin/static/admin.js").status_code == 200


# --------------------------------------------------------------------------- picture and name

JPEG = b"\xff\xd8\xff\xe0" + b"\x10" * 300 + b"\xff\xd9"


def test_maps_list_and_page_show_the_picture_and_the_display_name(
    api: Api, upload: dict[str, Any]
) -> None:
    put = api.client.put(
        f"/v1/sessions/{upload['session_id']}/image",
        content=JPEG,
        headers={**ADMIN, "Content-Type": "image/jpeg"},
    )
    assert put.status_code == 200
    image_path = put.json()["image_url"].replace("/v1/", "/admin/")

    listing = api.client.get("/admin/maps").text
    assert f'src="{image_path}"' in listing
    page = api.client.get(f"/admin/maps/{upload['map_id']}").text
    assert 'id="map-picture"' in page
    assert 'id="rename-form"' in page
    picture = api.client.get(image_path)
    assert picture.status_code == 200
    assert picture.content == JPEG
    assert picture.headers["Cache-Control"].endswith("immutable")


def test_an_admin_renames_a_map_on_its_page(api: Api, upload: dict[str, Any]) -> None:
    map_id = upload["map_id"]
    response = post(api, f"/admin/maps/{map_id}/rename", {"display_name": " Lobby, ground floor "})
    assert response.status_code == 303
    assert api.client.get(f"/v1/maps/{map_id}", headers=ADMIN).json()["display_name"] == (
        "Lobby, ground floor"
    )
    assert (
        f"<h1>Map {map_id}: Lobby, ground floor</h1>"
        in api.client.get(f"/admin/maps/{map_id}").text
    )


@pytest.mark.parametrize(
    ("name", "message"), [("   ", "display_name is empty"), ("x" * 201, "longer than 200")]
)
def test_a_bad_name_is_refused_on_the_page(
    api: Api, upload: dict[str, Any], name: str, message: str
) -> None:
    map_id = upload["map_id"]
    before = api.client.get(f"/v1/maps/{map_id}", headers=ADMIN).json()["display_name"]
    response = post(api, f"/admin/maps/{map_id}/rename", {"display_name": name})
    assert response.status_code == 422
    assert message in response.text
    assert 'id="rename-error"' in response.text
    assert api.client.get(f"/v1/maps/{map_id}", headers=ADMIN).json()["display_name"] == before


def test_picture_and_rename_of_missing_maps_and_without_csrf(
    api: Api, upload: dict[str, Any]
) -> None:
    assert api.client.get(f"/admin/maps/{upload['map_id']}/image").status_code == 404
    assert api.client.get("/admin/maps/999999/image").status_code == 404
    assert post(api, "/admin/maps/999999/rename", {"display_name": "X"}).status_code == 404
    forged = api.client.post(
        f"/admin/maps/{upload['map_id']}/rename",
        data={"display_name": "X", "csrf_token": "forged"},
        follow_redirects=False,
    )
    assert forged.status_code == 403


# --------------------------------------------------------------------------- several sessions


def test_a_maps_sessions_merge_and_remove_from_the_dashboard(
    api: Api, built: dict[str, Any]
) -> None:
    from app.config import Settings
    from workers.main import Worker

    other = api.uploaded(SESSIONS_DIR / "desnat_straight_once.json")
    assert [s["map_id"] for s in other["shares_tags_with"]] == [built["map_id"]]
    assert run_next_job(api.db, path_graph=True) == other["job_id"]
    map_id = built["map_id"]
    page = api.client.get(f"/admin/maps/{map_id}")
    assert page.status_code == 200
    assert 'id="map-sessions"' in page.text
    assert "the only session" in page.text
    assert f"Merge map {other['map_id']} into map {map_id}" in page.text  # shares 302–305

    response = post(api, f"/admin/maps/{map_id}/merge", {"map_id": str(other["map_id"])})
    assert response.status_code == 303
    worker = Worker(api.db, Settings(database_url="sqlite://", lease_s=60, heartbeat_s=5))
    while worker.run_once():
        pass
    page = api.client.get(f"/admin/maps/{map_id}")
    assert f"Remove session {other['session_id']}" in page.text
    assert "2 sessions (below)" in page.text
    # each walk alone against the building map, and why it weighs what it does (issue 25)
    assert 'id="map-sessions-report"' in page.text
    assert "weighed by its own noise" in page.text or "down-weighted" in page.text
    floors = figure_of(page.text)["floors"]
    optimized = [floor["optimized"] for floor in floors]
    assert any(None in line["x"] for line in optimized if line)  # no line between two walks
    names = {s["name"] for floor in floors for s in floor["sessions"] or []}
    assert names == {f"Session {built['session_id']}", f"Session {other['session_id']}"}
    assert "The optimized trajectory of each session in its own colour" in page.text

    response = post(api, f"/admin/maps/{map_id}/merge", {"map_id": str(map_id)})
    assert response.status_code == 303  # refused, said in the flash message
    response = post(api, f"/admin/maps/{map_id}/sessions/{other['session_id']}/remove")
    assert response.status_code == 303
    while worker.run_once():
        pass
    page = api.client.get(f"/admin/maps/{map_id}")
    assert "the only session" in page.text
