"""The contact sheet in Chromium on the real ``face-retarget serve`` (issue 32 item 4): open the
card, click a frame of the sheet and the page shows that frame; the summary's "max" error is a
link to the worst frame. Screenshot: tests/artifacts/contact_sheet_page.png (looked at when the
test was written)."""

from __future__ import annotations

import re

import pytest

from conftest import served
from core.contact_sheet import SHEET_FRAMES
from test_dashboard import VIEWERS_READY, slider_value


@pytest.fixture(scope="module")
def server(artifacts):
    with served(artifacts / "server_contact_sheet.log", "--no-review") as base:
        yield base


def _frame(page) -> int:
    return int(slider_value(page, r"^Frame:"))


def _wait_frame(page, frame: int, timeout_ms: int = 30_000) -> int:
    """The page's frame once it is ``frame`` (or what it is after ``timeout_ms``)."""
    for _ in range(timeout_ms // 250):
        if _frame(page) == frame:
            break
        page.wait_for_timeout(250)
    return _frame(page)


@pytest.mark.browser
@pytest.mark.slow
def test_click_a_frame_of_the_sheet_and_the_max_link(page, server, artifacts):
    page.goto(server + "/")
    page.wait_for_function(VIEWERS_READY, timeout=180_000)
    start = _frame(page)
    page.get_by_text("Contact sheet: the most expressive frames").first.click()
    frames = page.locator("a.fr-sheet-frame")
    frames.first.wait_for(timeout=90_000)
    assert frames.count() == SHEET_FRAMES
    page.wait_for_timeout(300)
    page.screenshot(path=str(artifacts / "contact_sheet_page.png"), full_page=True)
    wanted = [int(frames.nth(i).get_attribute("data-fr-frame")) for i in range(SHEET_FRAMES)]
    pick = next(f for f in wanted[1:] if f != start)
    frames.nth(wanted.index(pick)).locator("img").click()
    assert _wait_frame(page, pick) == pick
    assert page.url.rstrip("/") == server.rstrip("/")  # a jump, not a navigation
    # the summary's max: a link to the worst frame, which is the sheet's first
    link = page.locator("a.fr-worst-frame")
    assert re.fullmatch(r"[\d.]+ mm at frame \d+", link.inner_text().strip())
    worst = int(link.get_attribute("data-fr-frame"))
    assert worst == wanted[0] and worst != pick
    link.click()
    assert _wait_frame(page, worst) == worst
    page.screenshot(path=str(artifacts / "contact_sheet_worst_frame.png"), full_page=False)
    assert not [e for e in page.console_errors if "fr_frame" in e or "ReactiveHTML" in e]
