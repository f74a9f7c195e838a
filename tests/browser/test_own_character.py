"""A first-time user's own character, end to end in Chromium, without the command line.

The test makes a rig the project does not bundle (the Jeeliz tiger with its shapes renamed and
its mesh scaled 1.2x: no layout exists for it), uploads it, chooses it as the target, lets the
page place the markers, moves one marker, retargets the bundled Live Link take onto it, plays,
changes a setting, downloads the GLB and re-opens it — then uploads bad files and checks each
gets its message and stays out of the lists. Screenshots of each step go to tests/artifacts/
own_*.png (looked at when the test was written); the time of each step is printed.
"""

from __future__ import annotations

import io
import re
import time

import numpy as np
import pytest

from test_dashboard import ALL_TEXT, VIEWERS_READY, canvas
from test_pick import camera, project

APP = "/app"
RIG_NAME = "my_character.glb"
TIMES: dict = {}


def sidebar_select(page, label):
    # anchored: "Method" is also inside "Jitter filter (per-frame methods)"
    return page.locator(".bk-input-group:visible",
                        has=page.locator("label", has_text=re.compile("^" + re.escape(label)))).locator("select")


def upload(page, name, data, mime="application/octet-stream"):
    page.locator("input[type=file]").set_input_files({"name": name, "mimeType": mime, "buffer": data})


def banner(page, pattern):
    return page.get_by_text(re.compile(pattern)).first


@pytest.fixture(scope="module")
def my_rig(tmp_path_factory):
    """The tiger renamed and scaled: GLB bytes and the Rig."""
    from core.io.gltf import read_rig, write_rig
    from core.model import Rig
    from datapaths import RIGS

    t = read_rig(RIGS / "jeeliz_tiger.glb")
    rig = Rig(t.neutral * 1.2, t.faces, t.deltas * 1.2, [f"my_{n}" for n in t.names], t.uvs, t.units, "my_character")
    path = tmp_path_factory.mktemp("own") / RIG_NAME
    write_rig(path, rig)
    return path.read_bytes(), rig


@pytest.fixture(scope="module")
def page(new_page, panel_server):
    base = panel_server("dashboard/app.py")
    ctx, pg = new_page()
    pg.goto(base + APP)
    pg.wait_for_function(VIEWERS_READY, timeout=120_000)
    yield pg
    ctx.close()


def step(name, t0):
    TIMES[name] = round(time.monotonic() - t0, 2)
    print(f"step {name}: {TIMES[name]} s")


