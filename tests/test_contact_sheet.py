"""The contact sheet (core.contact_sheet, issue 32 item 4): its rasteriser against a per-pixel loop,
its frames (the worst one among them, the others far apart in expression), its PNG (the size
it should have, both faces drawn in every cell), the page's card and frame links without a
browser, and ``evaluate --html``."""

import base64
import io
import re

import numpy as np
import pytest
import trimesh
from PIL import Image

from datapaths import PERFORMANCES, RIGS

from core.contact_sheet import COLUMNS, GAP, SHEET_FRAMES, TILE, contact_sheet, rasterize, sheet_size
from core.evaluate import summarize, worst_frame
from core.geometry import vertex_normals
from core.pipeline import Pipeline, StageCache

SAMPLE = dict(source=str(PERFORMANCES / "livelinkface_take_s07.csv"), source_rig=str(RIGS / "ict_facekit.glb"),
              target_rig=str(RIGS / "rocketbox_female_adult_02.glb"), target_shapes="arkit", last_frame=599)


def _reference(V, faces, size, box):
    """The rasteriser written as the definition: every pixel centre, every triangle, keep the nearest."""
    from core.contact_sheet import LIGHT

    W, H = size
    x0, x1, y0, y1 = box
    s = min(W / (x1 - x0), H / (y1 - y0))
    P = np.c_[(V[:, 0] - 0.5 * (x0 + x1)) * s + 0.5 * W, 0.5 * H - (V[:, 1] - 0.5 * (y0 + y1)) * s]
    shade = np.abs(vertex_normals(V, faces) @ LIGHT)
    img, depth = np.full((H, W), np.nan), np.full((H, W), -np.inf)
    for j in range(H):
        for i in range(W):
            p = np.array([i + 0.5, j + 0.5])
            for f in faces:
                a, b, c = P[f]
                T = np.c_[a - c, b - c]
                if abs(np.linalg.det(T)) < 1e-12:
                    continue
                l0, l1 = np.linalg.solve(T, p - c)
                lam = np.array([l0, l1, 1 - l0 - l1])
                if (lam >= -1e-9).all():
                    z = lam @ V[f, 2]
                    if z > depth[j, i]:
                        depth[j, i], img[j, i] = z, lam @ shade[f]
    return img


def test_rasterize_matches_the_per_pixel_definition():
    """Two overlapping spheres (the nearer one hides part of the other): the same pixels drawn,
    the same shading, to rounding."""
    a, b = trimesh.creation.icosphere(1, radius=1.0), trimesh.creation.icosphere(1, radius=0.7)
    V = np.vstack([a.vertices, b.vertices + [0.8, 0.3, 0.6]])
    faces = np.vstack([a.faces, b.faces + len(a.vertices)])
    box = (-1.2, 1.7, -1.2, 1.2)
    got, want = rasterize(V, faces, (24, 20), box), _reference(V, faces, (24, 20), box)
    np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
    assert 150 < np.isfinite(got).sum() < 24 * 20  # a picture, not a blank or a full frame
    np.testing.assert_allclose(got[np.isfinite(got)], want[np.isfinite(want)], atol=1e-9)


def test_rasterize_single_triangle_covers_the_pixel_centres_inside_it():
    """A right triangle over a 4 x 4 image: exactly the 10 pixel centres on or under its diagonal
    (x + y <= 4 in pixels), flat-lit (normal along +z, shading |n . L| = L_z)."""
    from core.contact_sheet import LIGHT

    V = np.array([[0.0, 0.0, 0.0], [4.0, 0.0, 0.0], [0.0, 4.0, 0.0]])
    img = rasterize(V, np.array([[0, 1, 2]]), (4, 4), (0.0, 4.0, 0.0, 4.0))
    rows, cols = np.nonzero(np.isfinite(img))
    # image row j is y = 4 - (j + 0.5); column i is x = i + 0.5
    assert sorted(zip(rows, cols)) == sorted((j, i) for j in range(4) for i in range(4) if (i + 0.5) + (3.5 - j) <= 4)
    np.testing.assert_allclose(img[np.isfinite(img)], LIGHT[2])


@pytest.fixture(scope="module")
def sample():
    pipe = Pipeline(cache=StageCache(), **SAMPLE)
    return pipe.results(["load", "frames", "stabilize", "synthesize", "evaluate"])


def test_the_sheet_has_the_worst_frame_and_frames_far_apart(sample):
    ev = sample["evaluate"]
    worst = worst_frame(ev)
    # the worst frame is the frame of the summary's "max": the largest marker error RMS of a frame
    assert ev["marker_error_mm"][worst] == np.nanmax(ev["marker_error_mm"])
    sheet = contact_sheet(sample, sample["synthesize"]["weights"], worst, error_mm=ev["marker_error_mm"])
    n = SHEET_FRAMES
    assert sheet.frames[0] == worst and len(set(sheet.frames)) == n
    assert "worst" in sheet.captions[0] and all("worst" not in c for c in sheet.captions[1:])
    # the range's smile and blink are on it (the sheet's reach at least 3/4 of the range's largest)
    S = np.nan_to_num(sample["stabilize"]["source"].source_weights)
    names = list(sample["load"]["source_rig"].names)
    for shape in ("mouthSmile_L", "eyeBlink_L"):
        k = names.index(shape)
        assert S[sheet.frames, k].max() > 0.75 * S[:, k].max(), shape
    # far apart in expression: each pair of sheet frames differs more in the source's curves than
    # the median pair of the take's frames does
    pick = S[sheet.frames]
    gaps = np.linalg.norm(pick[:, None] - pick[None], axis=2)[np.triu_indices(n, 1)]
    rng = np.random.default_rng(0)
    i, j = rng.integers(0, len(S), (2, 2000))
    assert gaps.min() > np.median(np.linalg.norm(S[i] - S[j], axis=1))


