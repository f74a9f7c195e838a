"""A first-time user's page (issue 32), in Chromium against the real ``face-retarget serve``.

* The layout holds at 1280, 1440 and 1920 px: the main cards and plots do not overlap each other,
  and nothing sticks out of the page (bounding boxes, shadow roots included); no number in the
  page is printed in scientific notation. Screenshots: tests/artifacts/first_page_<width>.png.
* The whole path: open the page, drop a rig of one's own anywhere on the page (a copy of the
  bundled ICT head under another name: no marker layout), *Use as target* in its note (the page
  places the markers), see the result, create a shared shot, read the address bar (``?shot=``,
  no reload), open that address in a second browser context and see the same shot; a reload of
  the first page stays on it. Screenshots: tests/artifacts/first_path_*.png.

The server runs on a free 127.0.0.1 port with a review store in a temporary folder, and is
killed (its process group) at the end.
"""

from __future__ import annotations

import base64
import re

import pytest

from conftest import ROOT, served
from test_dashboard import VIEWERS_READY

WIDTHS = (1280, 1440, 1920)
RIG_NAME = "my_head.glb"

#: the page's main pieces by their handles (dashboard/app.py) and the two 3D views, with every
#: element inside them (shadow roots included): {name: [left, top, right, bottom]} and the
#: rightmost edge of anything inside, the page's client and scroll widths
BOXES = """() => {
  const want = ['fr-sidebar', 'fr-summary', 'fr-curves', 'fr-edit-column', 'fr-shapes'];
  const found = {};
  const walk = (root) => { for (const el of root.querySelectorAll('*')) {
      for (const c of want) if (el.classList.contains(c) && !found[c]) found[c] = el;
      if (el.tagName === 'CANVAS' && el.classList.contains('face-retarget-canvas')) found['view ' + el.dataset.label] = el;
      if (el.shadowRoot) walk(el.shadowRoot); } };
  walk(document);
  // (a Bokeh plot's renderers have empty placeholder elements, sized as they like: what they draw
  // is clipped to the plot's canvas, so they are not measured)
  const rightmost = (el) => { let r = el.getBoundingClientRect().right;
    const inner = (root) => { for (const e of root.querySelectorAll('*')) { const b = e.getBoundingClientRect();
        if (b.width > 0 && b.height > 0 && !String(e.className).includes('Renderer')) r = Math.max(r, b.right);
        if (e.shadowRoot) inner(e.shadowRoot); } };
    inner(el); if (el.shadowRoot) inner(el.shadowRoot); return r; };
  const boxes = {}, inside = {};
  for (const [k, el] of Object.entries(found)) { const b = el.getBoundingClientRect();
    boxes[k] = [b.left, b.top, b.right, b.bottom]; inside[k] = rightmost(el); }
  return {boxes, inside, client: document.documentElement.clientWidth, scroll: document.documentElement.scrollWidth};
}"""

#: the text a person can read in the page: every text node outside style and script elements,
#: shadow roots included
PAGE_TEXT = """() => { const out = []; const walk = (root) => {
    const it = document.createTreeWalker(root, NodeFilter.SHOW_TEXT);
    for (let n = it.nextNode(); n; n = it.nextNode()) {
      const p = n.parentElement; if (p && !['STYLE', 'SCRIPT', 'TEMPLATE', 'NOSCRIPT'].includes(p.tagName)) out.push(n.textContent); }
    for (const el of root.querySelectorAll('*')) if (el.shadowRoot) walk(el.shadowRoot); };
  walk(document); return out.join(' '); }"""

SCIENTIFIC = re.compile(r"\b\d+(\.\d+)?e[+-]?\d+\b", re.IGNORECASE)


@pytest.fixture(scope="module")
def server(artifacts, tmp_path_factory):
    with served(artifacts / "server_first_page.log", "--data-dir", str(tmp_path_factory.mktemp("review")), "--warm-pages", "0") as base:
        yield base


def overlap(a, b) -> float:
    """The area two [left, top, right, bottom] boxes share."""
    w = min(a[2], b[2]) - max(a[0], b[0])
    h = min(a[3], b[3]) - max(a[1], b[1])
    return max(w, 0) * max(h, 0)


