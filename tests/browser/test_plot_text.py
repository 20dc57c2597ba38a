"""User strings drawn by plotly.js are text, never markup (finding 12 of issue 19): a point of
interest named like a link or a styled span is drawn as written on the map plot — no live link,
no element it styles — in a real browser (headless Chromium) against a real server and worker.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from playwright.sync_api import expect

pytestmark = [pytest.mark.browser, pytest.mark.slow, pytest.mark.xdist_group("plot_text")]

POIS = Path(__file__).resolve().parents[2] / "data" / "demo" / "floor_2_pois.json"
LINK = '<a href="https://example.com/phish">Exit</a>'
STYLED = '<span style="position:fixed;top:0;left:0;font-size:80px">Fire exit</span>'
BUILD_TIMEOUT_S = 120.0


@pytest.fixture(scope="module")
def hostile_map(api, worker, tmp_path_factory: pytest.TempPathFactory) -> int:
    document = json.loads(POIS.read_bytes())
    document["location_data"][0]["name"] = LINK
    document["location_data"][1]["name"] = STYLED
    path = tmp_path_factory.mktemp("hostile") / "pois.json"
    path.write_text(json.dumps(document))
    worker.on()
    accepted = api.upload_session(path)
    api.wait_for_job(accepted["job_id"], timeout_s=BUILD_TIMEOUT_S)
    map_id: int = accepted["map_id"]
    return map_id


def test_point_of_interest_names_are_drawn_as_written(page, hostile_map: int) -> None:
    page.goto(f"/admin/maps/{hostile_map}")
    plot = page.locator(".plot").first
    expect(plot).to_have_attribute("data-rendered", "true")
    drawn = page.evaluate(
        """() => Array.from(document.querySelectorAll('.plot .textpoint text'))
                      .map((text) => text.textContent)"""
    )
    assert LINK in drawn
    assert STYLED in drawn
    assert page.locator(".plot a").count() == 0  # no link in the plot's SVG
    styled = page.evaluate(
        """() => Array.from(document.querySelectorAll('.plot [style]'))
                      .filter((e) => e.getAttribute('style').includes('position:fixed')
                                     || e.getAttribute('style').includes('position: fixed'))
                      .length"""
    )
    assert styled == 0
