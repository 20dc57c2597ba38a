"""The corridor editor, the map page and the route tester as an outside tester found them
(issue 39, item 4), in a real browser: a point of interest added in the editor is drawn and
listed everywhere routing sees it; ] walks along the corridor; the focus stays in the graph after
connecting; labels do not cover each other; taking out an edge added a moment ago deletes its
edit; a one-walk map lists its session; edges take the focus; a skip link leads to the graph;
the route tester says its result; and a whole edit done by keyboard alone, checked in the
graph's tables and the page's announcements (for an operator who is blind), with axe.

One server, one worker and one logged-in page per module (conftest.py); the tests run in file
order on the demo floor with points of interest, each leaving the map as it found it where a
later test depends on it.
"""

from __future__ import annotations

import math
import re
from typing import Any

import pytest
from axe_playwright_python.sync_playwright import Axe
from playwright.sync_api import expect
from test_dashboard import (
    BUILD_TIMEOUT_MS,
    DEMO,
    data,
    dead_ends,
    history,
    open_editor,
)

pytestmark = [pytest.mark.browser, pytest.mark.slow, pytest.mark.xdist_group("corridor_editor")]

#: What the page's live region said last (each announcement empties it first).
ANNOUNCER = "#live-announcer"


@pytest.fixture(scope="module")
def map_id(api, worker) -> int:
    """The demo floor with points of interest, built (once per module)."""
    worker.on()
    accepted = api.upload_session(DEMO, idempotency_key="browser-editor-39")
    api.wait_for_job(accepted["job_id"], timeout_s=BUILD_TIMEOUT_MS / 1000)
    return int(accepted["map_id"])


def neighbours(graph: dict[str, Any]) -> dict[int, list[int]]:
    around: dict[int, list[int]] = {n["id"]: [] for n in graph["nodes"]}
    for edge in graph["edges"]:
        around[edge["from"]].append(edge["to"])
        around[edge["to"]].append(edge["from"])
    return around


def turn_rad(graph: dict[str, Any], a: int, b: int, c: int) -> float:
    """The turn from the way a→b to the way b→c (0: straight on)."""
    nodes = {n["id"]: n for n in graph["nodes"]}
    h1 = math.atan2(nodes[b]["z"] - nodes[a]["z"], nodes[b]["x"] - nodes[a]["x"])
    h2 = math.atan2(nodes[c]["z"] - nodes[b]["z"], nodes[c]["x"] - nodes[b]["x"])
    d = abs(h2 - h1) % (2 * math.pi)
    return 2 * math.pi - d if d > math.pi else d


def focused(page) -> dict[str, str | None]:  # type: ignore[no-untyped-def]
    """The focused element's node or edge (data-node, data-edge) and id."""
    result: dict[str, str | None] = page.evaluate(
        """() => { const e = document.activeElement;
                   return {node: e.dataset ? (e.dataset.node ?? null) : null,
                           edge: e.dataset ? (e.dataset.edge ?? null) : null,
                           id: e.id || null, tag: e.tagName}; }"""
    )
    return result


def status(page):  # type: ignore[no-untyped-def]
    return page.locator("#editor-status")


def edge_between(graph: dict[str, Any], a: int, b: int) -> dict[str, Any] | None:
    return next((e for e in graph["edges"] if {e["from"], e["to"]} == {a, b}), None)


def tab_to(page, selector: str, *, limit: int = 400, back: bool = False) -> None:  # type: ignore[no-untyped-def]
    """Press Tab (Shift+Tab: back) until the element at ``selector`` has the focus."""
    for _ in range(limit):
        if page.evaluate(f"() => document.activeElement === document.querySelector('{selector}')"):
            return
        page.keyboard.press("Shift+Tab" if back else "Tab")
    raise AssertionError(f"{selector} never took the focus")


# ------------------------------------------------------------------ points of interest


def _plotted_pois(page) -> list[str]:  # type: ignore[no-untyped-def]
    names: list[str] = page.evaluate(
        """() => Array.from(document.querySelectorAll('.plot')).flatMap((plot) =>
            plot._fullData.filter((t) => t.name === 'Points of interest')
                .flatMap((t) => Array.from(t.text)))"""
    )
    return names