def test_the_png_has_its_size_and_both_faces_in_every_cell(sample):
    ev = sample["evaluate"]
    sheet = contact_sheet(sample, sample["synthesize"]["weights"], worst_frame(ev), n=6)
    png = sheet.png()
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    img = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=np.float64)
    assert img.shape == (sheet_size(6)[1], sheet_size(6)[0], 3) == (2 * (TILE[1] + 34 + GAP) + GAP, COLUMNS * (2 * TILE[0] + GAP) + GAP, 3)
    assert img.std() > 30  # not blank
    for k in range(6):
        r, c = divmod(k, COLUMNS)
        x, y = GAP + c * (2 * TILE[0] + GAP), GAP + r * (TILE[1] + 34 + GAP)
        for half in (img[y + 20:y + TILE[1], x:x + TILE[0]], img[y + 20:y + TILE[1], x + TILE[0] + 1:x + 2 * TILE[0]]):
            face = (half < 250).any(axis=2)  # the white background is 255
            assert 0.2 < face.mean() < 0.98 and half[face].std() > 10  # a shaded face, not a flat block
    # the source (blue-grey) on the left, the target (warm) on the right of each cell
    left, right = img[GAP + 20:GAP + TILE[1], GAP:GAP + TILE[0]], img[GAP + 20:GAP + TILE[1], GAP + TILE[0] + 1:GAP + 2 * TILE[0]]
    lf, rf = (left < 250).any(2), (right < 250).any(2)
    assert left[lf][:, 2].mean() > left[lf][:, 0].mean() and right[rf][:, 0].mean() > right[rf][:, 2].mean()
    assert sheet.png() == png  # the same bytes every time


def test_the_target_follows_the_source_at_the_sheet_frames(sample):
    """Where the source's jaw is open on the sheet the target's is too: the target's mesh moves at
    each frame whose source curves move (the picture is of the result, not the neutral)."""
    sheet = contact_sheet(sample, sample["synthesize"]["weights"], worst_frame(sample["evaluate"]), n=6)
    neutral = np.asarray(contact_sheet(sample, np.zeros_like(sample["synthesize"]["weights"]),
                                       sheet.worst, n=6).tiles[0], dtype=np.float64)
    moved = np.asarray(sheet.tiles[0], dtype=np.float64)
    W = TILE[0]
    assert np.abs(moved[:, W:] - neutral[:, W:]).mean() > 0.5  # the target changed from its neutral
    np.testing.assert_array_equal(moved[:, :W], neutral[:, :W])  # the source is the source either way


def test_page_card_renders_and_links_jump_to_frames():
    """Without a browser: opening the card renders the sheet with a link per frame, the worst
    first; the summary's max links to the worst frame; a click (FrameLinks.jump) moves the page."""
    from dashboard.app import DashboardApp
    from dashboard.session import Session

    app = DashboardApp(Session(cache=StageCache()))
    app.pipe.configure(last_frame=599)
    app.refresh()
    ev = app.s.snapshot["evaluate"]
    worst = worst_frame(ev)
    assert f'data-fr-frame="{worst}"' in app.summary.w_summary.object and "mm at frame" in app.summary.w_summary.object
    assert app.contact.sheet is None  # closed: nothing rendered
    app.contact.card.collapsed = False
    sheet = app.contact.sheet
    assert sheet is not None and sheet.frames[0] == worst
    links = [int(f) for f in re.findall(r'data-fr-frame="(\d+)"', app.contact.w_sheet.object)]
    assert links == sheet.frames
    # the summary's max and the worst frame's caption are the same number, said as the same kind:
    # the marker error RMS of that frame (the batch summary's marker_max_mm)
    summary = re.sub(r"<[^>]+>", "", app.summary.w_summary.object)
    said = re.search(r"marker error RMS \*\*[\d.]+ mm\*\* \(per frame: max ([\d.]+) mm at frame (\d+)\)", summary)
    assert said and int(said[2]) == worst, summary
    caption = re.search(r"worst · marker RMS ([\d.]+) mm", sheet.captions[0])
    assert caption and caption[1] == said[1], (sheet.captions[0], said[0])
    best = summarize(ev, app.s.snapshot["weights"])["marker_max_mm"]
    assert float(said[1]) == pytest.approx(best, abs=0.05)
    assert app.contact.w_png.filename.endswith("_contact_sheet.png")
    assert app.contact.w_png.callback().read() == sheet.png()
    target = sheet.frames[2]
    assert app.frame != target
    app.contact.links.jump = f"{target}:1"
    assert app.frame == target and app.pipe.frame == target
    app.contact.links.jump = f"{worst}:2"
    assert app.frame == worst


def test_evaluate_html_has_the_contact_sheet(tmp_path, capsys):
    from core.cli import main

    out = tmp_path / "r.html"
    assert main(["evaluate", "--source", SAMPLE["source"], "--source-rig", SAMPLE["source_rig"], "--target-rig",
                 SAMPLE["target_rig"], "--target-shapes", "arkit", "--methods", "bounded", "--last-frame", "299",
                 "--html", str(out), "--quiet"]) == 0
    capsys.readouterr()
    doc = out.read_text()
    m = re.search(r"<h2>Contact sheet of bounded: [^<]*worst frame[^<]*</h2><img src=\"data:image/png;base64,([^\"]+)\"", doc)
    assert m, "no contact sheet in the report"
    img = Image.open(io.BytesIO(base64.b64decode(m.group(1))))
    assert img.size == sheet_size(SHEET_FRAMES)