def open_page(browser, url: str, width: int):
    ctx = browser.new_context(viewport={"width": width, "height": 900})
    page = ctx.new_page()
    page.console_errors = []
    page.on("pageerror", lambda exc: page.console_errors.append(str(exc)))
    page.goto(url)
    page.wait_for_function(VIEWERS_READY, timeout=180_000)
    return ctx, page


#: the text of the page's summary line (inside its shadow root)
SUMMARY = """() => { let t = null; const walk = (root) => { for (const el of root.querySelectorAll('*')) {
    if (t === null && el.classList.contains('fr-summary')) t = (el.shadowRoot || el).textContent;
    if (el.shadowRoot) walk(el.shadowRoot); } }; walk(document); return t || ''; }"""


def summary_text(page) -> str:
    return page.evaluate(SUMMARY)


@pytest.mark.browser
@pytest.mark.slow
def test_the_layout_holds_at_three_widths(browser, server, artifacts):
    for width in WIDTHS:
        ctx, page = open_page(browser, server + "/", width)
        try:
            page.wait_for_timeout(1000)  # the layout settles after the first render
            got = page.evaluate(BOXES)
            page.screenshot(path=str(artifacts / f"first_page_{width}.png"), full_page=True)
            boxes = got["boxes"]
            assert set(boxes) >= {"fr-sidebar", "fr-summary", "fr-curves", "fr-edit-column", "fr-shapes"}, boxes
            assert sum(k.startswith("view ") for k in boxes) == 2, boxes
            names = sorted(boxes)
            for i, a in enumerate(names):
                for b in names[i + 1:]:
                    assert overlap(boxes[a], boxes[b]) < 1.0, f"{width} px: {a} {boxes[a]} overlaps {b} {boxes[b]}"
            for name, right in got["inside"].items():
                assert right <= got["client"] + 0.5, f"{width} px: something in {name} ends at {right} px, past the page"
            edit, curves = boxes["fr-edit-column"], boxes["fr-curves"]
            assert got["inside"]["fr-edit-column"] <= edit[2] + 0.5, f"{width} px: the Edit card's contents stick out"
            assert got["inside"]["fr-curves"] <= edit[0] + 0.5, f"{width} px: the curves run under the Edit card"
            assert curves[2] - curves[0] > 0.4 * width, f"{width} px: the curves are squeezed ({curves})"
            assert got["scroll"] <= got["client"], f"{width} px: the page scrolls sideways ({got})"
            text = page.evaluate(PAGE_TEXT)
            assert not SCIENTIFIC.search(text), f"{width} px: scientific notation in the page: {SCIENTIFIC.search(text)}"
            assert "mm²" not in text and "per frame" in text
        finally:
            ctx.close()


def drop_file(page, target, name: str, data: bytes, mime: str) -> None:
    """Drop ``data`` as a file called ``name`` on ``target`` (a locator), as a file dragged in
    from the desktop: a DataTransfer carrying a File, dragover then drop."""
    dt = page.evaluate_handle(
        """([b64, name, mime]) => { const bin = atob(b64); const u = new Uint8Array(bin.length);
             for (let i = 0; i < bin.length; i++) u[i] = bin.charCodeAt(i);
             const dt = new DataTransfer(); dt.items.add(new File([u], name, {type: mime})); return dt; }""",
        [base64.b64encode(data).decode(), name, mime])
    target.dispatch_event("dragover", {"dataTransfer": dt})
    target.dispatch_event("drop", {"dataTransfer": dt})


def own_head(folder) -> bytes:
    """A head the project does not bundle: the ICT head with its ARKit-named shapes, 1.1x larger
    (other bytes, other vertex positions, no marker layout), as GLB bytes."""
    from core.io.gltf import read_rig, write_rig
    from core.model import Rig

    ict = read_rig(ROOT / "data" / "rigs" / "ict_facekit.glb")
    rig = Rig(ict.neutral * 1.1, ict.faces, ict.deltas * 1.1, list(ict.names), ict.uvs, ict.units, "my_head")
    write_rig(folder / RIG_NAME, rig)
    return (folder / RIG_NAME).read_bytes()


