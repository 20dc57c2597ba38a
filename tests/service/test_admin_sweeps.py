"""The dashboard's Sweeps pages through the app (TestClient): the login and CSRF checks, the start
form (and its refusals: 4xx on the page, the field at fault focused, never a 500), a sweep run by
an in-process worker to its results, the plots as PNG, apply and cancel. SQLite and PostgreSQL."""

from __future__ import annotations

import json
import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from admin_support import assert_error_pages, csrf_token, logged_in
from api_support import ADMIN, OCCAM, ONETAG, Api, run_next_job, running_api
from fastapi.testclient import TestClient
from sqlalchemy import select

from app.config import Settings
from app.domain.evaluation.tuning import TUNABLE_PARAMS
from app.storage.orm import Job, Sweep
from workers.main import Worker

pytestmark = pytest.mark.db

GROUND_TRUTH = OCCAM.parents[1] / "ground_truth" / "occam_room_tape.json"
#: 2 × 2 = 4 trials: a best, a heat map and a scatter, in a few seconds.
SMALL_SPACE = {
    "odom_linear_var_m2_per_s": ("1e-5", "1e-1", "2"),
    "tag_orientation_var_rad2": ("1e-4", "1", "2"),
}


@pytest.fixture
def api(database_url: str, tmp_path: Path) -> Iterator[Api]:
    with running_api(database_url, data_dir=tmp_path) as running:
        logged_in(running.client)
        yield running


@pytest.fixture
def map_id(api: Api) -> int:
    """A map (not built: a sweep only needs its session)."""
    return int(api.uploaded(ONETAG)["map_id"])


@pytest.fixture
def occam_map(api: Api) -> int:
    """A map of occam_room with its first version built."""
    created = api.uploaded(OCCAM)
    assert run_next_job(api.db) == created["job_id"]
    return int(created["map_id"])


def start_form(map_id: int | str, /, **changes: Any) -> dict[str, Any]:
    """The start form's fields as a browser sends them, with ``SMALL_SPACE`` checked."""
    form: dict[str, Any] = {
        "map_id": str(map_id),
        "method": "grid",
        "trials": "100",
        "objective": "shift",
        "ground_truth_text": "",
        "sweep": list(SMALL_SPACE),
    }
    for name in TUNABLE_PARAMS:
        low, high, num = SMALL_SPACE.get(name, ("1e-8", "1", "10"))
        form.update({f"{name}_low": low, f"{name}_high": high, f"{name}_num": num})
    form.update(changes)
    return form


def post(api: Api, path: str, data: dict[str, Any] | None = None, **kwargs: Any):  # type: ignore[no-untyped-def]
    """A form post with the CSRF token, not followed."""
    form = {"csrf_token": csrf_token(api.client, "/admin/sweeps"), **(data or {})}
    return api.client.post(path, data=form, follow_redirects=False, **kwargs)


def started(api: Api, map_id: int, **changes: Any) -> int:
    """Start a sweep through the form; its id."""
    response = post(api, "/admin/sweeps", start_form(map_id, **changes))
    assert response.status_code == 303, response.text
    match = re.fullmatch(r"/admin/sweeps/(\d+)", response.headers["location"])
    assert match is not None
    return int(match.group(1))


def checkbox(page_html: str, name: str) -> str:
    """The attributes of the start form's checkbox of ``name``, up to ``checked`` if it is."""
    match = re.search(rf'id="start-{name}" name="sweep" value="{name}"( checked)?', page_html)
    assert match is not None, name
    return match.group(0)


def drain(api: Api) -> int:
    """Run queued jobs in this process until none is left; how many ran."""
    ran, worker = 0, Worker(api.db, Settings(database_url="sqlite://", lease_s=60, heartbeat_s=5))
    while worker.run_once():
        ran += 1
    return ran


def sweep_json(api: Api, sweep_id: int) -> dict[str, Any]:
    response = api.client.get(f"/v1/sweeps/{sweep_id}", headers=ADMIN)
    assert response.status_code == 200, response.text
    return dict(response.json())


