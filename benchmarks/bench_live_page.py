"""Benchmark: the Live tab's drawn frame rate in headless Chromium (software WebGL, SwiftShader).

Case ``live_page_fps``: the real ``face-retarget serve`` (tests/browser/conftest.py ``served``),
the Live tab listening on 127.0.0.1, the S07 take sent to it as Live Link Face packets at 60 Hz;
both live views (ICT FaceKit source, 14,629 vertices, 53 shapes; Rocketbox target) draw the
streamed weights. Per-frame time = measured seconds / frames drawn (mean of the two views).

* ours: the page as shipped (each frame sent to the page as the server answers it; viewer.js
  ``blendCpu``: streamed weights blended incrementally over the changed shapes' supports, drawn
  in the animation frame they are blended in, at the render scale the view's frame cost calls
  for: ``frameCost``).
* ref: the same page and stream with ``window.__faceRetargetFullBlend = true``: every frame
  re-blended from scratch over the dense deltas (the blend before issue 31's change; the render
  scale adapts in both).

The two alternate in the same page (ours, ref, ours, ref; WINDOW_S each) so that the machine's
load (``load1``; 2 cores shared by several agents) weighs on both alike. Extra keys: the JS
blend of both views per drawn frame, timed alone afterwards on 60 of the weight vectors they
received (every second one, as drawn at ~30 fps; best of 5; ``blend_ms`` ours, ``ref_blend_ms``
the dense blend from scratch: viewer.js ``benchBlend``), the page's own animation frames
per second (``page_fps``: what the browser could draw at all; each frame waits on SwiftShader,
whose drawing of the two meshes is most of a frame, see ``tests/artifacts/live_tab.json``), and
the weight messages each view received per second from the server (``messages_per_s``: a view
cannot draw more new frames than that), and ``scales``: the share of ours' drawn frames at each
render scale (1, 0.75, 0.5; every one a new frame of the stream).

Run: ``python benchmarks/bench_live_page.py`` (needs /usr/bin/chromium and ``npm ci``).
"""

from __future__ import annotations

import importlib.util
import os
import socket
import sys
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

from core.io.livelink import read_livelink  # noqa: E402
from core.io.livelink_udp import ARKIT_CHANNELS, encode  # noqa: E402

TAKE = ROOT / "data/performances/livelinkface_take_s07.csv"
WINDOW_S = 5.0
ROUNDS = 2
READY = ("() => window.__faceRetarget && Object.keys(window.__faceRetarget.viewers).length === 2 && "
         "Object.values(window.__faceRetarget.viewers).every(v => v.self.width > 0 && v.self.stats.renders > 0)")
LIVE_READY = ("() => Object.entries(window.__faceRetarget.viewers).filter(([k, v]) => k.startsWith('live ') && "
              "v.self.width > 0).length === 2")
# keep the weights each live view receives (to time the blend alone on them afterwards)
RECORD_STREAM = """() => { window.__benchStream = {};
  for (const [k, v] of Object.entries(window.__faceRetarget.viewers)) {
    if (!k.startsWith('live ')) continue;
    const rec = window.__benchStream[k] = [], self = v.self, orig = self.receiveStreamed.bind(self);
    self.receiveStreamed = (w) => { if (rec.length < 400) rec.push(Array.from(w)); orig(w); };
  } }"""
COUNT_FRAMES = """() => { const c = window.__benchFrames = {n: 0};
  const tick = () => { c.n += 1; requestAnimationFrame(tick); }; requestAnimationFrame(tick); }"""


