"""The corridor editor (issue 27) in a real browser (headless Chromium through Playwright) against
a real server and worker: quiet a bend with the keyboard and see the route tester lose the turn,
drag a node, connect two nodes and remove the edge with the mouse and the keyboard, undo, and an
automated accessibility check (axe-core). It also writes the screenshot of docs/navigation.md.

The tests share one server, one worker, one logged-in page and one map (the demo floor with
points of interest) and run in file order.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any

import pytest
from axe_playwright_python.sync_playwright import Axe
from playwright.sync_api import expect

pytestmark = [pytest.mark.browser, pytest.mark.slow]

ROOT = Path(__file__).resolve().parents[2]
DEMO = ROOT / "data" / "demo" / "floor_2_pois.json"
#: Where the screenshot of the docs goes, when INVISIBLE_MAP_SCREENSHOTS=1.
SCREENSHOT = ROOT / "docs" / "corridor-editor.png"
BUILD_TIMEOUT_S = 180.0


@pytest.fixture(scope="module")
def map_id(api, worker) -> int:
    worker.on()
    accepted = api.upload_session(DEMO, idempotency_key="browser-editor")
    api.wait_for_job(accepted["job_id"], timeout_s=BUILD_TIMEOUT_S)
    return int(accepted["map_id"])


def open_editor(page, map_id: int) -> None:
    page.goto(f"/admin/maps/{map_id}/editor")
    expect(page.locator("#editor")).to_have_attribute("data-ready", "true")


def data(page, map_id: int) -> dict[str, Any]:
    response = page.request.get(f"/admin/maps/{map_id}/editor/data")
    assert response.ok, response.text()
    result: dict[str, Any] = response.json()
    return result


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
    graph = data(page, map_id)
    degree: dict[int, int] = {}
    for edge in graph["edges"]:
        for end in (edge["from"], edge["to"]):
            degree[end] = degree.get(end, 0) + 1
    ends = [n for n in graph["nodes"] if degree.get(n["id"]) == 1]
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
    count = history(page).count()

    # select the new edge with the keyboard ([ and ] go through a node's edges), remove it
    page.locator(f'[data-node="{a["id"]}"]').focus()
    for _ in range(4):
        page.keyboard.press("]")
        status = page.locator("#editor-status").inner_text()
        if f"node {b['id']}" in status or f"node {a['id']} to node {b['id']}" in status:
            break
    expect(page.locator("#editor-status")).to_contain_text("Edge from node")
    page.keyboard.press("Delete")
    expect(history(page)).to_have_count(count + 1)
    expect(history(page).last).to_contain_text("remove the edge")
    assert not any({e["from"], e["to"]} == {a["id"], b["id"]} for e in data(page, map_id)["edges"])

    page.locator(f'[data-node="{a["id"]}"]').focus()
    page.keyboard.press("Control+z")
    expect(history(page)).to_have_count(count)
    expect(history(page).last).to_contain_text("add a door")
    assert any({e["from"], e["to"]} == {a["id"], b["id"]} for e in data(page, map_id)["edges"])


def test_a_refused_edit_says_why_and_changes_nothing(page, map_id):
    open_editor(page, map_id)
    count = history(page).count()
    quiet = next(n for n in data(page, map_id)["nodes"] if n["quiet"])
    page.locator(f'[data-node="{quiet["id"]}"]').focus()
    page.keyboard.press("q")
    expect(page.locator("#editor-error")).to_contain_text("quiet already")
    expect(history(page)).to_have_count(count)


def test_the_map_page_says_how_many_edits_apply(page, map_id):
    page.goto(f"/admin/maps/{map_id}")
    count = len(data(page, map_id)["edits"])
    expect(page.locator("#corridor-edits-summary")).to_contain_text(
        f"Corridor edits: {count} of {count} applied to this version"
    )


def test_delete_an_edit_from_the_history(page, map_id):
    open_editor(page, map_id)
    count = history(page).count()
    door = history(page).filter(has_text="add a door")
    edit_id = door.get_attribute("data-edit-id")
    door.get_by_role("button", name=f"Delete edit {edit_id}").click()
    expect(history(page)).to_have_count(count - 1)
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
        page.locator("#editor").screenshot(path=str(SCREENSHOT))