# --------------------------------------------------------------------------- login, CSRF, 404


def test_sweep_pages_need_a_login(api: Api) -> None:
    anonymous = TestClient(api.app)
    for path in (
        "/admin/sweeps",
        "/admin/sweeps/1",
        "/admin/live/sweeps/1",
        "/admin/live/sweeps/1/results",
        "/admin/sweeps/1/heatmap.png",
        "/admin/sweeps/1/shift-vs-gt.png",
    ):
        response = anonymous.get(path, follow_redirects=False)
        assert response.status_code == 303, path
        assert response.headers["location"].startswith("/admin/login?next=/admin/"), path
    refused = anonymous.post("/admin/sweeps", data=start_form(1), follow_redirects=False)
    assert refused.status_code == 303
    assert api.count(Sweep) == 0


def test_sweep_forms_need_the_csrf_token(api: Api, map_id: int) -> None:
    sweep_id = started(api, map_id)
    for path, data in (
        ("/admin/sweeps", start_form(map_id)),
        (f"/admin/sweeps/{sweep_id}/apply", {}),
        (f"/admin/sweeps/{sweep_id}/cancel", {}),
    ):
        for token in (None, "forged"):
            sent = data if token is None else {**data, "csrf_token": token}
            response = api.client.post(path, data=sent, follow_redirects=False)
            assert response.status_code == 403, path
            assert "security token is missing or wrong" in response.text
    assert api.count(Sweep) == 1
    assert sweep_json(api, sweep_id)["state"] == "running"
    assert sweep_json(api, sweep_id)["applied_job_id"] is None


UNKNOWN = [
    ("/admin/sweeps/999", 404, "Sweep 999 not found."),
    ("/admin/live/sweeps/999", 404, "Sweep 999 not found."),
    ("/admin/live/sweeps/999/results", 404, "Sweep 999 not found."),
    ("/admin/sweeps/999/heatmap.png", 404, "Sweep 999 not found."),
    ("/admin/sweeps/0", 404, "Sweep 0 not found."),
    ("/admin/sweeps?map_id=999", 404, "Map 999 not found."),
    ("/admin/sweeps/abc", 422, "Invalid sweep_id: input should be a valid integer"),
]


def test_unknown_sweeps_are_404_pages(api: Api) -> None:
    assert_error_pages(api.client, UNKNOWN)
    for action in ("/admin/sweeps/999/apply", "/admin/sweeps/999/cancel"):
        response = post(api, action)
        assert response.status_code == 404, action
        assert "Sweep 999 not found." in response.text


# --------------------------------------------------------------------------- starting


def test_the_start_form_creates_the_sweep_it_describes(api: Api, map_id: int) -> None:
    page = api.client.get(f"/admin/sweeps?map_id={map_id}")
    assert page.status_code == 200
    assert re.search(rf'<option value="{map_id}" selected>Map {map_id}', page.text)
    assert 'enctype="multipart/form-data"' in page.text
    assert checkbox(page.text, "tag_orientation_var_rad2").endswith(" checked")  # the paper's
    assert checkbox(page.text, "odom_linear_var_m2_per_s").endswith(" checked")
    assert not checkbox(page.text, "gravity_var_rad2").endswith(" checked")

    ground_truth = GROUND_TRUTH.read_text()
    sweep_id = started(api, map_id, objective="ground_truth", ground_truth_text=ground_truth)
    body = sweep_json(api, sweep_id)
    assert (body["method"], body["objective"], body["state"]) == ("grid", "ground_truth", "running")
    assert body["has_ground_truth"]
    assert body["trials_total"] == 4
    assert body["space"] == {
        "odom_linear_var_m2_per_s": {"low": 1e-5, "high": 0.1, "num": 2},
        "tag_orientation_var_rad2": {"low": 1e-4, "high": 1.0, "num": 2},
    }
    detail = api.client.get(f"/admin/sweeps/{sweep_id}")
    assert f"Sweep {sweep_id} of map {map_id} started: 4 trials (grid)." in detail.text
    assert 'data-sweep-state="running"' in detail.text
    assert f"Cancel sweep {sweep_id}" in detail.text
    assert "The plots appear when the first trials have finished." in detail.text

    sampler = post(
        api,
        "/admin/sweeps",
        start_form(map_id, method="sampler", trials="3", ground_truth_text=""),
        files={"ground_truth_file": ("tape.json", GROUND_TRUTH.read_bytes(), "application/json")},
    )
    assert sampler.status_code == 303, sampler.text
    second = int(sampler.headers["location"].rsplit("/", 1)[1])
    body = sweep_json(api, second)
    assert (body["method"], body["trials_total"], body["has_ground_truth"]) == ("sampler", 3, True)

    listed = api.client.get(f"/admin/sweeps?map_id={map_id}").text
    assert re.findall(r'<tr data-sweep-id="(\d+)"', listed) == [str(second), str(sweep_id)]
    assert "0 of 4" in listed
    assert f'aria-label="Sweep {sweep_id} progress"' in listed