@pytest.mark.browser
def test_own_rig_markers_retarget_play_download(page, my_rig, artifacts):
    data, rig = my_rig
    t0 = time.monotonic()
    upload(page, RIG_NAME, data, "model/gltf-binary")
    banner(page, rf"Note:.*{re.escape(RIG_NAME)}.*blend shapes.*rig lists").wait_for(timeout=30_000)
    step("upload", t0)
    # choose it as the target: the page says it has no layout, in its own words, and opens the Markers card
    t0 = time.monotonic()
    sidebar_select(page, "Target rig").select_option(label=f"⤒ {RIG_NAME}")
    msg = banner(page, rf"Error:.*{re.escape(RIG_NAME)} has no marker layout yet")
    msg.wait_for(timeout=60_000)
    text = msg.inner_text()
    assert "--" not in text and "/tmp" not in text and "face-retarget layout" not in text, text
    page.get_by_text("The views show the last good result").first.wait_for(timeout=10_000)
    page.screenshot(path=str(artifacts / "own_1_no_layout.png"))
    step("choose target (no layout)", t0)
    # place the markers automatically
    t0 = time.monotonic()
    page.get_by_role("button", name="Place markers automatically").click()
    page.get_by_text(re.compile(r"Placed 41 markers on my_character")).first.wait_for(timeout=120_000)
    from playwright.sync_api import expect

    # the page recomputes with the new markers: the summary names the new target, the banner goes
    expect(page.locator("p", has_text="marker error RMS").first).to_contain_text("my_character.glb", timeout=120_000)
    expect(banner(page, r"Error:")).to_be_hidden(timeout=10_000)
    page.wait_for_function(VIEWERS_READY, timeout=120_000)
    page.wait_for_timeout(1000)
    page.screenshot(path=str(artifacts / "own_2_markers_placed.png"))
    step("place markers + retarget", t0)
    # move one marker: toggle the mode, click the marker, click where it should go
    t0 = time.monotonic()
    page.get_by_role("button", name=re.compile("Move markers")).click()
    page.wait_for_timeout(500)
    label = "my_character"
    cam = camera(page, label)
    frame0 = rig.neutral  # the target shows frame 0 of the retargeted take: close to the neutral
    from core.registration import place_markers

    layout, _ = place_markers(rig)  # the same (deterministic) placement the page made
    target = layout.select(["NoseHead"]).points(frame0)[0]
    tip = int(np.argmin(np.linalg.norm(frame0 - target, axis=1)))
    front = frame0[:, 2] > frame0[tip, 2] - 0.1 * rig.size
    beside = int(np.flatnonzero(front)[np.argmin(np.abs(np.linalg.norm(frame0[front] - frame0[tip], axis=1) - 0.06 * rig.size))])
    x, y = project(cam, frame0[tip])[0]
    page.mouse.click(x, y)
    sel = page.get_by_text(re.compile(r"Marker \S+: now click where it should be|No marker there"))
    sel.first.wait_for(timeout=20_000)
    assert "now click" in sel.first.inner_text(), sel.first.inner_text()
    x2, y2 = project(cam, frame0[beside])[0]
    page.mouse.click(x2, y2)
    page.get_by_text(re.compile(r"Marker \S+ moved to vertex \d+")).first.wait_for(timeout=60_000)
    page.wait_for_function(VIEWERS_READY, timeout=120_000)
    page.screenshot(path=str(artifacts / "own_3_marker_moved.png"))
    step("move a marker", t0)
    # play, then change a setting (the method)
    t0 = time.monotonic()
    page.get_by_role("button", name=re.compile("Play")).first.click()
    # on a loaded machine the first frames can take longer than a fixed wait (it failed once at 1.5 s
    # in a fresh-clone run beside the benchmarks): wait for the target view to leave frame 0
    # (the viewers may be re-registered while the page updates: a missing one is "not yet")
    page.wait_for_function("() => { const v = Object.values(window.__faceRetarget.viewers)[1]; return !!v && v.frame > 0; }",
                           timeout=30_000)
    page.get_by_role("button", name=re.compile("Play")).first.click()
    frame = page.evaluate("() => Object.values(window.__faceRetarget.viewers)[1].frame")
    assert frame > 0, "playback did not advance"
    from core.stages.methods import METHODS

    sidebar_select(page, "Method").select_option(label=METHODS["bounded"].label)
    page.get_by_text(re.compile(r"method \*?\*?bounded|method bounded")).first.wait_for(timeout=60_000)
    page.screenshot(path=str(artifacts / "own_4_bounded.png"))
    step("play + change method", t0)
    # download the GLB and re-open it
    t0 = time.monotonic()
    with page.expect_download(timeout=60_000) as dl:
        page.get_by_role("button", name="Download GLB").click()
    path = dl.value.path()
    from core.io.gltf import read_animation, read_rig

    got, anim = read_rig(path), read_animation(path)
    assert got.n_vertices == rig.n_vertices and got.names == rig.names
    assert anim.n_frames > 1000 and anim.data.min() >= -1e-6 and anim.data.max() <= 1 + 1e-6
    step("download GLB", t0)
    text = page.evaluate(ALL_TEXT)
    assert "Traceback" not in text


def _glb_without_shapes(rig) -> bytes:
    """A valid GLB mesh with no morph targets."""
    import tempfile
    from pathlib import Path

    from core.io.gltf import write_rig
    from core.model import Rig

    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "plain.glb"
        write_rig(p, Rig(rig.neutral, rig.faces, np.zeros((0,) + rig.neutral.shape), [], None, "m", "plain"))
        return p.read_bytes()


@pytest.mark.browser
def test_bad_uploads_get_their_message_and_stay_out_of_the_lists(page, my_rig, artifacts):
    """(An empty file never leaves the browser: Bokeh's file input sends nothing for it; the
    server's own refusal of an empty upload is tested in tests/test_uploads.py.)"""
    _, rig = my_rig
    cases = [
        ("garbage.glb", b"\x00\x01 certainly not a binary glTF", r"garbage\.glb is not a GLB file"),
        ("no_shapes.glb", _glb_without_shapes(rig), r"no_shapes\.glb has no blend shapes"),
        ("no_frames.csv", b"Timecode,BlendShapeCount,EyeBlinkLeft\n", r"no_frames\.csv"),
        ("notes.txt", b"hello", r"notes\.txt: files of type \.txt"),
    ]
    for name, data, pattern in cases:
        t0 = time.monotonic()
        upload(page, name, data)
        b = banner(page, r"Error:\s*" + pattern)
        b.wait_for(timeout=30_000)
        msg = b.inner_text()
        assert "/tmp" not in msg and "b'" not in msg and "--" not in msg, msg
        options = page.evaluate("() => Array.from(document.querySelectorAll('*')).flatMap(e => e.shadowRoot ? "
                                "Array.from(e.shadowRoot.querySelectorAll('option')).map(o => o.textContent) : [])")
        assert not any(name in o for o in options), f"{name} was added to a list"
        TIMES[f"bad upload {name}"] = round(time.monotonic() - t0, 2)
        print(f"{name}: {msg}")
    page.evaluate("() => window.scrollTo(0, 0)")
    page.screenshot(path=str(artifacts / "own_5_bad_upload.png"))
