"""The admin dashboard in a real browser (headless Chromium through Playwright) against a real
server and worker: logging in, live progress, the map plot, rebuild, cancel, keys, CSRF, a sweep
started, watched and applied, an automated accessibility check (axe-core) of every page, and the
corridor editor (issue 27).

The tests share one server, one worker and one logged-in page (see conftest.py) and run in file
order: the cancel test needs the worker off, the later ones turn it on.
"""

from __future__ import annotations

import math
import os
import re
from pathlib import Path
from typing import Any

import httpx
import pytest
from axe_playwright_python.sync_playwright import Axe
from dashboard_support import TIMEOUT_MS, log_in
from playwright.sync_api import expect

pytestmark = [pytest.mark.browser, pytest.mark.slow, pytest.mark.xdist_group("dashboard")]

SESSIONS = Path(__file__).resolve().parents[2] / "data" / "sessions"
OCCAM = SESSIONS / "occam_room.json"
ONETAG = SESSIONS / "onetag.json"
GROUND_TRUTH = SESSIONS.parent / "ground_truth" / "occam_room_tape.json"
OCCAM_IDEMPOTENCY_KEY = "browser-occam"
#: How long a build may take to be seen succeeding (the worker imports gtsam first), ms.
BUILD_TIMEOUT_MS = 120_000
#: axe-core impacts that fail the check.
FAILING_IMPACTS = {"serious", "critical"}


@pytest.fixture(scope="module")
def built_map(api, worker):
    """The occam_room session uploaded and built (once per module)."""
    worker.on()
    accepted = api.upload_session(OCCAM, idempotency_key=OCCAM_IDEMPOTENCY_KEY)
    api.wait_for_job(accepted["job_id"], timeout_s=BUILD_TIMEOUT_MS / 1000)
    return accepted


def test_without_a_login_a_page_redirects_to_the_login_and_back(browser, server):
    context = browser.new_context(base_url=server.url)
    context.set_default_timeout(TIMEOUT_MS)
    tab = context.new_page()
    response = tab.goto("/admin/maps?page=1")
    assert response is not None
    redirect = response.request.redirected_from
    assert redirect is not None
    assert redirect.response().status == 303
    assert tab.url == f"{server.url}/admin/login?next=/admin/maps%3Fpage%3D1"
    expect(tab.get_by_role("heading", name="Log in")).to_be_visible()

    tab.get_by_label("Admin API key").fill(server.admin_key)
    tab.get_by_role("button", name="Log in").click()
    expect(tab).to_have_url(f"{server.url}/admin/maps?page=1")
    expect(tab.get_by_role("heading", name="Maps", exact=True)).to_be_visible()

    tab.get_by_role("button", name="Log out").click()
    expect(tab.get_by_role("status").filter(has_text="logged out")).to_be_visible()
    tab.goto("/admin")
    expect(tab).to_have_url(f"{server.url}/admin/login?next=/admin")
    context.close()


def test_log_in_with_the_admin_key(browser, server):
    context = browser.new_context(base_url=server.url)
    tab = context.new_page()
    log_in(tab, server)
    expect(tab.get_by_role("heading", name="Overview")).to_be_visible()
    expect(tab.get_by_text("Logged in with the server's admin key")).to_be_visible()
    cookie = next(c for c in context.cookies() if c["name"] == "im_admin_login")
    assert cookie["httpOnly"]
    assert cookie["sameSite"] == "Strict"
    assert cookie["path"] == "/admin"
    context.close()


def test_cancel_a_queued_job(page, api, worker):
    worker.off()  # so that the job stays queued
    job_id = api.upload_session(ONETAG)["job_id"]
    page.goto(f"/admin/jobs/{job_id}")
    expect(page.locator("#job-state")).to_have_text("queued")
    page.get_by_role("button", name=f"Cancel job {job_id}").click()
    expect(page.locator(".flash")).to_have_text(f"Job {job_id} canceled.")
    expect(page.locator("#job-state")).to_have_text("canceled")
    assert api.get_job(job_id)["state"] == "canceled"
    expect(page.get_by_role("button", name=f"Retry job {job_id}")).to_be_visible()


