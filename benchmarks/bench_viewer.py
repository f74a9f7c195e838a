"""Benchmark: the three.js viewer's frame time in headless Chromium (software WebGL, SwiftShader).

Case ``viewer_forced_frame_ict``: scripts/viewer_demo.py (ICT FaceKit, 14,629 vertices, 53
shapes, and Rocketbox on one Live Link Face take) served by ``panel serve`` as the browser
tests serve it (tests/browser/conftest.py); on the ICT viewer, ``v.benchRender(40, 200)``
renders track frames 200-239 back to back, each forced to finish with a 1-pixel readPixels:
the sustainable frame time, independent of the 30 fps capture clock (this was the browser test
that asserted ``0 < ms < 2000``).

* ours: the viewer as shipped (``blend=auto``: on a software renderer it blends the 53 shapes
  in JS and lights per vertex).
* ref: the same page with ``?blend=gpu``, three.js's own morph targets, in the same run.

``rocketbox_ms`` is ours on the Rocketbox viewer of the same page. Needs Debian Chromium at
/usr/bin/chromium and ``npm ci`` (three.js is served from node_modules).

Run: ``python benchmarks/bench_viewer.py``
"""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SRC = "ICT FaceKit (source)"
TGT = "Rocketbox Female_Adult_02 (target)"
FRAMES, START, REPEAT = 40, 200, 3


def _harness():
    """tests/browser/conftest.py (free_port, wait_http, the Chromium path and flags), by path:
    the module name ``conftest`` is ambiguous."""
    spec = importlib.util.spec_from_file_location("browser_harness", ROOT / "tests" / "browser" / "conftest.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _open(browser, base, query=""):
    ctx = browser.new_context(viewport={"width": 1280, "height": 900})
    page = ctx.new_page()
    page.goto(f"{base}/viewer_demo{query}")
    page.wait_for_function(
        "() => window.__faceRetarget && Object.keys(window.__faceRetarget.viewers).length === 2 && "
        "Object.values(window.__faceRetarget.viewers).every(v => v.self.width > 0 && v.self.stats.renders > 0)",
        timeout=120_000)
    page.wait_for_timeout(300)
    return ctx, page


def _frame_ms(page, label, expect_blend):
    """Best of REPEAT ``benchRender`` runs (ms per frame) on one viewer; checks the blend mode."""
    blend = page.evaluate("(l) => window.__faceRetarget.viewers[l].info().blend", label)
    if blend != expect_blend:
        raise RuntimeError(f"{label}: blend {blend!r}, expected {expect_blend!r}")
    return min(page.evaluate(f"(l) => window.__faceRetarget.viewers[l].benchRender({FRAMES}, {START})", label)
               for _ in range(REPEAT))


def main():
    h = _harness()
    if not Path(h.CHROMIUM).exists():
        raise RuntimeError(f"{h.CHROMIUM} not found: apt-get install -y chromium")
    from playwright.sync_api import sync_playwright

    port = h.free_port()
    log = Path(os.environ.get("TMPDIR", "/tmp")) / f"bench_viewer_server_{port}.log"
    cmd = [sys.executable, "-m", "panel", "serve", str(ROOT / "scripts" / "viewer_demo.py"), "--address", "127.0.0.1",
           "--port", str(port), "--allow-websocket-origin", f"127.0.0.1:{port}", "--liveness",
           "--plugins", "dashboard.assets"]
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    with open(log, "w") as fh:
        proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=fh, stderr=subprocess.STDOUT)
        try:
            base = f"http://127.0.0.1:{port}"
            h.wait_http(f"{base}/liveness", 120, proc, log)
            with sync_playwright() as pw:
                browser = pw.chromium.launch(executable_path=h.CHROMIUM, args=h.CHROMIUM_ARGS, headless=True)
                try:
                    ctx, page = _open(browser, base)
                    software = page.evaluate("(l) => window.__faceRetarget.viewers[l].info().software", SRC)
                    ours = _frame_ms(page, SRC, "cpu")
                    rocketbox = _frame_ms(page, TGT, "cpu")
                    ctx.close()
                    ctx, page = _open(browser, base, "?blend=gpu")
                    ref = _frame_ms(page, SRC, "gpu")
                    ctx.close()
                finally:
                    browser.close()
        finally:
            proc.terminate()
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(timeout=10)
    print(f"BENCH viewer_forced_frame_ict ours_s={ours / 1000:.4f} ref_s={ref / 1000:.4f} ratio={ref / ours:.2f} "
          f"V=14629 K=53 frames={FRAMES} ours=blend-auto(cpu) ref=blend-gpu(three.js-morph-targets) "
          f"rocketbox_ms={rocketbox:.1f} software_webgl={int(software)}", flush=True)


if __name__ == "__main__":
    main()
