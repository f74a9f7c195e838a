"""The per-shape controls table in Chromium: it lists the target's shapes with the current
frame's weight, sorts by a column, and an edited gain reaches the solve (the curve follows)."""

from __future__ import annotations

import re

import pytest

from test_dashboard import VIEWERS_READY

APP = "/app"


@pytest.fixture(scope="module")
def page(new_page, panel_server):
    base = panel_server("dashboard/app.py")
    ctx, pg = new_page()
    pg.goto(base + APP)
    pg.wait_for_function(VIEWERS_READY, timeout=120_000)
    yield pg
    ctx.close()


@pytest.mark.browser
def test_shape_table_sorts_and_an_edited_gain_reaches_the_result(page, artifacts):
    from playwright.sync_api import expect

    page.get_by_text("Shapes (per-shape controls)").first.click()
    table = page.locator(".tabulator").first
    table.wait_for(timeout=30_000)
    expect(table.locator(".tabulator-row").first).to_be_visible(timeout=30_000)
    rows = table.locator(".tabulator-row")
    assert rows.count() > 10
    # sort by the current frame's weight, descending (two clicks on the header)
    header = table.locator(".tabulator-col", has_text="now")
    header.click()
    header.click()
    page.wait_for_timeout(500)
    first = rows.first.locator(".tabulator-cell[tabulator-field=shape]").inner_text()
    assert first.startswith(("AK_", "AA_", "AU_", "HB_", "SR_")), first
    # edit the gain of the most active shape now (the table's first row after the sort)
    row = rows.first
    gain = row.locator(".tabulator-cell[tabulator-field=gain]")
    gain.click()
    editor = gain.locator("input")
    editor.fill("2")
    editor.press("Enter")
    expect(page.locator("p", has_text="marker error RMS").first).to_be_visible(timeout=60_000)
    page.wait_for_timeout(2000)
    shown = table.locator(".tabulator-row", has_text=first).locator(".tabulator-cell[tabulator-field=gain]")
    expect(shown).to_have_text(re.compile(r"^2(\.0)?$"), timeout=30_000)
    page.wait_for_function(VIEWERS_READY, timeout=60_000)
    table.screenshot(path=str(artifacts / "shape_table.png"))
    page.screenshot(path=str(artifacts / "shape_table_page.png"), full_page=True)
    assert not page.console_errors, page.console_errors
