"""Shared review in Chromium: two pages joined to one shot see each other's settings, edits,
seeks and notes; after ``kill -9`` of the server and a restart on the same data directory the
note and the edit are there. Cross-page propagation is timed (printed and written to
tests/artifacts/review_measurements.json); screenshots tests/artifacts/review_*.png.

The server is ``face-retarget serve --data-dir <tmp>`` (the review store), started here on
127.0.0.1 and killed in a finally block.
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time

import pytest

from conftest import ROOT, free_port, wait_http
from test_dashboard import METHOD_LABEL, VIEWERS_READY

MEASURED: dict = {}


def start_server(data_dir, log, *extra: str):
    port = free_port()
    cmd = [sys.executable, "-m", "core.cli", "serve", "--address", "127.0.0.1", "--port", str(port),
           "--data-dir", str(data_dir), *extra]
    fh = open(log, "a")
    proc = subprocess.Popen(cmd, cwd=ROOT, env=dict(os.environ, PYTHONUNBUFFERED="1"), stdout=fh, stderr=subprocess.STDOUT,
                            start_new_session=True)
    wait_http(f"http://127.0.0.1:{port}/liveness", 90, proc, log)
    return proc, fh, f"http://127.0.0.1:{port}"


def new_shared_shot(new_page, base):
    """A fresh page at ``base`` that turns what it shows into a shared shot: (context, page, shot id)."""
    ctx, page = new_page()
    page.goto(base + "/")
    page.get_by_text("Shared review", exact=True).first.click()  # the card is collapsed until used
    page.get_by_role("button", name=re.compile("New shared shot")).click()
    page.wait_for_url(re.compile(r"\?shot="), timeout=30_000)
    page.wait_for_function(VIEWERS_READY, timeout=120_000)
    return ctx, page, re.search(r"shot=([^&]+)", page.url).group(1)


def summary(page):
    return page.locator("p", has_text="marker error RMS").first


def method_select(page):
    return page.get_by_label("Method", exact=True)


# Propagation is timed inside the receiving page (a poller started before the action; its
# wall clock is this machine's, like the test's): Playwright's own retries wait up to a second
# between checks.
DEEP_TEXT = ("const deep = (r) => { let t = r.textContent || ''; r.querySelectorAll('*').forEach(e => "
             "{ if (e.shadowRoot) t += ' ' + deep(e.shadowRoot); }); return t; };")


def arm(page, predicate: str, arg=None, every_ms: int = 20):
    """Start polling ``predicate`` (a JS function of ``arg``) in ``page``; :func:`seen` waits."""
    page.evaluate(
        "([src, arg, every]) => { const f = eval(src); window.__seen = new Promise(r => { const tick = () => "
        "f(arg) ? r(Date.now()) : setTimeout(tick, every); tick(); }); }", [predicate, arg, every_ms])


def seen(page, name, t_action, timeout_s=15.0):
    t = page.evaluate(f"() => Promise.race([window.__seen, new Promise(r => setTimeout(() => r(null), {int(timeout_s * 1000)}))])")
    assert t is not None, f"{name}: not seen on the other page within {timeout_s} s"
    MEASURED[f"{name}_propagation_s"] = round(t / 1000 - t_action, 3)
    print(f"{name}: {MEASURED[f'{name}_propagation_s']} s")


def has_text(regex: str) -> str:
    return f"(re) => {{ {DEEP_TEXT} return new RegExp(re).test(deep(document)); }}"


@pytest.mark.browser
def test_two_pages_one_shot_and_a_kill_minus_9(new_page, tmp_path, artifacts):
    from playwright.sync_api import expect

    log = artifacts / "server_review.log"
    log.write_text("")
    proc, fh, base = start_server(tmp_path / "data", log)
    try:
        ctx_a, a, sid = new_shared_shot(new_page, base)
        assert len(sid) >= 16  # >= 96 random bits, url-safe
        ctx_b, b = new_page()
        b.goto(f"{base}/?shot={sid}")
        b.wait_for_function(VIEWERS_READY, timeout=120_000)
        # names, and each page lists the other
        for pg, name in ((a, "ana"), (b, "bo")):
            box = pg.locator("input.fr-name")
            box.fill(name)
            box.press("Enter")
            box.blur()
        expect(b.get_by_text(re.compile(r"Here now: ana, bo"))).to_be_visible(timeout=15_000)

        # a setting, the method: the other page shows it (its widget, timed in that page), then
        # its result (recomputed)
        method_select(b).evaluate(
            "(el, want) => { window.__seen = new Promise(r => { const tick = () => el.value === want ? "
            "r(Date.now()) : setTimeout(tick, 5); tick(); }); }", METHOD_LABEL["bounded"])
        t0, w0 = time.monotonic(), time.time()
        method_select(a).select_option(label=METHOD_LABEL["bounded"])
        seen(b, "setting", w0)
        expect(summary(b)).to_contain_text("method bounded", timeout=15_000)
        MEASURED["setting_result_s"] = round(time.monotonic() - t0, 3)  # Playwright-polled: an upper bound
        print(f"setting result: {MEASURED['setting_result_s']} s")
        # an edit from page b's Edit card, seen on page a
        b.locator(".bk-input-group:visible", has=b.locator("label", has_text="Shape")).locator("select").select_option(
            "AK_25_JawOpen")
        slider = b.locator(".bk-input-group:visible", has=b.locator(".bk-slider-title", has_text=re.compile("^Frame:")))
        slider.first.locator(".noUi-handle").focus()
        for _ in range(20):
            b.keyboard.press("ArrowRight")
        EDIT = r"frame \d+: .?AK_25_JawOpen"
        arm(a, has_text(EDIT), EDIT, every_ms=50)
        w0 = time.time()
        b.get_by_role("button", name="Set pose at this frame").click()
        seen(a, "edit", w0)
        # a note from page a, seen on page b
        a.get_by_placeholder("a note at this frame…").fill("the jaw opens late here")
        arm(b, has_text("the jaw opens late here"), "the jaw opens late here", every_ms=50)
        w0 = time.time()
        a.get_by_role("button", name="Add note at this frame").click()
        seen(b, "note", w0)
        # the presenter seeks, the follower follows
        a.get_by_role("button", name=re.compile("Present: the others follow")).click()
        sa = a.locator(".bk-input-group:visible", has=a.locator(".bk-slider-title", has_text=re.compile("^Frame:")))
        sa.first.locator(".noUi-handle").focus()
        FRAME = "Object.values(window.__faceRetarget.viewers)[0].frame"
        want = a.evaluate(f"() => {FRAME}") + 1
        arm(b, f"(want) => {FRAME} === want", want, every_ms=5)
        w0 = time.time()
        a.keyboard.press("ArrowRight")
        seen(b, "seek", w0)
        a.wait_for_function(f"() => {FRAME} === {want}")  # the presenter is there too
        a.wait_for_timeout(1000)
        a.screenshot(path=str(artifacts / "review_page_a.png"))
        b.screenshot(path=str(artifacts / "review_page_b.png"))
        ctx_a.close()
        ctx_b.close()

        # kill -9 and restart on the same data directory: the note and the edit are there
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(timeout=30)
        fh.close()
        proc, fh, base = start_server(tmp_path / "data", log)
        ctx_c, c = new_page()
        c.goto(f"{base}/?shot={sid}")
        c.wait_for_function(VIEWERS_READY, timeout=120_000)
        expect(c.get_by_text(re.compile("the jaw opens late here"))).to_be_visible(timeout=30_000)
        expect(c.get_by_text(re.compile(r"frame \d+: .?AK_25_JawOpen"))).to_be_visible(timeout=30_000)
        expect(summary(c)).to_contain_text("method bounded", timeout=30_000)
        c.screenshot(path=str(artifacts / "review_after_kill.png"))
        ctx_c.close()
        from core.store import Store

        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=30)
        st = Store(tmp_path / "data")
        assert st.integrity_check() in ("ok", True) or st.integrity_check() == ["ok"]
        st.close()
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
        fh.close()
        (artifacts / "review_measurements.json").write_text(json.dumps(MEASURED, indent=2) + "\n")
    for k, v in MEASURED.items():  # the 1 s target is the benchmark's (benchmarks/bench_review.py); here: no hang
        assert v < 5.0, f"{k} took {v} s"


@pytest.mark.browser
def test_a_warm_page_made_ahead_works_in_chromium(new_page, tmp_path, artifacts):
    """A page of the shot built, caught up and rendered while the server was idle
    (dashboard.warm: its HTML made with a stand-in token) is handed out to Chromium: it connects
    with the token written into it, shows the shot as it is now, and its changes reach the
    first page."""
    from playwright.sync_api import expect

    log = artifacts / "server_review_warm.log"
    log.write_text("")
    proc, fh, base = start_server(tmp_path / "data", log, "--warm-pages", "1", "--warm-wait", "2")
    try:
        ctx_a, a, sid = new_shared_shot(new_page, base)
        box = a.locator("input.fr-name")
        box.fill("ana")
        box.press("Enter")
        # a change while the warm page waits: it catches up, then its page is made again
        method_select(a).select_option(label=METHOD_LABEL["bounded"])
        expect(summary(a)).to_contain_text("method bounded", timeout=30_000)
        t0 = time.monotonic()
        while "1 warm pages current, their documents made" not in log.read_text(errors="replace"):
            assert time.monotonic() - t0 < 120, log.read_text(errors="replace")[-3000:]
            time.sleep(0.5)
        ctx_b, b = new_page()
        encodings = []  # (url, Content-Encoding) of the blobs the page fetched
        b.on("response", lambda r: encodings.append((r.url, r.headers.get("content-encoding")))
             if "/face-retarget/payload/" in r.url else None)
        b.goto(f"{base}/?shot={sid}")
        b.wait_for_function(VIEWERS_READY, timeout=120_000)
        # the meshes came gzip-compressed (dashboard.payloads) and the viewers decoded them
        assert sum(enc == "gzip" for _, enc in encodings) >= 2, encodings
        handed = [ln for ln in log.read_text(errors="replace").splitlines() if "a warm page handed out" in ln]
        assert handed and handed[-1].endswith("(its page and document made ahead)"), handed
        expect(summary(b)).to_contain_text("method bounded", timeout=15_000)
        box = b.locator("input.fr-name")
        box.fill("bo")
        box.press("Enter")
        expect(a.get_by_text(re.compile(r"Here now: ana, bo"))).to_be_visible(timeout=15_000)
        method_select(b).select_option(label=METHOD_LABEL["spacetime"])
        expect(summary(a)).to_contain_text("method spacetime", timeout=30_000)
        b.wait_for_timeout(500)
        b.screenshot(path=str(artifacts / "review_warm_page.png"))
        assert not b.console_errors, b.console_errors
        assert not any("cdn" in u for u in b.requests), [u for u in b.requests if "cdn" in u]
        ctx_a.close()
        ctx_b.close()
    finally:
        os.killpg(proc.pid, signal.SIGKILL)
        fh.close()