def _harness():
    """tests/browser/conftest.py (served, free_port, the Chromium path and flags), by path."""
    spec = importlib.util.spec_from_file_location("browser_harness", ROOT / "tests" / "browser" / "conftest.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def take_values() -> np.ndarray:
    """(T, 61) the take in the packet's channel order (NaN: 0)."""
    perf = read_livelink(TAKE)
    col = {c.lower(): i for i, c in enumerate(perf.names)}
    arkit = np.column_stack([perf.data[:, col[c.lower()]] for c in ARKIT_CHANNELS])
    rot = np.hstack([perf.extras[k] for k in ("head_rotation", "eye_rotation_left", "eye_rotation_right")])
    return np.nan_to_num(np.hstack([arkit, rot]))


def _window(page, full: bool) -> dict:
    """Draws of the two live views over WINDOW_S seconds with the reference blend on or off."""
    page.evaluate(f"() => {{ window.__faceRetargetFullBlend = {str(full).lower()}; }}")
    time.sleep(0.5)
    page.evaluate("() => window.__faceRetargetStats.reset()")
    page.evaluate(COUNT_FRAMES)
    t0 = time.monotonic()
    time.sleep(WINDOW_S)
    stats = page.evaluate("() => JSON.parse(JSON.stringify(window.__faceRetargetStats.viewers))")
    frames = page.evaluate("() => window.__benchFrames.n")
    elapsed = time.monotonic() - t0
    live = [s for k, s in stats.items() if k.startswith("live ")]
    draws = sum(s.get("streamDraws", 0) for s in live)
    scales = {}
    for s in live:
        for k, n in s.items():
            if k.startswith("draws@"):
                scales[k[6:]] = scales.get(k[6:], 0) + n
    return {"elapsed": elapsed, "draws": draws / len(live), "page_frames": frames, "scales": scales,
            "messages": sum(s.get("streamed", 0) for s in live) / len(live),
            "blend_ms": sum(s.get("blendMs", 0) for s in live) / max(draws / len(live), 1)}


def main():
    h = _harness()
    if not Path(h.CHROMIUM).exists():
        raise RuntimeError(f"{h.CHROMIUM} not found: apt-get install -y chromium")
    from playwright.sync_api import sync_playwright

    X = take_values()
    log = Path(os.environ.get("TMPDIR", "/tmp")) / f"bench_live_page_server_{os.getpid()}.log"
    stop = threading.Event()
    with h.served(log, "--no-review") as base, sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=h.CHROMIUM, args=h.CHROMIUM_ARGS, headless=True)
        try:
            page = browser.new_page(viewport={"width": 1280, "height": 900})
            page.goto(base + "/")
            page.wait_for_function(READY, timeout=180_000)
            page.get_by_text("Live", exact=True).first.click()
            udp = h.free_port()
            address = page.locator("input[placeholder='HOST:PORT']")
            address.fill(f"127.0.0.1:{udp}")
            address.press("Enter")
            page.get_by_role("button", name="Listen").click()
            page.wait_for_function(LIVE_READY, timeout=180_000)

            def send():
                tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
                start = time.perf_counter()
                i = 0
                while not stop.is_set():
                    while time.perf_counter() < start + i / 60:
                        time.sleep(0.0005)
                    tx.sendto(encode("iPhone", i, X[i % len(X)]), ("127.0.0.1", udp))
                    i += 1
                tx.close()

            sender = threading.Thread(target=send, daemon=True)
            sender.start()
            time.sleep(3.0)  # the first frames make the shapes' normal deltas and supports
            page.evaluate(RECORD_STREAM)
            runs = {False: [], True: []}
            for _ in range(ROUNDS):
                for full in (False, True):
                    runs[full].append(_window(page, full))
            stop.set()
            sender.join(5)
            # the JS blend alone, on 60 weight vectors the views received (every 2nd: ~30 fps)
            blends = {label: page.evaluate(
                "(l) => { const v = window.__faceRetarget.viewers[l]; const ws = window.__benchStream[l]; "
                "return v.benchBlend(ws.filter((_, i) => i % 2 === 0).slice(0, 60), 5); }", label)
                for label in page.evaluate("() => Object.keys(window.__benchStream)")}
        finally:
            browser.close()

    def per_frame(rs):
        return sum(r["elapsed"] for r in rs) / max(sum(r["draws"] for r in rs), 1)

    ours, ref = per_frame(runs[False]), per_frame(runs[True])
    blend = sum(b["ours"] for b in blends.values())
    ref_blend = sum(b["ref"] for b in blends.values())
    page_fps = sum(r["page_frames"] for r in runs[False]) / sum(r["elapsed"] for r in runs[False])
    msgs = sum(r["messages"] for r in runs[False]) / sum(r["elapsed"] for r in runs[False])
    drawn = {}
    for r in runs[False]:
        for k, n in r["scales"].items():
            drawn[k] = drawn.get(k, 0) + n
    scales = "/".join(f"{k}:{n / max(sum(drawn.values()), 1):.2f}" for k, n in sorted(drawn.items(), reverse=True) if n)
    print(f"BENCH live_page_fps ours_s={ours:.4f} ref_s={ref:.4f} ratio={ref / ours:.2f} fps={1 / ours:.1f} "
          f"ref_fps={1 / ref:.1f} blend_ms={blend:.2f} ref_blend_ms={ref_blend:.2f} page_fps={page_fps:.1f} "
          f"messages_per_s={msgs:.1f} scales={scales or 'none'} "
          f"windows={ROUNDS}x{WINDOW_S:.0f}s load1={os.getloadavg()[0]:.1f} views=ict_facekit+rocketbox stream=60Hz "
          f"ref=full-dense-blend-every-frame", flush=True)


if __name__ == "__main__":
    main()