def test_a_poi_added_in_the_editor_is_on_the_map_page_and_the_route_tester(page, map_id):
    open_editor(page, map_id)
    target = next(n for n in data(page, map_id)["nodes"] if n["kind"] == "node")
    page.locator(f'[data-node="{target["id"]}"]').focus()
    page.get_by_label("Name").fill("Water fountain")
    page.get_by_role("button", name="Add at the selected place").click()
    expect(history(page).last).to_contain_text("Water fountain")
    expect(history(page).last).to_contain_text("Applied")

    page.goto(f"/admin/maps/{map_id}")
    expect(page.locator(".plot").first).to_have_attribute("data-rendered", "true")
    expect(page.locator("#pois-floor-0 tbody th", has_text="Water fountain")).to_have_count(1)
    assert "Water fountain" in _plotted_pois(page)

    page.goto(f"/admin/maps/{map_id}/route?from=tag:300&to=poi:Water+fountain")
    expect(page.locator("#route-steps li").last).to_contain_text("Water fountain")
    expect(page.locator(".plot").first).to_have_attribute("data-rendered", "true")
    assert "Water fountain" in _plotted_pois(page)

    # taken out again (the later tests count the editor's points of interest)
    open_editor(page, map_id)
    edit = history(page).filter(has_text="Water fountain")
    edit_id = edit.get_attribute("data-edit-id")
    edit.get_by_role("button", name=f"Delete edit {edit_id}").click()
    expect(history(page).filter(has_text="Water fountain")).to_have_count(0)


# ------------------------------------------------------------------ [ and ] along the corridor


def test_right_bracket_walks_along_the_corridor_the_straightest_way(page, map_id):
    open_editor(page, map_id)
    graph = data(page, map_id)
    around = neighbours(graph)
    start = min(n["id"] for n in dead_ends(graph))
    page.locator(f'[data-node="{start}"]').focus()
    previous, here = start, around[start][0]
    page.keyboard.press("]")
    expect(status(page)).to_contain_text(f"Edge from node {previous} to node {here} selected")
    assert focused(page)["edge"] is not None  # the edge has the focus, not the node
    junctions = 0
    for _ in range(12):
        onward = [n for n in around[here] if n != previous]
        if not onward:
            break
        junctions += len(onward) > 1
        nxt = min(onward, key=lambda n: turn_rad(graph, previous, here, n))
        page.keyboard.press("]")
        expect(status(page)).to_contain_text(f"Edge from node {here} to node {nxt} selected")
        edge = edge_between(graph, here, nxt)
        assert edge is not None
        assert focused(page)["edge"] == f"{edge['from']}-{edge['to']}"
        previous, here = here, nxt
    assert junctions, "the walk passed no junction: pick another start"
    page.keyboard.press("[")  # and back one
    back = [n for n in around[previous] if n != here]
    expect(status(page)).to_contain_text(f"to node {previous} selected")
    assert back


# ------------------------------------------------------------------ connect, then the keyboard


def test_after_connecting_the_new_edge_has_the_focus_and_enter_works(page, map_id):
    open_editor(page, map_id)
    ends = dead_ends(data(page, map_id))
    a, b = ends[0], ends[-1]
    page.locator(f'[data-node="{a["id"]}"]').click()
    page.get_by_role("button", name="Connect to… (C)").click()
    expect(status(page)).to_contain_text(f"Connecting from node {a['id']}")
    page.locator(f'[data-node="{b["id"]}"]').click()
    expect(history(page).last).to_contain_text("Applied")
    edge = edge_between(data(page, map_id), a["id"], b["id"])
    assert edge is not None
    expect(page.locator(f'[data-edge="{edge["from"]}-{edge["to"]}"]')).to_be_focused()
    page.keyboard.press("Enter")
    expect(status(page)).to_contain_text(f"Edge from node {a['id']} to node {b['id']} selected")
    expect(page.locator(ANNOUNCER)).to_contain_text("selected")


def test_taking_out_an_edge_added_a_moment_ago_deletes_its_edit(page, map_id):  # noqa: ARG001
    # the edge of the test before is selected and focused on this page
    listed = page.locator("#editor-history li[data-edit-id]")
    count = listed.count()
    expect(history(page).last).to_contain_text("add a walk")
    page.keyboard.press("Delete")
    expect(listed).to_have_count(count - 1)
    expect(history(page).filter(has_text="remove the edge")).to_have_count(0)
    expect(history(page).filter(has_text="add a walk")).to_have_count(0)
    expect(page.locator(ANNOUNCER)).to_contain_text("which added it, is deleted")
    assert focused(page)["node"] is not None  # the focus stays in the graph