def test_the_overview_shows_an_upload_succeed_without_reloading(page, api, worker):
    page.goto("/admin")
    page.evaluate("window.notReloaded = true")
    worker.on()
    job_id = api.upload_session(OCCAM, idempotency_key=OCCAM_IDEMPOTENCY_KEY)["job_id"]
    row = page.locator(f'#recent-jobs tr[data-job-id="{job_id}"]')
    expect(row).to_be_visible()
    expect(row).to_have_attribute("data-job-state", "succeeded", timeout=BUILD_TIMEOUT_MS)
    expect(row.locator("progress")).to_have_attribute("value", "1.0")
    expect(row).to_contain_text("100%")
    assert page.evaluate("window.notReloaded") is True
    expect(page.locator("#live-announcer")).to_contain_text(f"Job {job_id}: succeeded.")
    expect(page.locator("#workers-heading + div table tbody tr")).to_have_count(1)


def _plotted_tags(page) -> int:
    """How many tag markers the plots of the page drew (in the SVG), over all floors."""
    return page.evaluate(
        """() => Array.from(document.querySelectorAll('.plot')).reduce((total, plot) => {
            const index = plot._fullData.findIndex((trace) => trace.name === 'Tags');
            const layer = plot.querySelectorAll('.scatterlayer .trace')[index];
            return total + layer.querySelectorAll('.points .point').length;
        }, 0)"""
    )


def test_the_map_page_plots_every_tag(page, api, built_map):
    tags = api.get_map(built_map["map_id"])["current_version"]["tags"]
    assert len(tags) > 1
    page.goto(f"/admin/maps/{built_map['map_id']}")
    expect(page.locator(".plot").first).to_have_attribute("data-rendered", "true")
    assert _plotted_tags(page) == len(tags)
    expect(page.locator(".tag-table tbody th")).to_have_count(len(tags))
    expect(page.locator("#tag-count")).to_have_text(str(len(tags)))


def test_rebuild_with_other_parameters_makes_a_new_version(page, api, built_map, worker):
    worker.on()
    map_id = built_map["map_id"]
    before = len(api.map_versions(map_id))
    page.goto(f"/admin/maps/{map_id}")
    page.get_by_label("Tag position variance at 1 m").fill("1e-3")
    page.get_by_role("button", name=f"Rebuild map {map_id}").click()
    expect(page.locator(".flash")).to_contain_text("tag_position_var_m2 = 0.001")
    versions = page.locator("#versions tbody tr")
    expect(versions).to_have_count(before + 1, timeout=BUILD_TIMEOUT_MS)  # live, no reload
    expect(versions.last).to_contain_text("tag_position_var_m2 = 0.001")
    expect(page.locator("#new-version-notice")).to_contain_text(f"Version {before + 1} is ready")
    page.get_by_role("link", name="show its plot and figures").click()
    expect(page.get_by_role("heading", name=f"Version {before + 1} (current)")).to_be_visible()
    newest = api.map_versions(map_id)[-1]
    assert newest["number"] == before + 1
    assert newest["params"]["tag_position_var_m2"] == 1e-3


def test_the_route_tester_draws_a_route_and_its_steps(page, built_map):
    page.goto(f"/admin/maps/{built_map['map_id']}/route")
    page.locator("#route-from").select_option("tag:0")
    expect(page.locator(".plot").first).to_have_attribute("data-rendered", "true")
    page.get_by_role("radio", name="To").check()
    tag_marker = page.locator(".scatterlayer .trace .points .point").nth(5)
    tag_marker.click(force=True)  # clicking a tag on the map chooses it
    expect(page.locator("#route-to")).to_have_value("tag:5")
    page.get_by_role("button", name="Plan the route").click()
    expect(page.locator("#route-steps li").last).to_contain_text("arrive at tag 5")
    expect(page.locator(".plot").first).to_have_attribute("data-rendered", "true")
    assert page.evaluate(
        "() => document.querySelector('.plot')._fullData.some((t) => t.name === 'Route')"
    )


