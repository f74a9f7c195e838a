"""Normal maps on the 3D viewer in headless Chromium (SwiftShader), tests/browser/normalmap_app.py.

* Orientation: the neutral's own baked map, read through the rig's UVs with the viewer's
  convention (row 0 = v 0, flipY false), renders like the smooth-shaded full-resolution mesh;
  the same map upside down does not (control). A map on a "fast"-shaded viewer switches it
  to the standard material (and back when removed).
* The dashboard view (Liu 2011 §5): on an expression frame, the decimated mesh (10 % of the
  triangles) with the blended normal map is closer to the full-resolution render than the
  decimated mesh with its own normals (mean absolute pixel difference over the face). Turning
  the map off makes (b) look like (c); a frame change sends a new map, nothing else big.

Screenshots go to tests/artifacts/normalmap_*.png.
"""

from __future__ import annotations

import importlib.util
import io
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
APP = "/normalmap_app"
BACKGROUND = (0x2B, 0x2F, 0x36)


@pytest.fixture(scope="module")
def nm_app():
    spec = importlib.util.spec_from_file_location("normalmap_app_under_test", ROOT / "tests" / "browser" / "normalmap_app.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def nm_url(panel_server):
    return panel_server("tests/browser/normalmap_app.py")


def open_app(page, url, labels):
    page.goto(url)
    page.wait_for_function(
        "(labels) => labels.every(l => { const v = window.__faceRetarget && window.__faceRetarget.viewers[l]; "
        "return v && v.self.width > 0 && v.self.stats.renders > 0 && v.self.pendingRender === null; })",
        arg=list(labels), timeout=90_000)
    page.wait_for_timeout(400)


def js(page, label, expr, arg=None):
    return page.evaluate(
        f"([label, arg]) => {{ const v = window.__faceRetarget.viewers[label]; return ({expr}); }}", [label, arg])


def shot(page, label, path=None) -> np.ndarray:
    from PIL import Image

    png = page.locator(f'canvas.face-retarget-canvas[data-label="{label}"]').screenshot(path=str(path) if path else None)
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(np.int64)


def foreground(img) -> np.ndarray:
    fg = np.abs(img - np.array(BACKGROUND)).sum(axis=2) > 24
    fg[:30] = False  # the label overlay
    return fg


def mad(a, b, mask) -> float:
    """Mean absolute difference per channel (0..255) over ``mask``."""
    return float(np.abs(a - b)[mask].mean())


@pytest.mark.browser
def test_neutral_map_renders_like_the_smooth_mesh_and_a_flipped_one_does_not(page, nm_url, nm_app, artifacts):
    plain, mapped, flipped, fast = nm_app.ORIENTATION_LABELS
    open_app(page, nm_url + APP + "?check=orientation", (plain, mapped, flipped, fast))
    info = js(page, mapped, "v.info()")
    assert info["material"] == "standard" and info["uvs"] and info["normalMap"]["width"] == 1024
    assert info["normalMap"]["height"] == 512 and info["normalMap"]["space"] == "object"
    assert js(page, plain, "v.info().normalMap") is None
    imgs = {lab: shot(page, lab, artifacts / f"normalmap_orientation_{lab.replace(' ', '_')}.png")
            for lab in (plain, mapped, flipped)}
    fg = foreground(imgs[plain])
    assert 0.15 < fg.mean() < 0.9
    same = mad(imgs[mapped], imgs[plain], fg)
    wrong = mad(imgs[flipped], imgs[plain], fg)
    off = (np.abs(imgs[mapped] - imgs[plain]).sum(axis=2) > 24)[fg].mean()
    print(f"orientation: MAD neutral map vs plain {same:.2f}, flipped map vs plain {wrong:.2f}; "
          f"{100 * off:.2f}% face pixels differ by > 24")
    assert same < 2.0 and off < 0.01, (same, off)
    assert wrong > 10 * same and wrong > 10

    # "fast" (per-vertex) shading cannot read a map: the viewer switches to the standard
    # material while a map is set, and back when it is removed
    info = js(page, fast, "v.info()")
    assert info["shading"] == "fast" and info["material"] == "standard" and info["normalMap"] is not None
    assert mad(shot(page, fast, artifacts / "normalmap_orientation_fast_with_map.png"), imgs[mapped], fg) < 0.5
    page.get_by_role("button", name="remove map").click()
    page.wait_for_function("(l) => window.__faceRetarget.viewers[l].info().material === 'fast'", arg=fast, timeout=30_000)
    page.wait_for_timeout(300)
    unmapped = shot(page, fast, artifacts / "normalmap_orientation_fast_removed.png")
    assert js(page, fast, "v.info().normalMap") is None
    assert foreground(unmapped).mean() > 0.15 and mad(unmapped, imgs[mapped], fg) > 0.5  # lit, per-vertex look


@pytest.mark.browser
def test_blended_map_restores_the_full_resolution_shading(page, nm_url, nm_app, artifacts):
    from core.io.gltf import read_rig

    rig = read_rig(nm_app.RIG)
    full, mapped, plain = (f"{rig.name} full resolution", f"{rig.name} decimated + normal map", f"{rig.name} decimated")
    open_app(page, nm_url + APP, (full, mapped, plain))
    page.wait_for_function("(l) => window.__faceRetarget.viewers[l].info().normalMap !== null", arg=mapped, timeout=30_000)
    infos = {lab: js(page, lab, "v.info()") for lab in (full, mapped, plain)}
    assert all(i["T"] == nm_app.T and js(page, lab, "v.frame") == nm_app.FRAME for lab, i in infos.items())
    assert infos[mapped]["V"] == infos[plain]["V"] < 0.2 * infos[full]["V"]
    assert infos[mapped]["normalMap"]["width"] == 512 and infos[plain]["normalMap"] is None
    assert all(i["material"] == "standard" for i in infos.values())
    page.screenshot(path=str(artifacts / "normalmap_page.png"))
    imgs = {lab: shot(page, lab, artifacts / f"normalmap_{name}.png")
            for lab, name in ((full, "full"), (mapped, "decimated_mapped"), (plain, "decimated_plain"))}
    face = foreground(imgs[full]) & foreground(imgs[mapped]) & foreground(imgs[plain])
    assert face.mean() > 0.1
    d_map = mad(imgs[mapped], imgs[full], face)
    d_plain = mad(imgs[plain], imgs[full], face)
    print(f"frame {nm_app.FRAME}: MAD to full resolution over {face.sum()} face pixels: decimated + map {d_map:.2f}, "
          f"decimated {d_plain:.2f}")
    assert d_map < 0.7 * d_plain, (d_map, d_plain)

    # a frame change from Python: a new map (H*W*3 bytes + envelope), the mesh arrays stay
    n0 = len(page.ws_frames)
    updates = infos[mapped]["normalMap"]["updates"]
    page.locator("select").first.select_option(str(nm_app.FRAME - 8))
    page.wait_for_function("([l, n]) => window.__faceRetarget.viewers[l].info().normalMap.updates > n",
                           arg=[mapped, updates], timeout=30_000)
    page.wait_for_timeout(300)
    got = sum(f["size"] for f in page.ws_frames[n0:] if f["dir"] == "in")
    print(f"frame change: {got} bytes in (map {256 * 512 * 3})")
    assert 256 * 512 * 3 <= got < 1.2 * 256 * 512 * 3
    assert js(page, mapped, "v.frame") == nm_app.FRAME - 8

    # map off: (b) shows the decimated mesh's own normals, i.e. looks like (c)
    page.get_by_role("button", name="Normal map on/off").click()
    page.wait_for_function("(l) => window.__faceRetarget.viewers[l].info().normalMap === null", arg=mapped, timeout=30_000)
    page.wait_for_timeout(400)
    off = shot(page, mapped, artifacts / "normalmap_decimated_map_off.png")
    ref = shot(page, plain, artifacts / "normalmap_decimated_plain_same_frame.png")
    fg = foreground(ref)
    assert mad(off, ref, fg) < 0.5
