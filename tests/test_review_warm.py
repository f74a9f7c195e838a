"""Warm pages (dashboard.warm) on a real server: pages of a shot built ahead while the server is
idle are not participants and do not follow the shot while they wait; handed out, a page is the
shot as it is now (a change made while it waited included), joins under its reviewer's name,
and its own changes reach the other pages. Localhost only, one server, bounded in time."""

from __future__ import annotations

import asyncio
import math
import re
import time
from pathlib import Path

import pytest

import review_client as rc

ALPHA, BETA = re.compile(r"Seol α"), re.compile(r"Seol β")

# a real server that builds warm pages after seconds of quiet: 30-40 s a test
pytestmark = pytest.mark.slow


def _said(log: Path, what: str) -> list:
    return [ln for ln in log.read_text(errors="replace").splitlines() if what in ln]


async def _until(pred, timeout=20.0):
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        if pred():
            return True
        await asyncio.sleep(0.2)
    return False


def _people(page):
    (m,) = [m for m in page.doc.models if type(m).__name__ == "HTML" and "Here now" in str(getattr(m, "text", ""))]
    return lambda: str(page.value(m, "text"))


def _name(page, name):
    for nb in [m for m in page.doc.models if type(m).__name__.startswith("NameBox")]:
        page.set(nb, value=name)


def test_a_warm_page_is_the_shot_as_it_is_now(tmp_path):
    rc.register_models()
    sid = rc.sample_shot(tmp_path / "data", "warm", last_frame=199)
    log = tmp_path / "server.log"
    # --warm-wait 3: build while ana is on the shot after 3 s of quiet (the default waits 30 s)
    with rc.Server("--data-dir", str(tmp_path / "data"), "--warm-pages", "2", "--warm-wait", "3", log=log) as srv:
        async def scenario():
            (a,), _ = await rc.open_pages(srv.base, sid, 1)
            _name(a, "ana")
            # the server builds two pages once it is idle; they are nobody yet
            assert await _until(lambda: _said(log, "2 of 2 warm pages ready"), 120), log.read_text()[-2000:]
            people_a = _people(a)
            assert await _until(lambda: "ana" in people_a())
            assert "someone" not in people_a(), people_a()
            # a change while the warm pages wait
            alpha = a.one("Slider", title=ALPHA)
            at = math.log10(0.05)  # the α slider is over log10 α (dashboard.widgets.LogSlider)
            a.set(alpha, value=at, value_throttled=at)
            await asyncio.sleep(1.0)
            (b,), _ = await rc.open_pages(srv.base, sid, 1)
            assert len(_said(log, "a warm page handed out")) == 1
            b_alpha = b.one("Slider", title=ALPHA)
            assert await _until(lambda: b.value(b_alpha, "value") == at), b.value(b_alpha, "value")
            _name(b, "bo")
            assert await _until(lambda: "ana, bo" in people_a()), people_a()
            # the handed-out page is live: its change reaches the first page
            a_beta = a.one("Slider", title=BETA)
            b.set(b.one("Slider", title=BETA), value=0.2, value_throttled=0.2)
            assert await _until(lambda: a.value(a_beta, "value") == 0.2), a.value(a_beta, "value")
            # the page left waiting catches up with both changes while the server is idle, and its
            # document is made ahead: handed out, it is sent as made, then joins under its name
            made = len(_said(log, "their documents made"))
            assert await _until(lambda: len(_said(log, "their documents made")) > made, 60), log.read_text()[-2000:]
            (c,), _ = await rc.open_pages(srv.base, sid, 1)
            assert _said(log, "a warm page handed out")[-1].endswith("(its page and document made ahead)")
            assert c.value(c.one("Slider", title=ALPHA), "value") == at
            assert c.value(c.one("Slider", title=BETA), "value") == 0.2
            _name(c, "cy")
            assert await _until(lambda: "cy" in people_a() and "bo" in people_a()), people_a()
            for p in (a, b, c):
                assert not p.errors, p.errors
                await p.close()

        rc.run(scenario())
        assert srv.alive()
    assert not _said(log, "ERROR"), _said(log, "ERROR")


def test_a_shot_keeps_as_many_warm_pages_as_it_had_people_at_once(tmp_path):
    rc.register_models()
    sid = rc.sample_shot(tmp_path / "data", "peak", last_frame=59)
    log = tmp_path / "server.log"
    with rc.Server("--data-dir", str(tmp_path / "data"), "--warm-pages", "1", "--warm-wait", "3", log=log) as srv:
        async def scenario():
            pages, _ = await rc.open_pages(srv.base, sid, 3)  # three people at once; --warm-pages is 1
            assert await _until(lambda: "someone ×3" in _people(pages[0])(), 30), _people(pages[0])()
            assert await _until(lambda: _said(log, "3 of 3 warm pages ready"), 120), log.read_text()[-2000:]
            assert not _said(log, "4 of 4 warm pages ready")
            for p in pages:
                await p.close()
            # they come back: three pages ready for them
            again, _ = await rc.open_pages(srv.base, sid, 3)
            assert len(_said(log, "a warm page handed out")) == 3, _said(log, "warm page")
            for p in again:
                assert not p.errors, p.errors
                await p.close()

        rc.run(scenario())