def test_create_and_revoke_a_key(page, server):
    page.goto("/admin/keys")
    page.get_by_label("Name (who or what uses it)").fill("browser test phone")
    page.get_by_label("Role").select_option("device")
    page.get_by_role("button", name="Create the key").click()
    expect(page.locator("#created-heading")).to_contain_text("created")
    secret = page.locator("#new-key").input_value()
    key_id = int(page.locator("#created-heading").inner_text().split()[1])
    headers = {"Authorization": f"Bearer {secret}"}
    assert httpx.get(f"{server.url}/v1/info", headers=headers).status_code == 200

    page.once("dialog", lambda dialog: dialog.accept())
    page.get_by_role("button", name=f"Revoke key {key_id}").click()
    expect(page.locator(".flash")).to_contain_text(f"Key {key_id} (browser test phone) is revoked")
    expect(page.locator(f"#key-{key_id} .key-status")).to_contain_text("revoked")
    expect(page.locator("#new-key")).to_have_count(0)  # shown once only
    assert httpx.get(f"{server.url}/v1/info", headers=headers).status_code == 401


def test_a_form_posted_without_its_csrf_token_is_refused(page, api):
    keys_before = len(api.list_keys())
    page.goto("/admin/keys")
    page.locator("#create-key-form input[name=csrf_token]").evaluate("input => input.remove()")
    page.get_by_label("Name (who or what uses it)").fill("forged")
    with page.expect_response(
        lambda r: r.url.endswith("/admin/keys") and r.request.method == "POST"
    ) as answer:
        page.get_by_role("button", name="Create the key").click()
    assert answer.value.status == 403
    expect(page.get_by_role("heading", name="Refused")).to_be_visible()
    assert len(api.list_keys()) == keys_before


def test_start_a_sweep_watch_it_finish_and_apply_its_best_parameters(page, api, built_map, worker):
    worker.on()
    map_id = built_map["map_id"]
    before = len(api.map_versions(map_id))
    page.goto(f"/admin/maps/{map_id}")
    page.get_by_role("link", name="Sweeps of this map").click()
    expect(page.get_by_label("Map", exact=True)).to_have_value(str(map_id))

    # a refused form: shown again with the reason, and the field at fault focused
    for name in ("Tag orientation variance", "Odometry linear variance", "Odometry angular"):
        page.get_by_role("group", name=re.compile(name)).get_by_role("checkbox").uncheck()
    page.get_by_role("button", name="Start the sweep").click()
    expect(page.locator("#start-error")).to_have_text(
        "The search space is empty: give at least one parameter to sweep."
    )
    expect(page.locator("#start-tag_position_var_m2")).to_be_focused()
    assert not _serious_violations(page)

    # a 2 × 2 grid scored against the tape-measured ground truth (a file)
    for name, low, high in (
        ("Tag orientation variance", "1e-4", "1"),
        ("Odometry linear variance", "1e-5", "0.1"),
    ):
        axis = page.get_by_role("group", name=re.compile(name))
        axis.get_by_role("checkbox").check()
        axis.get_by_label("Low").fill(low)
        axis.get_by_label("High").fill(high)
        axis.get_by_label("Values").fill("2")
    page.get_by_label("Ground-truth file").set_input_files(GROUND_TRUTH)
    page.get_by_role("button", name="Start the sweep").click()
    expect(page.locator(".flash")).to_contain_text("started: 4 trials (grid)")
    sweep_id = int(page.url.rsplit("/", 1)[1])

    page.evaluate("window.notReloaded = true")
    expect(page.locator("#sweep-state")).to_have_text("succeeded", timeout=BUILD_TIMEOUT_MS)
    expect(page.locator("#sweep-trials")).to_have_text("4 of 4")
    expect(page.locator("#live-announcer")).to_contain_text(f"Sweep {sweep_id}: succeeded.")
    heatmap = page.locator("#sweep-heatmap")
    expect(heatmap).to_have_attribute("src", re.compile(r"heatmap\.png\?trials=4$"))
    expect(heatmap).to_have_attribute("alt", re.compile(r"^Heat maps of the best shift metric"))
    page.wait_for_function(
        """() => { const img = document.getElementById('sweep-heatmap');
                   return !!img && img.complete && img.naturalWidth > 0; }"""
    )
    expect(page.locator("#sweep-shift-vs-gt")).to_be_visible()
    expect(page.locator("#best-trials tbody tr")).to_have_count(4)
    assert page.evaluate("window.notReloaded") is True

    page.get_by_role("button", name="Apply best parameters").click()
    expect(page.locator(".flash")).to_contain_text(f"with sweep {sweep_id}'s best parameters")
    job_link = page.locator(".flash a")
    expect(job_link).to_have_text(re.compile(r"^Follow job \d+$"))
    applied = page.locator("#sweep-applied")  # live, no reload
    expect(applied).to_contain_text(
        f"version {before + 1} of map {map_id}", timeout=BUILD_TIMEOUT_MS
    )
    applied.get_by_role("link", name=f"version {before + 1} of map {map_id}").click()
    expect(page.get_by_role("heading", name=f"Version {before + 1} (current)")).to_be_visible()
    best = api.request("GET", f"/v1/sweeps/{sweep_id}").json()["summary"]["best_values"]
    newest = api.map_versions(map_id)[-1]
    assert newest["number"] == before + 1
    for name, value in best.items():
        assert newest["params"][name] == pytest.approx(value)


