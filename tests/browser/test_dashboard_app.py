"""The dashboard in headless Chromium: load the sample, change a solver setting, scrub, play,
switch method, upload a broken file. Pixels are compared, not just the DOM; screenshots go to
tests/artifacts/ (dashboard_*.png)."""

from __future__ import annotations

import io
import re
import time

import numpy as np
import pytest

APP = "/app"
pytestmark = pytest.mark.browser


def _img(png: bytes) -> np.ndarray:
    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(int)


def _changed(a, b) -> float:
    return float((np.abs(a - b).sum(axis=2) > 24).mean())


@pytest.fixture(scope="module")
def dash(panel_server, new_page, artifacts):
    base = panel_server("dashboard/app.py", timeout=120)
    ctx, page = new_page()
    page.set_viewport_size({"width": 1500, "height": 1100})
    t0 = time.monotonic()
    page.goto(base + APP)
    page.wait_for_function(
        "() => window.__faceRetarget && Object.keys(window.__faceRetarget.viewers).length === 2 && "
        "Object.values(window.__faceRetarget.viewers).every(v => v.self.stats.renders > 0)", timeout=120_000)
    page.wait_for_timeout(1500)
    page.load_s = time.monotonic() - t0
    yield page
    ctx.close()


def group(page, label):
    return page.locator("div.bk-input-group", has_text=label).first


def canvas3d(page, label):
    return page.locator(f'canvas.face-retarget-canvas[data-label="{label}"]')


def curves_png(page) -> np.ndarray:
    plots = [c for c in page.locator("canvas:not(.face-retarget-canvas)").all() if (c.bounding_box() or {}).get("height", 0) > 150]
    return _img(plots[0].screenshot())


def summary(page) -> str:
    # text selectors pierce Panel's shadow roots (document.body.innerText does not)
    return page.get_by_text("marker error RMS").first.inner_text()


def wait_text_change(page, old: str, timeout=60.0) -> str:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        new = summary(page)
        if new != old:
            return new
        page.wait_for_timeout(200)
    raise TimeoutError("the summary line did not change")


def viewer_frames(page):
    return page.evaluate("() => Object.values(window.__faceRetarget.viewers).map(v => v.frame)")


def server_ms(page) -> float:
    text = page.locator("table", has_text="server total").first.inner_text()
    return float(re.search(r"server total\s+([\d.]+) ms", text).group(1))


def set_frame_fraction(page, fraction):
    g = group(page, "Frame:")
    base = g.locator(".noUi-base").bounding_box()
    handle = g.locator(".noUi-handle").bounding_box()
    y = handle["y"] + handle["height"] / 2
    page.mouse.move(handle["x"] + handle["width"] / 2, y)
    page.mouse.down()
    page.mouse.move(base["x"] + fraction * base["width"], y, steps=6)
    page.mouse.up()
    page.wait_for_function(
        "() => { const vs = Object.values(window.__faceRetarget.viewers); const f = vs[0].frame; "
        "return f > 0 && vs.every(v => v.frame === f && v.self.lastShown === f && v.self.pendingRender === null); }",
        timeout=30_000)
    page.wait_for_timeout(400)


def test_loads_sample_with_faces_curves_and_no_external_requests(dash, artifacts):
    page = dash
    page.screenshot(path=str(artifacts / "dashboard_loaded.png"), full_page=True)
    for label in ("ict_facekit", "rocketbox_female_adult_02"):
        img = _img(canvas3d(page, label).screenshot())
        spread = img.reshape(-1, 3).std(0).mean()
        assert spread > 10, f"{label} canvas looks blank"
    cur = curves_png(page)
    coloured = (np.abs(cur - cur.mean(axis=(0, 1))).sum(axis=2) > 60) & (cur.std(axis=2) > 20)
    assert coloured.mean() > 0.005, "no coloured curves drawn"
    assert "marker error RMS" in summary(page)
    assert not [r for r in page.requests if not r.startswith(("http://127.0.0.1", "ws://127.0.0.1", "data:", "blob:"))]
    assert not [e for e in page.console_errors if "Rejected map override" not in e]
    print(f"dashboard load {page.load_s:.1f}s")


def test_alpha_change_redraws_curves_and_target_face(dash, artifacts):
    page = dash
    set_frame_fraction(page, 0.4)
    before_curves = curves_png(page)
    before_face = _img(canvas3d(page, "rocketbox_female_adult_02").screenshot())
    old = summary(page)
    handle = group(page, "Alpha:").locator(".noUi-handle")
    handle.focus()
    for _ in range(20):
        page.keyboard.press("ArrowRight")
    wait_text_change(page, old)
    page.wait_for_timeout(2500)  # the new track reaches the browser and renders
    after_curves = curves_png(page)
    after_face = _img(canvas3d(page, "rocketbox_female_adult_02").screenshot(path=str(artifacts / "dashboard_alpha.png")))
    assert _changed(before_curves, after_curves) > 0.002
    assert _changed(before_face, after_face) > 0.0005
    ms = server_ms(page)
    print(f"server total after an alpha change: {ms:.1f} ms")
    assert ms < 5000


def test_scrub_moves_both_viewers_and_the_cursor(dash):
    page = dash
    set_frame_fraction(page, 0.2)
    f1 = viewer_frames(page)
    c1 = curves_png(page)
    set_frame_fraction(page, 0.7)
    f2 = viewer_frames(page)
    c2 = curves_png(page)
    assert f1[0] == f1[1] and f2[0] == f2[1] and f2[0] > f1[0]
    assert _changed(c1, c2) > 0.0005  # the red time cursor moved


def test_play_advances_both_viewers_in_the_browser(dash):
    page = dash
    f0 = viewer_frames(page)[0]
    page.get_by_role("button", name=re.compile("Play")).click()
    page.wait_for_timeout(2500)
    page.get_by_role("button", name=re.compile("Play")).click()
    page.wait_for_timeout(800)
    f = viewer_frames(page)
    assert abs(f[0] - f[1]) <= 1
    advanced = (f[0] - f0) % 2028
    print(f"frames advanced in 2.5 s of playback: {advanced}")
    assert advanced > 5


def test_switching_method_recomputes(dash):
    page = dash
    group(page, "Method").locator("select").select_option("prior_pf")
    page.get_by_text("method prior_pf").first.wait_for(timeout=60_000)


def test_broken_upload_shows_a_readable_error(dash, artifacts):
    page = dash
    page.locator("input[type=file]").set_input_files(
        files=[{"name": "broken.csv", "mimeType": "text/csv", "buffer": b"Timecode,BlendShapeCount\n1,2,3\n"}])
    banner = page.get_by_text(re.compile(r"Error: broken\.csv")).first
    banner.wait_for(timeout=60_000)
    page.screenshot(path=str(artifacts / "dashboard_error.png"), full_page=True)
    text = banner.inner_text()
    assert text.startswith("Error: broken.csv") and "line 2" in text  # file, field, what was expected
    assert "/tmp/" not in text
    assert page.get_by_text("Traceback").count() == 0