def _bad_json_file() -> dict[str, Any]:
    return {"files": {"ground_truth_file": ("gt.json", b'{"poses": [', "application/json")}}


def _file_with_a_nul() -> dict[str, Any]:
    """A valid ground truth whose file also holds a NUL (JSONB cannot: issue 28, finding 1)."""
    document = json.loads(GROUND_TRUTH.read_bytes())
    document["source"] = "tape\x00measure"
    return {"files": {"ground_truth_file": ("gt.json", json.dumps(document), "application/json")}}


BAD_STARTS = [
    # (form changes, post kwargs, status, message, element focused)
    ({"sweep": []}, {}, 422, "The search space is empty", "start-tag_position_var_m2"),
    (
        {"odom_linear_var_m2_per_s_low": "0"},
        {},
        422,
        "Odometry linear variance (odom_linear_var_m2_per_s): low must be a positive variance",
        "start-odom_linear_var_m2_per_s-low",
    ),
    (
        {"tag_orientation_var_rad2_high": "-1"},
        {},
        422,
        "high must be a positive variance",
        "start-tag_orientation_var_rad2-high",
    ),
    (
        {"tag_orientation_var_rad2_num": "many"},
        {},
        422,
        "values: not a whole number (&#39;many&#39;)",
        "start-tag_orientation_var_rad2-num",
    ),
    ({"objective": "ground_truth"}, {}, 422, "needs ground truth", "start-objective"),
    (
        {"ground_truth_text": '{"poses": [}'},
        {},
        422,
        "Ground truth: not valid JSON (Expecting value, line 1 column 12)",
        "start-gt-text",
    ),
    (
        {"ground_truth_text": '{"poses": 1}'},
        {},
        422,
        "Ground truth: poses: expected a list",
        "start-gt-text",
    ),
    ({"ground_truth_text": "[1, 2]"}, {}, 422, "expected a JSON object", "start-gt-text"),
    ({}, _bad_json_file(), 422, "Ground truth: not valid JSON", "start-gt-file"),
    ({}, _file_with_a_nul(), 422, "Ground truth: source holds a NUL character", "start-gt-file"),
    (
        {"ground_truth_text": '{"poses": []}'},
        {"files": {"ground_truth_file": ("gt.json", b"{}", "application/json")}},
        422,
        "give a file or paste it in the text box, not both",
        "start-gt-text",
    ),
    (
        {"method": "sampler", "trials": "0"},
        {},
        422,
        "Trials must be between 1 and 10000",
        "start-trials",
    ),
    ({"method": "sampler", "trials": "ten"}, {}, 422, "Trials: not a whole number", "start-trials"),
    ({"method": "exhaustive"}, {}, 422, "Method: choose grid or sampler", "start-method-grid"),
    ({"map_id": ""}, {}, 422, "Map: choose the map", "start-map"),
    ({"map_id": "999"}, {}, 404, "Map 999 not found", "start-map"),
]