def _pages(built_map, api) -> dict[str, str]:
    job_id = api.list_jobs()["data"][0]["id"]
    map_id = built_map["map_id"]
    pages = {
        "overview": "/admin",
        "sessions": "/admin/sessions",
        "session": f"/admin/sessions/{built_map['session_id']}",
        "jobs": "/admin/jobs",
        "job": f"/admin/jobs/{job_id}",
        "maps": "/admin/maps",
        "map": f"/admin/maps/{map_id}",
        "routes": "/admin/routes",
        "route": f"/admin/maps/{map_id}/route?from=tag:0&to=tag:5",
        "keys": "/admin/keys",
        "sweeps": "/admin/sweeps",
        "not found": "/admin/maps/999999",
    }
    sweeps = api.request("GET", "/v1/sweeps", params={"limit": 1}).json()["data"]
    if sweeps:  # the sweep test ran
        pages["sweep"] = f"/admin/sweeps/{sweeps[0]['id']}"
    return pages


def _serious_violations(page) -> list[str]:
    results = Axe().run(page)
    return [
        f"{violation['id']} ({violation['impact']}): {violation['help']} — "
        + "; ".join(node["target"][0] for node in violation["nodes"][:5])
        for violation in results.response["violations"]
        if violation["impact"] in FAILING_IMPACTS
    ]


def test_every_page_has_no_serious_accessibility_violation(page, browser, server, api, built_map):
    failures = {}
    for name, path in _pages(built_map, api).items():
        page.goto(path)
        if page.locator(".plot").count():
            expect(page.locator(".plot").first).to_have_attribute("data-rendered", "true")
        if page.locator("#sweep-heatmap").count():
            page.wait_for_function(
                "() => document.getElementById('sweep-heatmap').naturalWidth > 0"
            )
        found = _serious_violations(page)
        if found:
            failures[name] = found
    context = browser.new_context(base_url=server.url)
    login = context.new_page()
    login.goto("/admin/login")
    found = _serious_violations(login)
    if found:
        failures["login"] = found
    context.close()
    assert not failures, failures


# --------------------------------------------------------------------------- the corridor editor
# (issue 27): quiet a bend with the keyboard and see the route tester lose the turn, drag a node,
# connect two nodes and take the edge out again (its edit deleted), undo, delete from the list, a
# refused edit, the map page's summary, axe; and the screenshot of docs/navigation.md
# (INVISIBLE_MAP_SCREENSHOTS=1).