# ------------------------------------------------------------------ labels


def test_labels_do_not_cover_each_other_or_a_node(page, map_id):
    open_editor(page, map_id)
    boxes = page.evaluate(
        """() => Array.from(document.querySelectorAll('#editor-canvas text')).map((t) => {
            const b = t.getBBox(); return [t.textContent, b.x, b.y, b.x + b.width, b.y + b.height];
        })"""
    )
    overlapping = [
        (a[0], b[0])
        for k, a in enumerate(boxes)
        for b in boxes[k + 1 :]
        if a[1] < b[3] and a[3] > b[1] and a[2] < b[4] and a[4] > b[2]
    ]
    assert not overlapping, overlapping
    nodes = page.evaluate(
        """() => Array.from(document.querySelectorAll('#editor-canvas [data-node]')).map((c) => {
            const b = c.getBBox(); return [c.dataset.node, b.x, b.y, b.x + b.width, b.y + b.height];
        })"""
    )
    covered = [
        (a[0], f"node {b[0]}")
        for a in boxes
        for b in nodes
        if a[1] < b[3] and a[3] > b[1] and a[2] < b[4] and a[4] > b[2]
    ]
    assert not covered, covered
    assert all(b[1] >= 0 and b[3] <= 800 and b[2] >= 0 and b[4] <= 560 for b in boxes), boxes
    shown = {b[0] for b in boxes}
    assert {p["name"] for p in data(page, map_id)["pois"]} <= shown  # never a POI's label hidden


# ------------------------------------------------------------------ the map page's sessions


def test_a_one_walk_maps_sessions_table_lists_its_session(page, map_id, api):
    page.goto(f"/admin/maps/{map_id}")
    rows = page.locator("#map-sessions tbody tr")
    expect(rows).to_have_count(1)
    cells = rows.first.locator("td").all_inner_texts()
    version = api.get_map(map_id)["current_version"]
    # in the current version, poses, tags, detections used, rejected
    assert cells[0] == "yes"
    assert cells[1] not in {"—", ""}
    assert cells[2] == str(len(version["tags"]))
    assert cells[3] == str(version["detections_used"])


# ------------------------------------------------------------------ the keyboard and axe


def test_an_edge_takes_the_focus_with_tab_and_is_selected_with_enter_or_space(page, map_id):
    open_editor(page, map_id)
    graph = data(page, map_id)
    first = min(n["id"] for n in graph["nodes"])
    page.locator(f'[data-node="{first}"]').focus()
    page.keyboard.press("Tab")
    edge = focused(page)["edge"]
    assert edge is not None, focused(page)
    a, b = (int(x) for x in edge.split("-"))
    expect(status(page)).to_contain_text(f"Edge from node {a} to node {b} selected")
    expect(page.locator(f'[data-edge="{edge}"]')).to_have_attribute("aria-pressed", "true")
    page.keyboard.press("Escape")
    expect(status(page)).to_contain_text("Nothing selected")
    page.keyboard.press("Space")
    expect(status(page)).to_contain_text(f"Edge from node {a} to node {b} selected")


def test_the_first_tab_stop_skips_to_the_graph(page, map_id):
    open_editor(page, map_id)
    page.keyboard.press("Tab")
    expect(page.get_by_role("link", name="Skip to the corridor graph")).to_be_focused()
    page.keyboard.press("Enter")
    assert focused(page)["node"] is not None, focused(page)
    expect(status(page)).to_contain_text("selected")


def test_the_route_tester_says_its_result_after_the_page_reloads(page, map_id):
    page.goto(f"/admin/maps/{map_id}/route")
    page.locator("#route-from").select_option("tag:300")
    page.locator("#route-to").select_option("poi:Restroom")
    page.get_by_role("button", name="Plan the route").click()
    expect(page.locator("#route-steps li").last).to_contain_text("Restroom")
    expect(page.locator("#route-result h2")).to_be_focused()
    expect(page.locator(ANNOUNCER)).to_contain_text(re.compile(r"The route: [\d.]+ m, \d+ steps"))
    page.goto(f"/admin/maps/{map_id}/route?from=tag:300&to=poi:Nowhere")
    expect(page.locator("#route-error")).to_be_focused()
    expect(page.locator(ANNOUNCER)).to_contain_text("No route")