@pytest.mark.parametrize(
    ("changes", "kwargs", "status", "message", "element"),
    BAD_STARTS,
    ids=[case[-1] + ":" + case[3][:24] for case in BAD_STARTS],
)
def test_a_bad_start_form_is_refused_on_the_page_with_the_field_focused(
    api: Api,
    map_id: int,
    changes: dict[str, Any],
    kwargs: dict[str, Any],
    status: int,
    message: str,
    element: str,
) -> None:
    response = post(api, "/admin/sweeps", start_form(map_id, **changes), **kwargs)
    assert response.status_code == status, response.text
    assert response.headers["content-type"].startswith("text/html")
    error = re.search(r'<p class="error" role="alert" id="start-error">([^<]*)</p>', response.text)
    assert error is not None
    assert message in error.group(1)
    tag = re.search(rf'<[a-z]+ [^>]*id="{element}"[^>]*>', response.text)
    assert tag is not None, element
    assert 'aria-invalid="true"' in tag.group(0)
    assert "autofocus" in tag.group(0)
    assert response.text.count("autofocus") == 1
    assert api.count(Sweep) == 0


def test_a_refused_start_form_keeps_what_was_typed(api: Api, map_id: int) -> None:
    typed = {"odom_linear_var_m2_per_s_high": "0.5", "ground_truth_text": '{"poses": [}'}
    response = post(api, "/admin/sweeps", start_form(map_id, **typed))
    assert response.status_code == 422
    assert 'id="start-odom_linear_var_m2_per_s-high" name="odom_linear_var_m2_per_s_high"' in (
        response.text
    )
    assert 'value="0.5"' in response.text
    assert "{&#34;poses&#34;: [}</textarea>" in response.text
    assert re.search(rf'<option value="{map_id}" selected>', response.text)
    assert not checkbox(response.text, "gravity_var_rad2").endswith(" checked")
    assert checkbox(response.text, "odom_linear_var_m2_per_s").endswith(" checked")


# --------------------------------------------------------------------------- results, apply


def test_a_finished_sweep_shows_its_results_and_apply_queues_a_rebuild(
    api: Api, occam_map: int
) -> None:
    ground_truth = GROUND_TRUTH.read_text()
    sweep_id = started(api, occam_map, ground_truth_text=ground_truth)
    early = post(api, f"/admin/sweeps/{sweep_id}/apply")  # no trial yet
    assert early.status_code == 409
    refusal = re.search(r'role="alert" id="apply-error">([^<]*)<', early.text)
    assert refusal is not None
    assert refusal.group(1) == f"Sweep {sweep_id} has no converged trial yet."
    assert "Apply best parameters becomes possible once a trial has converged." in early.text

    assert drain(api) >= 1
    body = sweep_json(api, sweep_id)
    assert (body["state"], body["trials_done"]) == ("succeeded", 4)
    best = body["summary"]["best_values"]

    live = api.client.get(f"/admin/live/sweeps/{sweep_id}")
    assert live.status_code == 200
    assert "<html" not in live.text
    assert 'data-sweep-state="succeeded"' in live.text
    assert "4 of 4" in live.text
    assert 'value="1.0"' in live.text
    assert "Apply best parameters" in live.text
    assert f"Cancel sweep {sweep_id}" not in live.text
    metrics = live.text.split('id="sweep-metrics"')[1]
    for label in ("Pre-optimized", "Chosen by the shift metric", "Chosen by the ground-truth"):
        assert label in metrics
    assert f"{body['summary']['gt_metric_pre']:.3g}" in metrics
    assert "Spearman rank correlation" in live.text

    results = api.client.get(f"/admin/live/sweeps/{sweep_id}/results").text
    assert f'src="/admin/sweeps/{sweep_id}/heatmap.png?trials=4"' in results
    assert f'src="/admin/sweeps/{sweep_id}/shift-vs-gt.png?trials=4"' in results
    assert re.search(r'alt="Heat maps of the best shift metric per cell[^"]+star marks', results)
    assert re.search(r'alt="Scatter plot of the shift metric[^"]+converged trials', results)
    rows = re.findall(r"<tr><th scope=\"row\">(\d+)</th><td>(\d+)</td>", results)
    assert [rank for rank, _ in rows] == ["1", "2", "3", "4"]
    listed = api.client.get("/admin/sweeps").text
    assert f"{body['summary']['best_shift']:.3g}" in listed
    assert "4 of 4" in listed

    applied = post(api, f"/admin/sweeps/{sweep_id}/apply")
    assert applied.status_code == 303
    assert applied.headers["location"] == f"/admin/sweeps/{sweep_id}"
    job_id = sweep_json(api, sweep_id)["applied_job_id"]
    page = api.client.get(f"/admin/sweeps/{sweep_id}").text
    assert f"queued as job {job_id}" in page
    assert f'<a href="/admin/jobs/{job_id}">Follow job {job_id}</a>' in page  # the flash's link
    job = api.client.get(f"/v1/jobs/{job_id}", headers=ADMIN).json()
    assert (job["kind"], job["map_id"], job["state"]) == ("build_map", occam_map, "queued")
    assert job["params"] == pytest.approx({**best, "estimate_noise": False})

    assert drain(api) == 1
    live = api.client.get(f"/admin/live/sweeps/{sweep_id}").text
    assert f'href="/admin/maps/{occam_map}?version=2">version 2 of map {occam_map}</a>' in live
    versions = api.client.get(f"/v1/maps/{occam_map}/versions", headers=ADMIN).json()["data"]
    assert max(v["number"] for v in versions) == 2