ROOT = Path(__file__).resolve().parents[2]
DEMO = ROOT / "data" / "demo" / "floor_2_pois.json"
#: Where the screenshot of the docs goes, when INVISIBLE_MAP_SCREENSHOTS=1.
SCREENSHOT = ROOT / "docs" / "corridor-editor.png"


@pytest.fixture(scope="module")
def map_id(api, worker) -> int:
    """The demo floor with points of interest, built (once per module)."""
    worker.on()
    accepted = api.upload_session(DEMO, idempotency_key="browser-editor")
    api.wait_for_job(accepted["job_id"], timeout_s=BUILD_TIMEOUT_MS / 1000)
    return int(accepted["map_id"])


def open_editor(page, map_id: int) -> None:
    page.goto(f"/admin/maps/{map_id}/editor")
    expect(page.locator("#editor")).to_have_attribute("data-ready", "true")


def data(page, map_id: int) -> dict[str, Any]:
    response = page.request.get(f"/admin/maps/{map_id}/editor/data")
    assert response.ok, response.text()
    result: dict[str, Any] = response.json()
    return result


def dead_ends(graph: dict[str, Any]) -> list[dict[str, Any]]:
    """The editor data's nodes with one edge (where a door can join two corridors)."""
    degree: dict[int, int] = {}
    for edge in graph["edges"]:
        for end in (edge["from"], edge["to"]):
            degree[end] = degree.get(end, 0) + 1
    return [n for n in graph["nodes"] if degree.get(n["id"]) == 1]


def history(page):  # type: ignore[no-untyped-def]
    return page.locator("#editor-history li")


def a_turn(page, map_id: int) -> tuple[str, str, list[float]]:
    """A route of the map with a turn: (from, to, where the turn is)."""
    tags = [t["id"] for t in data(page, map_id)["tags"]]
    for goal in reversed(tags[1:]):
        route = page.request.get(
            f"/admin/maps/{map_id}/editor/route",
            params={"from": f"tag:{tags[0]}", "to": f"tag:{goal}"},
        ).json()
        turns = [s for s in route["steps"] if s["kind"] == "turn"]
        if turns:
            return f"tag:{tags[0]}", f"tag:{goal}", turns[0]["position"]
    raise AssertionError("no route of the demo map turns")


def nearest_node(page, map_id: int, point: list[float]) -> dict[str, Any]:
    nodes = data(page, map_id)["nodes"]
    return min(nodes, key=lambda n: math.hypot(n["x"] - point[0], n["z"] - point[2]))


def plan(page, start: str, goal: str) -> list[str]:
    page.locator("#editor-from").select_option(start)
    page.locator("#editor-to").select_option(goal)
    page.get_by_role("button", name="Plan", exact=True).click()
    expect(page.locator("#editor-steps li").last).to_contain_text("arrive at")
    return page.locator("#editor-steps li").all_inner_texts()


def decisions(steps: list[str]) -> list[str]:
    """The turns and bears said at a decision point (not their "in 5 m" announcements)."""
    return [s for s in steps if s.startswith(("turn", "bear")) and "face the way" not in s]


def test_quiet_a_bend_with_the_keyboard_and_the_route_loses_the_turn(page, map_id):
    open_editor(page, map_id)
    start, goal, at = a_turn(page, map_id)
    before = plan(page, start, goal)
    bend = nearest_node(page, map_id, at)
    node = page.locator(f'[data-node="{bend["id"]}"]')
    node.focus()
    expect(page.locator("#editor-status")).to_contain_text(f"Node {bend['id']} selected")
    page.keyboard.press("q")
    expect(history(page).last).to_contain_text("quiet at")
    expect(history(page).last).to_contain_text("Applied")
    expect(page.locator(f'[data-node="{bend["id"]}"]')).to_have_class(
        "node node-" + bend["kind"] + " quiet selected"
    )
    expect(page.locator("#editor-steps li")).not_to_have_count(len(before))  # re-planned at once
    after = page.locator("#editor-steps li").all_inner_texts()
    assert len(decisions(after)) == len(decisions(before)) - 1, (before, after)


