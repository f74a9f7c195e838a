"""The dashboard's first page as a person opens it: ``face-retarget serve`` in a process of its own
(127.0.0.1, a free port, its own review store, bounded in time) and one Chromium page on ``/``,
until both 3D viewers have drawn the sample (pixels read back from their WebGL canvases, not
just a canvas). Shared by tests/browser/test_first_page_speed.py (asserts the pixels) and
benchmarks/bench_first_page.py (prints the time); nothing here asserts a time.
"""

from __future__ import annotations

import importlib.util
import io
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from PIL import Image

ROOT = Path(__file__).resolve().parents[2]
#: dashboard.serve.COLD_FIRST_PAGE (not imported: this module must not import panel)
COLD_FIRST_PAGE = "FACE_RETARGET_COLD_FIRST_PAGE"
#: what the server logs once its first pages are built ahead (dashboard.warm)
FIRST_PAGES_READY = "first page: 2 of 2 pages built ahead ready"

#: per viewer, statistics of its canvas read back (``pixels()`` renders, then ``readPixels``):
#: the luminance variance and the share of pixels away from the background; null until its mesh
#: and track are in (a canvas drawn before them is the background alone)
DRAWN_STATS = """() => {
  const r = window.__faceRetarget;
  if (!r) return null;
  const vs = Object.entries(r.viewers);
  if (vs.length < 2) return null;
  const out = {};
  for (const [label, v] of vs) {
    if (!v.self.width || !v.self.mesh || !v.self.track) return null;
    const p = v.pixels(), d = p.data;
    const bg = [d[0], d[1], d[2]];  // a corner: the background
    let s = 0, s2 = 0, n = 0, away = 0;
    for (let i = 0; i < d.length; i += 4 * 5) {
      const y = d[i] + d[i + 1] + d[i + 2];
      s += y; s2 += y * y; n++;
      if (Math.abs(d[i] - bg[0]) + Math.abs(d[i + 1] - bg[1]) + Math.abs(d[i + 2] - bg[2]) > 30) away++;
    }
    const m = s / n;
    out[label] = { variance: s2 / n - m * m, foreground: away / n, width: p.width, height: p.height };
  }
  return out;
}"""

#: true once every viewer's canvas holds a drawn face (see DRAWN_STATS)
DRAWN = ("() => { const s = (" + DRAWN_STATS + ")(); return !!s && Object.values(s).every("
         "v => v.variance > 100 && v.foreground > 0.02); }")


class Server:
    """``face-retarget serve`` on 127.0.0.1 (``with Server() as srv``; ``srv.base``, ``srv.log``).

    ``cold``: the first page is built when asked for, as before issue 30 (the benchmark's
    reference). Otherwise entering waits until the server has built its first pages ahead
    (``timeout`` s at most) and then ``quiet`` s more: an idle server."""

    def __init__(self, cold: bool = False, timeout: float = 180.0, quiet: float = 1.0, log: Path | None = None):
        self.cold, self.timeout, self.quiet = cold, timeout, quiet
        self._tmp = tempfile.TemporaryDirectory(prefix="face-retarget-first-page-")
        self.log = Path(log) if log else Path(self._tmp.name) / "server.log"

    def __enter__(self) -> "Server":
        spec = importlib.util.spec_from_file_location("browser_harness", Path(__file__).with_name("conftest.py"))
        harness = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(harness)
        port = harness.free_port()
        env = dict(os.environ, PYTHONUNBUFFERED="1", PYTHONPATH=str(ROOT))
        env.pop(COLD_FIRST_PAGE, None)
        if self.cold:
            env[COLD_FIRST_PAGE] = "1"
        self._fh = open(self.log, "w")
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "core.cli", "serve", "--address", "127.0.0.1", "--port", str(port),
             "--data-dir", str(Path(self._tmp.name) / "data")],
            cwd=ROOT, env=env, stdout=self._fh, stderr=subprocess.STDOUT, start_new_session=True)
        self.base = f"http://127.0.0.1:{port}"
        try:
            harness.wait_http(self.base + "/liveness", self.timeout, self.proc, self.log)
            if not self.cold:
                deadline = time.monotonic() + self.timeout
                while FIRST_PAGES_READY not in self.log.read_text(errors="replace"):
                    if self.proc.poll() is not None or time.monotonic() > deadline:
                        raise RuntimeError(f"the server built no first page ahead within {self.timeout} s:\n"
                                           + self.log.read_text(errors="replace")[-3000:])
                    time.sleep(0.25)
            time.sleep(self.quiet)
        except BaseException:
            self.__exit__()
            raise
        return self

    def __exit__(self, *exc) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=10)
        self._fh.close()
        self._tmp.cleanup()


def open_first_page(browser, base: str, timeout_s: float = 120.0):
    """Open ``base + "/"`` in a fresh 1280x900 page and wait until both viewers have drawn.
    Returns ``(context, page, seconds from the request to both drawn, DRAWN_STATS)``; the caller
    closes the context."""
    ctx = browser.new_context(viewport={"width": 1280, "height": 900})
    page = ctx.new_page()
    t0 = time.monotonic()
    page.goto(base + "/", wait_until="commit")
    page.wait_for_function(DRAWN, timeout=timeout_s * 1000, polling=50)
    seconds = time.monotonic() - t0
    return ctx, page, seconds, page.evaluate(DRAWN_STATS)


#: the viewer of the target rig on the sample page
TARGET = "rocketbox_female_adult_02"
#: the α slider's title (plain words first, the paper's letter after)
ALPHA_TITLE = r"^Stay near the rig's own expressions \(Seol α\):"


def _group(page, title_re: str, label: bool = False):
    inner = page.locator("label" if label else ".bk-slider-title", has_text=re.compile(title_re))
    return page.locator(".bk-input-group:visible", has=inner)


def mark_track(page, label: str = TARGET) -> None:
    """Remember viewer ``label``'s current track (to notice when a new one is shown)."""
    page.evaluate("(l) => { window.__markedTrack = window.__faceRetarget.viewers[l].self.track; }", label)


def wait_new_track(page, label: str = TARGET, timeout_s: float = 60.0) -> None:
    """Until viewer ``label`` holds a track other than the one :func:`mark_track` remembered
    and has rendered it."""
    page.wait_for_function(
        "(l) => { const v = window.__faceRetarget.viewers[l].self; "
        "return v.track && v.track !== window.__markedTrack && v.pendingRender === null && v.stats.renders > 0; }",
        arg=label, timeout=timeout_s * 1000, polling=10)


def choose_method(page, label_text: str, timeout_s: float = 120.0) -> None:
    """Pick a method in the sidebar's list and wait until its result is shown."""
    mark_track(page)
    _group(page, r"^Method", label=True).locator("select").select_option(label=label_text)
    wait_new_track(page, timeout_s=timeout_s)


def change_alpha(page, key: str = "Home", timeout_s: float = 60.0) -> float:
    """Move the α slider with ``key`` on its handle (Home: its lower end) — one value change, one
    recompute — and wait until the target view shows the new result. Returns the seconds from
    the key press to the new track drawn."""
    mark_track(page)
    handle = _group(page, ALPHA_TITLE).locator(".noUi-handle")
    handle.focus()
    t0 = time.monotonic()
    page.keyboard.press(key)
    wait_new_track(page, timeout_s=timeout_s)
    return time.monotonic() - t0


def curve_pixels(page):
    """(H, W, 3) uint8 screenshot of the weight-curve plot (the page's first Bokeh canvas)."""
    png = page.locator(".bk-Canvas").first.screenshot()
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"))