def test_the_plots_are_pngs(api: Api, occam_map: int) -> None:
    with_gt = started(api, occam_map, ground_truth_text=GROUND_TRUTH.read_text())
    without = started(api, occam_map)
    drain(api)
    for path in (
        f"/admin/sweeps/{with_gt}/heatmap.png?trials=4",
        f"/admin/sweeps/{with_gt}/shift-vs-gt.png",
        f"/admin/sweeps/{without}/heatmap.png",
    ):
        response = api.client.get(path)
        assert response.status_code == 200, path
        assert response.headers["content-type"] == "image/png"
        assert response.content.startswith(b"\x89PNG\r\n\x1a\n")
    refused = api.client.get(f"/admin/sweeps/{without}/shift-vs-gt.png")
    assert refused.status_code == 409
    assert "has no ground truth" in refused.text
    page = api.client.get(f"/admin/sweeps/{without}").text
    assert "heatmap.png" in page
    assert "shift-vs-gt.png" not in page  # no scatter without ground truth


def test_cancel_a_running_sweep(api: Api, map_id: int) -> None:
    sweep_id = started(api, map_id)
    canceled = post(api, f"/admin/sweeps/{sweep_id}/cancel")
    assert canceled.status_code == 303
    page = api.client.get(f"/admin/sweeps/{sweep_id}").text
    assert f"Sweep {sweep_id} canceled" in page
    assert 'data-sweep-state="canceled"' in page
    assert f"Cancel sweep {sweep_id}" not in page
    assert sweep_json(api, sweep_id)["state"] == "canceled"
    with api.db.read() as db_session:
        states = db_session.scalars(select(Job.state).where(Job.sweep_id == sweep_id)).all()
    assert states == ["canceled"]
    again = post(api, f"/admin/sweeps/{sweep_id}/cancel")
    assert again.status_code == 303
    shown = api.client.get(again.headers["location"]).text
    assert f"Sweep {sweep_id} is canceled: nothing to cancel." in shown


def test_the_map_page_links_to_its_sweeps(api: Api, map_id: int) -> None:
    page = api.client.get(f"/admin/maps/{map_id}").text
    assert f'href="/admin/sweeps?map_id={map_id}"' in page
    assert (
        '<a href="/admin/sweeps" aria-current="page">Sweeps</a>'
        in api.client.get("/admin/sweeps").text
    )