def test_drag_a_node(page, map_id):
    open_editor(page, map_id)
    before = data(page, map_id)
    target = next(n for n in before["nodes"] if n["kind"] == "node" and not n["quiet"])
    box = page.locator(f'[data-node="{target["id"]}"]').bounding_box()
    x, y = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
    page.mouse.move(x, y)
    page.mouse.down()
    page.mouse.move(x + 10, y + 5, steps=4)
    page.mouse.move(x + 20, y + 10, steps=4)
    page.mouse.up()
    expect(history(page).last).to_contain_text("move the node")
    expect(history(page).last).to_contain_text("Applied")
    after = {n["id"]: n for n in data(page, map_id)["nodes"]}
    moved = after[target["id"]]
    assert math.hypot(moved["x"] - target["x"], moved["z"] - target["z"]) > 0.1


def test_connect_two_nodes_remove_the_edge_and_undo_with_the_keyboard(page, map_id):
    open_editor(page, map_id)
    ends = dead_ends(data(page, map_id))
    a, b = ends[0], ends[-1]
    page.locator("#editor-kind").select_option("door")
    page.locator(f'[data-node="{a["id"]}"]').focus()
    page.keyboard.press("c")
    expect(page.locator("#editor-status")).to_contain_text(f"Connecting from node {a['id']}")
    page.locator(f'[data-node="{b["id"]}"]').focus()
    expect(page.locator("#editor-status")).to_contain_text("Press Enter to connect")
    page.keyboard.press("Enter")
    expect(history(page).last).to_contain_text("add a door")
    edges = data(page, map_id)["edges"]
    assert any({e["from"], e["to"]} == {a["id"], b["id"]} and e["kind"] == "door" for e in edges)
    listed = page.locator("#editor-history li[data-edit-id]")  # not the "No edit yet." line
    count = listed.count()

    # the new edge is selected and has the focus: Delete takes it out by deleting the edit that
    # added it (issue 39), not by a second edit
    expect(page.locator("#editor-status")).to_contain_text("The new edge is selected")
    page.keyboard.press("Delete")
    expect(listed).to_have_count(count - 1)
    expect(history(page).filter(has_text="add a door")).to_have_count(0)
    expect(history(page).filter(has_text="remove the edge")).to_have_count(0)
    assert not any({e["from"], e["to"]} == {a["id"], b["id"]} for e in data(page, map_id)["edges"])

    page.locator(f'[data-node="{a["id"]}"]').focus()
    page.keyboard.press("Control+z")
    expect(listed).to_have_count(count)
    expect(history(page).last).to_contain_text("add a door")
    assert any({e["from"], e["to"]} == {a["id"], b["id"]} for e in data(page, map_id)["edges"])


def test_a_refused_edit_says_why_and_changes_nothing(page, map_id):
    open_editor(page, map_id)
    quiet = next((n for n in data(page, map_id)["nodes"] if n["quiet"]), None)
    if quiet is None:  # this worker's map has none yet (the tests may run on either worker)
        quiet = next(n for n in data(page, map_id)["nodes"] if n["kind"] == "node")
        page.locator(f'[data-node="{quiet["id"]}"]').focus()
        page.keyboard.press("q")
        expect(history(page).last).to_contain_text("Applied")
        # the editor redraws and plans its route after an edit; a key meanwhile is told to wait
        expect(page.locator("#editor")).not_to_have_attribute("aria-busy", "true")
    count = history(page).count()
    page.locator(f'[data-node="{quiet["id"]}"]').focus()
    page.keyboard.press("q")
    expect(page.locator("#editor-error")).to_contain_text("quiet already")
    expect(history(page)).to_have_count(count)


