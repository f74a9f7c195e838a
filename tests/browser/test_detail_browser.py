"""Fine-scale detail editing in the dense-transfer tab, end to end in headless Chromium.

The page (tests/browser/detail_app.py) shows a transfer of the tiger on frame 20 with its
details as the viewer's offsets. The test clicks a vertex on the canvas (detail selection),
checks the selection is coloured, presses "Apply detail edit" (scale ×3 on every frame of the μ window)
and compares what the browser draws with core's result computed here: the vertex positions
the browser shows must be neutral + w Δ + the edited details; "Undo detail edit" restores the
picture.
"""

from __future__ import annotations

import importlib.util
import re
from pathlib import Path

import numpy as np
import pytest

from test_pick import camera, canvas_box, js, project, shot

ROOT = Path(__file__).resolve().parents[2]
APP = "/detail_app"


@pytest.fixture(scope="module")
def detail_app():
    spec = importlib.util.spec_from_file_location("detail_app_under_test", ROOT / "tests" / "browser" / "detail_app.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def case(detail_app):
    from core.io.gltf import read_rig
    from core.transfer.detail_edit import DetailEditor

    rig = read_rig(detail_app.RIG)
    res = detail_app.transfer()
    return rig, res, DetailEditor.from_result(res)


@pytest.fixture(scope="module")
def detail_url(panel_server):
    return panel_server("tests/browser/detail_app.py")


def shown(res, details, frame):
    """(V, 3) the viewer's mesh at ``frame``: neutral + w Δ + details."""
    return res.neutral + np.einsum("k,kvc->vc", res.weights[frame], res.deltas) + details[frame]


def status(page):
    return page.get_by_text(re.compile(r"^(selection:|detail edit|undone|⚠|\d+ frames)")).first.inner_text()


@pytest.mark.browser
def test_click_select_apply_and_undo_a_detail_edit(page, detail_url, detail_app, case, artifacts):
    from playwright.sync_api import expect

    rig, res, ed = case
    label, k = detail_app.LABEL, detail_app.KEY
    page.goto(detail_url + APP)
    page.wait_for_function(
        "(label) => { const v = window.__faceRetarget && window.__faceRetarget.viewers[label]; "
        "return v && v.self.width > 0 && v.self.stats.renders > 0 && v.self.pendingRender === null "
        "&& v.info().offsets; }", arg=label, timeout=90_000)
    page.wait_for_timeout(300)
    assert js(page, label, "v.self.clock.frame") == k
    # the details of frame 20 are drawn: the browser's vertices are neutral + w Δ + D_20
    mesh = shown(res, res.details, k)
    ids = list(range(0, rig.n_vertices, 97))
    got = np.array(js(page, label, "v.vertexPositions(arg)", ids))
    assert np.abs(got - mesh[ids]).max() < 1e-6
    before = shot(page, label, artifacts / "detail_before.png")

    # click on a smooth, front-facing vertex with details near the middle of the face
    N = ed.normals(k)[ed.wi]
    cam = camera(page, label)
    view_dir = mesh.mean(0) - cam["position"]
    coat = np.linalg.norm(ed.coating(k), axis=1)[ed.wi]
    front = (N @ view_dir < -0.7 * np.linalg.norm(view_dir)) & (coat > np.percentile(coat, 90))
    target = int(np.flatnonzero(front)[np.argmax(coat[front])])
    x, y = project(cam, mesh[target])[0]
    page.mouse.click(x, y)
    expect(page.get_by_text(re.compile(r"^selection: vertex"))).to_be_visible(timeout=20_000)
    picked = int(re.search(r"vertex (\d+)", status(page)).group(1))
    assert np.linalg.norm(project(cam, mesh[picked])[0] - [x, y]) < 25
    page.wait_for_function("(label) => window.__faceRetarget.viewers[label].self.pendingRender === null", arg=label)
    page.wait_for_timeout(500)
    selected = shot(page, label, artifacts / "detail_selected.png")
    orange = (selected[..., 0] > 150) & (selected[..., 1] > 90) & (selected[..., 2] < 60) & \
             ~((before[..., 0] > 150) & (before[..., 1] > 90) & (before[..., 2] < 60))
    assert orange.sum() > 30, "the selection is not coloured on the mesh"
    box = canvas_box(page, label)
    oy, ox = np.argwhere(orange).mean(0)
    assert np.hypot(box["x"] + ox - x, box["y"] + oy - y) < 60, "the coloured selection is not where the click was"

    # apply: the browser shows core's edited details
    page.get_by_role("button", name="Apply detail edit").click()
    expect(page.get_by_text(re.compile(r"^detail edit 1:"))).to_be_visible(timeout=30_000)
    radius = round(3000 * ed.mean_edge(), 1) / 1000
    region = ed.select_paint(ed.to_editor([picked]), radius, k)
    want = ed.apply(ed.scale(region, k, detail_app.FACTOR), lam_e=detail_app.LAM_E, propagation="per_frame")
    new_mesh = shown(res, want.details, k)
    page.wait_for_function(
        "([label, v, z]) => Math.abs(window.__faceRetarget.viewers[label].vertexPositions([v])[0][2] - z) < 1e-6",
        arg=[label, int(ed.rep[region[0]]), float(new_mesh[ed.rep[region[0]], 2])], timeout=20_000)
    moved = ed.to_rig(region)
    got = np.array(js(page, label, "v.vertexPositions(arg)", [int(i) for i in moved]))
    assert np.abs(got - new_mesh[moved]).max() < 1e-6
    assert np.abs(new_mesh[moved] - mesh[moved]).max() > 1e-4  # a real change (> 0.1 mm)
    page.wait_for_timeout(500)
    applied = shot(page, label, artifacts / "detail_applied.png")
    diff = np.abs(applied.astype(int) - before.astype(int)).sum(2) > 30
    assert diff.sum() > 20, "the edit does not show"
    dy, dx = np.argwhere(diff).mean(0)
    assert np.hypot(box["x"] + dx - x, box["y"] + dy - y) < 80, "the change is not around the selection"

    # undo: the transfer's own details again, the picture as before
    page.get_by_role("button", name="Undo detail edit", exact=True).click()
    expect(page.get_by_text(re.compile(r"^undone"))).to_be_visible(timeout=20_000)
    page.wait_for_function(
        "([label, v, z]) => Math.abs(window.__faceRetarget.viewers[label].vertexPositions([v])[0][2] - z) < 1e-6",
        arg=[label, int(ed.rep[region[0]]), float(mesh[ed.rep[region[0]], 2])], timeout=20_000)
    page.wait_for_timeout(500)
    undone = shot(page, label, artifacts / "detail_undone.png")
    assert (np.abs(undone.astype(int) - before.astype(int)).sum(2) > 30).sum() <= 5


@pytest.mark.browser
def test_details_play_along_as_morph_targets_in_the_browser(page, detail_url, detail_app, case, artifacts):
    """Tick "Details while playing": the viewer gets K + r shapes in one rebuild and, on any
    frame it plays to, draws the transfer with its details (to the factorisation's error)."""
    from playwright.sync_api import expect

    from core.transfer.details import detail_morph_targets

    rig, res, ed = case
    label, k = detail_app.LABEL, detail_app.KEY
    page.goto(detail_url + APP)
    page.wait_for_function(
        "(label) => { const v = window.__faceRetarget && window.__faceRetarget.viewers[label]; "
        "return v && v.self.width > 0 && v.self.stats.renders > 0 && v.info().offsets; }", arg=label, timeout=90_000)
    C, B, err = detail_morph_targets(res.details)
    K = res.n_bases
    page.get_by_role("button", name=re.compile("Details while playing")).click()  # a toggle: its label is the button
    expect(page.get_by_text(re.compile(r"^details play as \d+ extra morph targets"))).to_be_visible(timeout=30_000)
    page.wait_for_function("([label, K]) => window.__faceRetarget.viewers[label].self.K === K && "
                           "!window.__faceRetarget.viewers[label].info().offsets", arg=[label, K + len(B)], timeout=30_000)
    page.get_by_role("button", name=re.compile("Play")).click()
    page.wait_for_timeout(1200)
    page.get_by_role("button", name=re.compile("Play")).click()
    page.wait_for_function("(label) => !window.__faceRetarget.viewers[label].self.clock.playing", arg=label,
                           timeout=10_000)
    f = js(page, label, "v.self.clock.frame")
    assert f != k, "playback did not advance"
    ids = list(range(0, rig.n_vertices, 53))
    got = np.array(js(page, label, "v.vertexPositions(arg)", ids))
    want = shown(res, res.details, f)
    assert np.linalg.norm(got - want[ids], axis=1).max() <= err + 2e-6
    shot(page, label, artifacts / "detail_playing.png")
