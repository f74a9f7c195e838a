"""Direct manipulation on the 3D viewer (pick_mode="vertex") in headless Chromium (SwiftShader).

The page (tests/browser/pick_app.py) shows the Jeeliz tiger on frame 30 of a synthetic track
(mouth wide open) and prints the Python values of the viewer's ``picked`` / ``dragged``.
What the browser reports is checked against a reference computed here, independently of
three.js: the mesh of that frame from ``Rig.evaluate``, the camera matrices the browser
rendered with, a ray through the clicked pixel intersected with every triangle in numpy
(Möller–Trumbore), and the hit triangle's vertex nearest to the hit point.
"""

from __future__ import annotations

import importlib.util
import io
import json
import re
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
APP = "/pick_app"


# -- fixtures and helpers -----------------------------------------------------------------
@pytest.fixture(scope="module")
def pick_app():
    spec = importlib.util.spec_from_file_location("pick_app_under_test", ROOT / "tests" / "browser" / "pick_app.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def scene(pick_app):
    """(rig, track, mesh shown on the page's frame)."""
    from core.io.gltf import read_rig

    rig = read_rig(pick_app.RIG)
    W = pick_app.track(rig)
    return rig, W, rig.evaluate(W[pick_app.FRAME])


@pytest.fixture(scope="module")
def pick_url(panel_server):
    return panel_server("tests/browser/pick_app.py")


def open_app(page, base, label, query=""):
    page.goto(base + APP + query)
    page.wait_for_function(
        "(label) => { const v = window.__faceRetarget && window.__faceRetarget.viewers[label]; "
        "return v && v.self.width > 0 && v.self.stats.renders > 0 && v.self.pendingRender === null; }",
        arg=label, timeout=60_000)
    page.wait_for_timeout(300)


def js(page, label, expr, arg=None):
    return page.evaluate(
        f"([label, arg]) => {{ const v = window.__faceRetarget.viewers[label]; return ({expr}); }}", [label, arg])


def python_value(page, name):
    """The param's value as Python holds it (the page prints ``name=<json>``)."""
    text = page.get_by_text(re.compile(f"^{name}=")).inner_text()
    return json.loads(text[len(name) + 1:])


def wait_python_count(page, name, count, timeout=15_000):
    """Wait until Python holds the ``count``-th report of ``name`` (playwright pierces shadow DOM)."""
    from playwright.sync_api import expect

    expect(page.get_by_text(re.compile(f"^{name}="))).to_contain_text(f'"count": {count},', timeout=timeout)


def camera(page, label):
    c = js(page, label, "v.camera()")
    V = np.array(c["view"]).reshape(4, 4).T  # three.js elements are column-major
    P = np.array(c["projection"]).reshape(4, 4).T
    c["M"] = P @ V
    c["V"] = V
    c["position"] = np.array(c["position"])
    return c


def project(cam, points):
    """(N, 3) world points -> (N, 2) client pixel coordinates."""
    p = np.c_[np.atleast_2d(points), np.ones(len(np.atleast_2d(points)))] @ cam["M"].T
    ndc = p[:, :3] / p[:, 3:]
    return np.c_[cam["left"] + (ndc[:, 0] + 1) / 2 * cam["width"], cam["top"] + (1 - ndc[:, 1]) / 2 * cam["height"]]


def ray(cam, x, y):
    nx = (x - cam["left"]) / cam["width"] * 2 - 1
    ny = -((y - cam["top"]) / cam["height"] * 2 - 1)
    far = np.linalg.solve(cam["M"], [nx, ny, 1.0, 1.0])
    d = far[:3] / far[3] - cam["position"]
    return cam["position"], d / np.linalg.norm(d)


def reference_pick(mesh, faces, cam, x, y, front_only):
    """Nearest triangle hit by the pixel's ray (numpy Möller–Trumbore over all faces) and its
    vertex nearest to the hit point: (vertex, hit point, face) or (None, None, None)."""
    o, d = ray(cam, x, y)
    v0, v1, v2 = (mesh[faces[:, i]] for i in range(3))
    e1, e2 = v1 - v0, v2 - v0
    p = np.cross(d, e2)
    det = np.einsum("ij,ij->i", e1, p)
    ok = np.abs(det) > 1e-18
    if front_only:  # three culls faces whose normal e1 x e2 points away from the viewer
        ok &= np.einsum("ij,j->i", np.cross(e1, e2), d) < 0
    inv = np.where(ok, 1 / np.where(ok, det, 1), 0)
    s = o - v0
    u = np.einsum("ij,ij->i", s, p) * inv
    q = np.cross(s, e1)
    v = (q @ d) * inv
    t = np.einsum("ij,ij->i", e2, q) * inv
    hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
    if not hit.any():
        return None, None, None
    f = int(np.flatnonzero(hit)[np.argmin(t[hit])])
    point = o + t[f] * d
    tri = faces[f]
    return int(tri[np.argmin(np.linalg.norm(mesh[tri] - point, axis=1))]), point, tri


def canvas_box(page, label):
    return page.locator(f'canvas.face-retarget-canvas[data-label="{label}"]').bounding_box()


def shot(page, label, path):
    from PIL import Image

    png = page.locator(f'canvas.face-retarget-canvas[data-label="{label}"]').screenshot(path=str(path))
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"))


def yellow(img):
    """Pixels of the highlight colour #ffd400 (lit spheres are unlit MeshBasicMaterial)."""
    return (img[..., 0] > 200) & (img[..., 1] > 170) & (img[..., 2] < 90)


def check_pick(page, label, scene, cam, x, y, got, faces):
    rig, W, mesh = scene
    front_only = js(page, label, "v.info().shading") == "fast"
    want, point, tri = reference_pick(mesh, faces, cam, x, y, front_only)
    assert want is not None, "the reference ray misses the mesh: bad click position in the test"
    assert got["vertex"] == want, f"picked {got['vertex']}, the reference ray gives {want} (triangle {tri})"
    assert np.abs(np.array(got["position"]) - mesh[want]).max() < 1e-5 * rig.size, "position is not the shown vertex"
    # the vertex projects near the click: within the hit triangle's longest edge on screen
    px = project(cam, mesh[tri])
    edge = max(np.linalg.norm(px[i] - px[(i + 1) % 3]) for i in range(3))
    dist = np.linalg.norm(project(cam, mesh[want])[0] - [x, y])
    assert dist <= edge, f"picked vertex is {dist:.1f} px from the click (triangle edges up to {edge:.1f} px)"
    return dist


# -- tests --------------------------------------------------------------------------------
@pytest.mark.browser
def test_click_picks_the_vertex_under_the_pointer_on_the_morphed_mesh(page, pick_url, scene, pick_app, artifacts):
    rig, W, mesh = scene
    label = pick_app.LABEL
    open_app(page, pick_url, label)
    assert python_value(page, "picked") == {}
    assert js(page, label, "v.frame") == pick_app.FRAME
    box = canvas_box(page, label)
    cx, cy = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
    cam = camera(page, label)
    page.mouse.click(cx, cy)
    wait_python_count(page, "picked", 1)
    got = python_value(page, "picked")
    assert got["frame"] == pick_app.FRAME and got["count"] == 1
    dist = check_pick(page, label, scene, cam, cx, cy, got, rig.faces)
    print(f"centre click: vertex {got['vertex']} at {dist:.1f} px, pick took {js(page, label, 'v.self.stats.pickMs'):.1f} ms")
    assert python_value(page, "dragged") == {}, "a click is not a drag"
    assert np.allclose(camera(page, label)["V"], cam["V"]), "a click in pick mode moved the camera"

    # Python highlights the pick: a sphere on the shown vertex, visible on the canvas
    page.wait_for_function(f"() => window.__faceRetarget.viewers['{label}'].highlightPositions().length === 1", timeout=10_000)
    page.wait_for_timeout(300)
    hp = np.array(js(page, label, "v.highlightPositions()"))[0]
    assert np.abs(hp - mesh[got["vertex"]]).max() < 1e-5 * rig.size
    img = shot(page, label, artifacts / "pick_click.png")
    ys, xs = np.nonzero(yellow(img))
    assert len(xs) > 20, f"highlight sphere not visible ({len(xs)} yellow pixels)"
    # canvas pixels vs CSS pixels: the sphere sits where the vertex projects
    sx = img.shape[1] / box["width"]
    vp = (project(cam, mesh[got["vertex"]])[0] - [box["x"], box["y"]]) * sx
    assert np.hypot(xs.mean() - vp[0], ys.mean() - vp[1]) < 6 * sx

    # a vertex that the open mouth moved (mouthOpen's most moving one): clicking where it is
    # shown must pick it, and the neutral mesh would give another answer there
    v_mouth = int(np.argmax(np.linalg.norm(rig.deltas[rig.index("mouthOpen")], axis=1)))
    mx, my = project(cam, mesh[v_mouth])[0]
    front_only = js(page, label, "v.info().shading") == "fast"
    on_neutral, _, _ = reference_pick(rig.neutral, rig.faces, cam, mx, my, front_only)
    assert on_neutral != v_mouth, "test needs a point where neutral and shown mesh differ"
    page.mouse.click(mx, my)
    wait_python_count(page, "picked", 2)
    got = python_value(page, "picked")
    check_pick(page, label, scene, cam, mx, my, got, rig.faces)
    assert got["vertex"] != on_neutral
    shot(page, label, artifacts / "pick_mouth.png")
    assert not page.console_errors, page.console_errors


@pytest.mark.browser
def test_drag_reports_a_displacement_in_the_view_plane(page, pick_url, scene, pick_app, artifacts):
    rig, W, mesh = scene
    label = pick_app.LABEL
    open_app(page, pick_url, label)
    box = canvas_box(page, label)
    cx, cy = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
    cam = camera(page, label)
    ex, ey = cx + 90, cy - 50
    page.mouse.move(cx, cy)
    page.mouse.down()
    page.mouse.move(ex, ey, steps=10)
    page.wait_for_timeout(300)
    # while dragging: a preview line from the vertex to the pointer (drawn in the highlight colour)
    img = shot(page, label, artifacts / "pick_dragging.png")
    assert yellow(img).sum() > 30, "no drag preview line"
    page.mouse.up()
    wait_python_count(page, "dragged", 1)
    got = python_value(page, "dragged")
    assert python_value(page, "picked") == {}, "a drag is not a click"
    assert got["frame"] == pick_app.FRAME
    start, end = np.array(got["start"]), np.array(got["end"])
    want, _, _ = reference_pick(mesh, rig.faces, cam, cx, cy, js(page, label, "v.info().shading") == "fast")
    assert got["vertex"] == want
    assert np.abs(start - mesh[want]).max() < 1e-5 * rig.size
    delta = end - start
    assert np.linalg.norm(delta) > 0.02 * rig.size, f"drag displacement too small: {delta}"
    # in the camera plane through the start point ...
    forward = -cam["V"][2, :3]
    assert abs(delta @ forward) < 1e-4 * np.linalg.norm(delta)
    # ... ending where the pointer was released ...
    assert np.linalg.norm(project(cam, end)[0] - [ex, ey]) < 1.0
    # ... in the drag's direction on screen (right and up)
    right, up = cam["V"][0, :3], cam["V"][1, :3]
    screen = np.array([delta @ right, delta @ up])
    cos = screen @ [90, 50] / (np.linalg.norm(screen) * np.hypot(90, 50))
    assert cos > 0.99, f"drag direction on screen {screen} vs (90, 50)"
    assert np.allclose(camera(page, label)["V"], cam["V"]), "a vertex drag moved the camera"
    page.wait_for_timeout(300)
    img = shot(page, label, artifacts / "pick_dragged.png")
    assert not page.console_errors, page.console_errors


@pytest.mark.browser
def test_orbit_in_pick_mode_and_no_pick_when_off(page, pick_url, scene, pick_app, artifacts):
    label = pick_app.LABEL
    open_app(page, pick_url, label)
    box = canvas_box(page, label)
    cx, cy = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
    corner = (box["x"] + 12, box["y"] + 12)  # background
    cam0 = camera(page, label)["V"]

    def drag(x, y, dx, dy):
        page.mouse.move(x, y)
        page.mouse.down()
        page.mouse.move(x + dx, y + dy, steps=6)
        page.mouse.up()
        page.wait_for_timeout(300)

    # pick mode: alt + left drag on the mesh orbits, and nothing is picked or dragged
    page.keyboard.down("Alt")
    drag(cx, cy, 100, 0)
    page.keyboard.up("Alt")
    assert not np.allclose(camera(page, label)["V"], cam0), "alt-drag did not orbit"
    page.mouse.dblclick(*corner)  # double click off the mesh resets the camera
    page.wait_for_timeout(300)
    assert np.allclose(camera(page, label)["V"], cam0)
    # a left drag that starts off the mesh orbits too
    drag(*corner, 80, 0)
    assert not np.allclose(camera(page, label)["V"], cam0), "left drag off the mesh did not orbit"
    page.mouse.dblclick(*corner)
    page.wait_for_timeout(300)
    page.mouse.click(*corner)  # a click off the mesh picks nothing
    page.wait_for_timeout(500)
    assert python_value(page, "picked") == {} and python_value(page, "dragged") == {}

    # switch picking off with the Panel widget: a click does not pick, a drag orbits
    page.get_by_role("button", name="off").click()
    page.wait_for_function(f"() => window.__faceRetarget.viewers['{label}'].self.model.pick_mode === 'off'", timeout=10_000)
    page.mouse.click(cx, cy)
    page.wait_for_timeout(800)
    assert python_value(page, "picked") == {}, "pick_mode off: a click picked"
    assert np.allclose(camera(page, label)["V"], cam0)
    drag(cx, cy, 100, 0)
    assert not np.allclose(camera(page, label)["V"], cam0), "pick_mode off: a drag must orbit"
    page.wait_for_timeout(500)
    assert python_value(page, "dragged") == {}
    shot(page, label, artifacts / "pick_off_orbited.png")
    # and back on: picking works again
    page.mouse.dblclick(*corner)
    page.get_by_role("button", name="vertex").click()
    page.wait_for_function(f"() => window.__faceRetarget.viewers['{label}'].self.model.pick_mode === 'vertex'", timeout=10_000)
    page.wait_for_timeout(300)
    page.mouse.click(cx, cy)
    wait_python_count(page, "picked", 1)
    assert not page.console_errors, page.console_errors


@pytest.mark.browser
def test_gpu_morph_path_picks_the_same_vertices(page, pick_url, scene, pick_app, artifacts):
    """blend=gpu: the mesh is morphed in the shader; three's raycast applies the influences
    on the CPU and the viewer recomputes the hit triangle's vertices from the weights."""
    rig, W, mesh = scene
    label = pick_app.LABEL
    open_app(page, pick_url, label, "?blend=gpu")
    assert js(page, label, "v.info().blend") == "gpu"
    box = canvas_box(page, label)
    cam = camera(page, label)
    v_mouth = int(np.argmax(np.linalg.norm(rig.deltas[rig.index("mouthOpen")], axis=1)))
    targets = [(box["x"] + box["width"] / 2, box["y"] + box["height"] / 2), tuple(project(cam, mesh[v_mouth])[0])]
    for n, (x, y) in enumerate(targets, start=1):
        page.mouse.click(x, y)
        wait_python_count(page, "picked", n)
        check_pick(page, label, scene, cam, x, y, python_value(page, "picked"), rig.faces)
    shot(page, label, artifacts / "pick_gpu.png")
    assert not page.console_errors, page.console_errors


def test_pick_params_and_highlight_validation(tiger):
    from dashboard.viewer import MeshViewer

    v = MeshViewer.from_rig(tiger, np.zeros((3, tiger.n_shapes)), pick_mode="vertex")
    assert v.pick_mode == "vertex" and v.picked == {} and v.dragged == {}
    v.set_highlight(np.array([3, 7]))
    assert v.highlight == [3, 7]
    with pytest.raises(ValueError, match=r"highlight: vertex ids must lie in \[0, 2100\)"):
        v.set_highlight([tiger.n_vertices])
    with pytest.raises(ValueError):
        v.pick_mode = "face"
    assert MeshViewer.from_rig(tiger).pick_mode == "off"