@pytest.mark.browser
@pytest.mark.slow
def test_the_whole_path_drop_a_rig_use_it_share_the_address(browser, server, artifacts, tmp_path):
    rig = own_head(tmp_path)
    ctx, page = open_page(browser, server + "/", 1440)
    other = None
    try:
        page.screenshot(path=str(artifacts / "first_path_1_open.png"))
        # the task first: the three choices and the method before the uploads and the review card
        order = page.evaluate("""() => { const own = (el) => Array.from(el.childNodes).filter((n) => n.nodeType === 3)
              .map((n) => n.textContent).join('').trim();
            const find = (t) => { let y = null; const walk = (root) => { for (const el of root.querySelectorAll('*')) {
                if (y === null && own(el).startsWith(t) && el.getBoundingClientRect().height > 0) y = el.getBoundingClientRect().top;
                if (el.shadowRoot) walk(el.shadowRoot); } }; walk(document); return y; };
            return ['Source performance', 'Target rig', 'Method', 'Drop a file anywhere', 'Shared review'].map(find); }""")
        assert None not in order and order == sorted(order), f"sidebar order (top px): {order}"
        # drop the rig on the curve plot: the page takes it, checks it and offers it
        drop_file(page, page.locator(".fr-curves").first, RIG_NAME, rig, "model/gltf-binary")
        note = page.get_by_text(re.compile(rf"Note:.*{re.escape(RIG_NAME)}.*blend shapes.*rig lists")).first
        note.wait_for(timeout=60_000)
        said = note.inner_text()
        assert "/tmp" not in said and "face-retarget-upload" not in said, said
        page.screenshot(path=str(artifacts / "first_path_2_dropped.png"))
        page.get_by_role("button", name="Use as target").click()
        # the page places the head's markers and shows the result on it
        page.wait_for_function(f"(name) => {{ const t = ({SUMMARY})(); return t.includes(name) && t.includes('marker error RMS'); }}",
                               arg=RIG_NAME, timeout=240_000)
        page.wait_for_function(VIEWERS_READY, timeout=60_000)
        page.wait_for_timeout(1000)
        mine = summary_text(page)
        assert f"→ ⤒ {RIG_NAME}" in mine, mine
        page.screenshot(path=str(artifacts / "first_path_3_result.png"))
        text = page.evaluate(PAGE_TEXT)
        assert "Placed 41 markers" in text, "the Markers card reports the automatic placement"
        assert not SCIENTIFIC.search(text), SCIENTIFIC.search(text)
        # share it: the Shared review card (collapsed until used) makes a shot of the page, in place
        page.evaluate("() => { window.__samePage = true; }")
        page.get_by_text("Shared review", exact=True).first.click()
        page.get_by_role("button", name=re.compile("New shared shot")).click()
        page.wait_for_function("() => /[?&]shot=/.test(window.location.search)", timeout=30_000)
        assert page.evaluate("() => window.__samePage === true"), "the page reloaded to show the shot"
        address = page.evaluate("() => window.location.href")
        sid = re.search(r"[?&]shot=([^&]+)", address).group(1)
        page.get_by_text(re.compile(rf"Share this page: \?shot={re.escape(sid)}")).first.wait_for(timeout=30_000)
        page.screenshot(path=str(artifacts / "first_path_4_shared.png"))
        # the address, as copied from the bar, in another browser: the same shot
        other, second = open_page(browser, address, 1440)
        second.wait_for_timeout(1000)
        theirs = summary_text(second)
        second.get_by_text(re.compile(rf"Share this page: \?shot={re.escape(sid)}")).first.wait_for(timeout=30_000)
        second.screenshot(path=str(artifacts / "first_path_5_second_browser.png"))
        numbers = re.compile(r"marker error RMS [\d.]+ mm \(per frame: max [\d.]+ mm at frame \d+\)")
        assert numbers.search(mine) and numbers.search(theirs).group(0) == numbers.search(mine).group(0), (mine, theirs)
        assert RIG_NAME in theirs, theirs
        # a reload of the first page stays on the shot
        page.reload()
        page.wait_for_function(VIEWERS_READY, timeout=180_000)
        assert f"shot={sid}" in page.evaluate("() => window.location.search")
        page.get_by_text(re.compile(rf"Share this page: \?shot={re.escape(sid)}")).first.wait_for(timeout=30_000)
        assert numbers.search(summary_text(page)).group(0) == numbers.search(mine).group(0)
        assert not page.console_errors and not second.console_errors, (page.console_errors, second.console_errors)
    finally:
        if other is not None:
            other.close()
        ctx.close()