def test_a_key_pressed_while_an_edit_is_saved_is_told_to_wait(page, map_id):
    open_editor(page, map_id)
    node = next(n for n in data(page, map_id)["nodes"] if n["kind"] == "node" and not n["quiet"])
    listed = page.locator("#editor-history li[data-edit-id]")  # not the "No edit yet." line
    count = listed.count()

    def slowly(route):  # type: ignore[no-untyped-def]
        page.wait_for_timeout(1500)
        route.continue_()

    page.route(f"**/admin/maps/{map_id}/editor/edits", slowly)
    try:
        page.locator(f'[data-node="{node["id"]}"]').focus()
        page.keyboard.press("q")
        expect(page.locator("#editor")).to_have_attribute("aria-busy", "true")
        page.keyboard.press("q")  # the same node again, while the first is saved
        expect(page.locator("#editor-status")).to_contain_text("Still saving the last change")
        expect(page.locator("#editor")).not_to_have_attribute("aria-busy", "true")
    finally:
        page.unroute(f"**/admin/maps/{map_id}/editor/edits")
    expect(listed).to_have_count(count + 1)
    expect(history(page).last).to_contain_text("Applied")
    expect(page.locator("#editor-error")).to_be_hidden()


def test_the_map_page_says_how_many_edits_apply(page, map_id):
    if not data(page, map_id)["edits"]:  # this worker's map has none yet (a page with none
        # says nothing of edits): quiet a node first
        open_editor(page, map_id)
        node = next(n for n in data(page, map_id)["nodes"] if n["kind"] == "node")
        page.locator(f'[data-node="{node["id"]}"]').focus()
        page.keyboard.press("q")
        expect(history(page).last).to_contain_text("Applied")
    page.goto(f"/admin/maps/{map_id}")
    count = len(data(page, map_id)["edits"])
    expect(page.locator("#corridor-edits-summary")).to_contain_text(
        f"Corridor edits: {count} of {count} applied to this version"
    )


def test_delete_an_edit_from_the_history(page, map_id):
    open_editor(page, map_id)
    if history(page).filter(has_text="add a door").count() == 0:
        # this worker's map has none yet (the tests may run on either worker): connect two ends
        ends = dead_ends(data(page, map_id))
        page.locator("#editor-kind").select_option("door")
        page.locator(f'[data-node="{ends[0]["id"]}"]').focus()
        page.keyboard.press("c")
        page.locator(f'[data-node="{ends[-1]["id"]}"]').focus()
        page.keyboard.press("Enter")
        expect(history(page).last).to_contain_text("Applied")
        open_editor(page, map_id)
    listed = page.locator("#editor-history li[data-edit-id]")  # not the "No edit yet." line
    count = listed.count()
    door = history(page).filter(has_text="add a door")
    edit_id = door.get_attribute("data-edit-id")
    door.get_by_role("button", name=f"Delete edit {edit_id}").click()
    expect(listed).to_have_count(count - 1)
    expect(history(page).filter(has_text="add a door")).to_have_count(0)
    assert all(e["kind"] != "door" for e in data(page, map_id)["edges"])


def test_the_editor_has_no_serious_accessibility_violation(page, map_id):
    open_editor(page, map_id)
    plan(page, *a_turn(page, map_id)[:2])
    results = Axe().run(page)
    serious = [
        f"{v['id']} ({v['impact']}): {v['help']} — {[n['target'][0] for n in v['nodes'][:5]]}"
        for v in results.response["violations"]
        if v["impact"] in {"serious", "critical"}
    ]
    assert not serious, serious
    page.goto("/admin/editor")
    expect(page.get_by_role("link", name=f"Map {map_id}:", exact=False)).to_be_visible()
    results = Axe().run(page)
    assert not [v for v in results.response["violations"] if v["impact"] in {"serious", "critical"}]
    if os.environ.get("INVISIBLE_MAP_SCREENSHOTS") == "1":
        open_editor(page, map_id)
        plan(page, *a_turn(page, map_id)[:2])
        editor = page.locator("#editor").bounding_box()
        form = page.locator("#poi-form").bounding_box()  # the map and its forms, not the tables
        page.screenshot(
            path=str(SCREENSHOT),
            full_page=True,
            clip={
                "x": editor["x"],
                "y": editor["y"],
                "width": editor["width"],
                "height": form["y"] + form["height"] - editor["y"],
            },
        )