def test_a_whole_edit_by_keyboard_alone(page, map_id):
    """Select an edge, remove it, connect two nodes, add a point of interest, undo: keys only
    (no click, no focus() by the test), checked in the tables and the announcements."""
    open_editor(page, map_id)
    graph = data(page, map_id)
    ends = sorted(n["id"] for n in dead_ends(graph))
    a, b = ends[0], ends[-1]
    said = page.locator(ANNOUNCER)
    edges_table = page.locator("#editor-edges tbody")
    listed = page.locator("#editor-history li[data-edit-id]")
    count = listed.count()

    # to the graph: the skip link, then Tab to node a
    page.keyboard.press("Tab")
    page.keyboard.press("Enter")
    tab_to(page, f'[data-node="{a}"]')
    expect(said).to_contain_text(f"Node {a} selected")

    # connect a to b (C, Tab on to b, Enter): a loop in the corridor graph
    page.keyboard.press("c")
    expect(said).to_contain_text(f"Connecting from node {a}")
    tab_to(page, f'[data-node="{b}"]')
    expect(said).to_contain_text(f"Press Enter to connect node {a} to it")
    page.keyboard.press("Enter")
    expect(said).to_contain_text(f"Connect node {a} to node {b} (walk): done")
    expect(said).to_contain_text("The new edge is selected")
    expect(
        edges_table.locator(
            "th", has_text=re.compile(rf"^Node ({a} to node {b}|{b} to node {a}) \(selected\)$")
        )
    ).to_have_count(1)
    expect(listed).to_have_count(count + 1)

    # select the next edge along the corridor (on from b) and remove it: the loop keeps every
    # tag reachable
    after_b = next(n for n in neighbours(data(page, map_id))[b] if n != a)
    page.keyboard.press("]")
    expect(said).to_contain_text(f"Edge from node {b} to node {after_b} selected")
    page.keyboard.press("Delete")
    expect(said).to_contain_text(f"to node {after_b}: done")
    expect(listed).to_have_count(count + 2)
    expect(history(page).last).to_contain_text("remove the edge")
    expect(
        edges_table.locator(
            "th", has_text=re.compile(rf"^Node ({b} to node {after_b}|{after_b} to node {b})\b")
        )
    ).to_have_count(0)
    assert focused(page)["node"] is not None  # still in the graph

    # a point of interest at the selected node: P, type, Tab to the button, Enter
    page.keyboard.press("p")
    expect(page.get_by_label("Name")).to_be_focused()
    page.keyboard.type("Water fountain")
    page.keyboard.press("Tab")
    expect(page.get_by_role("button", name="Add at the selected place")).to_be_focused()
    page.keyboard.press("Enter")
    expect(said).to_contain_text("Add point of interest Water fountain: done")
    expect(listed).to_have_count(count + 3)
    expect(page.locator("#editor-to option", has_text="Water fountain")).to_have_count(1)

    # undo it (Ctrl+Z from where the focus is: the form's button)
    page.keyboard.press("Control+z")
    expect(said).to_contain_text("Undone: Add point of interest Water fountain")
    expect(listed).to_have_count(count + 2)
    expect(page.locator("#editor-to option", has_text="Water fountain")).to_have_count(0)

    # the same edge from the tables: its Select button
    edge = edge_between(data(page, map_id), a, b)
    assert edge is not None
    select = f'[id="edge-{edge["from"]}-{edge["to"]}-select"]'
    tab_to(page, select)
    page.keyboard.press("Enter")
    expect(said).to_contain_text(f"Edge from node {edge['from']} to node {edge['to']} selected")
    expect(page.locator(select)).to_be_focused()
    expect(page.locator(select)).to_have_attribute("aria-pressed", "true")

    # undo the removal and the connection: the map is as it was
    page.keyboard.press("Control+z")
    expect(listed).to_have_count(count + 1)
    page.keyboard.press("Control+z")
    expect(listed).to_have_count(count)
    expect(said).to_contain_text("Undone: Connect node")

    results = Axe().run(page)
    serious = [
        f"{v['id']} ({v['impact']}): {v['help']} — {[n['target'][0] for n in v['nodes'][:5]]}"
        for v in results.response["violations"]
        if v["impact"] in {"serious", "critical"}
    ]
    assert not serious, serious
